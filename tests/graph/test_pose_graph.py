"""PoseGraph facade: conventions, buffer, batch state, statistics and error messages.

Truth comes from closed-form least squares (linear problems where the optimum is computable by
hand) and from the SE(2) helpers of iceg_common, never from gtsam itself.
"""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from scipy.optimize import brentq, least_squares

from graph import FactorKind, GraphConfig, PoseGraph
from graph.pose_graph import (
    STEP_BATCH,
    STEP_BATCH_CORRECTION,
    STEP_BATCH_GAUSSIAN_LOOPS,
    STEP_UPDATE,
    _clearly_positive_definite,
)
from iceg_common.errors import GraphError
from iceg_common.se2 import between, compose, wrap_angle

COV = np.diag([1e-2, 1e-2, 1e-3])


def _chain(n: int, config: GraphConfig | None = None) -> PoseGraph:
    """Nodes 0..n-1 one metre apart along x, odometry between consecutive nodes."""
    g = PoseGraph(config)
    for k in range(n):
        g.add_node(k, [float(k), 0.0, 0.0])
        if k:
            g.add_between(k - 1, k, [1.0, 0.0, 0.0], COV)
    return g


def _log(p: np.ndarray) -> np.ndarray:
    """SE(2) logarithm (Barfoot 2017, §7.1): (V(theta)^-1 t, theta)."""
    th = p[2]
    a = 1.0 - th**2 / 6.0 if abs(th) < 1e-9 else np.sin(th) / th
    b = th / 2.0 if abs(th) < 1e-9 else (1.0 - np.cos(th)) / th
    v_inv = np.array([[a, b], [-b, a]]) / (a * a + b * b)
    return np.array([*(v_inv @ p[:2]), th])


# Node 0 at X0; two measurements of node 1 in node 0's frame with zero rotation and a heading
# variance of 1e-12 rad², which pins the relative heading to 0 (within 1e-12 rad) and leaves a
# linear problem in the translation: t* = (S1^-1 + S2^-1)^-1 (S1^-1 z1 + S2^-1 z2), the
# information-weighted mean. Hand-computable, gtsam-free.
S1 = np.array([[0.02, 0.01, 0.0], [0.01, 0.03, 0.0], [0.0, 0.0, 1e-12]])
S2 = np.diag([0.01, 0.04, 1e-12])
Z1, Z2 = np.array([1.0, 0.2, 0.0]), np.array([1.3, -0.1, 0.0])
X0 = np.array([2.0, 1.0, 0.7])
W1, W2 = np.linalg.inv(S1[:2, :2]), np.linalg.inv(S2[:2, :2])
T_FUSED = np.linalg.solve(W1 + W2, W1 @ Z1[:2] + W2 @ Z2[:2])


def _two_measurements(g: PoseGraph) -> None:
    """Node 1 and its two measurements from node 0 (above)."""
    g.add_node(1, compose(X0, Z1))
    g.add_between(0, 1, Z1, S1, kind="odometry")
    g.add_between(0, 1, Z2, S2, kind=FactorKind.SCAN_MATCH)


def test_two_full_covariance_measurements_fuse_to_the_weighted_mean() -> None:
    # Prior on node 0 at its initial pose; each factor's error is 0.5 (t* - z_k)^T S_k^-1
    # (t* - z_k).
    g = PoseGraph()
    g.add_node(0, X0)
    _two_measurements(g)
    g.update()
    g.update()

    np.testing.assert_allclose(g.estimate(0), X0, atol=1e-9)
    np.testing.assert_allclose(between(g.estimate(0), g.estimate(1)), [*T_FUSED, 0.0], atol=1e-9)
    errors = g.residual_errors()
    e1, e2 = T_FUSED - Z1[:2], T_FUSED - Z2[:2]
    assert errors["odometry"] == pytest.approx(0.5 * e1 @ W1 @ e1, rel=1e-6)
    assert errors["scan_match"] == pytest.approx(0.5 * e2 @ W2 @ e2, rel=1e-6)
    assert errors["prior"] == pytest.approx(0.0, abs=1e-12)


def test_solve_pending_gives_a_buffered_node_its_estimate_without_an_update() -> None:
    # The same two measurements, node 1 buffered after node 0 went through iSAM2: its
    # estimate given node 0 is the information-weighted mean, without an iSAM2 update; the
    # update that follows starts there and keeps it.
    g = PoseGraph()
    g.add_node(0, X0)
    g.update()
    _two_measurements(g)
    g.solve_pending()

    np.testing.assert_allclose(between(X0, g.estimate(1)), [*T_FUSED, 0.0], atol=1e-9)
    np.testing.assert_array_equal(g.initial_pose(1), g.estimate(1))
    assert [s[0] for s in g.steps].count(STEP_UPDATE) == 1 and g.n_pending == (1, 2)
    solved = g.estimate(1)
    g.update()
    np.testing.assert_allclose(g.estimate(1), solved, atol=1e-9)
    np.testing.assert_allclose(g.estimate(0), X0, atol=1e-9)


def test_buffered_nodes_have_the_marginals_iSAM2_gives_them_after_the_update() -> None:
    # Nodes 6 and 7 buffered after a chain in iSAM2, each with odometry and a second, weaker
    # measurement from the node before; their marginal and relative covariances given the
    # anchor (node 5) must be those iSAM2 reports once updated (leaves inform nothing older).
    g = _chain(6)
    g.update()
    for k in (6, 7):
        g.add_node(k, [float(k), 0.02, 0.01])
        g.add_between(k - 1, k, [1.0, 0.0, 0.0], COV)
        g.add_between(k - 1, k, [1.05, 0.03, 0.01], 4.0 * COV, kind=FactorKind.SCAN_MATCH)
    g.solve_pending()
    pairs = [(2, 7), (5, 7), (6, 7), (7, 2), (7, 6)]
    buffered = [g.marginal_covariance(7), *(g.relative_covariance(i, j) for i, j in pairs)]
    g.update()
    in_isam = [g.marginal_covariance(7), *(g.relative_covariance(i, j) for i, j in pairs)]
    for got, want in zip(buffered, in_isam, strict=True):
        np.testing.assert_allclose(got, want, rtol=1e-5, atol=1e-12)


def test_between_convention_matches_an_independent_least_squares() -> None:
    # Truth: scipy least squares on the residuals written from the documented convention,
    # r_k = chol(S_k^-1)^T Log(z_k^-1 ∘ x0^-1 ∘ x1), with iceg_common SE(2) and a numpy Log.
    # Rotations are non-zero and the covariances full, so a wrong frame or a transposed
    # covariance would move the optimum.
    s1 = np.array([[0.02, 0.01, 0.002], [0.01, 0.03, -0.001], [0.002, -0.001, 0.01]])
    s2 = np.array([[0.05, -0.02, 0.0], [-0.02, 0.01, 0.001], [0.0, 0.001, 0.002]])
    z1, z2 = np.array([1.0, 0.4, 0.6]), np.array([1.3, 0.1, 0.9])
    x0 = np.array([-1.0, 2.0, 2.5])
    g = PoseGraph()
    g.add_node(0, x0)
    g.add_node(1, compose(x0, z1))
    g.add_between(0, 1, z1, s1)
    g.add_between(0, 1, z2, s2, kind="scan_match")
    for _ in range(3 * g.config.relinearize_skip):  # three relinearization checks
        g.update()

    roots = [np.linalg.cholesky(np.linalg.inv(s)).T for s in (s1, s2)]

    def residuals(x1: np.ndarray) -> np.ndarray:
        rel = between(x0, x1)
        pairs = zip(roots, (z1, z2), strict=True)
        return np.concatenate([r @ _log(between(z, rel)) for r, z in pairs])

    ref = least_squares(residuals, compose(x0, z1), xtol=1e-15, ftol=1e-15, gtol=1e-15)
    # iSAM2 stops relinearizing below its thresholds: close, not exact
    np.testing.assert_allclose(g.estimate(1)[:2], ref.x[:2], atol=1e-5)
    assert float(wrap_angle(g.estimate(1)[2] - ref.x[2])) == pytest.approx(0.0, abs=1e-5)
    g.optimize_batch()  # Levenberg–Marquardt iterates to convergence
    np.testing.assert_allclose(g.estimate(1)[:2], ref.x[:2], atol=1e-9)
    assert float(wrap_angle(g.estimate(1)[2] - ref.x[2])) == pytest.approx(0.0, abs=1e-9)
    r = residuals(ref.x)
    errors = g.residual_errors()
    assert errors["odometry"] == pytest.approx(0.5 * r[:3] @ r[:3], rel=1e-6)
    assert errors["scan_match"] == pytest.approx(0.5 * r[3:] @ r[3:], rel=1e-6)


@pytest.mark.parametrize(
    ("start", "xy_threshold_m", "relinearized"),
    [
        # node 1 starts 5 mm off along x: relinearized under 1e-3, not under 0.01 m for x, y
        ([1.005, 0.0, 0.0], None, 1),
        ([1.005, 0.0, 0.0], 0.01, 0),
        # 5 mrad off in heading: relinearized either way (the heading threshold stays 1e-3)
        ([1.0, 0.0, 0.005], None, 1),
        ([1.0, 0.0, 0.005], 0.01, 1),
    ],
)
def test_translation_threshold_applies_to_x_and_y_only(
    start: list[float], xy_threshold_m: float | None, relinearized: int
) -> None:
    g = PoseGraph(GraphConfig(relinearize_threshold_xy_m=xy_threshold_m, relinearize_skip=1))
    g.add_node(0, np.zeros(3))
    g.add_node(1, np.array(start))
    g.add_between(0, 1, np.array([1.0, 0.0, 0.0]), np.eye(3) * 1e-4)
    assert g.update().relinearized == 2  # new nodes are linearized where they start
    assert g.update().relinearized == relinearized  # the first check: delta is 5 mm / 5 mrad
    np.testing.assert_allclose(g.estimate(1), [1.0, 0.0, 0.0], atol=1e-9)


def test_buffer_is_cleared_and_no_factor_is_added_twice() -> None:
    g = _chain(3)
    assert g.n_pending == (3, 3)  # nodes 0..2; prior + 2 odometry factors
    stats = g.update()
    assert (stats.new_nodes, stats.new_factors) == (3, 3)
    assert g.n_pending == (0, 0)
    for _ in range(3):  # empty updates are extra iterations, not re-additions
        assert g.update().new_factors == 0
    assert g.isam2_factor_count == g.n_factors == 3
    g.add_node(3, [3.0, 0.0, 0.0])
    g.add_between(2, 3, [1.0, 0.0, 0.0], COV)
    g.add_between(0, 3, [3.0, 0.0, 0.0], COV, kind="loop_closure", robust="huber")
    assert g.update().new_factors == 2
    assert g.isam2_factor_count == g.n_factors == 5
    kinds = [f.kind.value for f in g.factors]
    assert kinds == ["prior", "odometry", "odometry", "odometry", "loop_closure"]
    assert [f.index for f in g.factors] == [0, 1, 2, 3, 4]
    assert g.factors[4].robust == "huber" and g.factors[4].robust_k == pytest.approx(1.345)
    assert g.factors[0].j is None and g.factors[0].i == 0
    with pytest.raises(ValueError):
        g.factors[1].measured[0] = 5.0  # records are read-only


def test_estimates_are_sorted_by_id_and_pending_nodes_report_their_initial_pose() -> None:
    g = PoseGraph()
    for n, x in [(5, 0.0), (2, 1.0), (9, 2.0)]:
        g.add_node(n, [x, 0.0, 0.0])
    g.add_between(5, 2, [1.0, 0.0, 0.0], COV)
    g.add_between(2, 9, [1.0, 0.0, 0.0], COV)
    g.update()
    g.add_node(7, [10.0, 0.0, 0.0])
    ids, poses = g.estimates()
    np.testing.assert_array_equal(ids, [2, 5, 7, 9])
    np.testing.assert_allclose(poses[:, 0], [1.0, 0.0, 10.0, 2.0], atol=1e-9)
    np.testing.assert_allclose(g.estimate(7), [10.0, 0.0, 0.0])
    assert g.n_nodes == 4


def test_batch_result_is_served_then_incremental_continues_from_it() -> None:
    # A square loop with a biased loop closure; the initial guess is off, so one iSAM2 step
    # is not the optimum. After optimize_batch the estimates are the batch values; a node
    # added afterwards with a single odometry factor lands exactly at batch estimate ∘ z.
    g = PoseGraph()
    truth = np.array([[0, 0, 0], [1, 0, np.pi / 2], [1, 1, np.pi], [0, 1, -np.pi / 2]], float)
    for k, p in enumerate(truth):
        g.add_node(k, p + np.array([0.05, -0.03, 0.02]) * k)
    for k in range(3):
        g.add_between(k, k + 1, between(truth[k], truth[k + 1]), COV)
    biased = between(truth[3], truth[0]) + np.array([0.1, 0.0, 0.0])
    g.add_between(3, 0, biased, COV, kind="loop_closure")
    g.update()
    stats = g.optimize_batch()
    assert stats.converged and stats.error_after < stats.error_before
    # served values are the ones the batch error was computed on
    assert sum(g.residual_errors().values()) == pytest.approx(stats.error_after, rel=1e-12)
    _, batch = g.estimates()
    assert g.isam2_factor_count == g.n_factors == 5  # re-seeded once, nothing duplicated

    z = np.array([0.5, 0.2, 0.3])
    g.add_node(4, [0.0, 0.0, 0.0])  # deliberately poor initial value
    g.add_between(3, 4, z, COV)
    g.update()
    g.update()
    _, after = g.estimates()
    np.testing.assert_allclose(after[:4], batch, atol=1e-7)
    np.testing.assert_allclose(after[4], compose(batch[3], z), atol=1e-7)


def test_a_batch_solve_frees_isam2_first_and_a_failed_one_rebuilds_it_at_the_estimates(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    """The batch solve runs without the iSAM2 it replaces (its memory is not held twice on a
    long log). When the solve fails, the estimates read as before it, and the next update
    rebuilds iSAM2 from every factor at them: an update from the optimum stays there."""
    g = _chain(5)
    g.add_between(0, 4, [4.2, 0.0, 0.0], COV, kind="loop_closure")
    g.update()
    assert g._isam is not None
    seen: list[bool] = []
    solve = PoseGraph._levenberg_marquardt

    def spy(self, *args):  # type: ignore[no-untyped-def]
        seen.append(self._isam is None)
        return solve(self, *args)

    monkeypatch.setattr(PoseGraph, "_levenberg_marquardt", spy)
    g.optimize_batch()
    assert seen == [True]
    _, optimum = g.estimates()

    def fail(self, *args):  # type: ignore[no-untyped-def]
        raise GraphError("batch Levenberg–Marquardt: simulated failure")

    monkeypatch.setattr(PoseGraph, "_levenberg_marquardt", fail)
    with pytest.raises(GraphError, match="simulated failure"):
        g.optimize_batch()
    _, after_failure = g.estimates()
    np.testing.assert_array_equal(after_failure, optimum)
    stats = g.update()
    assert stats.reseeded and stats.new_factors == g.n_factors == 6  # with the prior
    np.testing.assert_allclose(g.estimates()[1], optimum, atol=1e-9)
    # by hand: the 0.2 m the closure adds is shared by the five equal steps of the cycle
    np.testing.assert_allclose(optimum, [[1.04 * k, 0.0, 0.0] for k in range(5)], atol=1e-9)


def test_optimize_batch_includes_buffered_nodes() -> None:
    g = _chain(4)  # never updated
    g.add_between(0, 3, [3.3, 0.0, 0.0], COV, kind="loop_closure")
    g.optimize_batch()
    # linear problem along x: 3 odometry steps of 1 m and a 3.3 m loop closure with equal
    # variances share the 0.3 m discrepancy equally: each step 1.075 m (least squares)
    np.testing.assert_allclose(g.estimates()[1][:, 0], [0.0, 1.075, 2.15, 3.225], atol=1e-6)
    assert g.n_pending == (0, 0)


def _ring(config: GraphConfig | None = None) -> tuple[PoseGraph, list, np.ndarray]:
    """60 nodes on a 10 m circle, odometry with noise (seeded), initial values drifting
    0.03 rad a step, one loop closure back to node 0; updated once. Returns the graph, its
    factors ``(i, j, z, sigmas)`` and node 0's pose."""
    n, sig = 60, np.array([0.03, 0.03, 0.01])
    ang = np.linspace(0.0, 2.0 * np.pi, n, endpoint=False)
    truth = np.stack([10.0 * np.cos(ang), 10.0 * np.sin(ang), ang + np.pi / 2], axis=1)
    noise = np.random.default_rng(4).normal(0.0, sig, (n, 3))
    g = PoseGraph(config)
    g.add_node(0, truth[0])
    factors, est = [], truth[0].copy()
    for k in range(1, n):
        z = between(truth[k - 1], truth[k]) + noise[k]
        est = compose(est, z + np.array([0.0, 0.0, 0.03]))
        g.add_node(k, est)
        g.add_between(k - 1, k, z, np.diag(sig**2))
        factors.append((k - 1, k, z, sig))
    z = between(truth[n - 1], truth[0])
    g.add_between(n - 1, 0, z, np.diag(sig**2), kind="loop_closure")
    factors.append((n - 1, 0, z, sig))
    g.update()
    return g, factors, truth[0]


def test_a_correction_solve_stops_at_its_own_looser_tolerance() -> None:
    # Truth: scipy least squares on the whitened residuals Log(z^-1 (x_i^-1 x_j)) with node 0
    # fixed (the graph's prior). The default batch (relative tolerance 1e-10) reaches it; a
    # correction solve (a mid-run re-solve after global closures) stops at
    # correction_relative_error_tol, 1e-3 here: one iteration fewer, within 0.1 mm of it.
    g, factors, x0 = _ring()

    def residuals(flat: np.ndarray) -> np.ndarray:
        x = np.vstack([x0, flat.reshape(-1, 3)])
        return np.concatenate([_log(between(z, between(x[i], x[j]))) / s for i, j, z, s in factors])

    start = g.estimates()[1][1:].ravel()
    ref = least_squares(residuals, start, xtol=1e-15, ftol=1e-15, gtol=1e-15).x.reshape(-1, 3)

    def off(graph: PoseGraph) -> np.ndarray:
        d = graph.estimates()[1][1:] - ref
        return np.abs(np.column_stack([d[:, :2], wrap_angle(d[:, 2])]))

    tight = g.optimize_batch()
    assert off(g).max() < 1e-7
    loose, _, _ = _ring(GraphConfig(correction_relative_error_tol=1e-3))
    stats = loose.optimize_batch(correction=True)
    assert stats.converged and stats.iterations == tight.iterations - 1
    assert 1e-7 < off(loose).max() < 1e-4
    assert loose.steps[-1][0] == STEP_BATCH_CORRECTION
    with pytest.raises(GraphError, match="keeps the loop-closure kernels"):
        loose.optimize_batch(correction=True, loop_closure_kernels=False)


@pytest.mark.parametrize(
    ("kwargs", "message"),
    [
        ({"cov": np.diag([1e-2, -1e-2, 1e-3])}, "not positive definite"),
        ({"cov": np.array([[1e-2, 1e-3, 0], [0, 1e-2, 0], [0, 0, 1e-3]])}, "not symmetric"),
        ({"cov": np.eye(2)}, r"finite \(3, 3\)"),
        ({"cov": np.diag([np.nan, 1.0, 1.0])}, r"finite \(3, 3\)"),
        ({"measured": [1.0, np.inf, 0.0]}, r"measured must be a finite \(3,\)"),
        ({"measured": [1.0, 0.0]}, r"measured must be a finite \(3,\)"),
        ({"robust": "tukey"}, "robust must be None"),
        ({"robust": "cauchy", "robust_k": -1.0}, "robust_k must be a positive"),
    ],
)
def test_invalid_factor_raises_graph_error_naming_the_factor(kwargs: dict, message: str) -> None:
    g = _chain(2)
    args = {"measured": [1.0, 0.0, 0.0], "cov": COV, "kind": "loop_closure"} | kwargs
    with pytest.raises(GraphError, match=message) as info:
        g.add_between(0, 1, **args)
    assert "loop_closure factor between 0 and 1" in str(info.value)
    assert g.n_factors == 2  # nothing was added


# eigenvalues of covariances: negative, zero or positive, none subnormal
_EIG = st.one_of(st.floats(-1e-3, -1e-12), st.just(0.0), st.floats(1e-12, 1e2))


@given(_EIG, _EIG, _EIG, st.integers(0, 2**32 - 1))
def test_covariance_check_accepts_what_cholesky_accepts(  # type: ignore[no-untyped-def]
    e0, e1, e2, seed
) -> None:
    """The float pivot test of a covariance: whatever it accepts, LAPACK's Cholesky accepts
    (it leaves close calls to it), and a matrix conditioned below 1e6 it accepts itself."""
    q, _ = np.linalg.qr(np.random.default_rng(seed).normal(size=(3, 3)))
    eig = np.array([e0, e1, e2])
    c = q @ np.diag(eig) @ q.T
    c = 0.5 * (c + c.T)
    if _clearly_positive_definite(c.tolist()):
        np.linalg.cholesky(c)  # raises if not
    if eig.min() > 1e-6 * eig.max() > 0.0:
        assert _clearly_positive_definite(c.tolist())


def test_a_factor_keeps_the_symmetrised_covariance_numpy_gives() -> None:
    # The covariance a factor keeps is 0.5 * (c + c.T) of the given one, bit for bit, for
    # covariances asymmetric in the last bits as a product of matrices leaves them.
    rng = np.random.default_rng(3)
    g = _chain(2)
    for _ in range(50):
        a = rng.normal(size=(3, 3))
        c = a @ a.T + np.eye(3) * 1e-3
        c[0, 1] = np.nextafter(c[0, 1], np.inf)
        c[2, 1] = np.nextafter(c[2, 1], -np.inf)
        record = g.add_between(0, 1, [1.0, 0.0, 0.0], c, kind="scan_match")
        assert np.array_equal(record.cov, 0.5 * (c + c.T))


def test_structural_errors_name_the_node() -> None:
    g = _chain(2)
    unknown = "scan_match factor between 1 and 5 references unknown node 5"
    with pytest.raises(GraphError, match=unknown):
        g.add_between(1, 5, [1.0, 0.0, 0.0], COV, kind="scan_match")
    with pytest.raises(GraphError, match="node 1 already exists"):
        g.add_node(1, [0.0, 0.0, 0.0])
    with pytest.raises(GraphError, match="non-negative"):
        g.add_node(-3, [0.0, 0.0, 0.0])
    with pytest.raises(GraphError, match="kind 'wheel'"):
        g.add_between(0, 1, [1.0, 0.0, 0.0], COV, kind="wheel")
    with pytest.raises(GraphError, match="two different nodes"):
        g.add_between(1, 1, [1.0, 0.0, 0.0], COV)
    with pytest.raises(GraphError, match="unknown node 4"):
        g.estimate(4)
    g.add_node(7, [5.0, 0.0, 0.0])
    with pytest.raises(GraphError, match="node 7 has no factor"):
        g.update()
    with pytest.raises(GraphError, match="node 7 has not been through update"):
        g.marginal_covariance(7)


def test_indeterminant_system_is_wrapped_and_recoverable() -> None:
    # Nodes 5-6 form an island linked to nothing anchored: the linear system is singular.
    g = _chain(2)
    g.update()
    g.add_node(5, [5.0, 0.0, 0.0])
    g.add_node(6, [6.0, 0.0, 0.0])
    g.add_between(5, 6, [1.0, 0.0, 0.0], COV)
    with pytest.raises(GraphError, match=r"indeterminant linear system near node [56]") as info:
        g.update()
    assert "odometry 5-6" in str(info.value)
    with pytest.raises(GraphError, match="last update failed"):
        g.marginal_covariance(1)
    # linking the island rebuilds iSAM2 from every factor, each exactly once
    g.add_between(1, 5, [4.0, 0.0, 0.0], COV, kind="loop_closure")
    stats = g.update()
    assert stats.reseeded
    assert g.isam2_factor_count == g.n_factors == 4
    np.testing.assert_allclose(g.estimate(6), [6.0, 0.0, 0.0], atol=1e-9)


def test_repr_counts_kinds() -> None:
    g = _chain(3)
    assert "nodes=3" in repr(g) and "'odometry': 2" in repr(g) and "pending=3" in repr(g)


def test_cached_estimates_follow_every_change_and_are_copies() -> None:
    # estimates() is cached per graph state: after each add_node, update, optimize_batch it
    # equals the per-node estimate() (iSAM2, batch or initial values), and callers get copies.
    g = PoseGraph()
    g.add_node(0, [0.0, 0.0, 0.0])

    def check() -> None:
        # estimates_of, read node by node (before the cache is filled), gives the same bits.
        some = np.arange(g.n_nodes)[::2][::-1]  # unsorted, a subset
        sub_ids, sub = g.estimates_of(np.r_[some, some])
        ids, poses = g.estimates()
        np.testing.assert_array_equal(sub_ids, np.sort(some))
        np.testing.assert_array_equal(sub, poses[np.searchsorted(ids, sub_ids)])
        np.testing.assert_array_equal(g.estimates_of(some)[1], sub)  # now from the cache
        expect = np.array([g.estimate(int(n)) for n in ids])
        np.testing.assert_array_equal(poses, expect)
        poses[:] = 99.0  # a copy: the next call is unaffected
        np.testing.assert_array_equal(g.estimates()[1], expect)

    check()
    g.update()
    check()
    for k in range(1, 6):
        g.add_node(k, [k + 0.1, 0.05 * k, 0.0])
        check()  # the new node at its initial value
        g.add_between(k - 1, k, [1.0, 0.0, 0.0], COV)
        g.update()
        check()
    g.add_between(0, 5, [5.0, 0.0, 0.0], COV)
    g.optimize_batch()
    check()
    g.add_node(6, [6.0, 0.0, 0.0])
    check()
    g.add_between(5, 6, [1.0, 0.0, 0.0], COV)
    g.update()
    check()
    assert g.estimates()[0].tolist() == list(range(7))


def test_estimates_of_reads_many_nodes_at_once_with_the_bits_of_one_at_a_time() -> None:
    # estimates_of asks iSAM2 for every node it has not cached in one call
    # (calculateEstimate(keys)); each value must be the one calculateEstimatePose2 gives that
    # node alone, after relinearizing updates with a loop closure and curved headings.
    def build() -> PoseGraph:
        rng = np.random.default_rng(3)
        g = PoseGraph()
        g.add_node(0, [0.0, 0.0, 0.4])
        for k in range(1, 40):
            step = np.array([0.8, 0.1, 0.17]) + rng.normal(0.0, [0.05, 0.05, 0.02])
            g.add_node(k, compose(g.initial_pose(k - 1), step))
            g.add_between(k - 1, k, step + np.array([0.03, -0.02, 0.01]), COV, kind="odometry")
            if k % 7 == 0:
                g.update()
        g.add_between(
            3, 38, between(g.initial_pose(3), g.initial_pose(38)), COV, kind="loop_closure"
        )
        g.update()
        g.update()
        return g

    batched, alone = build(), build()
    some = np.array([38, 5, 17, 0, 21])
    batched.estimate(17)  # one of them cached first
    ids, poses = batched.estimates_of(some)
    np.testing.assert_array_equal(poses, np.array([alone.estimate(int(n)) for n in ids]))
    everything = np.arange(40)
    np.testing.assert_array_equal(
        batched.estimates_of(everything)[1], np.array([alone.estimate(int(n)) for n in everything])
    )


def test_full_reads_between_solver_changes_take_the_solver_rows_again(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    # add_node and solve_pending change only buffered nodes: after a full read, the next
    # full reads (and the node-by-node reads of iSAM2's nodes) take the solver's rows from
    # it instead of reading gtsam again. Every read gives what estimate() gives: iSAM2's
    # nodes as gtsam reads them one by one, a buffered node its initial value as it is. The
    # headings are not zero: through a Pose2 (gtsam's rows) a few differ in the last bit,
    # and then a run's results would depend on whether it read one node or all.
    import gtsam

    full_reads = 0
    extract = gtsam.utilities.extractPose2

    def counted(values: object) -> object:
        nonlocal full_reads
        full_reads += 1
        return extract(values)

    monkeypatch.setattr(gtsam.utilities, "extractPose2", counted)

    def through_pose2(pose: np.ndarray) -> float:
        return float(gtsam.Pose2(*pose.tolist()).theta())

    round_trip_differs = False
    g = PoseGraph()
    g.add_node(0, [0.0, 0.0, 0.2])
    in_isam: list[int] = []

    def check(pending: list[int]) -> bool:
        """Every read against estimate(); whether a buffered heading changes through a Pose2."""
        by_node = np.array([g.estimate(n) for n in in_isam]).reshape(-1, 3)  # one at a time
        raw = np.array([g.initial_pose(n) for n in pending]).reshape(-1, 3)
        everything = np.arange(g.n_nodes)[::-1]
        for poses in (
            g.estimates_of(everything)[1],  # node by node
            g.estimates()[1],
            g.estimates_of(everything)[1],  # from the table
        ):
            np.testing.assert_array_equal(poses[in_isam], by_node)
            np.testing.assert_array_equal(poses[pending], raw)
        return any(through_pose2(p) != p[2] for p in raw)

    updates = 0
    for k in range(1, 9):
        g.add_node(k, compose(g.initial_pose(k - 1), [1.0, 0.05, 0.3]))
        g.add_between(k - 1, k, [0.9, 0.1, 0.31], COV, kind="odometry")
        buffered = [n for n in range(k + 1) if n not in in_isam]
        round_trip_differs |= check(buffered)  # the new node at its initial value
        if 5 <= k <= 7:
            g.solve_pending()
        else:
            g.update()
            updates += 1
            in_isam, buffered = list(range(k + 1)), []
        round_trip_differs |= check(buffered)
    assert round_trip_differs  # the case the rows of buffered nodes must not take
    # one gtsam read per solver state (and one before the first update): none after
    # solve_pending or add_node
    assert updates == 5
    assert full_reads == updates + 1


def test_huber_scan_match_factor_pulls_a_bounded_amount() -> None:
    # The slam.scan_match_kernel mechanism: accurate odometry z1 (sigma 0.01 m) and a wrong
    # scan match z2 0.3 m away (sigma 0.05 m, 6 sigmas), the relative heading pinned to 0.
    # Gaussian: the information-weighted mean, x = (z1 / 0.01^2 + z2 / 0.05^2) / (1 / 0.01^2
    # + 1 / 0.05^2) = 1.01154. Huber (k = 1.345): where the match's residual r = (z2 - x) /
    # 0.05 exceeds k, its pull on x is constant, k / 0.05, so (x - z1) / 0.01^2 = k / 0.05
    # and x = z1 + k 0.01^2 / 0.05 = 1.00269 (r = 5.9 > k): a quarter of the Gaussian pull.
    s1 = np.diag([1e-4, 1e-4, 1e-12])
    s2 = np.diag([0.05**2, 0.05**2, 1e-12])
    z1, z2 = np.array([1.0, 0.0, 0.0]), np.array([1.3, 0.0, 0.0])
    x = {}
    for robust in (None, "huber"):
        g = PoseGraph()
        g.add_node(0, [0.0, 0.0, 0.0])
        g.add_node(1, z1)
        g.add_between(0, 1, z1, s1, kind="odometry")
        g.add_between(0, 1, z2, s2, kind=FactorKind.SCAN_MATCH, robust=robust)
        g.optimize_batch()
        x[robust] = g.estimate(1)
    gaussian = (z1[0] / s1[0, 0] + z2[0] / s2[0, 0]) / (1.0 / s1[0, 0] + 1.0 / s2[0, 0])
    np.testing.assert_allclose(x[None], [gaussian, 0.0, 0.0], atol=1e-6)
    np.testing.assert_allclose(x["huber"], [z1[0] + 1.345 * s1[0, 0] / 0.05, 0.0, 0.0], atol=1e-6)


def test_batch_without_loop_closure_kernels_solves_the_gaussian_problem() -> None:
    # Node 0 fixed at the origin by the prior; node 1 measured by odometry z1 and by a loop
    # closure z2 with a Cauchy kernel (k = 1) 30 sigmas away. The relative heading is pinned
    # to 0 (variance 1e-12), so without kernels the optimum is the information-weighted mean
    # of the translations (hand-computable); with the kernel, x balances the odometry's pull
    # (x - 1) / 0.1^2 against the Cauchy closure's r / (1 + r^2) / 0.01, r = (1.3 - x) / 0.01
    # (a scalar root, found by brentq): the closure is all but ignored.
    s1 = np.diag([0.01, 0.01, 1e-12])
    s2 = np.diag([1e-4, 1e-4, 1e-12])
    z1, z2 = np.array([1.0, 0.0, 0.0]), np.array([1.3, 0.0, 0.0])
    g = PoseGraph()
    g.add_node(0, [0.0, 0.0, 0.0])
    g.add_node(1, z1)
    g.add_between(0, 1, z1, s1, kind="odometry")
    g.add_between(0, 1, z2, s2, kind="loop_closure", robust="cauchy", robust_k=1.0)
    g.optimize_batch()

    def balance(x: float) -> float:
        r = (z2[0] - x) / 0.01  # the closure's residual in its own sigmas
        return (x - z1[0]) / s1[0, 0] - r / (1.0 + r * r) / 0.01

    x = brentq(balance, z1[0], z2[0])
    assert x < 1.05
    np.testing.assert_allclose(g.estimate(1), [x, 0.0, 0.0], atol=1e-6)

    g.optimize_batch(loop_closure_kernels=False)
    w1, w2 = np.linalg.inv(s1[:2, :2]), np.linalg.inv(s2[:2, :2])
    t = np.linalg.solve(w1 + w2, w1 @ z1[:2] + w2 @ z2[:2])
    np.testing.assert_allclose(g.estimate(1), [*t, 0.0], atol=1e-6)
    assert [s[0] for s in g.steps][-2:] == [STEP_BATCH, STEP_BATCH_GAUSSIAN_LOOPS]
    assert g.factors[-1].robust == "cauchy"  # the factor itself keeps its kernel


@pytest.mark.parametrize("kernel", ["cauchy", "huber"])
@pytest.mark.parametrize("gate", [16.27, None])
def test_final_refinement_keeps_the_kernel_of_a_closure_the_rest_contradicts(
    gate: float | None, kernel: str
) -> None:
    # As above, with odometry sigma 0.02 m (variance 4e-4) and a robust closure (variance
    # 1e-4) that says 2 m where the odometry says 1 m. The Gaussian optimum is the
    # information-weighted mean x = 1.8, where the closure is 20 sigmas off (chi-square 400).
    # Its relative covariance there (iSAM2, robust weight w at 400) holds 2500 + w * 1e4 of
    # information; without the closure's share, 2500: leave-one-out chi-square
    # 0.2^2 / (4e-4 + 1e-4) = 80 > 16.27. (Taking out the closure's full information instead
    # would leave a negative rest, and the closure would pass.) With the gate the final
    # refinement keeps the kernel and lands on the robust balance (x - 1) / 4e-4 =
    # psi(r) / 0.01, r = (2 - x) / 0.01: Cauchy (k = 1) psi(r) = r / (1 + r^2), a root
    # (brentq, as above); Huber psi(r) = k = 1.345 beyond k, so x = 1 + 4e-4 * 134.5 by hand.
    # Without the gate (None) the closure is Gaussian: x = 1.8.
    s_odometry = np.diag([4e-4, 4e-4, 1e-12])
    s_closure = np.diag([1e-4, 1e-4, 1e-12])
    z1, z2 = np.array([1.0, 0.0, 0.0]), np.array([2.0, 0.0, 0.0])
    k = 1.0 if kernel == "cauchy" else 1.345
    g = PoseGraph(GraphConfig(final_closure_consistency_chi2=gate))
    g.add_node(0, [0.0, 0.0, 0.0])
    g.add_node(1, z1)
    g.add_between(0, 1, z1, s_odometry, kind="odometry")
    g.add_between(0, 1, z2, s_closure, kind="loop_closure", robust=kernel, robust_k=k)
    g.optimize_batch()

    def balance(x: float) -> float:
        r = (z2[0] - x) / 0.01
        return (x - z1[0]) / 4e-4 - r / (1.0 + r * r) / 0.01

    robust_x = brentq(balance, z1[0], z2[0]) if kernel == "cauchy" else z1[0] + 4e-4 * k / 0.01
    g.optimize_batch(loop_closure_kernels=False)
    expected = robust_x if gate is not None else 1.8
    np.testing.assert_allclose(g.estimate(1), [expected, 0.0, 0.0], atol=1e-6)
