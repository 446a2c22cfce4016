"""Intersection features: two segments' infinite lines meeting near both (paper §III-B,
Fig. 1-2; docs/design.md step 4)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from iceg.features.config import FeatureConfig
from iceg.features.corners import Corners
from iceg.features.geometry import dot2
from iceg.features.neighbours import close_pairs, close_to_any
from iceg.features.pairs import SegmentPairs
from iceg.features.points import BeamPoints
from iceg.features.segments import Segments
from iceg_common.numba_loading import njit

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


class Intersections(NamedTuple):
    """I Intersection features, robot frame."""

    pairs: IntArray  # (I, 2) int64 the two segments
    xy: FloatArray  # (I, 2) float64 the lines' meeting point, metres
    cov: FloatArray  # (I, 2, 2) float64 its covariance, m²
    opening: FloatArray  # (I,) float64 angle between the rays to the far endpoints, radians

    @classmethod
    def empty(cls) -> Intersections:
        """No intersections."""
        return cls(
            np.zeros((0, 2), dtype=np.int64), np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros(0)
        )


def acceptable(
    beams: BeamPoints, segs: Segments, pairs: SegmentPairs, corners: Corners, cfg: FeatureConfig
) -> BoolArray:
    """Which steep pairs may be Intersections: not a corner pair, meeting point within
    ``intersection_max_distance_m`` of both segments and inside the usable range, position
    standard deviation at most ``intersection_max_std_m``, and farther than
    ``intersection_duplicate_m`` from every corner (:func:`~iceg.features.neighbours.
    close_to_any`; the other tests compiled, :func:`_acceptable`).

    Returns:
        ``(Q,)`` bool.
    """
    m = segs.lines.shape[0]
    corner_code = np.sort(corners.pairs[:, 0] * m + corners.pairs[:, 1])
    ok = _acceptable(
        segs.endpoints,
        pairs,
        corner_code,
        beams.origin,
        beams.range_max,
        cfg.intersection_max_distance_m,
        cfg.intersection_max_std_m**2,
    )
    return ok & ~close_to_any(pairs.xy, corners.xy, cfg.intersection_duplicate_m)


@njit(cache=True, nogil=True, error_model="numpy")
def _acceptable(
    endpoints: FloatArray,
    pairs: SegmentPairs,
    corner_code: IntArray,
    origin: FloatArray,
    range_max_m: float,
    max_distance_m: float,
    max_var_m2: float,
) -> BoolArray:
    """:func:`acceptable` but for the distance to the corners, pair by pair (``corner_code``:
    the corners' pairs ``first * M + second``, sorted): the meeting point's distance to both
    segments, its distance from the laser and the largest eigenvalue of its covariance
    (closed form), with the values of the numpy expressions they replaced."""
    m = endpoints.shape[0]
    q = pairs.first.shape[0]
    ok = np.empty(q, dtype=np.bool_)
    for r in range(q):
        i, j = pairs.first[r], pairs.second[r]
        x, y = pairs.xy[r, 0], pairs.xy[r, 1]
        code = i * m + j
        at = np.searchsorted(corner_code, code)
        is_corner = at < corner_code.shape[0] and corner_code[at] == code
        c = pairs.cov[r]
        largest = 0.5 * (c[0, 0] + c[1, 1]) + math.sqrt(
            0.25 * (c[0, 0] - c[1, 1]) ** 2 + c[0, 1] * c[0, 1]
        )
        ok[r] = (
            not is_corner
            and _point_segment_distance(x, y, endpoints[i]) <= max_distance_m
            and _point_segment_distance(x, y, endpoints[j]) <= max_distance_m
            and math.hypot(x - origin[0], y - origin[1]) < range_max_m
            and largest <= max_var_m2
        )
    return ok


@njit(cache=True, nogil=True, error_model="numpy")
def _point_segment_distance(x: float, y: float, ends: FloatArray) -> float:
    """Distance of the point ``(x, y)`` to the segment ``ends`` ``(2, 2)``, metres."""
    ax, ay = ends[0, 0], ends[0, 1]
    ex, ey = ends[1, 0] - ax, ends[1, 1] - ay
    t = dot2(x - ax, y - ay, ex, ey) / dot2(ex, ey, ex, ey)
    if t < 0.0:  # np.clip: NaN stays NaN
        t = 0.0
    elif t > 1.0:
        t = 1.0
    return math.hypot(x - (ax + t * ex), y - (ay + t * ey))


def best_determined(xy: FloatArray, cov: FloatArray, duplicate_m: float) -> IntArray:
    """Of meeting points within ``duplicate_m`` of each other (the same wall meeting split
    into collinear pieces), keep the best determined: greedy in increasing covariance trace
    (stable), a point is dropped when a kept one lies within ``duplicate_m``.

    Args:
        xy: ``(K, 2)`` float64 candidate positions, metres.
        cov: ``(K, 2, 2)`` float64 their covariances, m².
        duplicate_m: Distance, metres.

    Returns:
        ``(S,)`` int64 indices into the candidates, in increasing trace.
    """
    order = np.argsort(np.trace(cov, axis1=1, axis2=2), kind="stable")
    near = close_pairs(xy[order], duplicate_m)  # (a, b) positions in `order`, a < b
    return order[_kept_first(near, order.size)]


@njit(cache=True, nogil=True)
def _kept_first(near: IntArray, n: int) -> BoolArray:
    """``(n,)`` bool: the greedy of :func:`best_determined` over positions ``0 .. n - 1``,
    ``near`` ``(K, 2)`` the pairs ``(a, b)``, ``a < b``, sorted by ``a``: a kept position
    drops every later one near it (a position's own keep is settled before its pairs)."""
    keep = np.ones(n, dtype=np.bool_)
    for k in range(near.shape[0]):
        if keep[near[k, 0]]:
            keep[near[k, 1]] = False
    return keep


def find_intersections(
    beams: BeamPoints, segs: Segments, pairs: SegmentPairs, corners: Corners, cfg: FeatureConfig
) -> Intersections:
    """Intersections: steep pairs not forming a corner whose lines meet near both segments
    (:func:`acceptable`), duplicates removed (:func:`best_determined`). Opening angle between
    the rays from the point toward the far endpoint of each segment; no direction.

    Args:
        beams: The scan's beams.
        segs: Its segments.
        pairs: Their steep pairs.
        corners: The corners found among them.
        cfg: ``intersection_max_distance_m``, ``intersection_max_std_m``,
            ``intersection_duplicate_m``.

    Returns:
        :class:`Intersections`, in increasing covariance trace.
    """
    if pairs.first.size == 0:
        return Intersections.empty()
    cand = np.flatnonzero(acceptable(beams, segs, pairs, corners, cfg))
    if cand.size == 0:
        return Intersections.empty()
    sel = cand[best_determined(pairs.xy[cand], pairs.cov[cand], cfg.intersection_duplicate_m)]
    return Intersections(*_intersections(segs.endpoints, pairs, sel))


@njit(cache=True, nogil=True, error_model="numpy")
def _intersections(
    endpoints: FloatArray, pairs: SegmentPairs, sel: IntArray
) -> tuple[IntArray, FloatArray, FloatArray, FloatArray]:
    """The fields of :class:`Intersections` for the pairs ``sel``: the opening between the
    rays from each meeting point toward each segment's far endpoint (the farther one; the
    first of equal distances)."""
    n = sel.shape[0]
    inter_pairs = np.empty((n, 2), dtype=np.int64)
    xy = np.empty((n, 2))
    cov = np.empty((n, 2, 2))
    opening = np.empty(n)
    ray = np.empty((2, 2))
    for r in range(n):
        k = sel[r]
        inter_pairs[r, 0], inter_pairs[r, 1] = pairs.first[k], pairs.second[k]
        xy[r] = pairs.xy[k]
        cov[r] = pairs.cov[k]
        for side in range(2):
            e = endpoints[inter_pairs[r, side]]
            d0 = math.hypot(e[0, 0] - xy[r, 0], e[0, 1] - xy[r, 1])
            d1 = math.hypot(e[1, 0] - xy[r, 0], e[1, 1] - xy[r, 1])
            far = 1 if d1 > d0 or (math.isnan(d1) and not math.isnan(d0)) else 0  # argmax
            vx, vy = e[far, 0] - xy[r, 0], e[far, 1] - xy[r, 1]
            length = math.hypot(vx, vy)
            ray[side, 0], ray[side, 1] = vx / length, vy / length
        cos_open = dot2(ray[0, 0], ray[0, 1], ray[1, 0], ray[1, 1])
        if cos_open < -1.0:  # np.clip: NaN stays NaN
            cos_open = -1.0
        elif cos_open > 1.0:
            cos_open = 1.0
        opening[r] = math.acos(cos_open)
    return inter_pairs, xy, cov, opening
