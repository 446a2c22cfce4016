"""Intersection features: two segments' infinite lines meeting near both (paper §III-B,
Fig. 1-2; docs/design.md step 4)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from iceg.features.config import FeatureConfig
from iceg.features.corners import Corners
from iceg.features.geometry import (
    max_eigenvalue,
    norm,
    opening_angle,
    point_segment_distance,
    unit,
)
from iceg.features.neighbours import close_pairs, close_to_any
from iceg.features.pairs import SegmentPairs
from iceg.features.points import BeamPoints
from iceg.features.segments import Segments

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
    ``intersection_duplicate_m`` from every corner.

    Returns:
        ``(Q,)`` bool.
    """
    ii, jj, xy = pairs.first, pairs.second, pairs.xy
    m = segs.lines.shape[0]
    d_max = cfg.intersection_max_distance_m
    ok = (
        ~_is_corner_pair(ii * m + jj, corners.pairs[:, 0] * m + corners.pairs[:, 1])
        & (point_segment_distance(xy, segs.endpoints[ii, 0], segs.endpoints[ii, 1]) <= d_max)
        & (point_segment_distance(xy, segs.endpoints[jj, 0], segs.endpoints[jj, 1]) <= d_max)
        & (norm(xy - beams.origin) < beams.range_max)
        & (max_eigenvalue(pairs.cov) <= cfg.intersection_max_std_m**2)
    )
    return ok & ~close_to_any(xy, corners.xy, cfg.intersection_duplicate_m)


def _is_corner_pair(pair_code: IntArray, corner_code: IntArray) -> BoolArray:
    """``(Q,)`` bool: which pair codes ``first * M + second`` are among the corners' codes
    (a sorted look-up, ``O(Q log C)``)."""
    if corner_code.size == 0:
        return np.zeros(pair_code.shape[0], dtype=bool)
    codes = np.sort(corner_code)
    pos = np.minimum(np.searchsorted(codes, pair_code), codes.size - 1)
    hit: BoolArray = codes[pos] == pair_code
    return hit


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
    starts = np.searchsorted(near[:, 0], np.arange(order.size + 1))
    keep = np.ones(order.size, dtype=bool)
    for a in range(order.size):
        if keep[a]:
            keep[near[starts[a] : starts[a + 1], 1]] = False
    return order[keep]


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
    inter_pairs = np.stack([pairs.first[sel], pairs.second[sel]], axis=1)
    xy = pairs.xy[sel]
    far = []
    for col in (0, 1):
        e = segs.endpoints[inter_pairs[:, col]]  # (I, 2, 2)
        far.append(e[np.arange(sel.size), np.argmax(norm(e - xy[:, None, :]), axis=1)])
    opening = opening_angle(unit(far[0] - xy), unit(far[1] - xy))
    return Intersections(inter_pairs, xy, pairs.cov[sel], opening)
