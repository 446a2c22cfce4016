"""Maximum-likelihood line fitting in Hessian form with covariances, vectorized over segments.

docs/design.md "ICE matching, step by step", step 3. Each segment's points are fitted by weighted
total least squares, the weights being the inverse variances of the points' distances to
the line under a range/bearing noise model (Pfister, Roumeliotis & Burdick 2003, "Weighted
line fitting algorithms for mobile robot map building and efficient data representation";
closed form of Arras & Siegwart 1997). All segments are fitted at once with segment-wise
sums (``np.add.reduceat``).
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# A point's distance variance is floored at this fraction of sigma_range² (a beam exactly
# along the line with no bearing noise would otherwise get an infinite weight).
VARIANCE_FLOOR_FRACTION = 1e-6


def _moments(
    x: FloatArray, y: FloatArray, w: FloatArray, offsets: IntArray, seg_of: IntArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """Weighted sums per segment: ``W, mean_x, mean_y, Sxx, Syy, Sxy`` (central moments)."""
    sw = np.add.reduceat(w, offsets)
    mx = np.add.reduceat(w * x, offsets) / sw
    my = np.add.reduceat(w * y, offsets) / sw
    dx = x - mx[seg_of]
    dy = y - my[seg_of]
    wdx = w * dx
    sxx = np.add.reduceat(wdx * dx, offsets)
    syy = np.add.reduceat(w * dy * dy, offsets)
    sxy = np.add.reduceat(wdx * dy, offsets)
    return sw, mx, my, sxx, syy, sxy


def fit_lines(
    points_xy: FloatArray,
    ranges_m: FloatArray,
    beam_dirs: FloatArray,
    seg_point_range: IntArray,
    sigma_range_m: float,
    sigma_bearing_rad: float,
    variance_from_residuals: bool = False,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Fit a line ``(alpha, rho)`` with its covariance to each segment's points.

    Model: point ``i`` is measured along its beam direction ``u_i`` with range variance
    ``sigma_r²`` and across it with ``(r_i sigma_phi)²``, so its distance to a line of normal
    ``n`` has variance ``s_i² = sigma_r² (u_i·n)² + (r_i sigma_phi)² (1 - (u_i·n)²)``
    (Pfister et al. 2003, eq. 4-6). An unweighted total-least-squares fit gives ``n``; the
    weights ``w_i = 1 / s_i²`` then give the maximum-likelihood line by weighted total least
    squares, ``alpha = atan2(-2 Sxy, Syy - Sxx) / 2`` about the weighted centroid ``c`` and
    ``rho = n·c`` (Arras & Siegwart 1997). Its first-order covariance: the angle has variance
    ``1 / sum w_i t_i²`` (``t_i`` the points' coordinates along the line from ``c``), the
    offset at ``c`` has ``1 / sum w_i``, they are uncorrelated, and ``d rho / d alpha =
    (-sin alpha, cos alpha)·c``.

    With ``variance_from_residuals`` the covariances are scaled by the scan's a-posteriori
    variance factor (the estimated variance of unit weight of a least-squares adjustment):
    ``s0² = sum_i w_i d_i² / sum_m (n_m - 2)`` over all segments (``d_i`` a point's distance
    to its fitted line, ``n_m`` a segment's points), floored at 1. Where the scanner is
    noisier than ``sigma_range_m`` says, or its walls are not straight, the residuals say so
    and every line (and the features built from them) is as uncertain as the scan shows;
    the configured noise remains the floor.

    Args:
        points_xy: ``(P, 2)`` float64 valid beam endpoints, metres, robot frame.
        ranges_m: ``(P,)`` float64 their ranges, metres.
        beam_dirs: ``(P, 2)`` float64 unit beam directions in the robot frame.
        seg_point_range: ``(M, 2)`` int64 ``[start, stop)`` point ranges, each with >= 2
            points, in increasing order and not overlapping.
        sigma_range_m: Range noise standard deviation, metres.
        sigma_bearing_rad: Bearing noise standard deviation, radians.
        variance_from_residuals: Scale the covariances by the variance factor ``max(1,
            s0²)`` (above).

    Returns:
        ``lines`` ``(M, 2)`` float64 ``(alpha_rad, rho_m)`` with ``rho >= 0`` and ``alpha`` in
        ``(-pi, pi]``; ``cov`` ``(M, 2, 2)`` float64 covariance of ``(alpha, rho)``;
        ``endpoints`` ``(M, 2, 2)`` float64: the first and last points projected on the line.
    """
    m = seg_point_range.shape[0]
    if m == 0:
        return np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2, 2))
    idx, offsets, seg_of = _segment_points(seg_point_range)
    x = points_xy[idx, 0]
    y = points_xy[idx, 1]
    # Pass 1: unweighted total least squares for the normal direction.
    _, _, _, sxx, syy, sxy = _moments(x, y, np.ones_like(x), offsets, seg_of)
    alpha0 = 0.5 * np.arctan2(-2.0 * sxy, syy - sxx)
    w = _weights(beam_dirs[idx], ranges_m[idx], alpha0, seg_of, (sigma_range_m, sigma_bearing_rad))
    # Pass 2: weighted total least squares (maximum likelihood).
    sw, mx, my, sxx, syy, sxy = _moments(x, y, w, offsets, seg_of)
    alpha, rho, ca, sa = _hessian_line(0.5 * np.arctan2(-2.0 * sxy, syy - sxx), mx, my)
    # Covariance: along-line second moment about the weighted centroid.
    t_along = -(x - mx[seg_of]) * sa[seg_of] + (y - my[seg_of]) * ca[seg_of]
    stt = np.add.reduceat(w * t_along * t_along, offsets)
    cov = _line_covariance(1.0 / stt, 1.0 / sw, -sa * mx + ca * my)
    if variance_from_residuals:
        dist_i = x * ca[seg_of] + y * sa[seg_of] - rho[seg_of]
        dof = int(np.sum(np.maximum(seg_point_range[:, 1] - seg_point_range[:, 0] - 2, 0)))
        if dof > 0:
            cov *= max(1.0, float(np.sum(w * dist_i * dist_i)) / dof)
    # Endpoints: first and last points projected onto the line.
    ends = points_xy[np.stack([seg_point_range[:, 0], seg_point_range[:, 1] - 1], axis=1)]
    normal = np.stack([ca, sa], axis=1)
    dist = np.einsum("mkj,mj->mk", ends, normal) - rho[:, None]
    endpoints = ends - dist[..., None] * normal[:, None, :]
    return np.stack([alpha, rho], axis=1), cov, endpoints


def _segment_points(seg_point_range: IntArray) -> tuple[IntArray, IntArray, IntArray]:
    """Point indices of all segments concatenated ``(S,)``, each segment's offset in them
    ``(M,)`` and each concatenated point's segment ``(S,)`` (int64)."""
    m = seg_point_range.shape[0]
    starts = seg_point_range[:, 0]
    lengths = seg_point_range[:, 1] - starts
    offsets = np.zeros(m, dtype=np.int64)
    np.cumsum(lengths[:-1], out=offsets[1:])
    seg_of = np.repeat(np.arange(m), lengths)
    idx = np.arange(int(lengths.sum())) - offsets[seg_of] + starts[seg_of]
    return idx, offsets, seg_of


def _weights(
    dirs: FloatArray,
    ranges_m: FloatArray,
    alpha: FloatArray,
    seg_of: IntArray,
    sigmas: tuple[float, float],
) -> FloatArray:
    """Inverse variances ``1 / s_i²`` of the points' distances to their segment's line of
    normal angle ``alpha`` ``(M,)`` (Pfister et al. 2003, eq. 4-6): ``dirs`` ``(S, 2)``,
    ``ranges_m`` and ``seg_of`` ``(S,)``, ``sigmas`` (range m, bearing rad); ``(S,)``."""
    sigma_r, sigma_phi = sigmas
    cos_b = dirs[:, 0] * np.cos(alpha)[seg_of] + dirs[:, 1] * np.sin(alpha)[seg_of]
    cos2 = cos_b * cos_b
    var = sigma_r**2 * cos2 + (ranges_m * sigma_phi) ** 2 * (1.0 - cos2)
    w: FloatArray = 1.0 / np.maximum(var, VARIANCE_FLOOR_FRACTION * sigma_r**2)
    return w


def _hessian_line(
    alpha: FloatArray, mx: FloatArray, my: FloatArray
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """The line of normal angle ``alpha`` through centroids ``(mx, my)`` in Hessian form with
    ``rho >= 0`` and ``alpha`` in ``(-pi, pi]``: ``alpha, rho, cos alpha, sin alpha`` ``(M,)``."""
    ca, sa = np.cos(alpha), np.sin(alpha)
    rho = ca * mx + sa * my
    flip = rho < 0.0
    alpha = np.where(flip, alpha + np.pi, alpha)
    alpha = np.where(alpha > np.pi, alpha - 2.0 * np.pi, alpha)
    ca = np.where(flip, -ca, ca)
    sa = np.where(flip, -sa, sa)
    return alpha, np.abs(rho), ca, sa


def _line_covariance(var_alpha: FloatArray, var_off: FloatArray, drho: FloatArray) -> FloatArray:
    """``(M, 2, 2)`` covariance of ``(alpha, rho)`` from the angle variance, the offset
    variance at the centroid and ``d rho / d alpha`` (all ``(M,)``; Arras & Siegwart 1997)."""
    cov = np.empty((var_alpha.shape[0], 2, 2))
    cov[:, 0, 0] = var_alpha
    cov[:, 0, 1] = var_alpha * drho
    cov[:, 1, 0] = cov[:, 0, 1]
    cov[:, 1, 1] = var_alpha * drho * drho + var_off
    return cov
