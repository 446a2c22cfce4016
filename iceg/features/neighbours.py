"""Bounded-neighbourhood searches of feature extraction (issue 12: linear in the segments).

Feature tests only ever relate segments, endpoints or points that lie within a few metres of
each other, so instead of all ``O(M²)`` pairs a KD-tree (``scipy.spatial.cKDTree``) lists
the pairs within the test's radius, and the test's own arithmetic then decides on those
pairs exactly as it would on all pairs. Below ``DENSE_MAX_ROWS`` rows all pairs are cheaper
than a tree and are used directly; both give the same pairs after the exact test.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

from iceg.features.geometry import norm
from iceg_common.numba_loading import njit

if TYPE_CHECKING:
    from scipy.spatial import cKDTree

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


def _kdtree() -> type[cKDTree]:
    """scipy's ``cKDTree``, imported on first use (scipy costs most of a cold start, and
    most scans never need a tree)."""
    from scipy.spatial import cKDTree

    return cKDTree


# Up to this many rows all pairs are enumerated directly (a tree costs more than it saves).
DENSE_MAX_ROWS = 64
# KD-tree radii are widened by this relative and absolute slack, so that points the exact
# test (``hypot``) puts within the radius are never lost to the tree's own rounding.
_RADIUS_SLACK_REL = 1e-9
_RADIUS_SLACK_M = 1e-9
# Segments are sampled at most this far apart (metres) for the segment neighbourhood search.
SEGMENT_SAMPLE_STEP_M = 1.0


# All pairs (a < b) of up to DENSE_MAX_ROWS rows, as a mask: np.nonzero of a slice is ten
# times cheaper than np.triu_indices and gives the same pairs in the same order.
_UPPER = np.triu(np.ones((DENSE_MAX_ROWS, DENSE_MAX_ROWS), dtype=bool), k=1)


def _all_pairs(n: int) -> tuple[IntArray, IntArray]:
    """``np.triu_indices(n, k=1)`` for ``n <= DENSE_MAX_ROWS``: ``(K,)`` int64 each."""
    if n > _UPPER.shape[0]:
        a, b = np.triu_indices(n, k=1)
    else:
        a, b = np.nonzero(_UPPER[:n, :n])
    return a.astype(np.int64, copy=False), b.astype(np.int64, copy=False)


def _tree_radius(radius_m: float) -> float:
    return radius_m * (1.0 + _RADIUS_SLACK_REL) + _RADIUS_SLACK_M


def _lexicographic(first: IntArray, second: IntArray, n: int) -> IntArray:
    """Unique pairs ``(a, b)``, ``a < b < n``, sorted by ``a`` then ``b``: ``(Q, 2)`` int64."""
    a = np.minimum(first, second).astype(np.int64)
    b = np.maximum(first, second).astype(np.int64)
    code = np.unique((a * n + b)[a != b])
    return np.stack([code // n, code % n], axis=1)


def close_pairs(xy: FloatArray, radius_m: float) -> IntArray:
    """Pairs of points within ``radius_m`` of each other.

    Args:
        xy: ``(Q, 2)`` float64 points, metres.
        radius_m: Largest distance, metres (``hypot(xy[a] - xy[b]) <= radius_m``).

    Returns:
        ``(K, 2)`` int64 pairs ``(a, b)`` with ``a < b``, sorted by ``a`` then ``b``.
    """
    q = xy.shape[0]
    if q <= DENSE_MAX_ROWS:
        return _close_pairs_dense(np.ascontiguousarray(xy, dtype=np.float64), float(radius_m))
    cand = _kdtree()(xy).query_pairs(_tree_radius(radius_m), output_type="ndarray")
    a, b = _lexicographic(cand[:, 0], cand[:, 1], q).T
    near = norm(xy[a] - xy[b]) <= radius_m
    return np.stack([a[near], b[near]], axis=1).astype(np.int64, copy=False)


def close_to_any(xy: FloatArray, ref: FloatArray, radius_m: float) -> BoolArray:
    """Which points lie within ``radius_m`` of at least one reference point.

    Args:
        xy: ``(Q, 2)`` float64 points, metres.
        ref: ``(R, 2)`` float64 reference points, metres.
        radius_m: Largest distance, metres (``hypot(xy[q] - ref[r]) <= radius_m``).

    Returns:
        ``(Q,)`` bool.
    """
    out = np.zeros(xy.shape[0], dtype=bool)
    if xy.shape[0] == 0 or ref.shape[0] == 0:
        return out
    if xy.shape[0] * ref.shape[0] <= DENSE_MAX_ROWS**2:
        xy, ref = np.ascontiguousarray(xy, np.float64), np.ascontiguousarray(ref, np.float64)
        return _close_to_any_dense(xy, ref, float(radius_m))
    lists = _kdtree()(ref).query_ball_point(xy, _tree_radius(radius_m))
    counts = np.array([len(li) for li in lists], dtype=np.int64)
    q = np.repeat(np.arange(xy.shape[0]), counts)
    r = np.fromiter((k for li in lists for k in li), dtype=np.int64, count=int(counts.sum()))
    out[q[norm(xy[q] - ref[r]) <= radius_m]] = True
    return out


@njit(cache=True, nogil=True)
def _close_pairs_dense(xy: FloatArray, radius_m: float) -> IntArray:
    """:func:`close_pairs` by testing every pair, in ``np.triu_indices`` order."""
    q = xy.shape[0]
    out = np.empty((q * (q - 1) // 2, 2), dtype=np.int64)
    n = 0
    for a in range(q):
        for b in range(a + 1, q):
            if math.hypot(xy[a, 0] - xy[b, 0], xy[a, 1] - xy[b, 1]) <= radius_m:
                out[n, 0], out[n, 1] = a, b
                n += 1
    return out[:n]


@njit(cache=True, nogil=True)
def _close_to_any_dense(xy: FloatArray, ref: FloatArray, radius_m: float) -> BoolArray:
    """:func:`close_to_any` by testing every point against every reference point."""
    out = np.zeros(xy.shape[0], dtype=np.bool_)
    for q in range(xy.shape[0]):
        for r in range(ref.shape[0]):
            if math.hypot(xy[q, 0] - ref[r, 0], xy[q, 1] - ref[r, 1]) <= radius_m:
                out[q] = True
                break
    return out


def segment_pairs_within(endpoints: FloatArray, radius_m: float) -> tuple[IntArray, IntArray]:
    """Segment pairs that may lie within ``radius_m`` of each other (a superset).

    Each segment is sampled at most ``SEGMENT_SAMPLE_STEP_M`` apart along its length, so
    every point of it is within half a step of a sample: two segments closer than
    ``radius_m`` have samples closer than ``radius_m + SEGMENT_SAMPLE_STEP_M``.

    Args:
        endpoints: ``(M, 2, 2)`` float64 segment endpoints, metres.
        radius_m: Segment-to-segment distance of interest, metres.

    Returns:
        ``ii``, ``jj`` ``(Q,)`` int64 with ``ii < jj``, sorted by ``ii`` then ``jj``; all
        pairs (``np.triu_indices`` order) when ``M <= DENSE_MAX_ROWS``.
    """
    m = endpoints.shape[0]
    if m <= DENSE_MAX_ROWS:
        return _all_pairs(m)
    length = norm(endpoints[:, 1] - endpoints[:, 0])
    n_samples = np.ceil(length / SEGMENT_SAMPLE_STEP_M).astype(np.int64) + 1
    seg_of = np.repeat(np.arange(m), n_samples)
    first = np.cumsum(n_samples) - n_samples
    t = (np.arange(seg_of.shape[0]) - first[seg_of]) / (n_samples[seg_of] - 1)
    a, b = endpoints[seg_of, 0], endpoints[seg_of, 1]
    samples = a + t[:, None] * (b - a)
    reach = _tree_radius(radius_m + SEGMENT_SAMPLE_STEP_M)
    cand = _kdtree()(samples).query_pairs(reach, output_type="ndarray")
    pairs = _lexicographic(seg_of[cand[:, 0]], seg_of[cand[:, 1]], m)
    return pairs[:, 0], pairs[:, 1]
