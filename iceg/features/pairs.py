"""Segment pairs whose lines meet steeply: the candidates of Corners and Intersections.

Paper §III-B, Fig. 1-2; docs/design.md step 4 (lines meeting at 30°-150°).
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from iceg.features.config import FeatureConfig
from iceg.features.geometry import line_intersections
from iceg.features.neighbours import segment_pairs_within
from iceg.features.segments import Segments
from iceg_common.numba_loading import njit

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class SegmentPairs(NamedTuple):
    """Q segment pairs ``(first < second)`` whose lines meet steeply, robot frame."""

    first: IntArray  # (Q,) int64 segment index
    second: IntArray  # (Q,) int64 segment index, > first
    xy: FloatArray  # (Q, 2) float64 meeting point of the two infinite lines, metres
    cov: FloatArray  # (Q, 2, 2) float64 its covariance, m²


def pair_search_radius(segs: Segments, cfg: FeatureConfig) -> float:
    """Largest segment-to-segment distance at which a pair can still give a feature, metres.

    An Intersection lies within ``intersection_max_distance_m`` of both segments, so they are
    at most twice that apart; a Corner's facing endpoints are at most ``corner_gap_m`` plus
    the two endpoints' beam spacings apart.
    """
    widest = float(segs.spacing.max()) if segs.spacing.size else 0.0
    return max(2.0 * cfg.intersection_max_distance_m, cfg.corner_gap_m + 2.0 * widest)


def meeting_pairs(segs: Segments, cfg: FeatureConfig) -> SegmentPairs:
    """Segment pairs whose lines meet at ``meeting_angle_min_deg``-``180 - that`` degrees,
    with the lines' meeting point and its first-order covariance (paper §III-B).

    Only pairs within :func:`pair_search_radius` of each other are considered (a KD-tree
    neighbourhood, linear in M; issue 12); farther pairs can form no feature.

    Args:
        segs: The scan's segments.
        cfg: ``meeting_angle_min_deg``, ``intersection_max_distance_m``, ``corner_gap_m``.

    Returns:
        :class:`SegmentPairs`, sorted by ``first`` then ``second``.
    """
    ii, jj = segment_pairs_within(segs.endpoints, pair_search_radius(segs, cfg))
    sin_min = math.sin(math.radians(cfg.meeting_angle_min_deg))
    ii, jj = np.ascontiguousarray(ii), np.ascontiguousarray(jj)  # one compiled layout
    return SegmentPairs(*_steep_pairs(ii, jj, segs.lines, segs.cov, sin_min))


@njit(cache=True, nogil=True)
def _steep_pairs(
    ii: IntArray, jj: IntArray, lines: FloatArray, cov: FloatArray, sin_min: float
) -> tuple[IntArray, IntArray, FloatArray, FloatArray]:
    """The pairs ``(ii, jj)`` whose lines meet with ``|sin(alpha_i - alpha_j)| >= sin_min``,
    with their meeting points and covariances (:func:`line_intersections`), compiled: the
    values of the numpy expressions it replaced, bit for bit."""
    steep = np.empty(ii.shape[0], dtype=np.bool_)
    for q in range(ii.shape[0]):
        steep[q] = abs(math.sin(lines[ii[q], 0] - lines[jj[q], 0])) >= sin_min
    ii, jj = ii[steep], jj[steep]
    xy, pair_cov = line_intersections(lines[ii], cov[ii], lines[jj], cov[jj])
    return ii, jj, xy, pair_cov
