"""Robot steps through walls (``iceg.wall_crossings``), against hand-computed geometry."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from iceg.wall_crossings import nodes_of_walls_crossed
from iceg_common import se2

# A wall from (0, -1) to (0, 1) seen by nodes 3 and 5, and a wall from (2, -1) to (2, 1)
# seen by node 7.
WALLS = np.array(
    [
        [[0.0, -1.0], [0.0, 1.0]],
        [[0.0, 1.0], [0.0, -1.0]],  # the same wall, its ends the other way
        [[2.0, -1.0], [2.0, 1.0]],
    ]
)
NODES = np.array([3, 5, 7])
MARGIN_M = 0.3


def test_counts_the_distinct_nodes_of_the_walls_each_step_crosses() -> None:
    steps = np.array(
        [
            [[-1.0, 0.0], [1.0, 0.0]],  # through the first wall at its middle: nodes 3 and 5
            [[-1.0, 0.0], [3.0, 0.0]],  # through both walls: nodes 3, 5 and 7
            [[-1.0, 0.8], [1.0, 0.8]],  # 0.2 m from the first wall's end: within the margin
            [[-1.0, 0.6], [1.0, 0.6]],  # 0.4 m from its end: crosses
            [[-1.0, 0.0], [-0.1, 0.0]],  # stops short of it
            [[0.5, -2.0], [0.5, 2.0]],  # parallel to both
            [[-1.0, -1.0], [1.0, 1.0]],  # diagonally through the middle
        ]
    )
    got = nodes_of_walls_crossed(steps, WALLS, NODES, MARGIN_M)
    np.testing.assert_array_equal(got, [2, 3, 0, 2, 0, 0, 2])


def test_steps_beyond_one_chunk_are_counted_where_they_are() -> None:
    # 700 steps (three chunks), every 100th crosses the first wall.
    steps = np.zeros((700, 2, 2))
    steps[:, 0] = [-1.0, 5.0]
    steps[:, 1] = [-0.5, 5.0]
    steps[::100] = [[-1.0, 0.0], [1.0, 0.0]]
    got = nodes_of_walls_crossed(steps, WALLS[:2], NODES[:2], MARGIN_M)
    assert np.flatnonzero(got).tolist() == list(range(0, 700, 100))
    assert set(got[::100].tolist()) == {2}


def test_no_steps_or_no_walls() -> None:
    assert nodes_of_walls_crossed(np.zeros((0, 2, 2)), WALLS, NODES, MARGIN_M).shape == (0,)
    none = nodes_of_walls_crossed(np.ones((4, 2, 2)), np.zeros((0, 2, 2)), NODES[:0], MARGIN_M)
    np.testing.assert_array_equal(none, np.zeros(4))


@settings(max_examples=50, deadline=None)
@given(
    x=st.floats(-50.0, 50.0),
    y=st.floats(-50.0, 50.0),
    theta=st.floats(-np.pi, np.pi),
    seed=st.integers(0, 2**16),
)
def test_the_count_does_not_depend_on_the_map_frame(
    x: float, y: float, theta: float, seed: int
) -> None:
    rng = np.random.default_rng(seed)
    steps = rng.uniform(-3.0, 3.0, (40, 2, 2))
    walls = rng.uniform(-3.0, 3.0, (30, 2, 2))
    nodes = rng.integers(0, 6, 30)
    t = np.array([x, y, theta])

    def moved(a: np.ndarray) -> np.ndarray:
        return se2.transform_points(t, a.reshape(-1, 2)).reshape(a.shape)

    want = nodes_of_walls_crossed(steps, walls, nodes, MARGIN_M)
    got = nodes_of_walls_crossed(moved(steps), moved(walls), nodes, MARGIN_M)
    # A crossing within rounding (1e-15 relative) of a margin or a step's end could flip; with
    # uniform random endpoints that has a probability of about 1e-13 per example.
    np.testing.assert_array_equal(got, want)
