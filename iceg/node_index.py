"""Spatial index of pose-graph nodes for the loop-closure search (docs/design.md "Long logs").

The loop-closure search asks, every few nodes, which old nodes lie near a point (the current
estimate, a candidate place). Reading every node's estimate for that costs O(N) per search,
so a long log slows down with its length. :class:`NodeGrid` is a grid hash (cells of
``cell_m`` metres, a dict from cell to the node ids whose **indexed** position falls in it):
adding a node is O(1), and a query reads only the cells that overlap its disc, O(nodes
nearby). Up to :data:`SCAN_ALL_ROWS` nodes a query tests every indexed position in one
compiled pass instead, which costs less there than gathering the cells in Python; the cells
are built only when a query first needs them, and kept up to date from then on.

Indexed positions go stale when the graph moves its estimates. The caller bounds the
staleness: it queries with a radius enlarged by a margin, measures the exact distances on the
current estimates of the nodes returned, and rebuilds the index from all current estimates
when the estimates may have moved by more than the margin (a large correction, accumulated
loop-closure corrections). Grid hashing for neighbour queries: Teschner et al., "Optimized
Spatial Hashing for Collision Detection of Deformable Objects", VMV 2003.
"""

from __future__ import annotations

import itertools
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg_common.numba_loading import njit

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Up to this many rows (1 + the largest id indexed), :meth:`NodeGrid.query` tests every
#: row's position in one compiled pass (a few microseconds at MIT CSAIL's 1800 nodes, where
#: gathering the cells' lists in Python took about 80); beyond, it reads the overlapping
#: cells, O(nodes nearby). Both give the same ids (the test is the same expression).
SCAN_ALL_ROWS = 16384


class NodeGrid:
    """Node ids hashed by the grid cell of their indexed position ``(x_m, y_m)``, map frame.

    Args:
        cell_m: Cell edge length in metres (> 0); a query reads the cells its disc overlaps.
    """

    def __init__(self, cell_m: float) -> None:
        if not (math.isfinite(cell_m) and cell_m > 0):
            raise ValueError(f"NodeGrid: cell_m must be a positive number, got {cell_m!r}")
        self.cell_m = float(cell_m)
        # None until a query reads cells (more than SCAN_ALL_ROWS rows), then kept up to date
        self._cells: dict[tuple[int, int], list[int]] | None = None
        self._xy = np.zeros((0, 2))  # row = node id; NaN: not indexed
        self._n = 0  # rows in use (1 + the largest id indexed)
        self._count = 0
        self._lo = np.full(2, np.inf)
        self._hi = np.full(2, -np.inf)

    def __len__(self) -> int:
        """Number of indexed nodes."""
        return self._count

    def __contains__(self, node_id: object) -> bool:
        return (
            isinstance(node_id, int | np.integer)
            and 0 <= int(node_id) < self._n
            and not np.isnan(self._xy[int(node_id), 0])
        )

    @property
    def extent_m(self) -> float:
        """Diagonal of the bounding box of every position indexed since the last
        :meth:`clear` (m; 0 when empty): at least the extent of the current positions."""
        return float(np.hypot(*(self._hi - self._lo))) if self._count else 0.0

    def clear(self) -> None:
        """Forget every node."""
        self.__init__(self.cell_m)  # type: ignore[misc]

    def add(self, node_ids: ArrayLike, xy: ArrayLike) -> None:
        """Index nodes at positions ``xy`` ``(k, 2)`` metres (a node already indexed is moved).

        Raises:
            ValueError: negative ids, shapes that differ, or non-finite positions.
        """
        ids = np.asarray(node_ids, dtype=np.int64).reshape(-1)
        pts = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
        if ids.shape[0] != pts.shape[0] or (ids.size and int(ids.min()) < 0):
            raise ValueError("NodeGrid.add: need (k,) non-negative ids and (k, 2) positions")
        if not np.all(np.isfinite(pts)):
            raise ValueError("NodeGrid.add: positions must be finite")
        if ids.size == 0:
            return
        if ids.shape[0] > 1 and not bool((ids[1:] > ids[:-1]).all()):
            # The last position given for a repeated id wins (ids then ascending).
            _, last = np.unique(ids[::-1], return_index=True)
            keep = ids.shape[0] - 1 - last
            ids, pts = ids[keep], pts[keep]
        self._reserve(int(ids.max()) + 1)
        for n in ids[~np.isnan(self._xy[ids, 0])].tolist():  # moved nodes
            self._remove(n)
        self._xy[ids] = pts
        self._count += ids.shape[0]
        if self._cells is not None:
            _file(self._cells, ids, pts, self.cell_m)
        self._lo = np.minimum(self._lo, [pts[:, 0].min(), pts[:, 1].min()])
        self._hi = np.maximum(self._hi, [pts[:, 0].max(), pts[:, 1].max()])

    def query(self, center_xy: ArrayLike, radius_m: float) -> IntArray:
        """Ids of the nodes whose indexed position is within ``radius_m`` of ``center_xy``
        (``(2,)`` metres), ascending: the same set as a brute-force distance test.

        Returns:
            ``(k,)`` int64 node ids.
        """
        c = np.asarray(center_xy, dtype=np.float64).reshape(2)
        r = float(radius_m)
        if self._count == 0 or not r >= 0:
            return np.zeros(0, dtype=np.int64)
        if self._n <= SCAN_ALL_ROWS:
            return _rows_within(self._xy, self._n, float(c[0]), float(c[1]), r * r)
        if self._cells is None:  # the first query beyond SCAN_ALL_ROWS: file every node
            rows = np.flatnonzero(~np.isnan(self._xy[: self._n, 0]))
            self._cells = {}
            _file(self._cells, rows, self._xy[rows], self.cell_m)
        lo = np.floor((c - r) / self.cell_m).astype(np.int64)
        hi = np.floor((c + r) / self.cell_m).astype(np.int64)
        n_cells = int((hi[0] - lo[0] + 1) * (hi[1] - lo[1] + 1))
        if n_cells > len(self._cells):  # a disc wider than the map: scan the cells
            cells = list(self._cells.values())
        else:
            get = self._cells.get
            cells = [
                cell
                for cx in range(int(lo[0]), int(hi[0]) + 1)
                for cy in range(int(lo[1]), int(hi[1]) + 1)
                if (cell := get((cx, cy))) is not None
            ]
        count = sum(map(len, cells))
        ids = np.fromiter(itertools.chain.from_iterable(cells), dtype=np.int64, count=count)
        ids.sort()
        d = self._xy[ids] - c
        return ids[d[:, 0] ** 2 + d[:, 1] ** 2 <= r * r]

    def nearest_first(
        self, center_xy: FloatArray, radius_m: float, below: int
    ) -> tuple[IntArray, FloatArray]:
        """:meth:`query` of the ids below ``below``, ordered by their indexed distance to
        ``center_xy`` (``(2,)`` float64 metres, map frame; ties by id), with those distances.

        Returns:
            ``ids`` ``(k,)`` int64 and ``dist`` ``(k,)`` float64 metres (``np.hypot`` of the
            indexed position less the center). Raises nothing.
        """
        c = np.asarray(center_xy, dtype=np.float64).reshape(2)
        ids = self.query(c, radius_m)
        return _by_distance(self._xy, ids[ids < below], float(c[0]), float(c[1]))

    def position(self, node_ids: ArrayLike) -> FloatArray:
        """Indexed positions ``(k, 2)`` of indexed nodes (NaN rows for others)."""
        ids = np.asarray(node_ids, dtype=np.int64).reshape(-1)
        out = np.full((ids.shape[0], 2), np.nan)
        ok = (ids >= 0) & (ids < self._n)
        out[ok] = self._xy[ids[ok]]
        return out

    def _reserve(self, rows: int) -> None:
        if rows > self._xy.shape[0]:
            grown = np.full((max(rows, 2 * self._xy.shape[0], 256), 2), np.nan)
            grown[: self._n] = self._xy[: self._n]
            self._xy = grown
        self._n = max(self._n, rows)

    def _remove(self, n: int) -> None:
        if self._cells is not None:
            key = tuple(np.floor(self._xy[n] / self.cell_m).astype(np.int64).tolist())
            cell = self._cells[key]
            cell.remove(n)
            if not cell:
                del self._cells[key]
        self._xy[n] = np.nan
        self._count -= 1


def _file(
    cells: dict[tuple[int, int], list[int]], ids: IntArray, pts: FloatArray, cell_m: float
) -> None:
    """File the nodes ``ids`` ``(k,)`` int64 at ``pts`` ``(k, 2)`` float64 metres (in no cell
    yet) in ``cells`` (cells of ``cell_m`` metres): one dict step per cell, the nodes grouped
    by cell key."""
    if ids.shape[0] == 0:
        return
    keys = np.floor(pts / cell_m).astype(np.int64)
    order = np.lexsort((keys[:, 1], keys[:, 0]))
    keys, ids = keys[order], ids[order]
    starts = np.flatnonzero(np.any(np.diff(keys, axis=0) != 0, axis=1)) + 1
    bounds = [0, *starts.tolist(), ids.shape[0]]
    grouped = ids.tolist()
    for (cx, cy), a, b in zip(keys[bounds[:-1]].tolist(), bounds[:-1], bounds[1:], strict=True):
        cells.setdefault((cx, cy), []).extend(grouped[a:b])


@njit(cache=True, nogil=True)
def _rows_within(xy: np.ndarray, n: int, cx: float, cy: float, r2: float) -> np.ndarray:
    """``(k,)`` int64 the rows ``< n`` of ``xy`` ``(N, 2)`` whose position lies within
    ``sqrt(r2)`` of ``(cx, cy)``, ascending; NaN rows (not indexed) never do. The expression
    of :meth:`NodeGrid.query`'s cell path, so the same rows."""
    keep = np.empty(n, np.int64)
    k = 0
    for i in range(n):
        dx = xy[i, 0] - cx
        dy = xy[i, 1] - cy
        if dx**2 + dy**2 <= r2:
            keep[k] = i
            k += 1
    return keep[:k].copy()


@njit(cache=True, nogil=True)
def _by_distance(
    xy: np.ndarray, ids: np.ndarray, cx: float, cy: float
) -> tuple[np.ndarray, np.ndarray]:
    """``ids`` ``(k,)`` int64 (ascending) ordered by the distance of their rows of ``xy`` to
    ``(cx, cy)``, stably (ties by id), and those distances (``np.hypot`` of the differences,
    as numpy computes them). Raises nothing."""
    dist = np.empty(ids.shape[0])
    for i in range(ids.shape[0]):
        dist[i] = np.hypot(xy[ids[i], 0] - cx, xy[ids[i], 1] - cy)
    order = np.argsort(dist, kind="mergesort")
    return ids[order], dist[order]


@njit(cache=True, nogil=True)
def nearest_within(
    ids: np.ndarray, dist: np.ndarray, count: int, d: float
) -> tuple[np.ndarray, np.ndarray]:
    """The first ``count`` of ``ids`` ``(n,)`` int64 and ``dist`` ``(n,)`` float64 whose
    distance is at most ``d``, nearest first, ties by id (``np.lexsort((ids, dist))`` of
    those), and their distances. Raises nothing."""
    keep = np.empty(count, np.int64)
    k = 0
    for i in range(count):
        if dist[i] <= d:
            keep[k] = i
            k += 1
    kept_ids = ids[keep[:k]]
    kept_dist = dist[keep[:k]]
    by_id = np.argsort(kept_ids, kind="mergesort")
    order = by_id[np.argsort(kept_dist[by_id], kind="mergesort")]
    return kept_ids[order], kept_dist[order]


__all__ = ["NodeGrid", "nearest_within"]
