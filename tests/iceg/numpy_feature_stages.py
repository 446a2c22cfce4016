"""The vectorized numpy feature stages that the compiled ones replaced (issue 13), kept as the
reference the compiled stages must equal bit for bit (``test_features.py``): steep segment
pairs with their meeting points, corners, ends of wall and intersections."""

from __future__ import annotations

import math

import numpy as np

from iceg.features.config import FeatureConfig
from iceg.features.corners import Corners
from iceg.features.ends import UNIFORM_VAR_DIVISOR, EndsOfWall
from iceg.features.intersections import Intersections, best_determined
from iceg.features.neighbours import close_to_any, segment_pairs_within
from iceg.features.pairs import SegmentPairs, pair_search_radius
from iceg.features.points import BeamPoints
from iceg.features.segments import Segments
from tests.iceg import libm


def norm(v: np.ndarray) -> np.ndarray:
    return np.hypot(v[..., 0], v[..., 1])


def unit(v: np.ndarray) -> np.ndarray:
    return v / norm(v)[..., None]


def opening_angle(ray_a: np.ndarray, ray_b: np.ndarray) -> np.ndarray:
    return libm.arccos(np.clip(np.einsum("ki,ki->k", ray_a, ray_b), -1.0, 1.0))


def meet(lines_a: np.ndarray, lines_b: np.ndarray) -> tuple[np.ndarray, ...]:
    ca, sa = np.cos(lines_a[:, 0]), np.sin(lines_a[:, 0])
    cb, sb = np.cos(lines_b[:, 0]), np.sin(lines_b[:, 0])
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_det = 1.0 / (ca * sb - sa * cb)
    q = inv_det.shape[0]
    col_a = np.empty((q, 2))
    col_a[:, 0], col_a[:, 1] = sb * inv_det, -cb * inv_det
    col_b = np.empty((q, 2))
    col_b[:, 0], col_b[:, 1] = -sa * inv_det, ca * inv_det
    xy = col_a * lines_a[:, 1:2] + col_b * lines_b[:, 1:2]
    ja = np.empty((q, 2, 2))
    ja[:, :, 0] = col_a * (sa * xy[:, 0] - ca * xy[:, 1])[:, None]
    ja[:, :, 1] = col_a
    jb = np.empty((q, 2, 2))
    jb[:, :, 0] = col_b * (sb * xy[:, 0] - cb * xy[:, 1])[:, None]
    jb[:, :, 1] = col_b
    return xy, ja, jb


def sandwich(j: np.ndarray, c: np.ndarray) -> np.ndarray:
    return np.einsum("qij,qjk,qlk->qil", j, c, j)


def meeting_pairs(segs: Segments, cfg: FeatureConfig) -> SegmentPairs:
    ii, jj = segment_pairs_within(segs.endpoints, pair_search_radius(segs, cfg))
    sin_min = math.sin(math.radians(cfg.meeting_angle_min_deg))
    lines = segs.lines
    steep = np.abs(np.sin(lines[ii, 0] - lines[jj, 0])) >= sin_min
    ii, jj = ii[steep], jj[steep]
    xy, ja, jb = meet(lines[ii], lines[jj])
    return SegmentPairs(ii, jj, xy, sandwich(ja, segs.cov[ii]) + sandwich(jb, segs.cov[jj]))


def find_corners(segs: Segments, pairs: SegmentPairs, cfg: FeatureConfig) -> Corners:
    if pairs.first.size == 0:
        return Corners.empty()
    ei, ej = segs.endpoints[pairs.first], segs.endpoints[pairs.second]
    gaps = norm(ei[:, :, None, :] - ej[:, None, :, :]).reshape(-1, 4)
    best = np.argmin(gaps, axis=1)
    end_i, end_j = best // 2, best % 2
    gap = gaps[np.arange(best.shape[0]), best]
    q = np.arange(gap.shape[0])
    d_i = norm(pairs.xy - ei[q, end_i])
    d_j = norm(pairs.xy - ej[q, end_j])
    sp_i = segs.spacing[pairs.first, end_i]
    sp_j = segs.spacing[pairs.second, end_j]
    g = cfg.corner_gap_m
    ok = (gap <= g + sp_i + sp_j) & (d_i <= g + sp_i) & (d_j <= g + sp_j)
    cand = np.flatnonzero(ok)
    if cand.size == 0:
        return Corners.empty()
    used = np.zeros((segs.lines.shape[0], 2), dtype=bool)
    chosen = []
    for c in cand[np.argsort(gap[cand], kind="stable")]:
        a, b, ea, eb = pairs.first[c], pairs.second[c], end_i[c], end_j[c]
        if used[a, ea] or used[b, eb]:
            continue
        used[a, ea] = used[b, eb] = True
        chosen.append(c)
    sel = np.asarray(chosen, dtype=np.int64)
    corner_pairs = np.stack([pairs.first[sel], pairs.second[sel]], axis=1)
    ends = np.stack([end_i[sel], end_j[sel]], axis=1)
    xy = pairs.xy[sel]
    far_i = segs.endpoints[corner_pairs[:, 0], 1 - ends[:, 0]]
    far_j = segs.endpoints[corner_pairs[:, 1], 1 - ends[:, 1]]
    dirs = np.stack([unit(far_i - xy), unit(far_j - xy)], axis=1)
    opening = opening_angle(dirs[:, 0], dirs[:, 1])
    return Corners(corner_pairs, ends, xy, pairs.cov[sel], dirs, opening)


def find_ends_of_wall(
    beams: BeamPoints, segs: Segments, in_corner: np.ndarray, cfg: FeatureConfig
) -> EndsOfWall:
    n_beams, k = beams.ranges.shape[0], cfg.eow_check_beams
    outward = np.array([-1, 1], dtype=np.int64)
    nb = segs.end_beam[:, :, None] + outward[None, :, None] * np.arange(1, k + 1)[None, None, :]
    inside = (nb >= 0) & (nb < n_beams)
    nb = np.clip(nb, 0, n_beams - 1)
    cos_max_inc = math.cos(math.radians(cfg.eow_max_incidence_deg))
    n_dot_u = np.einsum("mj,mekj->mek", segs.normals, beams.dirs[nb])
    dist_to_line = segs.lines[:, 1] - segs.normals @ beams.origin
    with np.errstate(divide="ignore", invalid="ignore"):
        r_pred = dist_to_line[:, None, None] / n_dot_u
        predicted = (
            np.isfinite(r_pred)
            & (r_pred > 0.0)
            & (np.abs(n_dot_u) >= cos_max_inc)
            & (r_pred < beams.range_max - cfg.eow_range_margin_m)
        )
        farther = beams.valid[nb] & (beams.ranges[nb] > r_pred + cfg.eow_range_margin_m)
    past = inside & predicted & (farther | beams.no_return[nb])
    # junctions
    ends, sp, beam = segs.endpoints.reshape(-1, 2), segs.spacing.reshape(-1), segs.end_beam.ravel()
    n, window = ends.shape[0], k + 1
    a = np.repeat(np.arange(n), window)
    b = a + np.tile(np.arange(1, window + 1), n)
    a, b = a[b < n], b[b < n]
    close = (np.abs(beam[a] - beam[b]) <= window) & (a // 2 != b // 2)
    d = norm(ends[a] - ends[b])
    hit = np.zeros(n, dtype=bool)
    hit[a[close & (d <= cfg.corner_gap_m + sp[a] + sp[b])]] = True
    hit[b[close & (d <= cfg.corner_gap_m + sp[b] + sp[a])]] = True
    is_eow = np.all(past, axis=2) & ~in_corner & ~hit.reshape(-1, 2)
    seg, end = np.nonzero(is_eow)
    beyond = nb[seg, end, 0]
    n_e = seg.shape[0]
    if n_e == 0:
        no = np.zeros(0, dtype=np.int64)
        return EndsOfWall(no, no, np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2, 2)), no)
    end_xy = segs.endpoints[seg, end]
    wall_dir = unit(segs.endpoints[seg, 1 - end] - end_xy)
    ray_beams = np.concatenate([segs.end_beam[seg, end], beyond])
    rays = np.empty((2 * n_e, 2))
    rays[:, 0] = beams.bearing_robot[ray_beams] + 0.5 * np.pi
    rays[:, 1] = np.cos(rays[:, 0]) * beams.origin[0] + np.sin(rays[:, 0]) * beams.origin[1]
    hits, j_wall, _ = meet(np.concatenate([segs.lines[seg], segs.lines[seg]]), rays)
    xy = 0.5 * (hits[:n_e] + hits[n_e:])
    gap_len = norm(hits[n_e:] - hits[:n_e])
    along = (gap_len**2 / UNIFORM_VAR_DIVISOR)[:, None, None] * np.einsum(
        "ki,kj->kij", wall_dir, wall_dir
    )
    cov = sandwich(0.5 * (j_wall[:n_e] + j_wall[n_e:]), segs.cov[seg]) + along
    dirs = np.stack([wall_dir, np.full((n_e, 2), np.nan)], axis=1)
    return EndsOfWall(seg.astype(np.int64), end.astype(np.int64), xy, cov, dirs, beyond)


def _point_segment_distance(p: np.ndarray, a: np.ndarray, b: np.ndarray) -> np.ndarray:
    e = b - a
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.clip(np.einsum("qi,qi->q", p - a, e) / np.einsum("qi,qi->q", e, e), 0.0, 1.0)
    return norm(p - (a + s[:, None] * e))


def find_intersections(
    beams: BeamPoints, segs: Segments, pairs: SegmentPairs, corners: Corners, cfg: FeatureConfig
) -> Intersections:
    if pairs.first.size == 0:
        return Intersections.empty()
    ii, jj, xy = pairs.first, pairs.second, pairs.xy
    m = segs.lines.shape[0]
    codes = np.sort(corners.pairs[:, 0] * m + corners.pairs[:, 1])
    if codes.size:
        pos = np.minimum(np.searchsorted(codes, ii * m + jj), codes.size - 1)
        is_corner = codes[pos] == ii * m + jj
    else:
        is_corner = np.zeros(ii.shape[0], dtype=bool)
    c = pairs.cov
    largest = 0.5 * (c[:, 0, 0] + c[:, 1, 1]) + np.sqrt(
        0.25 * (c[:, 0, 0] - c[:, 1, 1]) ** 2 + c[:, 0, 1] * c[:, 0, 1]
    )
    d_max = cfg.intersection_max_distance_m
    ok = (
        ~is_corner
        & (_point_segment_distance(xy, segs.endpoints[ii, 0], segs.endpoints[ii, 1]) <= d_max)
        & (_point_segment_distance(xy, segs.endpoints[jj, 0], segs.endpoints[jj, 1]) <= d_max)
        & (norm(xy - beams.origin) < beams.range_max)
        & (largest <= cfg.intersection_max_std_m**2)
        & ~close_to_any(xy, corners.xy, cfg.intersection_duplicate_m)
    )
    cand = np.flatnonzero(ok)
    if cand.size == 0:
        return Intersections.empty()
    sel = cand[best_determined(xy[cand], pairs.cov[cand], cfg.intersection_duplicate_m)]
    inter_pairs = np.stack([ii[sel], jj[sel]], axis=1)
    xy = xy[sel]
    far = []
    for col in (0, 1):
        e = segs.endpoints[inter_pairs[:, col]]
        far.append(e[np.arange(sel.size), np.argmax(norm(e - xy[:, None, :]), axis=1)])
    opening = opening_angle(unit(far[0] - xy), unit(far[1] - xy))
    return Intersections(inter_pairs, xy, pairs.cov[sel], opening)
