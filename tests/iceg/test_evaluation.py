"""Relation metric and position errors against hand-computed values and real benchmark data."""

from __future__ import annotations

import numpy as np
import pytest

from iceg.evaluation import evo_ape_rpe, position_errors, relation_errors
from iceg_common import se2
from iceg_common.errors import EvaluationError
from tests.conftest import shared_file


def _truth() -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(3)
    steps = np.column_stack([rng.uniform(0.1, 0.3, 50), np.zeros(50), rng.normal(0, 0.1, 50)])
    poses = [np.zeros(3)]
    for s in steps:
        poses.append(se2.compose(poses[-1], s))
    return np.arange(51, dtype=float) * 0.2 + 100.0, np.array(poses)


def test_perfect_trajectory_scores_zero() -> None:
    stamps, poses = _truth()
    pairs = np.array([[0, 1], [3, 10], [20, 50]])
    rel = se2.between(poses[pairs[:, 0]], poses[pairs[:, 1]])
    summary, per = relation_errors(stamps, poses, stamps[pairs], rel)
    assert summary.n_matched == 3
    assert summary.trans_mean_m < 1e-12 and summary.rot_mean_deg < 1e-10
    assert np.all(per < 1e-9)


def test_known_error_is_reported_exactly() -> None:
    # Hand-computed: the estimate moves pose 1 by 0.1 m along x and 2 deg; the relation 0->1
    # then has error e = delta*^-1 ∘ delta with |e_xy| = 0.1 m (pose 0 is the identity) and
    # |e_theta| = 2 deg; relation 2->3 is untouched (0 error).
    stamps, poses = _truth()
    rel_pairs = np.array([[0, 1], [2, 3]])
    rel = se2.between(poses[rel_pairs[:, 0]], poses[rel_pairs[:, 1]])
    est = poses.copy()
    est[1] = poses[1] + np.array([0.1, 0.0, np.radians(2.0)])
    summary, per = relation_errors(stamps, est, stamps[rel_pairs], rel)
    expected_t = np.hypot(*se2.between(poses[1], est[1])[:2])  # rotate 0.1 m into pose-1 frame
    assert per[0, 0] == pytest.approx(expected_t, abs=1e-12)
    assert expected_t == pytest.approx(0.1, abs=1e-12)
    assert per[0, 1] == pytest.approx(2.0, abs=1e-9)
    assert per[1, 0] == pytest.approx(0.0, abs=1e-12)
    assert summary.trans_mean_m == pytest.approx(0.05, abs=1e-12)
    assert summary.rot_sq_mean_deg2 == pytest.approx(2.0, abs=1e-9)


def test_unmatched_relations_raise_a_clear_error() -> None:
    stamps, poses = _truth()
    with pytest.raises(EvaluationError, match="none of the 1 relations"):
        relation_errors(stamps, poses, [[5.0, 6.0]], [[0.0, 0.0, 0.0]])


def test_position_errors_recover_a_rigid_offset() -> None:
    _, poses = _truth()
    offset = np.array([3.0, -2.0, 0.7])
    moved = se2.compose(offset, poses)
    result = position_errors(moved, poses)
    assert result.mean_m < 1e-9 and result.rot_mean_deg < 1e-7
    np.testing.assert_allclose(se2.compose(result.alignment, offset), 0.0, atol=1e-9)
    raw = position_errors(poses + np.array([0.05, 0.0, 0.0]), poses, align=False)
    assert raw.mean_m == pytest.approx(0.05, abs=1e-12)


def test_raw_odometry_on_mit_csail_matches_the_published_figure() -> None:
    # Truth: issue 7 states raw odometry alone scores 1.68 m and 5.07 deg on MIT CSAIL.
    from frontends import open_log
    from frontends.relations import read_relations

    log = shared_file("mit-csail/mit-csail.clf")
    rel = read_relations(shared_file("mit-csail/mit-csail.relations"))
    scans = list(open_log(log))
    stamps = np.array([s.stamp_s for s in scans])
    odom = np.array([s.odom_pose for s in scans])
    summary, _ = relation_errors(stamps, odom, rel.stamps_s, rel.deltas)
    assert summary.n_matched == 1172
    assert summary.trans_mean_m == pytest.approx(1.68, abs=0.01)
    assert summary.rot_mean_deg == pytest.approx(5.07, abs=0.01)


def test_evo_ape_agrees_with_the_own_aligned_ate() -> None:
    """evo's APE (SE(3) Umeyama) and the project's SE(2)-aligned ATE are the same number on a
    planar trajectory; a rigid offset plus known noise gives the known RPE of a pure offset."""
    rng = np.random.default_rng(3)
    n = 200
    t = np.linspace(0.0, 2 * np.pi, n)
    truth = np.column_stack([5 * np.cos(t), 3 * np.sin(t), t + np.pi / 2])
    noisy = truth + np.column_stack([rng.normal(0, 0.05, (n, 2)), np.zeros(n)])
    estimate = se2.compose(np.array([1.0, -2.0, 0.4]), noisy)
    stamps = np.arange(n, dtype=np.float64)
    evo = evo_ape_rpe(stamps, estimate, truth)
    own = position_errors(estimate, truth)
    assert evo["ape_rmse_m"] == pytest.approx(own.rmse_m, rel=1e-6)
    assert evo["ape_mean_m"] == pytest.approx(own.mean_m, rel=1e-6)
    # RPE of a rigidly moved trajectory without noise is zero
    clean = evo_ape_rpe(stamps, se2.compose(np.array([1.0, -2.0, 0.4]), truth), truth)
    assert clean["rpe_trans_rmse_m"] == pytest.approx(0.0, abs=1e-9)
