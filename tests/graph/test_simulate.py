"""The Manhattan simulator used as ground truth by the robustness test and the benchmark.

Truth: the simulator's own stated noise models (normalized estimation error squared of the
measurements against the true relative poses has mean 3 for 3-dof Gaussian noise) and gtsam's
Pose2.Expmap for the exponential map.
"""

from __future__ import annotations

import gtsam
import numpy as np

from graph.simulate import se2_exp, simulate_manhattan
from iceg_common.se2 import between


def _log(p: np.ndarray) -> np.ndarray:
    return np.array([gtsam.Pose2.Logmap(gtsam.Pose2(*row)) for row in p])


def test_se2_exp_matches_gtsam_expmap() -> None:
    rng = np.random.default_rng(0)
    xi = rng.normal(size=(20, 3)) * [1.0, 1.0, 1.5]
    xi[0] = [0.3, -0.2, 0.0]  # the small-angle branch
    ref = np.array([[p.x(), p.y(), p.theta()] for p in (gtsam.Pose2.Expmap(v) for v in xi)])
    np.testing.assert_allclose(se2_exp(xi), ref, atol=1e-12)


def test_measurement_noise_has_the_stated_covariance() -> None:
    sim = simulate_manhattan(3000, seed=11, grid_cells=12, outlier_fraction=0.1)
    truth = sim.true_poses
    # the robot moves one 1 m cell per node, turning by multiples of 90 degrees
    steps = np.linalg.norm(np.diff(truth[:, :2], axis=0), axis=1)
    np.testing.assert_allclose(steps, 1.0)
    np.testing.assert_allclose(np.mod(truth[:, 2], np.pi / 2), 0.0, atol=1e-12)

    # odometry: e = Log(true^-1 ∘ measured) ~ N(0, Q_k); mean NEES 3 (+-0.15 is > 4 sigma
    # of the mean of 3000 chi2(3) samples: sqrt(6 / 3000) = 0.045)
    e = _log(between(between(truth[:-1], truth[1:]), sim.odometry_measured))
    nees = np.einsum("ni,nij,nj->n", e, np.linalg.inv(sim.odometry_cov), e)
    assert abs(nees.mean() - 3.0) < 0.15

    right = ~sim.loop_is_outlier
    i, j = sim.loop_ij[right, 0], sim.loop_ij[right, 1]
    e = _log(between(between(truth[i], truth[j]), sim.loop_measured[right]))
    nees = np.einsum("ni,ij,nj->n", e, np.linalg.inv(sim.loop_cov), e)
    assert abs(nees.mean() - 3.0) < 5.0 * np.sqrt(6.0 / right.sum())
    assert np.all(j - i >= 10)
    # right loop closures join nodes in the same cell; wrong ones nodes >= 3 m apart
    np.testing.assert_allclose(truth[i, :2], truth[j, :2])
    wrong = sim.loop_ij[sim.loop_is_outlier]
    far = np.linalg.norm(truth[wrong[:, 0], :2] - truth[wrong[:, 1], :2], axis=1)
    assert far.min() >= 3.0
    assert sim.loop_is_outlier.sum() == round(0.1 * len(sim.loop_ij))
