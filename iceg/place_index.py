"""Place recognition for global loop closure: a rotation-invariant keyframe descriptor and an
index over all older keyframes, independent of the pose estimate.

The ICE matcher needs no prediction (paper §III-C2: hypotheses come from feature pairs, not
from a search window), so a loop candidate can come from *appearance* instead of from the
current estimate. Each keyframe is summarised by two histograms, both invariant to a rotation
of the robot frame (and the first also to a translation):

* the distances between every pair of its ICE features (corners, ends of walls,
  intersections), as in the pairwise-geometry descriptors of geometric place recognition
  (e.g. the shape-context / "distance histogram" family; Olson 2009 matches pairs of local
  features in the same spirit): a revisited place from a nearby pose sees the same
  landmarks, hence the same distances;
* the ranges of its beam endpoints (the range histogram of Röfer / Bosse & Zlot 2009
  "Keypoint design and evaluation for place recognition in 2D lidar maps", rotation
  invariant), which still describes a place whose feature set is sparse.

Entries are spread linearly over the two nearest bins (continuous in the inputs), each
histogram is scaled to unit L2 norm, and similarity is the cosine (a dot product over all
older keyframes at once). Retrieval only proposes candidates: each one is verified by the
global ICE match and a consistency check (:mod:`iceg.loop_closure`).
"""

from __future__ import annotations

import functools
import math
import weakref
from collections.abc import Callable, Sequence

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field
from threadpoolctl import ThreadpoolController

from iceg.types import ScanFeatures
from iceg_common.numba_loading import njit

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


class PlaceIndexConfig(BaseModel):
    """Bins of the place descriptor (see :func:`place_descriptor`)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    pair_bins: int = Field(
        default=32, ge=2, description="Bins of the pairwise feature-distance histogram."
    )
    range_bins: int = Field(default=32, ge=2, description="Bins of the beam-range histogram.")
    range_weight: float = Field(
        default=1.0,
        ge=0,
        description="Weight of the range histogram relative to the feature-distance one.",
    )


def _soft_histogram(values: FloatArray, n_bins: int, max_value: float) -> FloatArray:
    """Histogram of ``values`` over ``[0, max_value]`` with linear interpolation between the
    two nearest bin centres (values beyond ``max_value`` are dropped), unit L2 norm (zeros
    when empty): the counts compiled (:func:`_soft_counts`), the norm numpy's."""
    if not max_value > 0.0:  # no span to bin over
        return np.zeros(n_bins)
    hist = _soft_counts(values, n_bins, max_value)
    norm = float(np.linalg.norm(hist))
    return hist / norm if norm > 0 else hist


@njit(cache=True, nogil=True)
def _soft_counts(values: FloatArray, n_bins: int, max_value: float) -> FloatArray:
    """:func:`_soft_histogram` before its norm: each value in ``[0, max_value]`` adds
    ``1 - w`` to the bin below its position and ``w`` to the bin above, all lower bins' terms
    first, in the order of the values (``np.add.at``'s order, so the numpy sums' bits)."""
    hist = np.zeros(n_bins)
    pos = np.empty(values.shape[0])
    n = 0
    for v in values:
        if v >= 0 and v <= max_value:
            p = v / max_value * n_bins - 0.5
            pos[n] = min(max(p, 0.0), n_bins - 1.0)  # np.clip (no NaN: v is in range)
            n += 1
    for k in range(n):
        lo = math.floor(pos[k])
        hist[int(lo)] += 1.0 - (pos[k] - lo)
    for k in range(n):
        lo = math.floor(pos[k])
        hist[min(int(lo) + 1, n_bins - 1)] += pos[k] - lo
    return hist


@njit(cache=True, nogil=True)
def _pair_distances(xy: FloatArray) -> FloatArray:
    """``(K (K - 1) / 2,)`` distances of every pair ``i < j`` of the points ``(K, 2)``, in
    ``np.triu_indices`` order (metres)."""
    k = xy.shape[0]
    out = np.empty(k * (k - 1) // 2)
    n = 0
    for i in range(k):
        for j in range(i + 1, k):
            out[n] = math.hypot(xy[i, 0] - xy[j, 0], xy[i, 1] - xy[j, 1])
            n += 1
    return out


@njit(cache=True, nogil=True)
def _ranges(points: FloatArray) -> FloatArray:
    """``(P,)`` distances of the points ``(P, 2)`` from their frame's origin (metres)."""
    out = np.empty(points.shape[0])
    for p in range(points.shape[0]):
        out[p] = math.hypot(points[p, 0], points[p, 1])
    return out


@functools.cache
def _blas() -> ThreadpoolController:
    """The process's thread pools (threadpoolctl), inspected once."""
    return ThreadpoolController()


#: Descriptors computed ahead (:func:`remember_place_descriptor`), by features object (dropped
#: with the features), with the configuration they were computed with.
_AHEAD: weakref.WeakKeyDictionary[ScanFeatures, tuple[PlaceIndexConfig, FloatArray]] = (
    weakref.WeakKeyDictionary()
)


def place_descriptor(features: ScanFeatures, config: PlaceIndexConfig | None = None) -> FloatArray:
    """Rotation-invariant descriptor of one keyframe.

    Args:
        features: The keyframe's ICE features, robot frame (``xy`` ``(K, 2)`` and
            ``points_xy`` ``(P, 2)``, metres); ``range_max_m`` sets the histogram spans
            (pair distances up to ``2 * range_max_m``, ranges up to ``range_max_m``).
        config: Bins and weights.

    Returns:
        ``(pair_bins + range_bins,)`` float64, unit L2 norm (zeros when the scan has neither
        two features nor a point). Unchanged (up to rounding) when the robot frame is
        rotated; its first block is also unchanged under a translation.
    """
    cfg = config or PlaceIndexConfig()
    ahead = _AHEAD.get(features)
    if ahead is not None and ahead[0] == cfg:
        return ahead[1]
    r_max = float(features.range_max_m)
    xy = np.ascontiguousarray(features.xy, dtype=np.float64).reshape(-1, 2)
    pair = _soft_histogram(_pair_distances(xy), cfg.pair_bins, 2.0 * r_max)
    pts = np.ascontiguousarray(features.points_xy, dtype=np.float64).reshape(-1, 2)
    ranges = _soft_histogram(_ranges(pts), cfg.range_bins, r_max)
    desc = np.concatenate([pair, cfg.range_weight * ranges])
    norm = float(np.linalg.norm(desc))
    return desc / norm if norm > 0 else desc


def remember_place_descriptor(
    features: ScanFeatures, config: PlaceIndexConfig, descriptor: FloatArray
) -> None:
    """Let :func:`place_descriptor` of ``features`` with ``config`` return ``descriptor``,
    which it computed for them (or for a copy of them, bit for bit: a feature worker's,
    :mod:`iceg.scan_products`)."""
    _AHEAD[features] = (config, descriptor)


class PlaceIndex:
    """Descriptors of all keyframes, queried by cosine similarity.

    Example::

        index = PlaceIndex()
        index.add(node_id, place_descriptor(features))
        best = index.query(place_descriptor(features), eligible, k=3, separation=10)

    Args:
        config: Descriptor bins (every added descriptor must have their total length).
    """

    def __init__(self, config: PlaceIndexConfig | None = None) -> None:
        self.config = config or PlaceIndexConfig()
        self._dim = self.config.pair_bins + self.config.range_bins
        self._rows = np.zeros((0, self._dim))
        self._ids = np.zeros(0, dtype=np.int64)  # row -> node id; capacity of _rows
        self._n = 0

    def __len__(self) -> int:
        return self._n

    def add(self, node_id: int, descriptor: FloatArray) -> None:
        """Store the descriptor ``(D,)`` of ``node_id`` (amortised O(1)).

        Raises:
            ValueError: the descriptor has the wrong length.
        """
        d = np.asarray(descriptor, dtype=np.float64).reshape(-1)
        if d.shape[0] != self._dim:
            raise ValueError(f"descriptor has {d.shape[0]} entries, expected {self._dim}")
        if self._n == self._rows.shape[0]:
            grow = max(64, self._n)
            self._rows = np.vstack([self._rows, np.zeros((grow, self._dim))])
            self._ids = np.concatenate([self._ids, np.zeros(grow, dtype=np.int64)])
        self._rows[self._n] = d
        self._ids[self._n] = int(node_id)
        self._n += 1

    def export_state(self) -> dict[str, np.ndarray]:
        """``{"rows": (n, D) descriptors, "ids": (n,) node ids}`` (saved sessions)."""
        return {"rows": self._rows[: self._n].copy(), "ids": self._ids[: self._n].copy()}

    def restore_state(self, state: dict[str, np.ndarray]) -> None:
        """Replace the contents by :meth:`export_state` arrays (same later queries).

        Raises:
            ValueError: the descriptors have the wrong length.
        """
        rows = np.asarray(state["rows"], dtype=np.float64).reshape(-1, self._dim)
        cap = 0
        while cap < rows.shape[0]:  # the capacity add() would have grown to
            cap += max(64, cap)
        self._rows = np.zeros((cap, self._dim))
        self._rows[: rows.shape[0]] = rows
        self._ids = np.zeros(cap, dtype=np.int64)
        self._ids[: rows.shape[0]] = np.asarray(state["ids"], dtype=np.int64).reshape(-1)
        self._n = rows.shape[0]

    def similarity(self, descriptor: FloatArray) -> tuple[IntArray, FloatArray]:
        """Cosine similarity of ``descriptor`` to every stored one: ``(node_ids (N,),
        similarity (N,))`` in insertion order."""
        # On one BLAS thread: the same product bit for bit (each similarity is one dot
        # product), and no OpenBLAS threads left spinning on the other core after each call
        # (docs/design.md, "Long logs").
        with _blas().limit(limits=1, user_api="blas"):
            sim = self._rows[: self._n] @ np.asarray(descriptor, dtype=np.float64).reshape(-1)
        return self._ids[: self._n].copy(), sim

    def query(
        self,
        descriptor: FloatArray,
        eligible: Sequence[int] | IntArray | Callable[[IntArray], BoolArray],
        k: int,
        separation: int,
    ) -> list[int]:
        """The ``k`` most similar eligible nodes, from distinct places.

        Greedy over the nodes by decreasing similarity (ties in insertion order); only the
        most similar are sorted (a prefix doubled until ``k`` places are found), so a query
        costs O(N) vectorized work plus O(m log m) for the m nodes looked at.

        Args:
            descriptor: ``(D,)`` query descriptor.
            eligible: Node ids that may be returned (e.g. old enough along the path), or a
                vectorized test: given the ``(N,)`` int64 node ids, a ``(N,)`` bool mask.
            k: Most results.
            separation: Results are more than this many node ids apart (non-maximum
                suppression: one result per stretch of path).

        Returns:
            Node ids, most similar first (fewer than ``k`` when few are eligible).
        """
        ids, sim = self.similarity(descriptor)
        if callable(eligible):
            keep = np.asarray(eligible(ids), dtype=bool)
        else:
            keep = np.isin(ids, np.asarray(eligible, dtype=np.int64))
        ids, sim = ids[keep], sim[keep]
        m = max(8 * k, 1)
        while True:
            if m >= ids.shape[0]:
                top = np.argsort(-sim, kind="stable")
            else:  # every node at least as similar as the m-th, ties included, in order
                kth = np.partition(sim, ids.shape[0] - m)[ids.shape[0] - m]
                few = np.flatnonzero(sim >= kth)
                top = few[np.argsort(-sim[few], kind="stable")]
            chosen: list[int] = []
            for n in ids[top].tolist():
                if all(abs(n - c) > separation for c in chosen):
                    chosen.append(n)
                    if len(chosen) == k:
                        return chosen
            if top.shape[0] == ids.shape[0]:
                return chosen
            m *= 2


__all__ = ["PlaceIndex", "PlaceIndexConfig", "place_descriptor"]
