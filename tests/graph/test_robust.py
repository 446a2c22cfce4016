"""Robust loop closures on a simulated Manhattan world with 10 % wrong loop closures.

Truth: the simulator's ground-truth poses (graph.simulate.simulate_manhattan). The position
error is the absolute trajectory error after a least-squares SE(2) alignment of the estimate to
the truth (Horn 1987 / Umeyama 1991; Sturm et al., IROS 2012), computed here with numpy; the
error anchored at node 0 (no alignment) is reported beside it.
"""

from __future__ import annotations

import numpy as np
import pytest

from graph import OdometryNoiseConfig, PoseGraph, odometry_covariance
from graph.simulate import SimulatedPoseGraph, simulate_manhattan
from iceg_common.se2 import between, compose

# Odometry of a good wheel encoder (1.5 cm and 0.1 deg + 1 % of the rotation per 1 m step)
# and scan-matching loop closures (2 cm, 0.3 deg).
ODOMETRY = OdometryNoiseConfig(
    sigma_xy_base_m=0.005,
    sigma_xy_per_distance_m_per_m=0.01,
    sigma_theta_base_deg=0.1,
    sigma_theta_per_rotation_deg_per_deg=0.01,
    sigma_theta_per_distance_deg_per_m=0.1,
)
N_NODES = 500


def _simulate(outlier_fraction: float, seed: int) -> SimulatedPoseGraph:
    return simulate_manhattan(
        N_NODES,
        seed=seed,
        grid_cells=8,
        odometry=ODOMETRY,
        loop_sigma_xy_m=0.02,
        loop_sigma_theta_deg=0.3,
        outlier_fraction=outlier_fraction,
    )


def _solve(sim: SimulatedPoseGraph, robust: str | None) -> np.ndarray:
    """Incremental SLAM back-end run: one node, its odometry and loop closures, update()."""
    g = PoseGraph()
    g.add_node(0, sim.true_poses[0])
    loops_at: dict[int, list[int]] = {}
    for idx, k in enumerate(sim.loop_ij[:, 1].tolist()):
        loops_at.setdefault(k, []).append(idx)
    for k in range(1, len(sim.true_poses)):
        z = sim.odometry_measured[k - 1]
        g.add_node(k, compose(g.estimate(k - 1), z))
        g.add_between(k - 1, k, z, odometry_covariance(z, ODOMETRY))
        for idx in loops_at.get(k, []):
            m = int(sim.loop_ij[idx, 0])
            g.add_between(
                m, k, sim.loop_measured[idx], sim.loop_cov, kind="loop_closure", robust=robust
            )
        g.update()
    for _ in range(3 * g.config.relinearize_skip):  # converge the newest nodes
        g.update()
    return g.estimates()[1]


def _errors(est: np.ndarray, truth: np.ndarray) -> tuple[float, float]:
    """(aligned mean position error, anchored mean position error) in metres."""
    anchored = float(np.mean(np.linalg.norm(est[:, :2] - truth[:, :2], axis=1)))
    a = est[:, :2] - est[:, :2].mean(axis=0)
    b = truth[:, :2] - truth[:, :2].mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    rot = (u @ d @ vt).T
    aligned = float(np.mean(np.linalg.norm(a @ rot.T - b, axis=1)))
    return aligned, anchored


@pytest.mark.parametrize("seed", [1, 2])
def test_cauchy_kernel_rejects_wrong_loop_closures(seed: int) -> None:
    sim = _simulate(0.1, seed)
    clean = _simulate(0.0, seed)  # same trajectory and noise, every loop closure right
    n_out = int(sim.loop_is_outlier.sum())
    assert n_out == round(0.1 * len(sim.loop_ij)) and n_out >= 15

    gauss_aligned, gauss_anchored = _errors(_solve(sim, None), sim.true_poses)
    est = _solve(sim, "cauchy")
    cauchy_aligned, cauchy_anchored = _errors(est, sim.true_poses)
    clean_aligned, clean_anchored = _errors(_solve(clean, None), clean.true_poses)
    report = (
        f"seed {seed}, {len(sim.loop_ij)} loop closures, {n_out} wrong; mean position error "
        f"aligned / anchored: Gaussian {gauss_aligned:.3f} / {gauss_anchored:.3f} m, Cauchy "
        f"{cauchy_aligned:.4f} / {cauchy_anchored:.4f} m, Gaussian without wrong closures "
        f"{clean_aligned:.4f} / {clean_anchored:.4f} m"
    )
    print(report)
    assert cauchy_aligned < 0.05, report
    assert gauss_aligned > 0.5, report  # at least ten times the target: far worse
    # the kernel brings the error back to what the right loop closures alone give
    assert cauchy_aligned < 1.25 * clean_aligned, report

    # every wrong closure ends up far out in the tail (Cauchy weight k²/(k²+d²) < 0.06) and
    # the right ones inside the Gaussian bulk (first-order residual, loop covariance)
    info = np.linalg.inv(sim.loop_cov)
    rel = between(est[sim.loop_ij[:, 0]], est[sim.loop_ij[:, 1]])
    res = between(sim.loop_measured, rel)
    d = np.sqrt(np.einsum("ni,ij,nj->n", res, info, res))
    assert d[sim.loop_is_outlier].min() > 10.0, report
    assert np.quantile(d[~sim.loop_is_outlier], 0.99) < 5.0, report
