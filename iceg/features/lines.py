"""Maximum-likelihood line fitting in Hessian form with covariances, vectorized over segments.

docs/design.md "ICE matching, step by step", step 3. Each segment's points are fitted by weighted
total least squares, the weights being the inverse variances of the points' distances to
the line under a range/bearing noise model (Pfister, Roumeliotis & Burdick 2003, "Weighted
line fitting algorithms for mobile robot map building and efficient data representation";
closed form of Arras & Siegwart 1997). One compiled pass over the segments (issue 13) whose
sums take numpy's order (:mod:`iceg.numpy_sums`): the results are those of the earlier
vectorized numpy fit (segment-wise ``np.add.reduceat`` sums) bit for bit.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import NDArray

from iceg.features.geometry import dot2
from iceg.numpy_sums import pairwise_sum
from iceg_common.numba_loading import njit

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

# A point's distance variance is floored at this fraction of sigma_range² (a beam exactly
# along the line with no bearing noise would otherwise get an infinite weight).
VARIANCE_FLOOR_FRACTION = 1e-6


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
    if seg_point_range.shape[0] == 0:
        return np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2, 2))
    return _fit_lines(
        np.ascontiguousarray(points_xy, dtype=np.float64),
        np.ascontiguousarray(ranges_m, dtype=np.float64),
        np.ascontiguousarray(beam_dirs, dtype=np.float64),
        np.ascontiguousarray(seg_point_range, dtype=np.int64),
        sigma_range_m**2,
        VARIANCE_FLOOR_FRACTION * sigma_range_m**2,
        float(sigma_bearing_rad),
        bool(variance_from_residuals),
    )


@njit(cache=True, nogil=True)
def _segment_sum(a: FloatArray, start: int, stop: int) -> float:
    """``a[start:stop]`` summed as ``np.add.reduceat`` sums a segment (its first term plus
    numpy's pairwise sum of the others), so the kernel's sums have numpy's bits."""
    return a[start] + pairwise_sum(a, start + 1, stop - start - 1)


@njit(cache=True, nogil=True)
def _moments(
    x: FloatArray, y: FloatArray, w: FloatArray, start: int, stop: int, buf: FloatArray
) -> tuple[float, float, float, float, float, float]:
    """Weighted sums of one segment's points ``[start, stop)``: ``W, mean_x, mean_y, Sxx,
    Syy, Sxy`` (central moments), each term formed as the numpy expressions of the earlier
    vectorized fit formed it (``w * dx * dx`` is ``(w * dx) * dx``); ``buf`` is scratch of
    at least ``stop`` entries."""
    sw = _segment_sum(w, start, stop)
    for i in range(start, stop):
        buf[i] = w[i] * x[i]
    mx = _segment_sum(buf, start, stop) / sw
    for i in range(start, stop):
        buf[i] = w[i] * y[i]
    my = _segment_sum(buf, start, stop) / sw
    for i in range(start, stop):
        dx = x[i] - mx
        buf[i] = w[i] * dx * dx
    sxx = _segment_sum(buf, start, stop)
    for i in range(start, stop):
        dy = y[i] - my
        buf[i] = w[i] * dy * dy
    syy = _segment_sum(buf, start, stop)
    for i in range(start, stop):
        buf[i] = w[i] * (x[i] - mx) * (y[i] - my)
    sxy = _segment_sum(buf, start, stop)
    return sw, mx, my, sxx, syy, sxy


@njit(cache=True, nogil=True)
def _fit_lines(
    points_xy: FloatArray,
    ranges_m: FloatArray,
    beam_dirs: FloatArray,
    seg_point_range: IntArray,
    var_range: float,
    var_floor: float,
    sigma_bearing_rad: float,
    variance_from_residuals: bool,
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """:func:`fit_lines` of ``M >= 1`` segments, compiled: ``var_range`` is ``sigma_range_m
    ** 2`` and ``var_floor`` the floor of a point's distance variance (both as Python
    computes them). Segment by segment, each sum in numpy's order (:func:`_segment_sum`),
    so the results are those of the vectorized numpy fit bit for bit."""
    m = seg_point_range.shape[0]
    n_pts = points_xy.shape[0]
    x = np.ascontiguousarray(points_xy[:, 0])
    y = np.ascontiguousarray(points_xy[:, 1])
    ones = np.ones(n_pts)
    w = np.empty(n_pts)
    buf = np.empty(n_pts)
    resid = np.empty(n_pts)
    lines = np.empty((m, 2))
    cov = np.empty((m, 2, 2))
    endpoints = np.empty((m, 2, 2))
    n_resid = 0
    dof = 0
    for k in range(m):
        start, stop = seg_point_range[k, 0], seg_point_range[k, 1]
        # Pass 1: unweighted total least squares for the normal direction.
        _, _, _, sxx, syy, sxy = _moments(x, y, ones, start, stop, buf)
        alpha0 = 0.5 * math.atan2(-2.0 * sxy, syy - sxx)
        c0, s0 = math.cos(alpha0), math.sin(alpha0)
        for i in range(start, stop):
            cos_b = beam_dirs[i, 0] * c0 + beam_dirs[i, 1] * s0
            cos2 = cos_b * cos_b
            across = ranges_m[i] * sigma_bearing_rad
            var = var_range * cos2 + across * across * (1.0 - cos2)
            w[i] = 1.0 / (var if not var < var_floor else var_floor)
        # Pass 2: weighted total least squares (maximum likelihood), in Hessian form.
        sw, mx, my, sxx, syy, sxy = _moments(x, y, w, start, stop, buf)
        alpha = 0.5 * math.atan2(-2.0 * sxy, syy - sxx)
        ca, sa = math.cos(alpha), math.sin(alpha)
        rho = ca * mx + sa * my
        if rho < 0.0:
            alpha += math.pi
            ca, sa = -ca, -sa
        if alpha > math.pi:
            alpha -= 2.0 * math.pi
        rho = abs(rho)
        # Covariance: along-line second moment about the weighted centroid.
        for i in range(start, stop):
            t = -(x[i] - mx) * sa + (y[i] - my) * ca
            buf[i] = w[i] * t * t
        var_alpha = 1.0 / _segment_sum(buf, start, stop)
        drho = -sa * mx + ca * my
        cov[k, 0, 0] = var_alpha
        cov[k, 0, 1] = var_alpha * drho
        cov[k, 1, 0] = cov[k, 0, 1]
        cov[k, 1, 1] = var_alpha * drho * drho + 1.0 / sw
        if variance_from_residuals:
            for i in range(start, stop):
                d = x[i] * ca + y[i] * sa - rho
                resid[n_resid] = w[i] * d * d
                n_resid += 1
            dof += max(stop - start - 2, 0)
        lines[k, 0] = alpha
        lines[k, 1] = rho
        # Endpoints: first and last points projected onto the line.
        for e in range(2):
            p = start if e == 0 else stop - 1
            d = dot2(points_xy[p, 0], points_xy[p, 1], ca, sa) - rho
            endpoints[k, e, 0] = points_xy[p, 0] - d * ca
            endpoints[k, e, 1] = points_xy[p, 1] - d * sa
    if variance_from_residuals and dof > 0:
        factor = pairwise_sum(resid, 0, n_resid) / dof
        if factor > 1.0:  # max(1.0, factor) as Python takes it (NaN: 1.0)
            cov *= factor
    return lines, cov, endpoints
