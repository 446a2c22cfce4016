"""Plane geometry of lines in Hessian form, vectorized over stacks (features, steps 3-4).

Lines are ``n·p = rho`` with ``n = (cos alpha, sin alpha)``, stored as ``(alpha_rad, rho_m)``
rows; points are ``(x, y)`` metres in the robot frame of the scan. Covariances are of
``(alpha, rho)`` (rad², rad·m, m²) or of ``(x, y)`` (m²).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]


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
    ca, sa = np.cos(lines_a[:, 0]), np.sin(lines_a[:, 0])
    cb, sb = np.cos(lines_b[:, 0]), np.sin(lines_b[:, 0])
    det = ca * sb - sa * cb
    # N^-1 = [[sb, -sa], [-cb, ca]] / det
    q = det.shape[0]
    inv_det = 1.0 / det
    col_a = np.empty((q, 2))
    col_a[:, 0] = sb * inv_det
    col_a[:, 1] = -cb * inv_det
    col_b = np.empty((q, 2))
    col_b[:, 0] = -sa * inv_det
    col_b[:, 1] = ca * inv_det
    xy = col_a * lines_a[:, 1:2] + col_b * lines_b[:, 1:2]
    ja = np.empty((q, 2, 2))
    ja[:, :, 0] = col_a * (sa * xy[:, 0] - ca * xy[:, 1])[:, None]  # -(t_a·p)
    ja[:, :, 1] = col_a
    jb = np.empty((q, 2, 2))
    jb[:, :, 0] = col_b * (sb * xy[:, 0] - cb * xy[:, 1])[:, None]
    jb[:, :, 1] = col_b
    return xy, ja, jb


def sandwich(j: FloatArray, c: FloatArray) -> FloatArray:
    """``J C J^T`` for stacks: ``j`` and ``c`` ``(Q, 2, 2)`` float64, result ``(Q, 2, 2)``."""
    return np.einsum("qij,qjk,qlk->qil", j, c, j)


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


def unit(v: FloatArray) -> FloatArray:
    """``(..., 2)`` vectors scaled to unit length (zero vectors give NaN, no error)."""
    return v / norm(v)[..., None]


def point_segment_distance(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distance of points ``p`` ``(Q, 2)`` to segments ``a``-``b`` ``(Q, 2)`` each, metres."""
    e = b - a
    s = np.clip(np.einsum("qi,qi->q", p - a, e) / np.einsum("qi,qi->q", e, e), 0.0, 1.0)
    return norm(p - (a + s[:, None] * e))


def max_eigenvalue(cov: FloatArray) -> FloatArray:
    """Largest eigenvalue of symmetric ``(Q, 2, 2)`` matrices, closed form; ``(Q,)``."""
    a = cov[:, 0, 0]
    d = cov[:, 1, 1]
    b = cov[:, 0, 1]
    return 0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b * b)


def opening_angle(ray_a: FloatArray, ray_b: FloatArray) -> FloatArray:
    """Angle between unit vectors ``(Q, 2)`` each, radians in ``[0, pi]``; ``(Q,)``."""
    return np.arccos(np.clip(np.einsum("ki,ki->k", ray_a, ray_b), -1.0, 1.0))
