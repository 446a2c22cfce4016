"""Corner features: two segments meeting at their facing endpoints (paper §III-B, Fig. 1-2)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from iceg.features.config import FeatureConfig
from iceg.features.geometry import dot2
from iceg.features.pairs import SegmentPairs
from iceg.features.segments import Segments
from iceg_common.numba_loading import njit

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


class Corners(NamedTuple):
    """C Corner features, robot frame."""

    pairs: IntArray  # (C, 2) int64 the two segments
    ends: IntArray  # (C, 2) int64 which endpoint (0 first, 1 last) of each segment meets
    xy: FloatArray  # (C, 2) float64 the lines' meeting point, metres
    cov: FloatArray  # (C, 2, 2) float64 its covariance, m²
    dirs: FloatArray  # (C, 2, 2) float64 unit vectors toward each segment's far endpoint
    opening: FloatArray  # (C,) float64 angle between dirs, radians

    @classmethod
    def empty(cls) -> Corners:
        """No corners."""
        no_pairs = np.zeros((0, 2), dtype=np.int64)
        return cls(
            no_pairs,
            no_pairs,
            np.zeros((0, 2)),
            np.zeros((0, 2, 2)),
            np.zeros((0, 2, 2)),
            np.zeros(0),
        )

    def endpoint_mask(self, n_segments: int) -> BoolArray:
        """``(M, 2)`` bool: which segment endpoints take part in a corner."""
        used = np.zeros((n_segments, 2), dtype=bool)
        used[self.pairs[:, 0], self.ends[:, 0]] = True
        used[self.pairs[:, 1], self.ends[:, 1]] = True
        return used


@njit(cache=True, nogil=True)
def facing_ends(
    endpoints: FloatArray, pairs: SegmentPairs
) -> tuple[IntArray, IntArray, FloatArray]:
    """Per pair, the endpoint combination (end of first, end of second) with the smallest gap
    (the first of equal gaps in the order (0, 0), (0, 1), (1, 0), (1, 1); a NaN gap counts
    as smallest, as for ``np.argmin``).

    Args:
        endpoints: ``(M, 2, 2)`` float64 segment endpoints, metres.
        pairs: Q segment pairs.

    Returns:
        ``end_i``, ``end_j`` ``(Q,)`` int64 in ``{0, 1}`` and ``gap`` ``(Q,)`` float64 metres.
    """
    q = pairs.first.shape[0]
    end_i = np.empty(q, dtype=np.int64)
    end_j = np.empty(q, dtype=np.int64)
    gap = np.empty(q)
    for r in range(q):
        a, b = pairs.first[r], pairs.second[r]
        best, best_gap = 0, np.nan
        for c in range(4):
            ea, eb = c // 2, c % 2
            d = math.hypot(
                endpoints[a, ea, 0] - endpoints[b, eb, 0], endpoints[a, ea, 1] - endpoints[b, eb, 1]
            )
            if c == 0 or (not math.isnan(best_gap) and (d < best_gap or math.isnan(d))):
                best, best_gap = c, d
        end_i[r], end_j[r], gap[r] = best // 2, best % 2, best_gap
    return end_i, end_j, gap


@njit(cache=True, nogil=True)
def greedy_by_gap(
    cand: IntArray, gap: FloatArray, keys: tuple[IntArray, IntArray, IntArray, IntArray], m: int
) -> IntArray:
    """Candidates in increasing gap (stable), each segment endpoint used at most once.

    Args:
        cand: ``(K,)`` int64 candidate pair indices.
        gap: ``(Q,)`` float64 gap of every pair, metres.
        keys: ``(first, second, end_i, end_j)`` ``(Q,)`` int64 of every pair.
        m: Number of segments.

    Returns:
        ``(C,)`` int64 chosen pair indices, in the order chosen.
    """
    first, second, end_i, end_j = keys
    used = np.zeros((m, 2), dtype=np.bool_)
    chosen = np.empty(cand.shape[0], dtype=np.int64)
    n = 0
    for c in cand[np.argsort(gap[cand], kind="mergesort")]:
        a, b, ea, eb = first[c], second[c], end_i[c], end_j[c]
        if used[a, ea] or used[b, eb]:
            continue
        used[a, ea] = used[b, eb] = True
        chosen[n] = c
        n += 1
    return chosen[:n]


def find_corners(segs: Segments, pairs: SegmentPairs, cfg: FeatureConfig) -> Corners:
    """Corners: steep pairs whose facing endpoints and whose lines' meeting point lie within
    ``corner_gap_m`` (plus the beam spacing at each endpoint) of each other (paper §III-B).

    Each endpoint joins at most one corner (greedy by gap). Position: the lines' meeting
    point, covariance propagated from both line covariances; directions: unit vectors from
    the corner toward each segment's far endpoint; opening angle between them. Compiled
    (:func:`_corners`, issue 13): the values of the numpy stage it replaced, bit for bit.

    Args:
        segs: The scan's segments.
        pairs: Their steep pairs (:func:`iceg.features.pairs.meeting_pairs`).
        cfg: ``corner_gap_m`` is read.

    Returns:
        :class:`Corners`, in increasing gap.
    """
    if pairs.first.size == 0:
        return Corners.empty()
    return Corners(*_corners(segs, pairs, cfg.corner_gap_m))


@njit(cache=True, nogil=True, error_model="numpy")
def _corners(
    segs: Segments, pairs: SegmentPairs, corner_gap_m: float
) -> tuple[IntArray, IntArray, FloatArray, FloatArray, FloatArray, FloatArray]:
    """:func:`find_corners` of at least one pair: the fields of :class:`Corners`."""
    end_i, end_j, gap = facing_ends(segs.endpoints, pairs)
    q = gap.shape[0]
    ok = np.empty(q, dtype=np.bool_)
    for r in range(q):
        a, b = pairs.first[r], pairs.second[r]
        e_i = segs.endpoints[a, end_i[r]]
        e_j = segs.endpoints[b, end_j[r]]
        d_i = math.hypot(pairs.xy[r, 0] - e_i[0], pairs.xy[r, 1] - e_i[1])
        d_j = math.hypot(pairs.xy[r, 0] - e_j[0], pairs.xy[r, 1] - e_j[1])
        sp_i, sp_j = segs.spacing[a, end_i[r]], segs.spacing[b, end_j[r]]
        ok[r] = (
            gap[r] <= corner_gap_m + sp_i + sp_j
            and d_i <= corner_gap_m + sp_i
            and d_j <= corner_gap_m + sp_j
        )
    keys = (pairs.first, pairs.second, end_i, end_j)
    sel = greedy_by_gap(np.flatnonzero(ok), gap, keys, segs.lines.shape[0])
    c = sel.shape[0]
    corner_pairs = np.empty((c, 2), dtype=np.int64)
    ends = np.empty((c, 2), dtype=np.int64)
    xy = np.empty((c, 2))
    cov = np.empty((c, 2, 2))
    dirs = np.empty((c, 2, 2))
    opening = np.empty(c)
    for r in range(c):
        k = sel[r]
        corner_pairs[r, 0], corner_pairs[r, 1] = pairs.first[k], pairs.second[k]
        ends[r, 0], ends[r, 1] = end_i[k], end_j[k]
        xy[r] = pairs.xy[k]
        cov[r] = pairs.cov[k]
        for side in range(2):
            far = segs.endpoints[corner_pairs[r, side], 1 - ends[r, side]]
            vx, vy = far[0] - xy[r, 0], far[1] - xy[r, 1]
            length = math.hypot(vx, vy)
            dirs[r, side, 0], dirs[r, side, 1] = vx / length, vy / length
        cos_open = dot2(dirs[r, 0, 0], dirs[r, 0, 1], dirs[r, 1, 0], dirs[r, 1, 1])
        if cos_open < -1.0:  # np.clip: NaN stays NaN
            cos_open = -1.0
        elif cos_open > 1.0:
            cos_open = 1.0
        opening[r] = math.acos(cos_open)
    return corner_pairs, ends, xy, cov, dirs, opening
