"""ICE feature extraction: one laser scan in, segments and Corner / EOW / Intersection out.

DESIGN.md "ICE matching, step by step", steps 1-4; paper §III-B (the features) and §III-C1
(split-and-merge with maximum-likelihood line fitting).
"""

from __future__ import annotations

import logging
import math

import numpy as np
from numpy.typing import NDArray

from frontends.scan import LaserScan
from iceg.features.config import FeatureConfig
from iceg.features.lines import fit_lines
from iceg.features.segmentation import breakpoints, split_and_merge
from iceg.types import FeatureKind, ScanFeatures
from iceg_common.errors import ConfigError

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


def _meet(lines_a: FloatArray, lines_b: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Meeting points of line pairs and their Jacobians with respect to each line.

    Lines ``n_k·p = rho_k`` with ``n_k = (cos alpha_k, sin alpha_k)``; with ``N = [n_a; n_b]``
    the point is ``p = N^-1 (rho_a, rho_b)``. Perturbing ``alpha_k`` and ``rho_k`` gives
    ``N dp = (d rho_a - (t_a·p) d alpha_a, d rho_b - (t_b·p) d alpha_b)`` with ``t_k = (-sin
    alpha_k, cos alpha_k)``, so ``J_a = N^-1[:, 0] (-(t_a·p), 1)`` and likewise ``J_b``.

    Args:
        lines_a, lines_b: ``(Q, 2)`` float64 ``(alpha_rad, rho_m)``; not parallel.

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


def _sandwich(j: FloatArray, c: FloatArray) -> FloatArray:
    """``J C J^T`` for stacks ``(Q, 2, 2)``."""
    return np.einsum("qij,qjk,qlk->qil", j, c, j)


def _line_intersections(
    lines_a: FloatArray, cov_a: FloatArray, lines_b: FloatArray, cov_b: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Meeting points of line pairs (see :func:`_meet`) and their covariance
    ``J_a C_a J_a^T + J_b C_b J_b^T`` (the two lines are fitted to disjoint points, hence
    independent).

    Returns:
        ``xy`` ``(Q, 2)`` float64 metres and ``cov`` ``(Q, 2, 2)`` float64 m².
    """
    xy, ja, jb = _meet(lines_a, lines_b)
    return xy, _sandwich(ja, cov_a) + _sandwich(jb, cov_b)


def _norm(v: FloatArray) -> FloatArray:
    """Euclidean norm over the last axis of ``(..., 2)`` vectors (cheaper than linalg.norm)."""
    return np.hypot(v[..., 0], v[..., 1])


def _unit(v: FloatArray) -> FloatArray:
    return v / _norm(v)[..., None]


def _point_segment_distance(p: FloatArray, a: FloatArray, b: FloatArray) -> FloatArray:
    """Distance of points ``p`` ``(Q, 2)`` to segments ``a``-``b`` ``(Q, 2)`` each, metres."""
    e = b - a
    s = np.clip(np.einsum("qi,qi->q", p - a, e) / np.einsum("qi,qi->q", e, e), 0.0, 1.0)
    return _norm(p - (a + s[:, None] * e))


def extract(scan: LaserScan, config: FeatureConfig | None = None) -> ScanFeatures:
    """Segments and ICE features (Corner, End of wall, Intersection) of one scan.

    Steps (DESIGN.md "ICE matching, step by step", 1-4):

    1. Valid beams (``range_min < r < min(range_max, config.range_max_m)``) to robot-frame
       points, laser offset applied; beams at or beyond the usable range are "no return".
    2. Clusters by adaptive breakpoints (Borges & Aldon 2004), also broken at invalid beams.
    3. Split-and-merge inside clusters (paper §III-C1, Nguyen et al. 2005), segments refit
       by maximum-likelihood weighted total least squares in Hessian form with covariances
       (Pfister et al. 2003; Arras & Siegwart 1997); endpoints are the first and last points
       projected on the line; short segments are dropped.
    4. Features (paper §III-B, Fig. 1-2):

       - Corner: two segments whose facing endpoints and whose lines' intersection lie within
         ``corner_gap_m`` (plus the along-wall beam spacing at each endpoint) of each other,
         the lines meeting at 30°-150°; each endpoint joins at most one corner (greedy by
         gap). Position: the lines' intersection, covariance propagated from both line
         covariances through the Jacobian of the intersection; directions: unit vectors from
         the corner toward each segment's far endpoint; opening angle between them.
       - End of wall: an endpoint that is neither in a corner nor a junction (another
         segment starting within ``eow_check_beams + 1`` beams and the corner gap of it)
         beyond which the next ``eow_check_beams`` beams all see past the wall's extension:
         a return farther than where the beam would meet the extended wall, or no return
         where the extended wall would have returned inside the usable range. Not an EOW: an
         endpoint next to nearer returns (occlusion), at the scan's angular limit, or where
         the wall's extension would lie beyond the usable range (a max-range gap: the wall
         may continue unseen) or at grazing incidence. Position: the wall ends between the
         ray of the endpoint's beam and the ray of the first beam beyond, so the EOW is the
         middle of their meeting points with the wall's line; covariance: that midpoint's
         Jacobian applied to the line covariance, plus ``gap² / 12`` along the wall
         (uniform). Direction: unit vector from the EOW into its wall.
       - Intersection: two segments not forming a corner whose infinite lines meet at
         30°-150° within ``intersection_max_distance_m`` of both segments and inside the
         usable range, with a position standard deviation at most
         ``intersection_max_std_m``; not within ``intersection_duplicate_m`` of a corner or
         of a better determined intersection. Opening angle between the rays from the point
         toward the far endpoint of each segment; no direction.

    Args:
        scan: One laser scan.
        config: Thresholds; defaults to :class:`FeatureConfig`.

    Returns:
        :class:`~iceg.types.ScanFeatures` in the robot frame of the scan: features ordered
        corners, then EOWs, then intersections; ``ids = arange(K)``.

    Raises:
        ConfigError: the scan's beams are not in increasing bearing order.
    """
    cfg = FeatureConfig() if config is None else config
    ranges = scan.ranges_m
    angles = scan.angles_rad
    n_beams = ranges.shape[0]
    range_max = float(min(cfg.range_max_m, scan.range_max_m))
    stamp = float(scan.stamp_s)
    if n_beams > 1 and np.any(np.diff(angles) <= 0.0):
        raise ConfigError(
            f"{scan.source}: beam bearings must increase strictly (got a non-increasing step); "
            "fix the reader's angle convention"
        )

    # Step 1: points.
    with np.errstate(invalid="ignore"):
        no_return = np.isposinf(ranges) | (np.isfinite(ranges) & (ranges >= range_max))
        valid = np.isfinite(ranges) & (ranges > scan.range_min_m) & (ranges < range_max)
    beam_index = np.flatnonzero(valid).astype(np.int64)
    points = scan.points_xy(valid)
    if points.shape[0] < cfg.min_segment_points:
        return ScanFeatures.empty(points, range_max, stamp)
    r = ranges[valid]
    origin = scan.laser_offset[:2]
    beam_angle_robot = angles + scan.laser_offset[2]  # (N,) beam directions, robot frame
    beam_dirs_all = np.stack([np.cos(beam_angle_robot), np.sin(beam_angle_robot)], axis=1)
    beam_dirs = beam_dirs_all[valid]

    # Step 2: breakpoints.
    bounds = breakpoints(
        points,
        r,
        angles[valid],
        beam_index,
        cfg.sigma_range_m,
        math.radians(cfg.breakpoint_lambda_deg),
    )
    inner = bounds[1:-1]
    gap_beams = beam_index[inner] - beam_index[inner - 1] - 1
    joinable = (gap_beams >= 1) & (gap_beams <= cfg.dropout_max_beams)

    # Step 3: split-and-merge and maximum-likelihood lines.
    seg_range = split_and_merge(
        np.ascontiguousarray(points[:, 0]),
        np.ascontiguousarray(points[:, 1]),
        bounds,
        joinable,
        cfg.split_distance_m,
        cfg.merge_distance_m,
        cfg.min_segment_points,
    )
    lines, seg_cov, endpoints = fit_lines(
        points,
        r,
        beam_dirs,
        seg_range,
        cfg.sigma_range_m,
        math.radians(cfg.sigma_bearing_deg),
    )
    seg_len = _norm(endpoints[:, 1] - endpoints[:, 0])
    keep = seg_len >= cfg.min_segment_length_m
    seg_range, lines, seg_cov, endpoints = (
        seg_range[keep],
        lines[keep],
        seg_cov[keep],
        endpoints[keep],
    )
    m = seg_range.shape[0]
    if m == 0:
        return ScanFeatures.empty(points, range_max, stamp)

    sin_min = math.sin(math.radians(cfg.meeting_angle_min_deg))
    normals = np.stack([np.cos(lines[:, 0]), np.sin(lines[:, 0])], axis=1)  # (M, 2)

    # Beam spacing along each segment's wall at its endpoints: (M, 2) metres. At grazing
    # incidence consecutive beams land far apart, so gaps near an endpoint scale with it.
    end_beam = np.stack([beam_index[seg_range[:, 0]], beam_index[seg_range[:, 1] - 1]], axis=1)
    dphi = (angles[-1] - angles[0]) / max(n_beams - 1, 1)
    cos_max_inc = math.cos(math.radians(cfg.eow_max_incidence_deg))
    cos_inc_end = np.abs(np.einsum("mj,mej->me", normals, beam_dirs_all[end_beam]))
    spacing = ranges[end_beam] * dphi / np.maximum(cos_inc_end, cos_max_inc)

    # Step 4a: corners over all segment pairs.
    ii, jj = np.triu_indices(m, k=1)
    sin_meet = np.abs(np.sin(lines[ii, 0] - lines[jj, 0]))
    steep = sin_meet >= sin_min
    ii, jj = ii[steep], jj[steep]
    corner_pairs = np.zeros((0, 2), dtype=np.int64)
    corner_ends = np.zeros((0, 2), dtype=np.int64)
    corner_xy = np.zeros((0, 2))
    corner_cov = np.zeros((0, 2, 2))
    pair_xy = np.zeros((0, 2))
    pair_cov = np.zeros((0, 2, 2))
    if ii.size:
        pair_xy, pair_cov = _line_intersections(lines[ii], seg_cov[ii], lines[jj], seg_cov[jj])
        # Facing endpoints: the combination (end of i, end of j) with the smallest gap.
        ei = endpoints[ii]  # (Q, 2, 2)
        ej = endpoints[jj]
        gaps = _norm(ei[:, :, None, :] - ej[:, None, :, :]).reshape(-1, 4)
        best = np.argmin(gaps, axis=1)
        end_i = best // 2
        end_j = best % 2
        q = np.arange(ii.size)
        gap = gaps[q, best]
        pi_ = ei[q, end_i]
        pj_ = ej[q, end_j]
        d_i = _norm(pair_xy - pi_)
        d_j = _norm(pair_xy - pj_)
        sp_i = spacing[ii, end_i]
        sp_j = spacing[jj, end_j]
        ok = (
            (gap <= cfg.corner_gap_m + sp_i + sp_j)
            & (d_i <= cfg.corner_gap_m + sp_i)
            & (d_j <= cfg.corner_gap_m + sp_j)
        )
        cand = np.flatnonzero(ok)
        if cand.size:
            # Each endpoint takes part in at most one corner: greedy by gap (few candidates).
            used = np.zeros((m, 2), dtype=bool)
            chosen = []
            for c in cand[np.argsort(gap[cand], kind="stable")]:
                a, b, ea, eb = ii[c], jj[c], end_i[c], end_j[c]
                if used[a, ea] or used[b, eb]:
                    continue
                used[a, ea] = used[b, eb] = True
                chosen.append(c)
            sel = np.asarray(chosen, dtype=np.int64)
            corner_pairs = np.stack([ii[sel], jj[sel]], axis=1)
            corner_ends = np.stack([end_i[sel], end_j[sel]], axis=1)
            corner_xy = pair_xy[sel]
            corner_cov = pair_cov[sel]
    n_c = corner_pairs.shape[0]
    if n_c:
        far_i = endpoints[corner_pairs[:, 0], 1 - corner_ends[:, 0]]
        far_j = endpoints[corner_pairs[:, 1], 1 - corner_ends[:, 1]]
        corner_dirs = np.stack([_unit(far_i - corner_xy), _unit(far_j - corner_xy)], axis=1)
        corner_open = np.arccos(
            np.clip(np.einsum("ki,ki->k", corner_dirs[:, 0], corner_dirs[:, 1]), -1.0, 1.0)
        )
    else:
        corner_dirs = np.zeros((0, 2, 2))
        corner_open = np.zeros(0)

    # Step 4b: ends of walls, over all 2M endpoints x eow_check_beams beams at once.
    in_corner = np.zeros((m, 2), dtype=bool)
    if n_c:
        in_corner[corner_pairs[:, 0], corner_ends[:, 0]] = True
        in_corner[corner_pairs[:, 1], corner_ends[:, 1]] = True
    outward = np.array([-1, 1], dtype=np.int64)
    k_steps = np.arange(1, cfg.eow_check_beams + 1, dtype=np.int64)
    nb = end_beam[:, :, None] + outward[None, :, None] * k_steps[None, None, :]  # (M, 2, K)
    inside = (nb >= 0) & (nb < n_beams)
    nb_c = np.clip(nb, 0, n_beams - 1)
    u = beam_dirs_all[nb_c]  # (M, 2, K, 2)
    n_dot_u = np.einsum("mj,mekj->mek", normals, u)
    dist_to_line = lines[:, 1] - normals @ origin  # (M,) signed distance laser -> line
    with np.errstate(divide="ignore", invalid="ignore"):
        r_pred = dist_to_line[:, None, None] / n_dot_u
    predicted = (
        np.isfinite(r_pred)
        & (r_pred > 0.0)
        & (np.abs(n_dot_u) >= cos_max_inc)
        & (r_pred < range_max - cfg.eow_range_margin_m)
    )
    r_nb = ranges[nb_c]
    with np.errstate(invalid="ignore"):
        farther = valid[nb_c] & (r_nb > r_pred + cfg.eow_range_margin_m)
    sees_past = inside & predicted & (farther | no_return[nb_c])
    # An endpoint whose next beams start another segment right there is a junction (a
    # corner, or walls meeting at a shallow angle), not an end of wall.
    flat_ends = endpoints.reshape(-1, 2)
    flat_sp = spacing.reshape(-1)
    flat_beam = end_beam.reshape(-1)
    d_ends = _norm(flat_ends[:, None, :] - flat_ends[None, :, :])
    touching = d_ends <= cfg.corner_gap_m + flat_sp[:, None] + flat_sp[None, :]
    touching &= np.abs(flat_beam[:, None] - flat_beam[None, :]) <= cfg.eow_check_beams + 1
    seg_of_end = np.repeat(np.arange(m), 2)
    touching &= seg_of_end[:, None] != seg_of_end[None, :]
    junction = touching.any(axis=1).reshape(m, 2)
    is_eow = np.all(sees_past, axis=2) & ~in_corner & ~junction  # (M, 2)
    eow_seg, eow_end = np.nonzero(is_eow)
    n_e = eow_seg.size
    if n_e:
        end_xy = endpoints[eow_seg, eow_end]
        other_xy = endpoints[eow_seg, 1 - eow_end]
        wall_dir = _unit(other_xy - end_xy)  # from the end into the wall
        # The wall ends between the ray of the endpoint's beam and the ray of the first beam
        # beyond: both meet the wall's line; the EOW is the middle, uniform in between.
        beams = np.concatenate([end_beam[eow_seg, eow_end], nb_c[eow_seg, eow_end, 0]])
        rays = np.empty((2 * n_e, 2))
        rays[:, 0] = beam_angle_robot[beams] + 0.5 * np.pi  # normal of the beam's ray
        rays[:, 1] = np.cos(rays[:, 0]) * origin[0] + np.sin(rays[:, 0]) * origin[1]
        hits, j_wall, _ = _meet(np.concatenate([lines[eow_seg], lines[eow_seg]]), rays)
        hit_end, hit_next = hits[:n_e], hits[n_e:]
        j_end, j_next = j_wall[:n_e], j_wall[n_e:]
        eow_xy = 0.5 * (hit_end + hit_next)
        gap_len = _norm(hit_next - hit_end)
        eow_cov = _sandwich(0.5 * (j_end + j_next), seg_cov[eow_seg]) + (gap_len**2 / 12.0)[
            :, None, None
        ] * np.einsum("ki,kj->kij", wall_dir, wall_dir)
        eow_dirs = np.stack([wall_dir, np.full((n_e, 2), np.nan)], axis=1)
    else:
        eow_xy = np.zeros((0, 2))
        eow_cov = np.zeros((0, 2, 2))
        eow_dirs = np.zeros((0, 2, 2))

    # Step 4c: intersections of the remaining steep pairs.
    inter_pairs = np.zeros((0, 2), dtype=np.int64)
    inter_xy = np.zeros((0, 2))
    inter_cov = np.zeros((0, 2, 2))
    if ii.size:
        is_corner_pair = np.zeros((m, m), dtype=bool)
        if n_c:
            is_corner_pair[corner_pairs[:, 0], corner_pairs[:, 1]] = True
        d_seg_i = _point_segment_distance(pair_xy, endpoints[ii, 0], endpoints[ii, 1])
        d_seg_j = _point_segment_distance(pair_xy, endpoints[jj, 0], endpoints[jj, 1])
        eig_max = _max_eigenvalue(pair_cov)
        ok = (
            ~is_corner_pair[ii, jj]
            & (d_seg_i <= cfg.intersection_max_distance_m)
            & (d_seg_j <= cfg.intersection_max_distance_m)
            & (_norm(pair_xy - origin) < range_max)
            & (eig_max <= cfg.intersection_max_std_m**2)
        )
        if n_c:
            d_corner = _norm(pair_xy[:, None, :] - corner_xy[None, :, :])
            ok &= d_corner.min(axis=1) > cfg.intersection_duplicate_m
        cand = np.flatnonzero(ok)
        if cand.size:
            # Duplicates (the same wall meeting split into collinear pieces): keep the best
            # determined (smallest covariance trace) of any cluster of nearby meeting points.
            cand = cand[np.argsort(np.trace(pair_cov[cand], axis1=1, axis2=2), kind="stable")]
            d = _norm(pair_xy[cand, None, :] - pair_xy[None, cand, :])
            near = d <= cfg.intersection_duplicate_m
            keep_c = np.ones(cand.size, dtype=bool)
            for a in range(cand.size):  # a handful of candidates
                if keep_c[a]:
                    keep_c[a + 1 :] &= ~near[a, a + 1 :]
            sel = cand[keep_c]
            inter_pairs = np.stack([ii[sel], jj[sel]], axis=1)
            inter_xy = pair_xy[sel]
            inter_cov = pair_cov[sel]
    n_i = inter_pairs.shape[0]
    if n_i:
        far = []
        for col in (0, 1):
            e = endpoints[inter_pairs[:, col]]  # (I, 2, 2)
            dd = _norm(e - inter_xy[:, None, :])
            far.append(e[np.arange(n_i), np.argmax(dd, axis=1)])
        ra = _unit(far[0] - inter_xy)
        rb = _unit(far[1] - inter_xy)
        inter_open = np.arccos(np.clip(np.einsum("ki,ki->k", ra, rb), -1.0, 1.0))
    else:
        inter_open = np.zeros(0)

    kind = np.concatenate(
        [
            np.full(n_c, FeatureKind.CORNER, dtype=np.int64),
            np.full(n_e, FeatureKind.EOW, dtype=np.int64),
            np.full(n_i, FeatureKind.INTERSECTION, dtype=np.int64),
        ]
    )
    k_total = kind.shape[0]
    segment_ids = np.concatenate(
        [
            corner_pairs,
            np.stack([eow_seg.astype(np.int64), np.full(n_e, -1, dtype=np.int64)], axis=1),
            inter_pairs,
        ]
    )
    if log.isEnabledFor(logging.DEBUG):
        log.debug(
            "%s: %d points, %d segments, %d corners, %d EOWs, %d intersections",
            scan.source,
            points.shape[0],
            m,
            n_c,
            n_e,
            n_i,
        )
    return ScanFeatures(
        points_xy=points,
        seg_endpoints=endpoints,
        seg_lines=lines,
        seg_cov=seg_cov,
        seg_point_range=seg_range,
        kind=kind,
        xy=np.concatenate([corner_xy, eow_xy, inter_xy]),
        cov=np.concatenate([corner_cov, eow_cov, inter_cov]),
        directions=np.concatenate([corner_dirs, eow_dirs, np.full((n_i, 2, 2), np.nan)]),
        opening_rad=np.concatenate([corner_open, np.full(n_e, np.nan), inter_open]),
        segment_ids=segment_ids,
        ids=np.arange(k_total, dtype=np.int64),
        range_max_m=range_max,
        stamp_s=stamp,
    )


def _max_eigenvalue(cov: FloatArray) -> FloatArray:
    """Largest eigenvalue of symmetric ``(Q, 2, 2)`` matrices, closed form."""
    a = cov[:, 0, 0]
    d = cov[:, 1, 1]
    b = cov[:, 0, 1]
    return 0.5 * (a + d) + np.sqrt(0.25 * (a - d) ** 2 + b * b)
