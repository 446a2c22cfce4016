"""SE(2) identities against gtsam.Pose2 as the reference implementation."""

from __future__ import annotations

import gtsam
import numpy as np
from hypothesis import given
from hypothesis import strategies as st

from iceg_common import se2

coord = st.floats(-50, 50, allow_nan=False)
angle = st.floats(-np.pi, np.pi, allow_nan=False, exclude_max=True)
poses = st.tuples(coord, coord, angle).map(np.array)


@given(poses, poses)
def test_compose_and_between_match_gtsam(a: np.ndarray, b: np.ndarray) -> None:
    ga, gb = gtsam.Pose2(*a), gtsam.Pose2(*b)
    ref = ga.compose(gb)
    np.testing.assert_allclose(se2.compose(a, b)[:2], [ref.x(), ref.y()], atol=1e-9)
    assert abs(se2.wrap_angle(se2.compose(a, b)[2] - ref.theta())) < 1e-9
    rel = ga.between(gb)
    np.testing.assert_allclose(se2.between(a, b)[:2], [rel.x(), rel.y()], atol=1e-9)
    assert abs(se2.wrap_angle(se2.between(a, b)[2] - rel.theta())) < 1e-9


@given(poses)
def test_inverse_composes_to_identity(a: np.ndarray) -> None:
    np.testing.assert_allclose(se2.compose(a, se2.inverse(a)), np.zeros(3), atol=1e-9)


@given(poses)
def test_adjoint_matches_gtsam(a: np.ndarray) -> None:
    np.testing.assert_allclose(se2.adjoint(a), gtsam.Pose2(*a).AdjointMap(), atol=1e-12)


def test_adjoint_of_a_batch_is_each_pose_s_adjoint() -> None:
    rng = np.random.default_rng(2)
    batch = np.column_stack([rng.normal(0, 20, (4, 5, 2)).reshape(-1, 2), rng.normal(0, 2, 20)])
    batch = batch.reshape(4, 5, 3)
    got = se2.adjoint(batch)
    assert got.shape == (4, 5, 3, 3)
    for i, j in np.ndindex(4, 5):
        expected = gtsam.Pose2(*batch[i, j]).AdjointMap()
        np.testing.assert_allclose(got[i, j], expected, atol=1e-12)


def test_one_pose_equals_the_same_pose_in_a_batch_bit_for_bit() -> None:
    # A single (3,) pose takes a scalar path (math); a batch takes numpy's. Runs are
    # deterministic only if both give the same bits.
    rng = np.random.default_rng(7)
    a = np.column_stack([rng.normal(0, 30, (500, 2)), rng.uniform(-20, 20, 500)])
    b = np.column_stack([rng.normal(0, 30, (500, 2)), rng.uniform(-20, 20, 500)])
    a[:3, 2] = [np.pi, -np.pi, 0.0]
    for f in (se2.compose, se2.between):
        batch = f(a, b)
        one = np.array([f(x, y) for x, y in zip(a, b, strict=True)])
        assert np.array_equal(one, batch)
    assert np.array_equal(np.array([se2.inverse(x) for x in a]), se2.inverse(a))
    # one pose against a batch (its own path) is the batch against the pose repeated
    for x in a[:20]:
        for f in (se2.compose, se2.between):
            assert np.array_equal(f(x, b), f(np.tile(x, (b.shape[0], 1)), b))
    points = rng.normal(0, 10, (50, 2))
    for x in a[:20]:
        expected = points @ se2.rotation_matrix(x[2]).T + x[:2]
        assert np.array_equal(se2.transform_points(x, points), expected)
    # math raises on an infinite angle where numpy gives NaN: the same NaN either way
    with np.errstate(invalid="ignore"):
        assert np.isnan(se2.inverse(np.array([1.0, 2.0, np.inf]))).all()


def test_wrap_angle_hand_values() -> None:
    np.testing.assert_allclose(
        se2.wrap_angle([np.pi, 3 * np.pi / 2, -np.pi]), [-np.pi, -np.pi / 2, -np.pi]
    )


@given(
    st.one_of(
        st.floats(-1e6, 1e6, allow_nan=False),
        st.sampled_from([np.pi, -np.pi, 2 * np.pi, -2 * np.pi, 0.0, -0.0, 5e-324, 1e-300]),
    )
)
def test_wrap_float_is_wrap_angle_bit_for_bit(theta: float) -> None:
    # Python's float modulo against numpy's remainder, for one angle: the same bits.
    got, want = se2.wrap_float(theta), float(se2.wrap_angle(theta))
    assert got == want and np.signbit(got) == np.signbit(want)


def test_accumulate_equals_composing_step_by_step() -> None:
    rng = np.random.default_rng(5)
    steps = np.column_stack(
        [rng.uniform(0, 1, 200), rng.normal(0, 0.2, 200), rng.normal(0, 0.5, 200)]
    )
    poses = [np.zeros(3)]
    for step in steps:
        poses.append(se2.compose(poses[-1], step))
    got = se2.accumulate(steps)
    assert got.shape == (201, 3)
    np.testing.assert_allclose(got[:, :2], np.array(poses)[:, :2], atol=1e-12)
    np.testing.assert_allclose(se2.wrap_angle(got[:, 2] - np.array(poses)[:, 2]), 0, atol=1e-12)
