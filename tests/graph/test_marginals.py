"""Marginal covariances against first-order propagation computed without gtsam.

Truth: for an odometry chain ``x_k+1 = x_k ∘ z_k ∘ Exp(e_k)``, ``e_k ~ N(0, Q_k)`` (the
BetweenFactorPose2 convention), and uncertainty ``x_k = x̂_k ∘ Exp(xi_k)``, ``xi_k ~ N(0, P_k)``
(body frame), first-order propagation gives

    P_k+1 = Ad(z_k^-1) P_k Ad(z_k^-1)^T + Q_k

with the SE(2) adjoint of ``iceg_common.se2.adjoint`` (Barfoot, *State Estimation for
Robotics*, 2017, §7.1). On a chain at zero residual this is exactly what the linearized graph
encodes, so the marginal of the last node must match it.
"""

from __future__ import annotations

import numpy as np
import pytest

from graph import GraphConfig, PoseGraph, odometry_covariance
from graph.simulate import se2_exp
from iceg_common.se2 import adjoint, compose, inverse


def _random_spd(rng: np.random.Generator) -> np.ndarray:
    a = rng.normal(size=(3, 3)) * np.array([0.05, 0.05, 0.01])[:, None]
    return a @ a.T + np.diag([1e-4, 1e-4, 1e-5])


def test_adjoint_moves_a_perturbation_across_a_pose() -> None:
    # sanity of the truth source: T ∘ Exp(xi) = Exp(Ad(T) xi) ∘ T (exact for SE(2))
    t = np.array([1.5, -0.7, 0.9])
    xi = np.array([0.03, -0.02, 0.05])
    np.testing.assert_allclose(compose(t, se2_exp(xi)), compose(se2_exp(adjoint(t) @ xi), t))


def test_chain_marginal_matches_analytic_propagation() -> None:
    rng = np.random.default_rng(7)
    config = GraphConfig()
    n = 40
    deltas = np.column_stack(
        [rng.uniform(0.2, 1.5, n - 1), rng.uniform(-0.3, 0.3, n - 1), rng.uniform(-0.8, 0.8, n - 1)]
    )
    # odometry covariances from the model, every third step a full correlated covariance
    covs = [
        _random_spd(rng) if k % 3 == 2 else odometry_covariance(d) for k, d in enumerate(deltas)
    ]

    g = PoseGraph(config)
    pose = np.array([3.0, -2.0, 1.0])
    g.add_node(0, pose)
    for k, (d, q) in enumerate(zip(deltas, covs, strict=True)):
        pose = compose(pose, d)
        g.add_node(k + 1, pose)
        g.add_between(k, k + 1, d, q)
        g.update()

    sxy, sth = config.prior_sigma_xy_m, config.prior_sigma_theta_rad
    p = np.diag([sxy**2, sxy**2, sth**2])
    analytic = [p]
    for d, q in zip(deltas, covs, strict=True):
        a = adjoint(inverse(d))
        p = a @ p @ a.T + q
        analytic.append(p)

    for node in (n // 2, n - 1):
        got = g.marginal_covariance(node)
        rel = np.linalg.norm(got - analytic[node]) / np.linalg.norm(analytic[node])
        assert rel < 0.01, f"node {node}: relative Frobenius error {rel:.2e}"
    # after a batch run, marginals come from iSAM2 re-linearized at the batch values
    g.optimize_batch()
    got = g.marginal_covariance(n - 1)
    rel = np.linalg.norm(got - analytic[-1]) / np.linalg.norm(analytic[-1])
    assert rel < 0.01, f"after batch: relative Frobenius error {rel:.2e}"
    # symmetric and in (x, y, theta) order: the heading variance is the sum along the chain
    assert got[2, 2] == pytest.approx(sth**2 + sum(q[2, 2] for q in covs), rel=1e-6)


def test_single_factor_marginal_is_the_factor_covariance_in_the_body_frame() -> None:
    # With node 0 pinned by its prior (1 mm, 0.01 deg), node 1's marginal is the factor's
    # covariance (tangent space of the measurement = body frame of node 1) plus the tiny
    # transported prior: an anisotropic covariance must come back unrotated despite a
    # 90 degree relative rotation and a 30 degree world heading.
    q = np.array([[0.04, 0.01, 0.0], [0.01, 0.01, 0.0], [0.0, 0.0, 0.001]])
    g = PoseGraph()
    g.add_node(0, [1.0, 2.0, np.radians(30.0)])
    z = np.array([2.0, 0.0, np.pi / 2])
    g.add_node(1, compose([1.0, 2.0, np.radians(30.0)], z))
    g.add_between(0, 1, z, q)
    g.update()
    cfg = g.config
    p0 = np.diag([cfg.prior_sigma_xy_m**2] * 2 + [cfg.prior_sigma_theta_rad**2])
    a = adjoint(inverse(z))
    np.testing.assert_allclose(g.marginal_covariance(1), a @ p0 @ a.T + q, rtol=1e-6, atol=1e-12)


def test_relative_covariance_is_the_chain_between_the_nodes_whatever_the_prior() -> None:
    # An odometry chain whose first node has a 30 m / 3 deg prior: each node's marginal carries
    # that uncertainty, the relative pose of two nodes does not. Its covariance is the
    # propagation of the steps between them from zero (the chain's own truth, above); in the
    # reverse order it is that covariance moved to the inverse's tangent space.
    rng = np.random.default_rng(11)
    deltas = np.column_stack(
        [rng.uniform(0.2, 1.5, 39), rng.uniform(-0.3, 0.3, 39), rng.uniform(-0.8, 0.8, 39)]
    )
    g = PoseGraph(GraphConfig(prior_sigma_xy_m=30.0, prior_sigma_theta_deg=3.0))
    pose = np.array([3.0, -2.0, 1.0])
    g.add_node(0, pose)
    for k, d in enumerate(deltas):
        pose = compose(pose, d)
        g.add_node(k + 1, pose)
        g.add_between(k, k + 1, d, _random_spd(rng))
    g.update()
    covs = [r.cov for r in g.factors if r.j is not None]
    p = np.zeros((3, 3))
    for d, q in zip(deltas[10:30], covs[10:30], strict=True):
        a = adjoint(inverse(d))
        p = a @ p @ a.T + q
    got = g.relative_covariance(10, 30)
    np.testing.assert_allclose(got, p, rtol=1e-4, atol=1e-9)
    assert g.marginal_covariance(30)[0, 0] > 100.0 * p[0, 0]
    rel = compose(inverse(g.estimate(10)), g.estimate(30))
    back = adjoint(rel) @ p @ adjoint(rel).T
    np.testing.assert_allclose(g.relative_covariance(30, 10), back, rtol=1e-4, atol=1e-9)
