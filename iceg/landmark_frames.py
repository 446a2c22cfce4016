"""The feature map's geometry moved between node frames, compiled (issue 13).

A reference for a match gathers every landmark and segment of its nodes into one frame, and
an update moves a matched observation into its landmark's anchor frame: per row a rotation
and a translation of points, direction vectors and 2 x 2 covariances, and Hessian lines with
their covariances (:func:`move_lines`, also behind the matcher's
:func:`~iceg.matching.geometry.transform_lines`). In numpy that is a dozen calls on
``(n, 2, 2)`` temporaries per gather (``rotation_matrix``, ``einsum``, stacked ``matmul``),
50-250 us for the few dozen to few hundred rows of a reference; these loops do it in one
pass. The arithmetic is that of the numpy expressions (``R p + t``, ``R C R^T``),
so the results agree to rounding (``tests/iceg/test_feature_map.py``). The rows' anchor
poses in the gather's frame (:func:`poses_in_frame`) are ``se2.between`` of the gathered rows
in one pass, the same bits.

Every pose is ``[x_m, y_m, theta_rad]`` of the source frame in the target frame, one per
row.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from iceg_common import se2
from iceg_common.numba_loading import njit


@njit(cache=True, nogil=True)
def move_features(
    rows: np.ndarray,
    poses: np.ndarray,
    xy: np.ndarray,
    cov: np.ndarray,
    dirs: np.ndarray,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Point features ``rows`` moved by ``poses``.

    Args:
        rows: ``(n,)`` int64 rows of the feature arrays.
        poses: ``(n, 3)`` float64 the pose of each row's frame in the target frame.
        xy: ``(N, 2)`` float64 positions (metres); ``cov`` ``(N, 2, 2)`` their covariances;
            ``dirs`` ``(N, k, 2)`` direction vectors (NaN rows stay NaN).

    Returns:
        ``(n, 2)`` positions ``R p + t``, ``(n, 2, 2)`` covariances ``R C R^T`` and
        ``(n, k, 2)`` directions ``R d``, in the target frame.
    """
    n = rows.shape[0]
    k = dirs.shape[1]
    out_xy = np.empty((n, 2))
    out_cov = np.empty((n, 2, 2))
    out_dirs = np.empty((n, k, 2))
    th, c, s = np.nan, 1.0, 0.0
    for i in range(n):
        r = rows[i]
        if poses[i, 2] != th:  # rows of one anchor share its pose
            th = poses[i, 2]
            c, s = math.cos(th), math.sin(th)
        out_xy[i, 0] = c * xy[r, 0] - s * xy[r, 1] + poses[i, 0]
        out_xy[i, 1] = s * xy[r, 0] + c * xy[r, 1] + poses[i, 1]
        # R C
        a00 = c * cov[r, 0, 0] - s * cov[r, 1, 0]
        a01 = c * cov[r, 0, 1] - s * cov[r, 1, 1]
        a10 = s * cov[r, 0, 0] + c * cov[r, 1, 0]
        a11 = s * cov[r, 0, 1] + c * cov[r, 1, 1]
        # (R C) R^T
        out_cov[i, 0, 0] = a00 * c - a01 * s
        out_cov[i, 0, 1] = a00 * s + a01 * c
        out_cov[i, 1, 0] = a10 * c - a11 * s
        out_cov[i, 1, 1] = a10 * s + a11 * c
        for j in range(k):
            out_dirs[i, j, 0] = c * dirs[r, j, 0] - s * dirs[r, j, 1]
            out_dirs[i, j, 1] = s * dirs[r, j, 0] + c * dirs[r, j, 1]
    return out_xy, out_cov, out_dirs


@njit(cache=True, nogil=True)
def move_points(poses: np.ndarray, pts: np.ndarray, translate: bool) -> np.ndarray:
    """Points ``pts`` ``(n, k, 2)`` (metres; NaN stays NaN) rotated by ``poses`` ``(n, 3)``
    and, with ``translate``, moved by their translations (direction vectors: without):
    ``(n, k, 2)`` float64 in the target frame."""
    n, k = pts.shape[0], pts.shape[1]
    out = np.empty((n, k, 2))
    th, c, s = np.nan, 1.0, 0.0
    for i in range(n):
        if poses[i, 2] != th:  # rows of one frame share its pose
            th = poses[i, 2]
            c, s = math.cos(th), math.sin(th)
        tx = poses[i, 0] if translate else 0.0
        ty = poses[i, 1] if translate else 0.0
        for j in range(k):
            out[i, j, 0] = c * pts[i, j, 0] - s * pts[i, j, 1] + tx
            out[i, j, 1] = s * pts[i, j, 0] + c * pts[i, j, 1] + ty
    return out


@njit(cache=True, nogil=True)
def move_point_blocks(poses: np.ndarray, counts: np.ndarray, pts: np.ndarray) -> np.ndarray:
    """Consecutive blocks of points, each moved by its own pose: :func:`move_points` of
    ``pts`` with each pose repeated over its block, the same bits, without the repeat.

    Args:
        poses: ``(n, 3)`` float64 the pose of each block's frame in the target frame.
        counts: ``(n,)`` int64 points in each block, summing to ``P``.
        pts: ``(P, 2)`` float64 the blocks' points, one after the other, metres.

    Returns:
        ``(P, 2)`` float64 ``R p + t`` in the target frame.
    """
    out = np.empty((pts.shape[0], 2))
    j = 0
    for i in range(poses.shape[0]):
        c, s = math.cos(poses[i, 2]), math.sin(poses[i, 2])
        tx, ty = poses[i, 0], poses[i, 1]
        for _ in range(counts[i]):
            out[j, 0] = c * pts[j, 0] - s * pts[j, 1] + tx
            out[j, 1] = s * pts[j, 0] + c * pts[j, 1] + ty
            j += 1
    return out


@njit(cache=True, nogil=True)
def move_lines(
    rows: np.ndarray, poses: np.ndarray, lines: np.ndarray, cov: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Hessian lines ``rows`` of ``lines`` ``(N, 2)`` ``(alpha_rad, rho_m)`` and their
    covariances ``cov`` ``(N, 2, 2)`` moved by ``poses`` ``(n, 3)`` (each row's frame in the
    target frame): ``alpha' = alpha + theta``, ``rho' = rho + (cos alpha', sin alpha') . t``,
    flipped to keep ``rho' >= 0`` (``alpha'`` then wrapped to ``[-pi, pi)``); the covariance
    by the Jacobian ``[[1, 0], [d rho'/d alpha, 1]]`` (its second row negated by a flip).
    Returns ``(n, 2)`` lines and ``(n, 2, 2)`` covariances (float64)."""
    n = rows.shape[0]
    out_lines = np.empty((n, 2))
    out_cov = np.empty((n, 2, 2))
    for i in range(n):
        r = rows[i]
        x, y = poses[i, 0], poses[i, 1]
        a = lines[r, 0] + poses[i, 2]
        ca = math.cos(a)
        sa = math.sin(a)
        rho = lines[r, 1] + ca * x + sa * y
        j10 = -sa * x + ca * y
        j11 = 1.0
        if rho < 0.0:
            a += math.pi
            rho = -rho
            j10 = -j10
            j11 = -1.0
        out_lines[i, 0] = (a + math.pi) % (2.0 * math.pi) - math.pi
        out_lines[i, 1] = rho
        # J C J^T with J = [[1, 0], [j10, j11]]
        c00, c01, c10, c11 = cov[r, 0, 0], cov[r, 0, 1], cov[r, 1, 0], cov[r, 1, 1]
        b10 = j10 * c00 + j11 * c10
        b11 = j10 * c01 + j11 * c11
        out_cov[i, 0, 0] = c00
        out_cov[i, 0, 1] = c00 * j10 + c01 * j11
        out_cov[i, 1, 0] = b10
        out_cov[i, 1, 1] = b10 * j10 + b11 * j11
    return out_lines, out_cov


class FeatureRows(NamedTuple):
    """Point features' columns as a replacement (:func:`keep_better`) reads a scan's (its
    frame) and reads and writes the landmark table's (each anchor's frame; the
    ``_Landmarks`` arrays of the same names, written in place).

    Attributes:
        xy: ``(K, 2)`` float64 positions, metres; ``cov`` ``(K, 2, 2)`` their covariances.
        dirs: ``(K, 2, 2)`` float64 direction vectors (NaN rows: none).
        opening: ``(K,)`` float64 opening angles, radians; ``kind`` ``(K,)`` int64 kinds.
        support: ``(K, 3, 2)``, ``wall_p``, ``wall_d`` ``(K, 2, 2)`` float64 the
            visibility geometry (``feature_map._geometry``), metres.
    """

    xy: np.ndarray
    cov: np.ndarray
    dirs: np.ndarray
    opening: np.ndarray
    kind: np.ndarray
    support: np.ndarray
    wall_p: np.ndarray
    wall_d: np.ndarray


@njit(cache=True, nogil=True)
def keep_better(
    pair_new: np.ndarray,
    pair_row: np.ndarray,
    anchor_in_new: np.ndarray,
    rank: np.ndarray,
    replace_ratio: float,
    obs: FeatureRows,
    lm: FeatureRows,
    lm_wall_side: np.ndarray,
) -> None:
    """Replace each paired landmark's stored observation by the new one where it is better
    (``FeatureMap._keep_better``), in place, in one pass: the numpy expressions' bits.

    A new observation replaces a landmark when it ranks higher (``rank`` by kind: an EOW seen
    as a Corner) or, of the same kind, when its covariance trace is below ``replace_ratio``
    of the stored one (all pairs judged before any is replaced). The replacement is the
    observation moved into the anchor's frame (``se2.inverse`` of the anchor's pose in the
    new node's frame; :func:`move_features` and :func:`move_points`), with the side of each
    wall the new node saw it from (``np.sign``: +1, -1, +0.0, NaN).

    Args:
        pair_new: ``(Q,)`` int64 new features; ``pair_row`` ``(Q,)`` int64 their landmark rows.
        anchor_in_new: ``(Q, 3)`` float64 each row's anchor pose in the new node's frame.
        rank: ``(3,)`` int64 rank of each kind.
        obs: The new scan's features; ``lm`` the landmarks' columns and ``lm_wall_side``
            ``(L, 2)`` float64 their walls' sides, both written.
    """
    n = pair_new.shape[0]
    better = np.zeros(n, dtype=np.bool_)
    for q in range(n):
        f, r = pair_new[q], pair_row[q]
        tr_new = obs.cov[f, 0, 0] + obs.cov[f, 1, 1]
        tr_old = lm.cov[r, 0, 0] + lm.cov[r, 1, 1]
        upgrade = rank[obs.kind[f]] > rank[lm.kind[r]]
        same = lm.kind[r] == obs.kind[f]
        better[q] = upgrade or (same and tr_new < replace_ratio * tr_old)
    for q in range(n):
        if not better[q]:
            continue
        f, r = pair_new[q], pair_row[q]
        # the new node in the anchor's frame: se2.inverse's expressions
        a = anchor_in_new[q]
        ca, sa = math.cos(a[2]), math.sin(a[2])
        ox = -(ca * a[0] + sa * a[1])
        oy = -(-sa * a[0] + ca * a[1])
        th = (-a[2] + math.pi) % (2.0 * math.pi) - math.pi
        c, s = math.cos(th), math.sin(th)
        lm.xy[r, 0] = c * obs.xy[f, 0] - s * obs.xy[f, 1] + ox
        lm.xy[r, 1] = s * obs.xy[f, 0] + c * obs.xy[f, 1] + oy
        a00 = c * obs.cov[f, 0, 0] - s * obs.cov[f, 1, 0]
        a01 = c * obs.cov[f, 0, 1] - s * obs.cov[f, 1, 1]
        a10 = s * obs.cov[f, 0, 0] + c * obs.cov[f, 1, 0]
        a11 = s * obs.cov[f, 0, 1] + c * obs.cov[f, 1, 1]
        lm.cov[r, 0, 0] = a00 * c - a01 * s
        lm.cov[r, 0, 1] = a00 * s + a01 * c
        lm.cov[r, 1, 0] = a10 * c - a11 * s
        lm.cov[r, 1, 1] = a10 * s + a11 * c
        for j in range(2):
            lm.dirs[r, j, 0] = c * obs.dirs[f, j, 0] - s * obs.dirs[f, j, 1]
            lm.dirs[r, j, 1] = s * obs.dirs[f, j, 0] + c * obs.dirs[f, j, 1]
        lm.opening[r] = obs.opening[f]
        lm.kind[r] = obs.kind[f]
        for j in range(3):
            lm.support[r, j, 0] = c * obs.support[f, j, 0] - s * obs.support[f, j, 1] + ox
            lm.support[r, j, 1] = s * obs.support[f, j, 0] + c * obs.support[f, j, 1] + oy
        for j in range(2):
            lm.wall_p[r, j, 0] = c * obs.wall_p[f, j, 0] - s * obs.wall_p[f, j, 1] + ox
            lm.wall_p[r, j, 1] = s * obs.wall_p[f, j, 0] + c * obs.wall_p[f, j, 1] + oy
            # a direction moves without the translation (move_points adds 0.0)
            lm.wall_d[r, j, 0] = c * obs.wall_d[f, j, 0] - s * obs.wall_d[f, j, 1] + 0.0
            lm.wall_d[r, j, 1] = s * obs.wall_d[f, j, 0] + c * obs.wall_d[f, j, 1] + 0.0
            side = lm.wall_d[r, j, 0] * (oy - lm.wall_p[r, j, 1]) - lm.wall_d[r, j, 1] * (
                ox - lm.wall_p[r, j, 0]
            )
            if side > 0.0:
                lm_wall_side[r, j] = 1.0
            elif side < 0.0:
                lm_wall_side[r, j] = -1.0
            elif side == 0.0:
                lm_wall_side[r, j] = 0.0
            else:
                lm_wall_side[r, j] = side  # NaN


def poses_in_frame(frame: np.ndarray, poses: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``se2.between(frame, poses[rows])`` in one compiled pass, the same bits (the same
    expressions in the same order, with the frame's inverse and its sine and cosine from
    :mod:`iceg_common.se2`): the anchors of a reference's rows in its frame.

    Args:
        frame: ``(3,)`` float64 the target frame's pose ``[x_m, y_m, theta_rad]``.
        poses: ``(N, 3)`` float64 poses in the frame ``frame`` is given in.
        rows: ``(n,)`` int64 rows of ``poses`` to express.

    Returns:
        ``(n, 3)`` float64 the rows' poses in the target frame, headings in ``[-pi, pi)``.
    """
    ax, ay, at, c, s = frame_inverse(frame).tolist()
    return _compose_rows(
        ax,
        ay,
        at,
        c,
        s,
        np.ascontiguousarray(poses, dtype=np.float64),
        np.asarray(rows, dtype=np.int64),
    )


def frame_inverse(frame: np.ndarray) -> np.ndarray:
    """The inverse of a frame's pose as :func:`poses_in_frame` composes with it: ``(5,)``
    float64 ``x_m, y_m, theta_rad`` of ``se2.inverse(frame)`` and that theta's cosine and
    sine (libm's, as numpy's), for the compiled passes that place rows in the frame.

    Args:
        frame: ``(3,)`` float64 the frame's pose ``[x_m, y_m, theta_rad]``.
    """
    pose = np.asarray(frame, dtype=np.float64).reshape(3)
    x, y, t = pose.tolist()
    if math.isfinite(t):  # se2.inverse's expressions for one pose, in floats
        c, s = math.cos(t), math.sin(t)
        ax, ay, at = -(c * x + s * y), -(-s * x + c * y), se2.wrap_float(-t)
    else:
        ax, ay, at = se2.inverse(pose).tolist()
    return np.array([ax, ay, at, math.cos(at), math.sin(at)])


@njit(cache=True, nogil=True)
def _compose_rows(
    ax: float, ay: float, at: float, c: float, s: float, poses: np.ndarray, rows: np.ndarray
) -> np.ndarray:
    """``a ∘ poses[rows]`` for ``a = (ax, ay, at)`` with ``c, s = cos at, sin at``: the
    expressions of ``se2.compose`` for one pose and a batch."""
    n = rows.shape[0]
    out = np.empty((n, 3))
    for i in range(n):
        r = rows[i]
        bx, by = poses[r, 0], poses[r, 1]
        out[i, 0] = ax + c * bx - s * by
        out[i, 1] = ay + s * bx + c * by
        out[i, 2] = (at + poses[r, 2] + math.pi) % (2.0 * math.pi) - math.pi
    return out


__all__ = [
    "FeatureRows",
    "frame_inverse",
    "keep_better",
    "move_features",
    "move_lines",
    "move_point_blocks",
    "move_points",
    "poses_in_frame",
]
