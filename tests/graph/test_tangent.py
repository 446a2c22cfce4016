"""The graph's tangent space against the closed-form SE(2) logarithm."""

from __future__ import annotations

import math

import numpy as np
import pytest

from graph import local_coordinates
from iceg_common import se2
from iceg_common.errors import GraphError
from tests.conftest import se2_log


def test_local_coordinates_is_the_logarithm_of_the_relative_pose() -> None:
    at = np.array([[1.0, 2.0, 0.3], [-4.0, 0.5, 3.0], [0.0, 0.0, 0.0]])
    to = np.array([[1.5, 1.0, 1.4], [-3.0, -2.0, -2.9], [2.0, -1.0, 0.0]])
    got = local_coordinates(at, to)
    assert got.shape == (3, 3)
    for row, a, b in zip(got, at, to, strict=True):
        np.testing.assert_allclose(row, se2_log(se2.between(a, b)), atol=1e-12)
    np.testing.assert_allclose(got[2], [2.0, -1.0, 0.0])  # a pure translation: itself
    np.testing.assert_allclose(local_coordinates(at[0], to[0]), got[0])  # one pose, (3,)
    # a rotation through +-pi takes the short way: -2.9 - 3.0 wraps to 2*pi - 5.9
    assert got[1, 2] == pytest.approx(2 * math.pi - 5.9)


def test_local_coordinates_refuses_mismatched_shapes() -> None:
    with pytest.raises(GraphError, match="must be"):
        local_coordinates(np.zeros((2, 3)), np.zeros((3, 3)))
    with pytest.raises(GraphError, match="must be"):
        local_coordinates(np.zeros(2), np.zeros(2))
