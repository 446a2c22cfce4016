"""Plane geometry of lines in Hessian form over stacks (features, steps 3-4).

Lines are ``n·p = rho`` with ``n = (cos alpha, sin alpha)``, stored as ``(alpha_rad, rho_m)``
rows; points are ``(x, y)`` metres in the robot frame of the scan. Covariances are of
``(alpha, rho)`` (rad², rad·m, m²) or of ``(x, y)`` (m²).

:func:`meet`, :func:`sandwich` and :func:`line_intersections` are compiled (issue 13): the
feature stages' kernels call them row by row, and each gives the bits of the numpy
expressions it replaced (``np.einsum``'s order of sums, :func:`dot2`).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from iceg_common.numba_loading import njit

FloatArray = NDArray[np.float64]


@njit(cache=True, nogil=True)
def dot2(a0: float, a1: float, b0: float, b1: float) -> float:
    """``a0 b0 + a1 b1`` as ``np.einsum`` sums two products (from +0.0: a -0.0 sum is
    +0.0), so a kernel's dot product has the bits of the numpy expression it replaced."""
    return a0 * b0 + a1 * b1 + 0.0


@njit(cache=True, nogil=True, error_model="numpy")
def meet(lines_a: FloatArray, lines_b: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Meeting points of line pairs and their Jacobians with respect to each line.

    Lines ``n_k·p = rho_k`` with ``n_k = (cos alpha_k, sin alpha_k)``; with ``N = [n_a; n_b]``
    the point is ``p = N^-1 (rho_a, rho_b)``. Perturbing ``alpha_k`` and ``rho_k`` gives
    ``N dp = (d rho_a - (t_a·p) d alpha_a, d rho_b - (t_b·p) d alpha_b)`` with ``t_k = (-sin
    alpha_k, cos alpha_k)``, so ``J_a = N^-1[:, 0] (-(t_a·p), 1)`` and likewise ``J_b``.

    Args:
        lines_a, lines_b: ``(Q, 2)`` float64 ``(alpha_rad, rho_m)``; not parallel (parallel
            lines give non-finite values, no error).

    Returns:
        ``xy`` ``(Q, 2)`` float64 metres; ``J_a``, ``J_b`` ``(Q, 2, 2)`` float64
        ``d xy / d (alpha, rho)`` of each line.
    """
    q = lines_a.shape[0]
    xy = np.empty((q, 2))
    ja = np.empty((q, 2, 2))
    jb = np.empty((q, 2, 2))
    for r in range(q):
        ca, sa = math.cos(lines_a[r, 0]), math.sin(lines_a[r, 0])
        cb, sb = math.cos(lines_b[r, 0]), math.sin(lines_b[r, 0])
        inv_det = 1.0 / (ca * sb - sa * cb)
        # N^-1 = [[sb, -sa], [-cb, ca]] / det: its columns
        col_a0, col_a1 = sb * inv_det, -cb * inv_det
        col_b0, col_b1 = -sa * inv_det, ca * inv_det
        x = col_a0 * lines_a[r, 1] + col_b0 * lines_b[r, 1]
        y = col_a1 * lines_a[r, 1] + col_b1 * lines_b[r, 1]
        xy[r, 0], xy[r, 1] = x, y
        ta = sa * x - ca * y  # -(t_a·p)
        tb = sb * x - cb * y
        ja[r, 0, 0], ja[r, 0, 1] = col_a0 * ta, col_a0
        ja[r, 1, 0], ja[r, 1, 1] = col_a1 * ta, col_a1
        jb[r, 0, 0], jb[r, 0, 1] = col_b0 * tb, col_b0
        jb[r, 1, 0], jb[r, 1, 1] = col_b1 * tb, col_b1
    return xy, ja, jb


@njit(cache=True, nogil=True)
def sandwich(j: FloatArray, c: FloatArray) -> FloatArray:
    """``J C J^T`` for stacks: ``j`` and ``c`` ``(Q, 2, 2)`` float64, result ``(Q, 2, 2)``;
    each entry summed as ``np.einsum("qij,qjk,qlk->qil", j, c, j)`` sums it (over ``k`` for
    each ``j``, then over ``j``, each sum from +0.0)."""
    out = np.empty((j.shape[0], 2, 2))
    for r in range(j.shape[0]):
        for i in range(2):
            for m in range(2):
                total = 0.0
                for a in range(2):
                    inner = 0.0
                    for b in range(2):
                        inner += j[r, i, a] * c[r, a, b] * j[r, m, b]
                    total += inner
                out[r, i, m] = total
    return out


@njit(cache=True, nogil=True, error_model="numpy")
def line_intersections(
    lines_a: FloatArray, cov_a: FloatArray, lines_b: FloatArray, cov_b: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Meeting points of line pairs (see :func:`meet`) and their covariance
    ``J_a C_a J_a^T + J_b C_b J_b^T`` (first-order propagation; the two lines are fitted to
    disjoint points, hence independent).

    Args:
        lines_a, lines_b: ``(Q, 2)`` float64 ``(alpha_rad, rho_m)``.
        cov_a, cov_b: ``(Q, 2, 2)`` float64 covariances of the lines' ``(alpha, rho)``.

    Returns:
        ``xy`` ``(Q, 2)`` float64 metres and ``cov`` ``(Q, 2, 2)`` float64 m².
    """
    xy, ja, jb = meet(lines_a, lines_b)
    return xy, sandwich(ja, cov_a) + sandwich(jb, cov_b)


def norm(v: FloatArray) -> FloatArray:
    """Euclidean norm over the last axis of ``(..., 2)`` vectors (cheaper than linalg.norm)."""
    return np.hypot(v[..., 0], v[..., 1])
