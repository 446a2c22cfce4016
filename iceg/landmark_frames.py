"""The feature map's geometry moved between node frames, compiled (issue 13).

A reference for a match gathers every landmark and segment of its nodes into one frame, and
an update moves a matched observation into its landmark's anchor frame: per row a rotation
and a translation of points, direction vectors and 2 x 2 covariances (Hessian lines move by
:func:`~iceg.matching.geometry.transform_lines`, compiled as well). In numpy that is a dozen
calls on ``(n, 2, 2)`` temporaries per gather (``rotation_matrix``, ``einsum``, stacked
``matmul``), 50-250 us for the few dozen to few hundred rows of a reference; these loops do
it in one pass. The arithmetic is that of the numpy expressions (``R p + t``, ``R C R^T``),
so the results agree to rounding (``tests/iceg/test_feature_map.py``). The rows' anchor
poses in the gather's frame (:func:`poses_in_frame`) are ``se2.between`` of the gathered rows
in one pass, the same bits.

Every pose is ``[x_m, y_m, theta_rad]`` of the source frame in the target frame, one per
row.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from iceg_common import se2


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
    ax, ay, at = se2.inverse(np.asarray(frame, dtype=np.float64).reshape(3)).tolist()
    return _compose_rows(  # type: ignore[no-any-return]
        ax,
        ay,
        at,
        math.cos(at),
        math.sin(at),
        np.ascontiguousarray(poses, dtype=np.float64),
        np.asarray(rows, dtype=np.int64),
    )


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


__all__ = ["move_features", "move_point_blocks", "move_points", "poses_in_frame"]
