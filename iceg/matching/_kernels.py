"""Compiled inner loop of the refinement (numba): point-to-segment association and the
generalised-least-squares normal equations of the point-to-line residuals, in one pass.

numpy builds (points x segments) temporaries and spends most of its time in call overhead
for scans of a few hundred points; this loop does the same arithmetic as
:func:`iceg.matching.geometry.associate_points` and ``refine._gls_system`` (see there for the
model) without temporaries. ``benchmarks/bench_matching.py`` prints both timings.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def point_line_system(
    pose: np.ndarray,
    points: np.ndarray,
    point_alpha: np.ndarray,
    seg_a: np.ndarray,
    seg_u: np.ndarray,
    seg_len: np.ndarray,
    seg_n: np.ndarray,
    seg_rho: np.ndarray,
    line_info: np.ndarray,
    gate_m: float,
    end_tol_m: float,
    sin_normal_gate: float,
    sigma_prev: float,
    sigma_min: float,
    cauchy_sigmas: float,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """Associate each point with its nearest compatible reference segment and build the
    GLS normal equations (reference frame perturbation ``(x, y, theta)``).

    Args:
        pose: ``(3,)`` pose of the new scan in the reference frame.
        points: ``(P, 2)`` new points (new frame); ``point_alpha`` ``(P,)`` their own
            segment's normal angle (new frame).
        seg_a, seg_u, seg_len, seg_n, seg_rho: reference segments (first endpoint, unit
            direction, length, unit line normal ``(cos alpha, sin alpha)``, line distance).
        line_info: ``(M, 2, 2)`` inverse covariance of each line's ``(alpha, rho)``.
        gate_m, end_tol_m, sin_normal_gate: association gates.
        sigma_prev: Point noise to use if too few points associate.
        sigma_min, cauchy_sigmas: noise floor and Cauchy scale (in sigmas).

    Returns:
        ``H`` (3, 3), ``g`` (3,), the estimated sigma, ``idx`` (P,) segment of each point
        (-1: none) and ``res`` (P,) signed residuals (NaN where none).
    """
    n_p = points.shape[0]
    n_m = seg_a.shape[0]
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    idx = np.full(n_p, -1, dtype=np.int64)
    res = np.full(n_p, np.nan)
    gate2 = gate_m * gate_m
    n_assoc = 0
    for i in range(n_p):
        px = c * points[i, 0] - s * points[i, 1] + pose[0]
        py = s * points[i, 0] + c * points[i, 1] + pose[1]
        qa = point_alpha[i] + pose[2]
        sq = math.sin(qa)
        cq = math.cos(qa)
        best = gate2
        bj = -1
        for j in range(n_m):
            if abs(sq * seg_n[j, 0] - cq * seg_n[j, 1]) > sin_normal_gate:
                continue
            rx = px - seg_a[j, 0]
            ry = py - seg_a[j, 1]
            along = rx * seg_u[j, 0] + ry * seg_u[j, 1]
            perp = rx * seg_u[j, 1] - ry * seg_u[j, 0]
            over = max(-end_tol_m - along, along - seg_len[j] - end_tol_m, 0.0)
            d2 = perp * perp + over * over
            if d2 <= best:
                best = d2
                bj = j
        if bj >= 0:
            idx[i] = bj
            res[i] = px * seg_n[bj, 0] + py * seg_n[bj, 1] - seg_rho[bj]
            n_assoc += 1
    sigma = sigma_prev
    if n_assoc >= 6:
        absr = np.empty(n_assoc)
        k = 0
        for i in range(n_p):
            if idx[i] >= 0:
                absr[k] = abs(res[i])
                k += 1
        sigma = max(sigma_min, 1.4826 * np.median(absr))
    cc = cauchy_sigmas * sigma
    jj = np.zeros((n_m, 3, 3))
    jb = np.zeros((n_m, 3, 2))
    bb = np.zeros((n_m, 2, 2))
    jr = np.zeros((n_m, 3))
    br = np.zeros((n_m, 2))
    used = np.zeros(n_m, dtype=np.bool_)
    jv = np.empty(3)
    bv = np.empty(2)
    for i in range(n_p):
        j = idx[i]
        if j < 0:
            continue
        used[j] = True
        ca = seg_n[j, 0]
        sa = seg_n[j, 1]
        rpx = c * points[i, 0] - s * points[i, 1]
        rpy = s * points[i, 0] + c * points[i, 1]
        qx = rpx + pose[0]
        qy = rpy + pose[1]
        r = res[i]
        w = 1.0 / (1.0 + (r / cc) ** 2) / (sigma * sigma)
        jv[0] = ca
        jv[1] = sa
        jv[2] = sa * rpx - ca * rpy
        bv[0] = -sa * qx + ca * qy
        bv[1] = -1.0
        for a in range(3):
            jr[j, a] += w * jv[a] * r
            for b in range(3):
                jj[j, a, b] += w * jv[a] * jv[b]
            for b in range(2):
                jb[j, a, b] += w * jv[a] * bv[b]
        for a in range(2):
            br[j, a] += w * bv[a] * r
            for b in range(2):
                bb[j, a, b] += w * bv[a] * bv[b]
    hess = np.zeros((3, 3))
    grad = np.zeros(3)
    for j in range(n_m):
        if not used[j]:
            continue
        m00 = line_info[j, 0, 0] + bb[j, 0, 0]
        m01 = line_info[j, 0, 1] + bb[j, 0, 1]
        m10 = line_info[j, 1, 0] + bb[j, 1, 0]
        m11 = line_info[j, 1, 1] + bb[j, 1, 1]
        det = m00 * m11 - m01 * m10
        k00 = m11 / det
        k01 = -m01 / det
        k10 = -m10 / det
        k11 = m00 / det
        for a in range(3):
            # (JB K) row a
            t0 = jb[j, a, 0] * k00 + jb[j, a, 1] * k10
            t1 = jb[j, a, 0] * k01 + jb[j, a, 1] * k11
            grad[a] += jr[j, a] - (t0 * br[j, 0] + t1 * br[j, 1])
            for b in range(3):
                hess[a, b] += jj[j, a, b] - (t0 * jb[j, b, 0] + t1 * jb[j, b, 1])
    return hess, grad, sigma, idx, res


@njit(cache=True, nogil=True)
def feature_system(
    pose: np.ndarray,
    pair_new: np.ndarray,
    pair_ref: np.ndarray,
    new_xy: np.ndarray,
    new_cov: np.ndarray,
    new_kind: np.ndarray,
    new_edge0: np.ndarray,
    ref_xy: np.ndarray,
    ref_cov: np.ndarray,
    ref_kind: np.ndarray,
    ref_edge0: np.ndarray,
    eow_kind: int,
    use_positions: bool,
    cauchy_c: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations of the feature pairs (see ``refine._feature_rows``): a pair that
    involves an EOW constrains the position along its wall (the reference EOW's wall, else
    the new one's rotated); other pairs, with ``use_positions``, their full 2D position
    with covariance ``R C_new R^T + C_ref``. Cauchy weights on the whitened residuals."""
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    hess = np.zeros((3, 3))
    grad = np.zeros(3)
    jv = np.empty(3)
    for k in range(pair_new.shape[0]):
        i = pair_new[k]
        j = pair_ref[k]
        rnx = c * new_xy[i, 0] - s * new_xy[i, 1]
        rny = s * new_xy[i, 0] + c * new_xy[i, 1]
        ex = rnx + pose[0] - ref_xy[j, 0]
        ey = rny + pose[1] - ref_xy[j, 1]
        a = new_cov[i, 0, 0]
        b = new_cov[i, 0, 1]
        d = new_cov[i, 1, 1]
        ca = c * c * a - 2 * c * s * b + s * s * d + ref_cov[j, 0, 0]
        cb = c * s * (a - d) + (c * c - s * s) * b + ref_cov[j, 0, 1]
        cd = s * s * a + 2 * c * s * b + c * c * d + ref_cov[j, 1, 1]
        if ref_kind[j] == eow_kind or new_kind[i] == eow_kind:
            ang = ref_edge0[j] if ref_kind[j] == eow_kind else new_edge0[i] + pose[2]
            dx = math.cos(ang)
            dy = math.sin(ang)
            r = dx * ex + dy * ey
            var = dx * dx * ca + 2 * dx * dy * cb + dy * dy * cd
            if not (var > 0.0) or not math.isfinite(r):
                continue
            w = 1.0 / (1.0 + r * r / var / (cauchy_c * cauchy_c)) / var
            jv[0] = dx
            jv[1] = dy
            jv[2] = dy * rnx - dx * rny
            for p in range(3):
                grad[p] += w * jv[p] * r
                for q in range(3):
                    hess[p, q] += w * jv[p] * jv[q]
        elif use_positions:
            det = ca * cd - cb * cb
            if not (det > 0.0):
                continue
            i00 = cd / det
            i01 = -cb / det
            i11 = ca / det
            m2 = ex * (i00 * ex + i01 * ey) + ey * (i01 * ex + i11 * ey)
            w = 1.0 / (1.0 + m2 / (cauchy_c * cauchy_c))
            # J = [[1, 0, -rny], [0, 1, rnx]]; H += w J^T I J; g += w J^T I e
            jx0, jx1, jx2 = 1.0, 0.0, -rny
            jy0, jy1, jy2 = 0.0, 1.0, rnx
            jv[0] = jx0
            jv[1] = jx1
            jv[2] = jx2
            ju = np.empty(3)
            ju[0] = jy0
            ju[1] = jy1
            ju[2] = jy2
            for p in range(3):
                grad[p] += w * (jv[p] * (i00 * ex + i01 * ey) + ju[p] * (i01 * ex + i11 * ey))
                for q in range(3):
                    hess[p, q] += w * (
                        jv[p] * (i00 * jv[q] + i01 * ju[q]) + ju[p] * (i01 * jv[q] + i11 * ju[q])
                    )
    return hess, grad


@njit(cache=True, nogil=True)
def _absw(x: float) -> float:
    y = (x + math.pi) % (2.0 * math.pi) - math.pi
    return abs(y)


@njit(cache=True, nogil=True)
def pair_nearest(
    poses: np.ndarray,
    new_xy: np.ndarray,
    new_heading: np.ndarray,
    new_edge: np.ndarray,
    new_opening: np.ndarray,
    ref_xy: np.ndarray,
    ref_heading: np.ndarray,
    ref_edge: np.ndarray,
    ref_opening: np.ndarray,
    codes: np.ndarray,
    gate_distance_m: float,
    gate_angle_rad: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Feature pairing of the correlation (see ``correlation.correlate``) for ``H`` poses:
    each new feature pairs with the nearest compatible reference feature inside both gates,
    and a reference feature keeps only its nearest new feature.

    Pair codes (``hypotheses.pair_codes``): 1 same directed kind (heading difference),
    2 new Corner / reference EOW and 3 new EOW / reference Corner (the closer Corner edge),
    4 Intersections (opening-angle difference), 0 incompatible.

    Returns:
        ``match`` (H, K_new) reference index or -1, ``dist`` and ``angle`` (H, K_new) of the
        pairs (NaN where unpaired).
    """
    h_n = poses.shape[0]
    kn = new_xy.shape[0]
    kr = ref_xy.shape[0]
    match = np.full((h_n, kn), -1, dtype=np.int64)
    dist = np.full((h_n, kn), np.nan)
    angle = np.full((h_n, kn), np.nan)
    owner = np.empty(kr, dtype=np.int64)
    for h in range(h_n):
        c = math.cos(poses[h, 2])
        s = math.sin(poses[h, 2])
        th = poses[h, 2]
        for i in range(kn):
            x = c * new_xy[i, 0] - s * new_xy[i, 1] + poses[h, 0]
            y = s * new_xy[i, 0] + c * new_xy[i, 1] + poses[h, 1]
            best = gate_distance_m
            bj = -1
            ba = 0.0
            for j in range(kr):
                code = codes[i, j]
                if code == 0:
                    continue
                d = math.hypot(x - ref_xy[j, 0], y - ref_xy[j, 1])
                if d >= best:
                    continue
                if code == 1:
                    a = _absw(new_heading[i] + th - ref_heading[j])
                elif code == 2:
                    a = min(
                        _absw(new_edge[i, 0] + th - ref_edge[j, 0]),
                        _absw(new_edge[i, 1] + th - ref_edge[j, 0]),
                    )
                elif code == 3:
                    a = min(
                        _absw(new_edge[i, 0] + th - ref_edge[j, 0]),
                        _absw(new_edge[i, 0] + th - ref_edge[j, 1]),
                    )
                else:
                    a = abs(new_opening[i] - ref_opening[j])
                if not (a < gate_angle_rad):  # NaN fails too
                    continue
                best = d
                bj = j
                ba = a
            if bj >= 0:
                match[h, i] = bj
                dist[h, i] = best
                angle[h, i] = ba
        # One new feature per reference feature: the nearest keeps it.
        owner[:] = -1
        for i in range(kn):
            j = match[h, i]
            if j < 0:
                continue
            o = owner[j]
            if o < 0:
                owner[j] = i
            elif dist[h, i] < dist[h, o]:
                match[h, o] = -1
                dist[h, o] = np.nan
                angle[h, o] = np.nan
                owner[j] = i
            else:
                match[h, i] = -1
                dist[h, i] = np.nan
                angle[h, i] = np.nan
    return match, dist, angle


@njit(cache=True, nogil=True)
def lattice_point_cost(
    deltas: np.ndarray,
    r0: np.ndarray,
    jac: np.ndarray,
    along0: np.ndarray,
    jac_along: np.ndarray,
    seg_len: np.ndarray,
    end_tol_m: float,
    gate_m: float,
    cauchy_c: float,
    sigma: float,
) -> np.ndarray:
    """Robust cost (Cauchy, in units of sigma^2) of the point-to-line residuals at each
    lattice perturbation (see ``refine._lattice_covariance``): residuals and along-segment
    coordinates move linearly with the perturbation; a point beyond its segment's extent
    or beyond the gate costs as much as one at the gate."""
    n_l = deltas.shape[0]
    n = r0.shape[0]
    out = np.zeros(n_l)
    c2 = cauchy_c * cauchy_c
    sat = 0.5 * c2 * math.log1p(gate_m * gate_m / c2)
    for k in range(n_l):
        dx, dy, dt = deltas[k, 0], deltas[k, 1], deltas[k, 2]
        acc = 0.0
        for i in range(n):
            r = r0[i] + jac[i, 0] * dx + jac[i, 1] * dy + jac[i, 2] * dt
            a = along0[i] + jac_along[i, 0] * dx + jac_along[i, 1] * dy + jac_along[i, 2] * dt
            if a < -end_tol_m or a > seg_len[i] + end_tol_m or abs(r) > gate_m:
                acc += sat
            else:
                acc += 0.5 * c2 * math.log1p(r * r / c2)
        out[k] = acc / (sigma * sigma)
    return out


@njit(cache=True, nogil=True)
def _solve3(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """Solve the 3x3 system ``a x = b`` by cofactors; ``ok`` False if singular."""
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    x = np.zeros(3)
    scale = abs(a[0, 0]) + abs(a[1, 1]) + abs(a[2, 2])
    if not (abs(det) > 1e-300) or not math.isfinite(det) or scale == 0.0:
        return x, False
    inv = np.empty((3, 3))
    inv[0, 0] = c00
    inv[1, 0] = c01
    inv[2, 0] = c02
    inv[0, 1] = a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]
    inv[1, 1] = a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]
    inv[2, 1] = a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]
    inv[0, 2] = a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]
    inv[1, 2] = a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]
    inv[2, 2] = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    for i in range(3):
        x[i] = (inv[i, 0] * b[0] + inv[i, 1] * b[1] + inv[i, 2] * b[2]) / det
    return x, True


@njit(cache=True, nogil=True)
def gn_phase(
    pose0: np.ndarray,
    prior_mean: np.ndarray,
    prior_info: np.ndarray,
    points: np.ndarray,
    point_alpha: np.ndarray,
    seg_a: np.ndarray,
    seg_u: np.ndarray,
    seg_len: np.ndarray,
    seg_n: np.ndarray,
    seg_rho: np.ndarray,
    line_info: np.ndarray,
    end_tol_m: float,
    sin_normal_gate: float,
    sigma_min: float,
    cauchy_sigmas: float,
    pair_new: np.ndarray,
    pair_ref: np.ndarray,
    new_xy: np.ndarray,
    new_cov: np.ndarray,
    new_kind: np.ndarray,
    new_edge0: np.ndarray,
    ref_xy: np.ndarray,
    ref_cov: np.ndarray,
    ref_kind: np.ndarray,
    ref_edge0: np.ndarray,
    eow_kind: int,
    coarse: bool,
    gate: float,
    sigma: float,
    max_it: int,
    gate_m: float,
    gate_sigmas: float,
    gate_min_m: float,
    tol_xy: float,
    tol_th: float,
) -> tuple[np.ndarray, float, float, int]:
    """One phase of the Gauss-Newton refinement (``refine.refine``, without off-segment
    points): point-to-line GLS rows, feature-pair rows (``pair_new``/``pair_ref``; full
    positions in the coarse phase), the bounds' prior pulling toward ``prior_mean``; the
    coarse phase keeps ``gate``, the fine phase sets it to ``gate_sigmas`` sigmas after each
    step. Stops when a step is below ``tol_xy`` / ``tol_th`` or after ``max_it`` steps.

    Returns:
        The pose, the point noise estimate, the gate for the next phase and the number of
        iterations run.
    """
    pose = pose0.copy()
    it = 0
    while it < max_it:
        it += 1
        hess, grad, sigma, _, _ = point_line_system(
            pose,
            points,
            point_alpha,
            seg_a,
            seg_u,
            seg_len,
            seg_n,
            seg_rho,
            line_info,
            gate,
            end_tol_m,
            sin_normal_gate,
            sigma,
            sigma_min,
            cauchy_sigmas,
        )
        if pair_new.shape[0] > 0:
            fh, fg = feature_system(
                pose,
                pair_new,
                pair_ref,
                new_xy,
                new_cov,
                new_kind,
                new_edge0,
                ref_xy,
                ref_cov,
                ref_kind,
                ref_edge0,
                eow_kind,
                coarse,
                2.5,
            )
            hess += fh
            grad += fg
        dp = pose - prior_mean
        dp[2] = (dp[2] + math.pi) % (2.0 * math.pi) - math.pi
        for i in range(3):
            for k in range(3):
                grad[i] += prior_info[i, k] * dp[k]
                hess[i, k] += prior_info[i, k]
            hess[i, i] += 1e-9
        for i in range(3):
            grad[i] = -grad[i]
        delta, ok = _solve3(hess, grad)
        if not ok:
            break
        pose[0] += delta[0]
        pose[1] += delta[1]
        pose[2] = (pose[2] + delta[2] + math.pi) % (2.0 * math.pi) - math.pi
        if not coarse:
            gate = min(gate_m, max(gate_min_m, gate_sigmas * sigma))
        if math.hypot(delta[0], delta[1]) < tol_xy and abs(delta[2]) < tol_th:
            break
    return pose, sigma, gate, it


@njit(cache=True, nogil=True)
def ray_wall_check(
    ep: np.ndarray,
    bearing: np.ndarray,
    ranges: np.ndarray,
    spacing: float,
    range_max_m: float,
    tol_m: float,
    cos_max_incidence: float,
) -> tuple[float, float]:
    """Cast segments ``ep`` (M, 2, 2) along beams (bearing, range) from the origin; see
    ``matcher._ray_check``. Returns the wall length seen through and confirmed (metres)."""
    see = 0.0
    cons = 0.0
    for b in range(bearing.shape[0]):
        dx = math.cos(bearing[b])
        dy = math.sin(bearing[b])
        best = np.inf
        bk = -1
        for k in range(ep.shape[0]):
            ax = ep[k, 0, 0]
            ay = ep[k, 0, 1]
            ex = ep[k, 1, 0] - ax
            ey = ep[k, 1, 1] - ay
            den = dx * ey - dy * ex
            if abs(den) <= 1e-12:
                continue
            t = (ax * ey - ay * ex) / den
            u = (ax * dy - ay * dx) / den
            if t > 0.0 and 0.0 <= u <= 1.0 and t < best:
                best = t
                bk = k
        if bk < 0 or best >= range_max_m - tol_m:
            continue
        ex = ep[bk, 1, 0] - ep[bk, 0, 0]
        ey = ep[bk, 1, 1] - ep[bk, 0, 1]
        el = math.hypot(ex, ey)
        if el <= 1e-12:
            continue
        cos_inc = abs(dx * ey - dy * ex) / el
        if cos_inc <= cos_max_incidence:
            continue
        cover = best * spacing / max(cos_inc, 1e-3)
        if ranges[b] > best + tol_m:
            see += cover
        elif abs(ranges[b] - best) <= tol_m:
            cons += cover
    return see, cons
