"""Corner features: two segments meeting at their facing endpoints (paper §III-B, Fig. 1-2)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from iceg.features.config import FeatureConfig
from iceg.features.geometry import norm, opening_angle, unit
from iceg.features.pairs import SegmentPairs
from iceg.features.segments import Segments

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


def facing_ends(
    endpoints: FloatArray, pairs: SegmentPairs
) -> tuple[IntArray, IntArray, FloatArray]:
    """Per pair, the endpoint combination (end of first, end of second) with the smallest gap.

    Args:
        endpoints: ``(M, 2, 2)`` float64 segment endpoints, metres.
        pairs: Q segment pairs.

    Returns:
        ``end_i``, ``end_j`` ``(Q,)`` int64 in ``{0, 1}`` and ``gap`` ``(Q,)`` float64 metres.
    """
    ei = endpoints[pairs.first]  # (Q, 2, 2)
    ej = endpoints[pairs.second]
    gaps = norm(ei[:, :, None, :] - ej[:, None, :, :]).reshape(-1, 4)
    best = np.argmin(gaps, axis=1)
    return best // 2, best % 2, gaps[np.arange(best.shape[0]), best]


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
    used = np.zeros((m, 2), dtype=bool)
    chosen = []
    for c in cand[np.argsort(gap[cand], kind="stable")]:
        a, b, ea, eb = first[c], second[c], end_i[c], end_j[c]
        if used[a, ea] or used[b, eb]:
            continue
        used[a, ea] = used[b, eb] = True
        chosen.append(c)
    return np.asarray(chosen, dtype=np.int64)


def find_corners(segs: Segments, pairs: SegmentPairs, cfg: FeatureConfig) -> Corners:
    """Corners: steep pairs whose facing endpoints and whose lines' meeting point lie within
    ``corner_gap_m`` (plus the beam spacing at each endpoint) of each other (paper §III-B).

    Each endpoint joins at most one corner (greedy by gap). Position: the lines' meeting
    point, covariance propagated from both line covariances; directions: unit vectors from
    the corner toward each segment's far endpoint; opening angle between them.

    Args:
        segs: The scan's segments.
        pairs: Their steep pairs (:func:`iceg.features.pairs.meeting_pairs`).
        cfg: ``corner_gap_m`` is read.

    Returns:
        :class:`Corners`, in increasing gap.
    """
    if pairs.first.size == 0:
        return Corners.empty()
    end_i, end_j, gap = facing_ends(segs.endpoints, pairs)
    q = np.arange(gap.shape[0])
    d_i = norm(pairs.xy - segs.endpoints[pairs.first][q, end_i])
    d_j = norm(pairs.xy - segs.endpoints[pairs.second][q, end_j])
    sp_i = segs.spacing[pairs.first, end_i]
    sp_j = segs.spacing[pairs.second, end_j]
    ok = (
        (gap <= cfg.corner_gap_m + sp_i + sp_j)
        & (d_i <= cfg.corner_gap_m + sp_i)
        & (d_j <= cfg.corner_gap_m + sp_j)
    )
    cand = np.flatnonzero(ok)
    if cand.size == 0:
        return Corners.empty()
    keys = (pairs.first, pairs.second, end_i, end_j)
    sel = greedy_by_gap(cand, gap, keys, segs.lines.shape[0])
    corner_pairs = np.stack([pairs.first[sel], pairs.second[sel]], axis=1)
    ends = np.stack([end_i[sel], end_j[sel]], axis=1)
    xy = pairs.xy[sel]
    far_i = segs.endpoints[corner_pairs[:, 0], 1 - ends[:, 0]]
    far_j = segs.endpoints[corner_pairs[:, 1], 1 - ends[:, 1]]
    dirs = np.stack([unit(far_i - xy), unit(far_j - xy)], axis=1)
    opening = opening_angle(dirs[:, 0], dirs[:, 1])
    return Corners(corner_pairs, ends, xy, pairs.cov[sel], dirs, opening)
