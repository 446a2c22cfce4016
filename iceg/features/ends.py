"""End-of-wall features: a segment endpoint beyond which the beams see past the wall's
extension (paper §III-B, Fig. 1; docs/design.md step 4)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from iceg.features.config import FeatureConfig
from iceg.features.geometry import dot2, meet, sandwich
from iceg.features.points import BeamPoints
from iceg.features.segments import Segments
from iceg_common.numba_loading import njit

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

# Variance of a uniform distribution over an interval of length g is g² / UNIFORM_VAR_DIVISOR.
UNIFORM_VAR_DIVISOR = 12.0


class EndsOfWall(NamedTuple):
    """E end-of-wall features, robot frame."""

    seg: IntArray  # (E,) int64 segment of each EOW
    end: IntArray  # (E,) int64 which endpoint (0 first, 1 last)
    xy: FloatArray  # (E, 2) float64 position, metres
    cov: FloatArray  # (E, 2, 2) float64 its covariance, m²
    dirs: FloatArray  # (E, 2, 2) float64 [0]: unit vector into the wall; [1]: NaN
    beyond: IntArray  # (E,) int64 the first beam beyond the endpoint


def junctions(segs: Segments, cfg: FeatureConfig) -> BoolArray:
    """Endpoints where another segment starts right there: within ``eow_check_beams + 1``
    beams and ``corner_gap_m`` plus both endpoints' beam spacing (a corner, or walls
    meeting at a shallow angle; not an end of wall).

    Endpoint beams strictly increase (first, last, first, ... of segments in point order),
    so only the next ``eow_check_beams + 1`` endpoints can be that close in beams: ``O(M)``
    work instead of all endpoint pairs (issue 12).

    Returns:
        ``(M, 2)`` bool.
    """
    return _junctions(segs, cfg.eow_check_beams + 1, cfg.corner_gap_m)


def find_ends_of_wall(
    beams: BeamPoints, segs: Segments, in_corner: BoolArray, cfg: FeatureConfig
) -> EndsOfWall:
    """Ends of wall: endpoints in no corner and no junction (:func:`junctions`) whose next
    ``eow_check_beams`` beams (in beam order, all inside the scan) all see past the wall's
    infinite line (paper §III-B, Fig. 1).

    A beam sees past the line when the range ``r_pred`` at which it meets the line (from the
    laser origin) is positive, below ``range_max - eow_range_margin_m`` and at an incidence
    of at most ``eow_max_incidence_deg`` from the normal, and the beam returns farther than
    ``r_pred + eow_range_margin_m``, or nothing, unless the first return past its run of
    returnless beams lies on the line again within ``eow_dropout_max_gap_m`` of the endpoint:
    the wall goes on past a dropout (a wider gap is an opening). So an endpoint next to
    nearer returns (occlusion), next to a dropout in its own wall, at the scan's angular
    limit, or where the wall's extension would lie beyond the usable range or at grazing
    incidence is no EOW.

    Position: the wall ends between the ray of the endpoint's beam and the ray of the first
    beam beyond; both meet the wall's line and the EOW is the middle of the two meeting
    points. Covariance: that midpoint's Jacobian applied to the line covariance, plus
    ``gap² / 12`` along the wall (uniform over the gap). Direction: the unit vector from the
    EOW into its wall. One compiled pass (:func:`_ends_of_wall`, issue 13), the values of
    the vectorized numpy stage it replaced bit for bit.

    Args:
        beams: The scan's beams.
        segs: Its segments.
        in_corner: ``(M, 2)`` bool endpoints taken by a corner.
        cfg: ``eow_check_beams``, ``eow_range_margin_m``, ``eow_max_incidence_deg``,
            ``corner_gap_m``.

    Returns:
        :class:`EndsOfWall`, by segment then endpoint.
    """
    # numpy's matrix product (BLAS) kept for its bits: laser -> line distance (M,)
    dist_to_line = segs.lines[:, 1] - segs.normals @ beams.origin
    settings = _EowSettings(
        cfg.eow_check_beams,
        cfg.eow_range_margin_m,
        beams.range_max - cfg.eow_range_margin_m,
        math.cos(math.radians(cfg.eow_max_incidence_deg)),
        cfg.corner_gap_m,
        cfg.eow_dropout_max_gap_m,
    )
    seg, end, xy, cov, wall_dir, beyond = _ends_of_wall(
        beams, segs, dist_to_line, np.ascontiguousarray(in_corner, dtype=np.bool_), settings
    )
    dirs = np.stack([wall_dir, np.full((seg.size, 2), np.nan)], axis=1)
    return EndsOfWall(seg, end, xy, cov, dirs, beyond)


class _EowSettings(NamedTuple):
    """:func:`find_ends_of_wall`'s thresholds for its kernel (metres)."""

    check_beams: int
    range_margin_m: float
    range_limit_m: float  # range_max - range_margin_m
    cos_max_incidence: float
    corner_gap_m: float
    dropout_max_gap_m: float


@njit(cache=True, nogil=True)
def _junctions(segs: Segments, window: int, corner_gap_m: float) -> BoolArray:
    """:func:`junctions` with ``window = eow_check_beams + 1``: each endpoint against the
    next ``window`` endpoints."""
    n = 2 * segs.endpoints.shape[0]
    ends = segs.endpoints.reshape(n, 2)
    sp = segs.spacing.reshape(n)
    beam = segs.end_beam.reshape(n)
    hit = np.zeros(n, dtype=np.bool_)
    for a in range(n):
        for b in range(a + 1, min(a + window + 1, n)):
            if abs(beam[a] - beam[b]) > window or a // 2 == b // 2:
                continue
            d = math.hypot(ends[a, 0] - ends[b, 0], ends[a, 1] - ends[b, 1])
            if d <= corner_gap_m + sp[a] + sp[b]:
                hit[a] = True
            if d <= corner_gap_m + sp[b] + sp[a]:
                hit[b] = True
    return hit.reshape(n // 2, 2)


@njit(cache=True, nogil=True)
def _meeting_range(
    beams: BeamPoints, normal: FloatArray, dist_to_line: float, beam: int, s: _EowSettings
) -> float:
    """The range (metres) at which ``beam`` meets the line of unit ``normal`` at
    ``dist_to_line`` from the laser; NaN where the line is not judged along it (the beam
    runs along it or away from it, meets it at more than ``eow_max_incidence_deg`` or beyond
    ``range_max - eow_range_margin_m``)."""
    n_dot_u = dot2(normal[0], normal[1], beams.dirs[beam, 0], beams.dirs[beam, 1])
    if n_dot_u == 0.0:  # the beam runs along the line: no meeting range
        return math.nan
    r_pred = dist_to_line / n_dot_u
    if not (
        math.isfinite(r_pred)
        and r_pred > 0.0
        and abs(n_dot_u) >= s.cos_max_incidence
        and r_pred < s.range_limit_m
    ):
        return math.nan
    return r_pred


@njit(cache=True, nogil=True)
def _sees_past(
    beams: BeamPoints,
    normal: FloatArray,
    dist_to_line: float,
    end_xy: FloatArray,
    beam: int,
    outward: int,
    s: _EowSettings,
) -> bool:
    """Whether ``beam``, a step ``outward`` (-1 or +1 in beam order) beyond a segment's
    endpoint ``end_xy`` ``(2,)`` (robot frame, metres), sees past the line of unit ``normal``
    at ``dist_to_line`` from the laser (:func:`find_ends_of_wall`): it returns farther than
    where it meets the line, or nothing, unless the first return past its run of returnless
    beams lies on the line (within ``eow_range_margin_m``) and within
    ``eow_dropout_max_gap_m`` of the endpoint: there the wall visibly goes on, and the beams
    without a return are dropouts on it (a dark or glossy patch), not a view past its
    end."""
    r_pred = _meeting_range(beams, normal, dist_to_line, beam, s)
    if math.isnan(r_pred):
        return False
    if beams.valid[beam]:
        return beams.ranges[beam] > r_pred + s.range_margin_m
    if not beams.no_return[beam]:
        return False
    if s.dropout_max_gap_m <= 0.0:
        return True
    n_beams = beams.ranges.shape[0]
    b = beam + outward
    while 0 <= b < n_beams and not beams.valid[b]:
        b += outward
    if not 0 <= b < n_beams:
        return True
    r_next = _meeting_range(beams, normal, dist_to_line, b, s)
    if not abs(beams.ranges[b] - r_next) <= s.range_margin_m:
        return True
    gap = math.hypot(
        beams.origin[0] + beams.ranges[b] * beams.dirs[b, 0] - end_xy[0],
        beams.origin[1] + beams.ranges[b] * beams.dirs[b, 1] - end_xy[1],
    )
    return not gap <= s.dropout_max_gap_m


@njit(cache=True, nogil=True, error_model="numpy")
def _ends_of_wall(
    beams: BeamPoints,
    segs: Segments,
    dist_to_line: FloatArray,
    in_corner: BoolArray,
    s: _EowSettings,
) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray, IntArray]:
    """:func:`find_ends_of_wall`'s EOWs: segment, endpoint, position, covariance, unit
    direction into the wall and first beam beyond, ``(E,)`` / ``(E, 2)`` / ``(E, 2, 2)``."""
    m = segs.lines.shape[0]
    n_beams = beams.ranges.shape[0]
    junction = _junctions(segs, s.check_beams + 1, s.corner_gap_m)
    seg = np.empty(2 * m, dtype=np.int64)
    end = np.empty(2 * m, dtype=np.int64)
    n_e = 0
    for k in range(m):
        for e in range(2):
            if in_corner[k, e] or junction[k, e]:
                continue
            outward = -1 if e == 0 else 1
            ok = True
            for step in range(1, s.check_beams + 1):
                b = segs.end_beam[k, e] + outward * step
                inside = 0 <= b < n_beams
                if not (
                    inside
                    and _sees_past(
                        beams,
                        segs.normals[k],
                        dist_to_line[k],
                        segs.endpoints[k, e],
                        b,
                        outward,
                        s,
                    )
                ):
                    ok = False
                    break
            if ok:
                seg[n_e], end[n_e] = k, e
                n_e += 1
    seg, end = seg[:n_e], end[:n_e]
    beyond = np.empty(n_e, dtype=np.int64)
    wall_dir = np.empty((n_e, 2))
    wall_lines = np.empty((2 * n_e, 2))
    rays = np.empty((2 * n_e, 2))
    for q in range(n_e):
        k, e = seg[q], end[q]
        beyond[q] = segs.end_beam[k, e] + (-1 if e == 0 else 1)
        vx = segs.endpoints[k, 1 - e, 0] - segs.endpoints[k, e, 0]
        vy = segs.endpoints[k, 1 - e, 1] - segs.endpoints[k, e, 1]
        length = math.hypot(vx, vy)
        wall_dir[q, 0], wall_dir[q, 1] = vx / length, vy / length
        for r, b in ((q, segs.end_beam[k, e]), (n_e + q, beyond[q])):
            wall_lines[r, 0], wall_lines[r, 1] = segs.lines[k, 0], segs.lines[k, 1]
            rays[r, 0] = beams.bearing_robot[b] + 0.5 * np.pi  # normal of the beam's ray
            ray = rays[r, 0]
            rays[r, 1] = math.cos(ray) * beams.origin[0] + math.sin(ray) * beams.origin[1]
    hits, j_wall, _ = meet(wall_lines, rays)
    xy = np.empty((n_e, 2))
    along = np.empty((n_e, 2, 2))
    j_mid = np.empty((n_e, 2, 2))
    line_cov = np.empty((n_e, 2, 2))
    for q in range(n_e):
        xy[q, 0] = 0.5 * (hits[q, 0] + hits[n_e + q, 0])
        xy[q, 1] = 0.5 * (hits[q, 1] + hits[n_e + q, 1])
        gap = math.hypot(hits[n_e + q, 0] - hits[q, 0], hits[n_e + q, 1] - hits[q, 1])
        var_along = gap * gap / UNIFORM_VAR_DIVISOR
        for i in range(2):
            for j in range(2):
                # np.einsum's outer product: +0.0 where the product is -0.0
                along[q, i, j] = var_along * (wall_dir[q, i] * wall_dir[q, j] + 0.0)
                j_mid[q, i, j] = 0.5 * (j_wall[q, i, j] + j_wall[n_e + q, i, j])
                line_cov[q, i, j] = segs.cov[seg[q], i, j]
    return seg, end, xy, sandwich(j_mid, line_cov) + along, wall_dir, beyond
