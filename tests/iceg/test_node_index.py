"""Tests of the spatial index of nodes (:mod:`iceg.node_index`): queries equal brute force."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from iceg import node_index
from iceg.node_index import NodeGrid

#: Coordinates in micrometres (a squared distance of 1e-250 m would underflow to 0).
coords = st.floats(-50.0, 50.0, allow_nan=False).map(lambda v: round(v, 6))
#: Up to 80 node positions, a query's center and radius.
positions = st.lists(st.tuples(coords, coords), min_size=0, max_size=80)
centers = st.tuples(coords, coords)
radii = st.floats(0.0, 120.0)
#: Both query paths: every row's position in one compiled pass, and the cells.
both_paths = pytest.mark.parametrize("scan_all_rows", [node_index.SCAN_ALL_ROWS, 0])


@both_paths
@settings(max_examples=60, deadline=None)
@given(
    positions,
    centers,
    radii,
    st.floats(0.5, 10.0),
    st.lists(st.tuples(st.integers(0, 79), coords, coords), max_size=10),
)
def test_query_equals_brute_force(
    scan_all_rows: int,
    points: list[tuple[float, float]],
    center: tuple[float, float],
    radius: float,
    cell: float,
    moves: list[tuple[int, float, float]],
) -> None:
    xy = np.array(points, dtype=np.float64).reshape(-1, 2)
    grid = NodeGrid(cell)
    half = xy.shape[0] // 2
    c = np.array(center)
    grid.add(np.arange(half), xy[:half])  # in two batches, as nodes arrive
    with pytest.MonkeyPatch.context() as mp:  # the cells, where read, are built here ...
        mp.setattr(node_index, "SCAN_ALL_ROWS", scan_all_rows)
        d2 = ((xy[:half] - c) ** 2).sum(axis=1)
        np.testing.assert_array_equal(grid.query(c, radius), np.flatnonzero(d2 <= radius * radius))
    grid.add(np.arange(half, xy.shape[0]), xy[half:])  # ... and kept up to date from then on
    moves = [(n, x, y) for n, x, y in moves if n < xy.shape[0]]
    for n, x, y in moves[:3]:  # re-indexing a node moves it
        xy[n] = (x, y)
        grid.add([n], [[x, y]])
    for n, x, y in moves[3:]:  # ... also in a batch, where the last of a repeated id wins
        xy[n] = (x, y)
    if moves[3:]:
        grid.add([n for n, _, _ in moves[3:]], [[x, y] for _, x, y in moves[3:]])
    d2 = ((xy - c) ** 2).sum(axis=1)
    # both paths: every row's position in one compiled pass, and the cells the disc overlaps
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(node_index, "SCAN_ALL_ROWS", scan_all_rows)
        got = grid.query(c, radius)
    np.testing.assert_array_equal(got, np.flatnonzero(d2 <= radius * radius))
    assert len(grid) == xy.shape[0]
    np.testing.assert_array_equal(grid.position(np.arange(xy.shape[0])), xy)
    if xy.shape[0]:  # the extent covers every position indexed (moved nodes' old ones too)
        span = float(np.hypot(*(xy.max(axis=0) - xy.min(axis=0))))
        assert grid.extent_m >= span
        if not moves:
            assert grid.extent_m == span
    grid.clear()
    assert len(grid) == 0 and grid.query(c, radius).shape == (0,)


@both_paths
@settings(max_examples=60, deadline=None)
@given(st.tuples(positions, centers, radii), st.integers(-1, 90))
def test_nearest_first_equals_the_numpy_expressions(
    scan_all_rows: int,
    query: tuple[list[tuple[float, float]], tuple[float, float], float],
    below: int,
) -> None:
    # The loop-closure search's ordering of the nodes near a point (one compiled call), bit
    # for bit the numpy expressions it replaced: the query, the ids below a bound, np.hypot
    # of the indexed positions less the center, a stable argsort (ties by id). Repeated
    # positions make ties.
    points, center, radius = query
    xy = np.array(points + points[:5], dtype=np.float64).reshape(-1, 2)
    grid = NodeGrid(1.0)
    grid.add(np.arange(xy.shape[0]), xy)
    c = np.array(center)
    with pytest.MonkeyPatch.context() as mp:
        mp.setattr(node_index, "SCAN_ALL_ROWS", scan_all_rows)
        ids, dist = grid.nearest_first(c, radius, below)
        want = grid.query(c, radius)
    want = want[want < below]
    want_dist = np.hypot(*(grid.position(want) - c).T)
    order = np.argsort(want_dist, kind="stable")
    np.testing.assert_array_equal(ids, want[order])
    np.testing.assert_array_equal(dist, want_dist[order])


@settings(max_examples=100, deadline=None)
@given(
    st.lists(
        st.tuples(st.integers(0, 60), st.integers(0, 12)), max_size=40, unique_by=lambda t: t[0]
    ),
    st.integers(0, 45),
    st.integers(0, 13),
)
def test_nearest_within_equals_a_lexsort(rows: list[tuple[int, int]], count: int, d: int) -> None:
    # The nodes of a prefix within a distance, nearest first and ties by id: the lexsort it
    # replaced. Distances on a coarse lattice (ties), ids in no order, a count past the end.
    ids = np.array([i for i, _ in rows], dtype=np.int64)
    dist = np.array([0.25 * k for _, k in rows], dtype=np.float64)
    count = min(count, ids.shape[0])
    got_ids, got_dist = node_index.nearest_within(ids, dist, count, 0.25 * d)
    keep = np.flatnonzero(dist[:count] <= 0.25 * d)
    order = keep[np.lexsort((ids[keep], dist[keep]))]
    np.testing.assert_array_equal(got_ids, ids[order])
    np.testing.assert_array_equal(got_dist, dist[order])
