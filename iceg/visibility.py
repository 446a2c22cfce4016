"""Which landmarks a scan should see: the compiled test behind the feature map's
time-validity counters (paper §III-C3; docs/design.md "Feature map and time-validity").

A landmark is **expected** in a scan when every support point it has lies inside the scan's
field of view (less a margin) and the expected range and is not occluded (both beams around
its bearing reach at least its distance less a tolerance, with no gap of missing beams
between them), and its walls are seen from the side they were seen from before and not at
grazing incidence: both walls for an Intersection, one for a Corner or an EOW (a Corner
whose other wall faces away shows as an EOW, paper §III-C2).

One loop per landmark instead of some forty numpy calls over ``(n, 3, 2)`` temporaries; the
arithmetic is that of the numpy expressions it replaced, term for term, so the answers are
the same bit for bit (``tests/iceg/test_feature_map.py``).

Each scan's matches and expectations update the counters (:func:`count_observations`), and
the counters then decide which landmarks go (:func:`pruned_landmarks`): the ratio and
time-validity tests of paper §III-C3 in one pass over them. What the test reads of a new scan
alone is computed once per scan, also compiled: its features' support points and walls
(:func:`visibility_geometry`) and its beams by bearing (:func:`beam_profile`).
"""

from __future__ import annotations

import math

import numpy as np

from iceg.numpy_sums import median
from iceg_common.numba_loading import njit


@njit(cache=True, nogil=True)
def _sign(v: float) -> float:
    """``np.sign`` of a float (NaN stays NaN; -0.0 gives +0.0, as numpy's does)."""
    if v > 0.0:
        return 1.0
    if v < 0.0:
        return -1.0
    return 0.0 if v == 0.0 else v


@njit(cache=True, nogil=True)
def beam_profile(
    angles: np.ndarray, ranges: np.ndarray, range_min_m: float, range_max_m: float
) -> tuple[np.ndarray, np.ndarray, float]:
    """A scan's beams by bearing for the visibility test: ``(N,)`` bearings (rad, stable
    order) and ranges (metres: a valid return's range, ``inf`` for a finite return at or
    beyond ``range_max_m``, which blocks nothing, 0 for any other invalid beam, which
    blocks the view), and the median step between consecutive bearings (rad; NaN under two
    beams). The numpy expressions' values (``feature_map._BeamProfile.of_scan``)."""
    n = angles.shape[0]
    order = np.argsort(angles, kind="mergesort")
    bearing = angles[order]
    beam_r = np.empty(n)
    for i in range(n):
        r = ranges[order[i]]
        if math.isfinite(r) and range_min_m < r < range_max_m:
            beam_r[i] = r
        elif math.isfinite(r) and r >= range_max_m:
            beam_r[i] = np.inf
        else:
            beam_r[i] = 0.0
    if n < 2:
        return bearing, beam_r, np.nan
    return bearing, beam_r, median(bearing[1:] - bearing[:-1])


@njit(cache=True, nogil=True)
def visibility_geometry(
    kind: np.ndarray,
    xy: np.ndarray,
    directions: np.ndarray,
    segment_ids: np.ndarray,
    seg_endpoints: np.ndarray,
    offset_m: float,
    intersection: int,
    min_norm: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Visibility geometry of each of a scan's ``K`` features in its frame (NaN-padded;
    ``iceg.feature_map`` keeps it with the landmarks the features become).

    Args:
        kind, xy, directions, segment_ids: The features' ``(K,)`` int64 kinds, ``(K, 2)``
            float64 positions (m), ``(K, 2, 2)`` float64 unit edge directions and ``(K, 2)``
            int64 segments, robot frame.
        seg_endpoints: ``(M, 2, 2)`` float64 the scan's segment endpoints, metres.
        offset_m: How far along a wall its support point lies, metres.
        intersection: The Intersection kind's code.
        min_norm: Floor of a segment's length where its direction is normalised, metres.

    Returns:
        ``support`` ``(K, 3, 2)``: points that must be in view and not occluded: the point
        and ``offset_m`` along each wall for Corners and EOWs (the second wall NaN for an
        EOW); for an Intersection a point ``offset_m`` inside each of its two segments from
        the end nearest to it (a segment id outside the scan's leaves its rows NaN).
        ``wall_p``, ``wall_d`` ``(K, 2, 2)``: a point on each wall and the wall's direction.
        ``wall_side`` ``(K, 2)``: on which side of each wall the sensor stood (+1 / -1): a
        wall is extracted from the side it was seen from. The values of the numpy
        expressions this replaced (``np.linalg.norm``'s sum of squares, ``np.argmin``'s
        first nearest end, ``np.sign``) bit for bit.
    """
    k = kind.shape[0]
    m = seg_endpoints.shape[0]
    support = np.full((k, 3, 2), np.nan)
    wall_p = np.full((k, 2, 2), np.nan)
    wall_d = np.full((k, 2, 2), np.nan)
    wall_side = np.full((k, 2), np.nan)
    for f in range(k):
        x, y = xy[f, 0], xy[f, 1]
        if kind[f] != intersection:
            support[f, 0, 0], support[f, 0, 1] = x, y
            for w in range(2):
                dx, dy = directions[f, w, 0], directions[f, w, 1]
                support[f, w + 1, 0] = x + offset_m * dx
                support[f, w + 1, 1] = y + offset_m * dy
                wall_p[f, w, 0], wall_p[f, w, 1] = x, y
                wall_d[f, w, 0], wall_d[f, w, 1] = dx, dy
        else:
            for w in range(2):
                sid = segment_ids[f, w]
                if sid < 0 or sid >= m:
                    continue
                ep = seg_endpoints[sid]
                d0 = math.sqrt((ep[0, 0] - x) ** 2 + (ep[0, 1] - y) ** 2)
                d1 = math.sqrt((ep[1, 0] - x) ** 2 + (ep[1, 1] - y) ** 2)
                near = 1 if d1 < d0 or (math.isnan(d1) and not math.isnan(d0)) else 0
                ux = ep[1 - near, 0] - ep[near, 0]
                uy = ep[1 - near, 1] - ep[near, 1]
                length = math.sqrt(ux**2 + uy**2)
                scale = length if not length < min_norm else min_norm  # np.maximum
                ux, uy = ux / scale, uy / scale
                support[f, w, 0] = ep[near, 0] + offset_m * ux
                support[f, w, 1] = ep[near, 1] + offset_m * uy
                wall_p[f, w, 0], wall_p[f, w, 1] = ep[near, 0], ep[near, 1]
                wall_d[f, w, 0], wall_d[f, w, 1] = ux, uy
        for w in range(2):
            wall_side[f, w] = _sign(
                wall_d[f, w, 1] * wall_p[f, w, 0] - wall_d[f, w, 0] * wall_p[f, w, 1]
            )
    return support, wall_p, wall_d, wall_side


@njit(cache=True, nogil=True)
def _clear(
    b: float,
    dist: float,
    bearing: np.ndarray,
    range_m: np.ndarray,
    max_gap_rad: float,
    tolerance_m: float,
) -> bool:
    """Both beams around bearing ``b`` reach ``dist - tolerance_m`` and no gap lies between
    them (``bearing`` ascending, ``range_m`` their ranges; one beam: it and the last)."""
    nb = bearing.shape[0]
    k = min(max(np.searchsorted(bearing, b), 1), nb - 1)
    if bearing[k] - bearing[k - 1] > max_gap_rad:
        return False
    r0, r1 = range_m[k - 1], range_m[k]
    near = r1 if math.isnan(r0) else (r0 if math.isnan(r1) else min(r0, r1))  # np.fmin
    return near >= dist - tolerance_m


@njit(cache=True, nogil=True)
def expected_landmarks(
    rows: np.ndarray,
    anchor_in_new: np.ndarray,
    support: np.ndarray,
    wall_p: np.ndarray,
    wall_d: np.ndarray,
    wall_side: np.ndarray,
    kind: np.ndarray,
    intersection_kind: int,
    bearing: np.ndarray,
    range_m: np.ndarray,
    max_gap_rad: float,
    sensor_pose: np.ndarray,
    fov_margin_rad: float,
    expected_max_range_m: float,
    occlusion_tolerance_m: float,
    sin_min_incidence: float,
) -> np.ndarray:
    """Which of the landmarks ``rows`` a scan should see (see the module docstring).

    Args:
        rows: ``(n,)`` int64 landmark rows into the per-landmark arrays below.
        anchor_in_new: ``(n, 3)`` float64 each landmark's anchor pose in the scan's robot
            frame ``[x_m, y_m, theta_rad]``.
        support: ``(L, 3, 2)`` float64 support points, anchor frame, metres (NaN: none).
        wall_p, wall_d: ``(L, 2, 2)`` float64 a point on each wall and its direction, anchor
            frame (NaN: no wall).
        wall_side: ``(L, 2)`` float64 side (+1 / -1) each wall was seen from (NaN: none).
        kind: ``(L,)`` int64 feature kinds; ``intersection_kind`` the Intersection's.
        bearing, range_m: ``(B,)`` float64 the scan's beams by ascending bearing (sensor
            frame, radians) and their ranges (metres; 0 blocks the view, inf does not),
            ``B >= 1``.
        max_gap_rad: Bearing step beyond which two neighbouring beams leave a gap.
        sensor_pose: ``(3,)`` float64 laser pose in the robot frame, or ``(0,)`` when the
            bearings are seen from the robot frame's origin.
        fov_margin_rad, expected_max_range_m, occlusion_tolerance_m: Field-of-view margin,
            range and occlusion allowance.
        sin_min_incidence: Sine of the smallest incidence at which a wall counts as seen.

    Returns:
        ``(n,)`` bool.
    """
    n = rows.shape[0]
    out = np.zeros(n, dtype=np.bool_)
    lo = bearing[0] + fov_margin_rad
    hi = bearing[bearing.shape[0] - 1] - fov_margin_rad
    offset = sensor_pose.shape[0] == 3
    cs, ss = (math.cos(sensor_pose[2]), math.sin(sensor_pose[2])) if offset else (1.0, 0.0)
    for i in range(n):
        row = rows[i]
        c, s = math.cos(anchor_in_new[i, 2]), math.sin(anchor_in_new[i, 2])
        tx, ty = anchor_in_new[i, 0], anchor_in_new[i, 1]
        any_point = False
        visible = True
        for k in range(3):
            px, py = support[row, k, 0], support[row, k, 1]
            x = c * px + -s * py + tx
            y = s * px + c * py + ty
            if not (math.isfinite(x) and math.isfinite(y)):
                continue
            any_point = True
            if offset:
                dx, dy = x - sensor_pose[0], y - sensor_pose[1]
                x, y = cs * dx + ss * dy, -ss * dx + cs * dy
            b = math.atan2(y, x)
            d = math.hypot(x, y)
            if not (
                b >= lo
                and b <= hi
                and d <= expected_max_range_m
                and _clear(b, d, bearing, range_m, max_gap_rad, occlusion_tolerance_m)
            ):
                visible = False
                break
        if not (visible and any_point):
            continue
        n_walls, n_seen = 0, 0
        for k in range(2):
            side_before = wall_side[row, k]
            if not math.isfinite(side_before):
                continue
            n_walls += 1
            qx, qy = wall_p[row, k, 0], wall_p[row, k, 1]
            ux, uy = wall_d[row, k, 0], wall_d[row, k, 1]
            px = c * qx + -s * qy + tx
            py = s * qx + c * qy + ty
            dx = c * ux + -s * uy
            dy = s * ux + c * uy
            norm = math.hypot(px, py)
            if norm < 1e-9:  # np.maximum(norm, 1e-9), NaN kept
                norm = 1e-9
            sin_inc = abs(px / norm * dy - py / norm * dx)
            if _sign(dy * px - dx * py) == side_before and sin_inc >= sin_min_incidence:
                n_seen += 1
        if kind[row] == intersection_kind:
            out[i] = n_walls > 0 and n_seen == n_walls
        else:
            out[i] = n_seen > 0
    return out


@njit(cache=True, nogil=True)
def count_observations(
    rows: np.ndarray,
    expected: np.ndarray,
    pair_row: np.ndarray,
    stamp_s: float,
    node_id: int,
    n_expected: np.ndarray,
    n_matched: np.ndarray,
    misses: np.ndarray,
    first_miss_s: np.ndarray,
    last_matched_s: np.ndarray,
    last_node: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """One scan's update of the time-validity counters (paper §III-C3), in place: a
    matched landmark counts as expected and matched, its misses reset (last matched now,
    by ``node_id``); an expected landmark not matched counts as expected and missed (its
    first miss now, unless it is already missing).

    Args:
        rows: ``(n,)`` int64 distinct landmark rows taking part; ``expected`` ``(n,)`` bool
            whether the scan should see each.
        pair_row: ``(m,)`` int64 rows of the matched landmarks (among ``rows``; repeats
            allowed).
        stamp_s: The scan's time, seconds.
        n_expected, n_matched, misses: ``(L,)`` int64 counters; ``first_miss_s``,
            ``last_matched_s`` ``(L,)`` float64 times (NaN: none); ``last_node`` ``(L,)``
            int64.

    Returns:
        The matched rows ``(k,)`` int64 (ascending, each once) and the rows counted as
        expected ``(e,)`` int64 (in the order of ``rows``).
    """
    matched = np.unique(pair_row)
    is_matched = np.zeros(n_expected.shape[0], dtype=np.bool_)
    for r in matched:
        is_matched[r] = True
    counted = np.empty(rows.shape[0], dtype=np.int64)
    e = 0
    for i in range(rows.shape[0]):
        r = rows[i]
        if expected[i] or is_matched[r]:
            n_expected[r] += 1
            counted[e] = r
            e += 1
    for r in matched:
        n_matched[r] += 1
        last_matched_s[r] = stamp_s
        misses[r] = 0
        first_miss_s[r] = np.nan
        last_node[r] = node_id
    for i in range(rows.shape[0]):
        r = rows[i]
        if expected[i] and not is_matched[r]:
            misses[r] += 1
            if math.isnan(first_miss_s[r]):
                first_miss_s[r] = stamp_s
    return matched, counted[:e].copy()


@njit(cache=True, nogil=True)
def pruned_landmarks(
    n_expected: np.ndarray,
    n_matched: np.ndarray,
    misses: np.ndarray,
    last_matched_s: np.ndarray,
    first_miss_s: np.ndarray,
    stamp_s: float,
    min_expected: int,
    min_match_ratio: float,
    min_misses: int,
    validity_s: float,
    miss_confirm_s: float,
) -> tuple[np.ndarray, np.ndarray]:
    """The landmarks the ratio and time-validity tests prune at ``stamp_s`` (paper §III-C3;
    ``FeatureMap._prune``): expected at least ``min_expected`` times and matched in fewer
    than ``min_match_ratio`` of them, or stale: ``min_misses`` consecutive expected misses,
    unmatched for ``validity_s`` and missed for ``miss_confirm_s`` since the first of them
    (a NaN time is never stale). One pass over the ``(L,)`` counters (int64) and times
    (float64, seconds) instead of eight numpy calls; the same comparisons.

    Returns:
        ``(rows (k,) int64 ascending, stale (k,) bool)``: the pruned rows and which of them
        the time-validity test prunes (else the ratio test). Raises nothing.
    """
    n = n_expected.shape[0]
    rows = np.empty(n, dtype=np.int64)
    stale = np.empty(n, dtype=np.bool_)
    k = 0
    for i in range(n):
        ratio = n_expected[i] >= min_expected and n_matched[i] < min_match_ratio * n_expected[i]
        old = (
            misses[i] >= min_misses
            and stamp_s - last_matched_s[i] >= validity_s
            and stamp_s - first_miss_s[i] >= miss_confirm_s
        )
        if ratio or old:
            rows[k] = i
            stale[k] = old
            k += 1
    return rows[:k], stale[:k]
