"""Steps 2-3 of feature extraction: breakpoints, split-and-merge, maximum-likelihood lines.

docs/design.md "ICE matching, step by step", steps 2-3; paper §III-C1.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from iceg.features.config import FeatureConfig
from iceg.features.geometry import dot2
from iceg.features.lines import fit_lines
from iceg.features.points import BeamPoints
from iceg.features.segmentation import breakpoints, split_and_merge
from iceg_common.numba_loading import njit

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class Segments(NamedTuple):
    """M line segments of one scan, robot frame."""

    point_range: IntArray  # (M, 2) int64 [start, stop) indices into BeamPoints.points
    lines: FloatArray  # (M, 2) float64 (alpha_rad, rho_m), rho >= 0
    cov: FloatArray  # (M, 2, 2) float64 covariance of (alpha, rho): rad², rad·m, m²
    endpoints: FloatArray  # (M, 2, 2) float64 first / last point projected on the line, m
    end_beam: IntArray  # (M, 2) int64 scan beam index of the first / last point
    spacing: FloatArray  # (M, 2) float64 along-wall beam spacing at each endpoint, m
    normals: FloatArray  # (M, 2) float64 unit line normals (cos alpha, sin alpha)


def segment_point_ranges(beams: BeamPoints, cfg: FeatureConfig) -> IntArray:
    """Point ranges of the segments: adaptive breakpoints (Borges & Aldon 2004, eq. 8), then
    split-and-merge inside clusters (paper §III-C1; Nguyen et al. 2005, Alg. 1), merging
    across at most ``cfg.dropout_max_beams`` invalid beams, or across beams that all return
    from the robot's own body (``cfg.robot_body_range_m``) or too close to measure (``-inf``,
    as ``cfg.robot_body_dark_deg`` reads the body's dark bearings).

    Args:
        beams: The scan's points (:func:`iceg.features.points.beam_points`).
        cfg: ``sigma_range_m``, ``breakpoint_lambda_deg``, ``dropout_max_beams``,
            ``split_distance_m``, ``merge_distance_m``, ``min_segment_points`` and
            ``robot_body_range_m`` are read.

    Returns:
        ``(M, 2)`` int64 ``[start, stop)`` indices into ``beams.points``, in point order.
    """
    return _segment_point_ranges(
        beams.points,
        beams.point_ranges,
        beams.angles[beams.valid],
        beams.beam_index,
        beams.ranges,
        _SegmentationSettings(
            cfg.sigma_range_m,
            math.radians(cfg.breakpoint_lambda_deg),
            cfg.dropout_max_beams,
            cfg.split_distance_m,
            cfg.merge_distance_m,
            cfg.min_segment_points,
            cfg.robot_body_range_m,
            cfg.min_segment_length_m,
        ),
    )


class _SegmentationSettings(NamedTuple):
    """:func:`segment_point_ranges`'s thresholds for its kernel."""

    sigma_range_m: float
    lambda_rad: float
    dropout_max_beams: int
    split_distance_m: float
    merge_distance_m: float
    min_segment_points: int
    robot_body_range_m: float
    min_segment_length_m: float


@njit(cache=True, nogil=True)
def _segment_point_ranges(
    points: FloatArray,
    ranges: FloatArray,
    bearings: FloatArray,
    beam_index: IntArray,
    all_ranges: FloatArray,
    s: _SegmentationSettings,
) -> IntArray:
    """:func:`segment_point_ranges`, compiled: clusters joinable across a dropout of 1 to
    ``dropout_max_beams`` invalid beams, or across beams that all return from the robot's
    own body (``0 < r <= robot_body_range_m``, ``all_ranges`` ``(N,)`` every beam's range) or
    too close to measure (``-inf``: :func:`~iceg.features.points.beam_points` reads the
    body's dark bearings so): the body hides the wall behind it, it does not end it. A wall
    joined across the body must stand on each side of it (:func:`_stands_on_each_side`)."""
    bounds = breakpoints(points, ranges, bearings, beam_index, s.sigma_range_m, s.lambda_rad)
    n_inner = max(bounds.shape[0] - 2, 0)
    joinable = np.empty(n_inner, dtype=np.bool_)
    body_gap = np.zeros(points.shape[0], dtype=np.bool_)  # a body's shadow before point i
    for c in range(n_inner):
        at = bounds[c + 1]
        gap_beams = beam_index[at] - beam_index[at - 1] - 1
        body = gap_beams >= 1
        b = beam_index[at - 1] + 1
        while body and b < beam_index[at]:
            r = all_ranges[b]
            body = r == -np.inf or 0.0 < r <= s.robot_body_range_m
            b += 1
        body_gap[at] = body
        joinable[c] = 1 <= gap_beams <= s.dropout_max_beams or body
    segments = split_and_merge(
        np.ascontiguousarray(points[:, 0]),
        np.ascontiguousarray(points[:, 1]),
        bounds,
        joinable,
        s.split_distance_m,
        s.merge_distance_m,
        s.min_segment_points,
    )
    if not body_gap.any():
        return segments
    return _stands_on_each_side(points, segments, body_gap, s)


@njit(cache=True, nogil=True)
def _stands_on_each_side(
    points: FloatArray, segments: IntArray, body_gap: NDArray[np.bool_], s: _SegmentationSettings
) -> IntArray:
    """``segments`` (``(M, 2)`` ``[start, stop)`` point ranges), each one that spans the
    robot's body (``body_gap[i]``: the body's shadow lies between points ``i - 1`` and
    ``i``) cut there unless the wall stands on both sides: each run of its points between
    shadows holds ``min_segment_points`` points and spans ``min_segment_length_m`` (first to
    last point), as a segment must. Two short runs (a few beams beside the shadow, a sliver
    at the edge of the view) always fit one line, seen or not, and the line would reach
    across the hidden span on their say alone. Pieces cut to fewer than
    ``min_segment_points`` points are dropped, as :func:`split_and_merge` drops them; the
    rest meet :func:`line_segments`'s length test as any segment."""
    out = np.empty((segments.shape[0] + points.shape[0], 2), dtype=np.int64)
    n = 0
    for k in range(segments.shape[0]):
        start, stop = segments[k, 0], segments[k, 1]
        run_start, piece_start = start, start
        for i in range(start + 1, stop + 1):
            if i < stop and not body_gap[i]:
                continue
            # points [run_start, i) are a run between shadows (or the segment's ends)
            length = math.hypot(
                points[i - 1, 0] - points[run_start, 0], points[i - 1, 1] - points[run_start, 1]
            )
            if i - run_start < s.min_segment_points or length < s.min_segment_length_m:
                # cut on both sides of the short run: the pieces before it and the run itself
                for lo, hi in ((piece_start, run_start), (run_start, i)):
                    if hi - lo >= s.min_segment_points:
                        out[n, 0], out[n, 1] = lo, hi
                        n += 1
                piece_start = i
            run_start = i
        if stop - piece_start >= s.min_segment_points:
            out[n, 0], out[n, 1] = piece_start, stop
            n += 1
    return out[:n]


def line_segments(beams: BeamPoints, cfg: FeatureConfig) -> Segments:
    """Line segments of a scan with their maximum-likelihood lines (docs/design.md steps 2-3).

    Segments from :func:`segment_point_ranges`, lines by weighted total least squares
    (:func:`iceg.features.lines.fit_lines`, Pfister et al. 2003); segments shorter than
    ``cfg.min_segment_length_m`` between their projected endpoints (Nguyen et al. 2005,
    L_min) are dropped.

    Args:
        beams: The scan's points; at least one.
        cfg: Segmentation thresholds, ``sigma_bearing_deg`` and ``min_segment_length_m``.

    Returns:
        :class:`Segments` (M may be 0).
    """
    seg_range = segment_point_ranges(beams, cfg)
    lines, seg_cov, endpoints = fit_lines(
        beams.points,
        beams.point_ranges,
        beams.dirs[beams.valid],
        seg_range,
        cfg.sigma_range_m,
        math.radians(cfg.sigma_bearing_deg),
        cfg.line_variance_from_residuals,
    )
    angles = beams.angles
    dphi = (angles[-1] - angles[0]) / max(angles.shape[0] - 1, 1)
    cos_max_inc = math.cos(math.radians(cfg.eow_max_incidence_deg))
    return Segments(
        *_kept_segments(
            seg_range,
            lines,
            seg_cov,
            endpoints,
            beams.beam_index,
            beams.ranges,
            beams.dirs,
            _FrameSettings(cfg.min_segment_length_m, float(dphi), cos_max_inc),
        )
    )


class _FrameSettings(NamedTuple):
    """:func:`_kept_segments`' settings."""

    min_length_m: float  # shortest segment kept, between its projected endpoints
    beam_step_rad: float  # the scan's mean beam step
    cos_max_incidence: float  # cosine of eow_max_incidence_deg


@njit(cache=True, nogil=True)
def _kept_segments(
    seg_range: IntArray,
    lines: FloatArray,
    cov: FloatArray,
    endpoints: FloatArray,
    beam_index: IntArray,
    ranges: FloatArray,
    dirs: FloatArray,
    settings: _FrameSettings,
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray, IntArray, FloatArray, FloatArray]:
    """The fields of :class:`Segments` for the fitted segments at least
    ``settings.min_length_m`` long between their projected endpoints. The along-wall distance
    between consecutive beams at an endpoint is ``r dphi / max(|cos incidence|,
    cos(eow_max_incidence_deg))``, ``r`` the endpoint beam's range, ``dphi`` the mean beam
    step and the incidence measured from the wall normal (at grazing incidence consecutive
    beams land far apart, so gaps near an endpoint scale with it)."""
    min_length, dphi, cos_max_inc = settings
    m = seg_range.shape[0]
    keep = np.empty(m, dtype=np.bool_)
    for k in range(m):
        dx = endpoints[k, 1, 0] - endpoints[k, 0, 0]
        dy = endpoints[k, 1, 1] - endpoints[k, 0, 1]
        keep[k] = math.hypot(dx, dy) >= min_length
    seg_range, lines, cov, endpoints = seg_range[keep], lines[keep], cov[keep], endpoints[keep]
    n = seg_range.shape[0]
    normals = np.empty((n, 2))
    end_beam = np.empty((n, 2), dtype=np.int64)
    spacing = np.empty((n, 2))
    for k in range(n):
        normals[k, 0], normals[k, 1] = math.cos(lines[k, 0]), math.sin(lines[k, 0])
        end_beam[k, 0] = beam_index[seg_range[k, 0]]
        end_beam[k, 1] = beam_index[seg_range[k, 1] - 1]
        for e in range(2):
            b = end_beam[k, e]
            cos_inc = abs(dot2(normals[k, 0], normals[k, 1], dirs[b, 0], dirs[b, 1]))
            spacing[k, e] = (
                ranges[b] * dphi / (cos_inc if not cos_inc < cos_max_inc else cos_max_inc)
            )
    return seg_range, lines, cov, endpoints, end_beam, spacing, normals
