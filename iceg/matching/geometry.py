"""Geometry shared by the matcher and the feature map: feature headings, moving features and
segments between frames, a scan's polar range profile, point-to-segment association.

All functions are vectorized over features, segments or points.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, replace

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg.landmark_frames import move_lines
from iceg.matching._kernels import (
    Rays,
    beam_directions,
    feature_angles,
    point_segments,
    polar_profile,
    segment_arrays,
)
from iceg.types import FeatureKind, ScanFeatures
from iceg_common.se2 import rotation_matrix as rot

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

CORNER = int(FeatureKind.CORNER)
EOW = int(FeatureKind.EOW)
INTERSECTION = int(FeatureKind.INTERSECTION)


#: A beam bracket or nearest-return lookup spanning more than this many beam spacings
#: crosses a gap of invalid beams (no return there).
MAX_GAP_BEAMS = 1.6


@dataclass(frozen=True, eq=False)
class FeatureGeometry:
    """Per-feature quantities the matcher uses, precomputed once per scan.

    Attributes:
        kind: ``(K,)`` int64 :class:`FeatureKind`.
        xy: ``(K, 2)`` float64 positions, metres, the features' frame.
        cov: ``(K, 2, 2)`` float64 position covariances, m² (regularised to be positive).
        heading: ``(K,)`` float64 radians: a Corner's bisector direction, an EOW's wall
            direction, NaN for an Intersection.
        edge: ``(K, 2)`` float64 radians: the direction angles of ``directions`` (NaN where
            there is none).
        opening: ``(K,)`` float64 opening angle, radians (NaN for an EOW).
        dist: ``(K,)`` float64 distance from the frame's origin, metres.
    """

    kind: IntArray
    xy: FloatArray
    cov: FloatArray
    heading: FloatArray
    edge: FloatArray
    opening: FloatArray
    dist: FloatArray

    @property
    def n(self) -> int:
        """Number of features."""
        return int(self.kind.shape[0])


def feature_geometry(features: ScanFeatures, min_std_m: float = 0.005) -> FeatureGeometry:
    """Headings, edge angles and distances of a scan's features (paper §III-B: "vector
    directions ... start from feature point"; a Corner's two edges define its bisector), in
    one compiled pass (:func:`~iceg.matching._kernels.feature_angles`).

    Args:
        features: The scan's (or reference's) features.
        min_std_m: Floor added to each position covariance (m), so that it is invertible.
    """
    kind = np.ascontiguousarray(features.kind, dtype=np.int64)
    xy = np.ascontiguousarray(features.xy, dtype=np.float64).reshape(-1, 2)
    edge, heading, cov, dist = feature_angles(
        kind,
        xy,
        np.ascontiguousarray(features.cov, dtype=np.float64).reshape(-1, 2, 2),
        np.ascontiguousarray(features.directions, dtype=np.float64).reshape(-1, 2, 2),
        min_std_m**2,
        CORNER,
        EOW,
    )
    return FeatureGeometry(
        kind=kind,
        xy=xy,
        cov=cov,
        heading=heading,
        edge=edge,
        opening=np.asarray(features.opening_rad, dtype=np.float64),
        dist=dist,
    )


def transform_lines(
    lines: FloatArray, cov: FloatArray, pose: ArrayLike
) -> tuple[FloatArray, FloatArray]:
    """Move Hessian lines ``(alpha_rad, rho_m)`` and their covariances into the parent frame
    of ``pose`` (the frame in which ``pose`` is given).

    A point ``p`` of the child frame maps to ``R p + t``; the line becomes
    ``alpha' = alpha + theta``, ``rho' = rho + (cos alpha', sin alpha') · t``, flipped to keep
    ``rho' >= 0``. The covariance follows with the Jacobian ``[[1, 0], [drho'/dalpha, 1]]``.

    Args:
        lines: ``(M, 2)`` float64 ``(alpha_rad, rho_m)``.
        cov: ``(M, 2, 2)`` float64 covariance of ``(alpha, rho)``.
        pose: ``(3,)`` float64 pose of the child frame in the parent frame, or ``(M, 3)``
            one pose per line.

    Returns:
        ``(M, 2)`` lines and ``(M, 2, 2)`` covariances in the parent frame.
    """
    lines = np.asarray(lines, dtype=np.float64).reshape(-1, 2)
    m = lines.shape[0]
    poses = np.broadcast_to(np.asarray(pose, dtype=np.float64), (m, 3))
    return move_lines(
        np.arange(m),
        np.ascontiguousarray(poses),
        lines,
        np.asarray(cov, dtype=np.float64).reshape(-1, 2, 2),
    )


def transform_line_rows(
    rows: IntArray, poses: FloatArray, lines: FloatArray, cov: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """:func:`transform_lines` of some rows without gathering them first (the same numbers
    as ``transform_lines(lines[rows], cov[rows], poses)``).

    Args:
        rows: ``(n,)`` int64 rows of ``lines`` ``(N, 2)`` float64 ``(alpha_rad, rho_m)`` and
            ``cov`` ``(N, 2, 2)`` float64; each in ``[0, N)`` (not checked: a compiled loop).
        poses: ``(n, 3)`` float64 the pose of each row's frame in the parent frame.

    Returns:
        ``(n, 2)`` lines and ``(n, 2, 2)`` covariances in the parent frame.
    """
    return move_lines(rows, poses, lines, cov)


def transform_features(
    features: ScanFeatures, pose: ArrayLike, keep_points: bool = True
) -> ScanFeatures:
    """Express a :class:`ScanFeatures` in the parent frame of ``pose``.

    Args:
        features: Features in the child frame.
        pose: ``(3,)`` float64 pose of the child frame in the parent frame.
        keep_points: Also move ``points_xy`` (else they are dropped and
            ``seg_point_range`` set to -1).

    Returns:
        A new :class:`ScanFeatures` in the parent frame (``ids`` unchanged).
    """
    p = np.asarray(pose, dtype=np.float64)
    r = rot(p[2])
    t = p[:2]
    lines, lcov = transform_lines(features.seg_lines, features.seg_cov, p)
    if keep_points:
        pts = features.points_xy @ r.T + t
        spr = features.seg_point_range
    else:
        pts = np.zeros((0, 2))
        spr = np.full_like(features.seg_point_range, -1)
    return replace(
        features,
        points_xy=pts,
        seg_endpoints=features.seg_endpoints @ r.T + t,
        seg_lines=lines,
        seg_cov=lcov,
        seg_point_range=spr,
        xy=features.xy @ r.T + t,
        cov=r @ features.cov @ r.T,
        directions=features.directions @ r.T,
    )


@dataclass(frozen=True, eq=False)
class PolarProfile:
    """A scan's ranges by bearing, for occlusion and free-space tests.

    Attributes:
        bearing: ``(B,)`` float64 sorted bearings (radians) of the returns, from ``origin``.
        range: ``(B,)`` float64 ranges (metres) of those returns.
        spacing: Typical angular spacing of consecutive beams (radians).
        range_max_m: Beams at or beyond this were invalid (not in the profile).
    """

    bearing: FloatArray
    range: FloatArray
    spacing: float
    range_max_m: float

    @functools.cached_property
    def directions(self) -> tuple[FloatArray, FloatArray]:
        """Cosines and sines ``(B,)`` float64 of ``bearing``, computed once per profile (a
        scan's free-space checks cast walls along its beams many times)."""
        return beam_directions(self.bearing)

    @functools.cached_property
    def rays(self) -> Rays:
        """The profile as the compiled free-space tests take it (built once per profile)."""
        cos_b, sin_b = self.directions
        return Rays(
            np.ascontiguousarray(self.bearing, dtype=np.float64),
            cos_b,
            sin_b,
            np.ascontiguousarray(self.range, dtype=np.float64),
            float(self.spacing),
            float(self.range_max_m),
        )

    @classmethod
    def from_points(cls, points_xy: FloatArray, range_max_m: float) -> PolarProfile:
        """Profile of points ``(P, 2)`` (metres) seen from the frame's origin: bearings in
        stable order, the median gap between distinct bearings as the spacing (compiled,
        :func:`~iceg.matching._kernels.polar_profile`)."""
        pts = np.ascontiguousarray(points_xy, dtype=np.float64).reshape(-1, 2)
        bearing, rng, spacing = polar_profile(pts)
        return cls(bearing, rng, float(spacing), float(range_max_m))


def point_segment_index(features: ScanFeatures) -> IntArray:
    """``(P,)`` int64: the segment each point of ``features.points_xy`` belongs to (-1 if
    none), from ``seg_point_range``."""
    spr = np.ascontiguousarray(features.seg_point_range, dtype=np.int64).reshape(-1, 2)
    return point_segments(spr, features.points_xy.shape[0])


@dataclass(frozen=True, eq=False)
class SegmentSet:
    """Reference segments prepared for point association.

    Attributes:
        a: ``(M, 2)`` first endpoints, metres.
        u: ``(M, 2)`` unit directions from ``a`` to the last endpoint.
        length: ``(M,)`` lengths, metres.
        normal: ``(M, 2)`` unit normals ``(cos alpha, sin alpha)`` of the fitted lines.
        rho: ``(M,)`` line distances, metres.
        alpha: ``(M,)`` line normal angles, radians.
        cov: ``(M, 2, 2)`` covariance of ``(alpha, rho)``.
    """

    a: FloatArray
    u: FloatArray
    length: FloatArray
    normal: FloatArray
    rho: FloatArray
    alpha: FloatArray
    cov: FloatArray

    @classmethod
    def from_features(cls, features: ScanFeatures) -> SegmentSet:
        """Segments of a :class:`ScanFeatures` (any frame)."""
        return cls(
            *segment_arrays(
                np.asarray(features.seg_endpoints, dtype=np.float64).reshape(-1, 2, 2),
                np.asarray(features.seg_lines, dtype=np.float64).reshape(-1, 2),
                np.asarray(features.seg_cov, dtype=np.float64).reshape(-1, 2, 2),
            )
        )

    @property
    def n(self) -> int:
        """Number of segments."""
        return int(self.a.shape[0])


def associate_points(
    q: FloatArray,
    q_alpha: FloatArray,
    segs: SegmentSet,
    gate_m: float,
    end_tol_m: float,
    normal_gate_rad: float,
) -> tuple[IntArray, FloatArray]:
    """Nearest reference segment of each point, with gates (docs/design.md step 8).

    A point associates with the segment of least point-to-segment distance (the segment
    extended by ``end_tol_m`` at both ends) among those whose line normal is within
    ``normal_gate_rad`` of the point's own segment normal (modulo pi), if that distance is
    below ``gate_m``.

    Args:
        q: ``(P, 2)`` float64 points in the reference frame, metres.
        q_alpha: ``(P,)`` float64 normal angle (radians, reference frame) of the segment each
            point lies on in its own scan.
        segs: Reference segments.
        gate_m: Distance gate, metres.
        end_tol_m: Endpoint extension, metres.
        normal_gate_rad: Normal-angle gate, radians (< pi/2).

    Returns:
        ``(P,)`` int64 segment index (-1: none) and ``(P,)`` float64 signed point-to-line
        residual ``n · q - rho`` (NaN where none).
    """
    n_p = q.shape[0]
    if segs.n == 0 or n_p == 0:
        return np.full(n_p, -1, dtype=np.int64), np.full(n_p, np.nan)
    rel_x = q[:, 0:1] - segs.a[None, :, 0]
    rel_y = q[:, 1:2] - segs.a[None, :, 1]
    s = rel_x * segs.u[None, :, 0] + rel_y * segs.u[None, :, 1]  # (P, M) along
    perp = rel_x * segs.u[None, :, 1] - rel_y * segs.u[None, :, 0]  # (P, M) across
    over = np.maximum(np.maximum(-end_tol_m - s, s - segs.length[None] - end_tol_m), 0.0)
    d2 = perp * perp + over * over
    sin_diff = np.abs(
        np.sin(q_alpha)[:, None] * segs.normal[None, :, 0]
        - np.cos(q_alpha)[:, None] * segs.normal[None, :, 1]
    )
    d2[sin_diff > math.sin(normal_gate_rad)] = np.inf
    j = np.argmin(d2, axis=1)
    best = d2[np.arange(n_p), j]
    ok = best <= gate_m * gate_m
    idx = np.where(ok, j, -1)
    res = np.full(n_p, np.nan)
    jj = j[ok]
    res[ok] = np.einsum("ij,ij->i", q[ok], segs.normal[jj]) - segs.rho[jj]
    return idx.astype(np.int64), res
