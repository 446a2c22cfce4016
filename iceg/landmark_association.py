"""Distance-gated association of a scan's features with the feature map's landmarks, in the
new node's frame (docs/design.md "Feature map and time-validity"): the geometric pairs that
complete the matcher's inlier pairs, and the duplicate landmarks to merge; and the rows of
landmark or node ids in a sorted id table (:func:`lookup_sorted`) and the union of id sets
(:func:`sorted_union`).

Compiled loops over (features x landmarks) instead of numpy's ``(K, n, 2)`` distance
temporaries; each distance is ``sqrt(dx^2 + dy^2)`` as ``np.linalg.norm`` computes it, so
the pairs are those of the numpy formulation (``tests/iceg/test_feature_map.py``).
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit


@njit(cache=True, nogil=True)
def nearest_free_pairs(
    feature_xy: np.ndarray,
    feature_paired: np.ndarray,
    landmark_xy: np.ndarray,
    landmark_paired: np.ndarray,
    gate_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Pair each unpaired feature with its nearest unpaired landmark (the first on a tie)
    when it lies within ``gate_m``; a landmark wanted by several features goes to the one
    of lowest index.

    Args:
        feature_xy: ``(K, 2)`` float64 feature positions, metres.
        feature_paired: ``(K,)`` bool features already paired.
        landmark_xy: ``(n, 2)`` float64 landmark positions, same frame.
        landmark_paired: ``(n,)`` bool landmarks already paired.
        gate_m: Association gate, metres.

    Returns:
        ``(features, landmarks)`` ``(m,)`` int64 indices of the new pairs, by ascending
        landmark index.
    """
    owner = np.full(landmark_xy.shape[0], -1, dtype=np.int64)
    for i in range(feature_xy.shape[0]):
        if feature_paired[i]:
            continue
        best, bj = np.inf, -1
        for j in range(landmark_xy.shape[0]):
            if landmark_paired[j]:
                continue
            dx = feature_xy[i, 0] - landmark_xy[j, 0]
            dy = feature_xy[i, 1] - landmark_xy[j, 1]
            d = math.sqrt(dx * dx + dy * dy)
            if d < best:
                best, bj = d, j
        if bj >= 0 and best <= gate_m and owner[bj] < 0:
            owner[bj] = i
    landmarks = np.flatnonzero(owner >= 0)
    return owner[landmarks], landmarks


@njit(cache=True, nogil=True)
def within_gate_of_any(
    feature_xy: np.ndarray, features: np.ndarray, landmark_xy: np.ndarray, gate_m: float
) -> np.ndarray:
    """Which landmarks lie within ``gate_m`` of at least one of the ``features``.

    Args:
        feature_xy: ``(K, 2)`` float64 feature positions, metres.
        features: ``(q,)`` int64 indices into ``feature_xy``.
        landmark_xy: ``(n, 2)`` float64 landmark positions, same frame.
        gate_m: Gate, metres.

    Returns:
        ``(n,)`` bool.
    """
    out = np.zeros(landmark_xy.shape[0], dtype=np.bool_)
    for j in range(landmark_xy.shape[0]):
        for i in features:
            dx = feature_xy[i, 0] - landmark_xy[j, 0]
            dy = feature_xy[i, 1] - landmark_xy[j, 1]
            if math.sqrt(dx * dx + dy * dy) <= gate_m:
                out[j] = True
                break
    return out


@njit(cache=True, nogil=True)
def lookup_sorted(table_ids: np.ndarray, query: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Rows of ids in a sorted id table: for each query id the first row whose id is not
    below it (``np.searchsorted``, side left), clipped to the last row, and whether that row
    holds the id; compiled, one call instead of numpy's four.

    Args:
        table_ids: ``(n,)`` int64 ids, ascending.
        query: ``(q,)`` int64 ids.

    Returns:
        ``pos`` ``(q,)`` int64 rows (0 for an empty table) and ``found`` ``(q,)`` bool.
    """
    n = table_ids.shape[0]
    if n == 0:
        return np.zeros(query.shape[0], dtype=np.int64), np.zeros(query.shape[0], dtype=np.bool_)
    pos = np.minimum(np.searchsorted(table_ids, query), n - 1)
    return pos, table_ids[pos] == query


@njit(cache=True, nogil=True)
def sorted_union(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.union1d(a, b)``: the ids in either array, ascending, each once; one compiled
    pass instead of numpy's concatenation, sort and unique.

    Args:
        a, b: ``(n,)`` and ``(m,)`` int64 ids, any order, repeats allowed.

    Returns:
        ``(k,)`` int64 sorted unique ids.
    """
    both = np.empty(a.shape[0] + b.shape[0], dtype=np.int64)
    both[: a.shape[0]] = a
    both[a.shape[0] :] = b
    both.sort()
    k = 0
    for i in range(both.shape[0]):
        if k == 0 or both[i] != both[k - 1]:
            both[k] = both[i]
            k += 1
    return both[:k].copy()
