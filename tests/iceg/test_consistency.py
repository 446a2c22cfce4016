"""NEES of factors and node estimates against hand-computed values, sampled honest noise and
real benchmark relations."""

from __future__ import annotations

import gtsam
import numpy as np
import pytest

from frontends import open_log
from frontends.relations import Relations, read_relations
from graph import FactorKind, FactorRecord
from iceg.consistency import (
    factor_nees,
    per_node,
    pose_nees,
    relation_factor_nees,
    summarize_nees,
)
from iceg.pipeline import run_scans
from iceg_common import se2
from iceg_common.errors import EvaluationError
from tests.conftest import se2_log, shared_file


def _factor(
    index: int, kind: FactorKind, i: int, j: int | None, measured: object, cov: object
) -> FactorRecord:
    return FactorRecord(
        index, kind, i, j, np.asarray(measured, float), np.asarray(cov, float), None, None
    )


def _off_by(truth_relative: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """A measurement ``z`` with ``Log(z^-1 ∘ T) = delta`` (``z = T ∘ Exp(delta)^-1``)."""
    t = gtsam.Pose2(*truth_relative.tolist())
    z = t.compose(gtsam.Pose2.Expmap(np.asarray(delta, float)).inverse())
    return np.array([z.x(), z.y(), z.theta()])


TRUTH = np.array([[0.0, 0.0, 0.0], [1.0, 0.5, 0.3], [2.0, 1.5, 1.2], [2.5, 3.0, 2.0]])


def test_a_known_error_gives_its_hand_computed_nees() -> None:
    # Hand-computed: delta = (0.1, -0.2, 0.05) under diag(0.01, 0.04, 0.0025) is one
    # standard deviation on each axis: NEES 1 + 1 + 1 = 3.
    delta = np.array([0.1, -0.2, 0.05])
    rel = se2.between(TRUTH[1], TRUTH[2])
    factors = [
        _factor(0, FactorKind.PRIOR, 0, None, TRUTH[0], np.eye(3) * 1e-6),
        _factor(1, FactorKind.ODOMETRY, 1, 2, _off_by(rel, delta), np.diag([0.01, 0.04, 0.0025])),
        _factor(2, FactorKind.SCAN_MATCH, 1, 2, rel, np.eye(3) * 1e-4),
    ]
    out = factor_nees(factors, TRUTH)
    assert out.kind.tolist() == ["odometry", "scan_match"]
    assert out.i.tolist() == [1, 1] and out.j.tolist() == [2, 2]
    np.testing.assert_allclose(out.error[0], delta, atol=1e-12)
    np.testing.assert_allclose(out.nees, [3.0, 0.0], atol=1e-9)


def test_the_error_is_the_se2_logarithm_of_the_measurement_to_the_truth() -> None:
    # gtsam's convention checked against the closed-form logarithm, on a large error where
    # the logarithm differs from the plain component differences.
    rel = se2.between(TRUTH[0], TRUTH[3])
    measured = se2.compose(rel, [0.3, -0.4, 0.6])
    out = factor_nees([_factor(0, FactorKind.LOOP_CLOSURE, 0, 3, measured, np.eye(3))], TRUTH)
    np.testing.assert_allclose(out.error[0], se2_log(se2.between(measured, rel)), atol=1e-12)
    assert not np.allclose(out.error[0], se2.between(measured, rel))  # not the plain difference


def test_honest_noise_has_the_chi_square_statistics() -> None:
    # Errors drawn from the covariance itself: NEES ~ chi-square(3), whose mean is 3, median
    # 2.366 and 95 % quantile 7.815 (4000 samples: the mean's standard error is 0.039).
    rng = np.random.default_rng(7)
    cov = np.array([[0.02, 0.005, 0.001], [0.005, 0.01, -0.002], [0.001, -0.002, 0.004]])
    deltas = rng.multivariate_normal(np.zeros(3), cov, size=4000)
    rel = se2.between(TRUTH[2], TRUTH[3])
    factors = [
        _factor(k, FactorKind.SCAN_MATCH, 2, 3, _off_by(rel, d), cov) for k, d in enumerate(deltas)
    ]
    out = factor_nees(factors, TRUTH)
    s = out.summary()["scan_match"]
    assert s.count == 4000
    assert s.mean == pytest.approx(3.0, abs=0.16)
    assert s.median == pytest.approx(2.366, abs=0.15)
    assert s.bound == pytest.approx(7.8147, abs=1e-3)
    assert s.beyond_bound == pytest.approx(0.05, abs=0.015)
    # The same errors under a covariance four times too small: overconfident by four.
    small = [_factor(f.index, f.kind, f.i, f.j, f.measured, cov / 4) for f in factors]
    assert factor_nees(small, TRUTH).summary()["scan_match"].scale == pytest.approx(
        4 * s.scale, rel=1e-9
    )


def test_the_default_bound_is_scipy_s_quantile() -> None:
    # The 95 % bound written out (a run scored against relations imports no scipy.special) is
    # scipy's chi-square quantile bit for bit; another confidence asks scipy.
    from scipy.special import chdtri

    values = np.array([0.5, 2.0, 9.0])
    assert summarize_nees(values).bound == float(chdtri(3, 1.0 - 0.95))
    assert summarize_nees(values, 0.99).bound == float(chdtri(3, 1.0 - 0.99))
    assert summarize_nees(values, 0.99).beyond_bound == 0.0  # 9.0 < 11.34
    assert summarize_nees(values).beyond_bound == pytest.approx(1 / 3)


def test_factors_of_nodes_without_truth_are_left_out() -> None:
    truth = TRUTH.copy()
    truth[2] = np.nan
    factors = [
        _factor(0, FactorKind.ODOMETRY, 0, 1, se2.between(TRUTH[0], TRUTH[1]), np.eye(3)),
        _factor(1, FactorKind.ODOMETRY, 1, 2, np.zeros(3), np.eye(3)),  # node 2 unknown
        _factor(2, FactorKind.ODOMETRY, 3, 7, np.zeros(3), np.eye(3)),  # node 7 past the table
    ]
    out = factor_nees(factors, truth)
    assert out.i.tolist() == [0] and out.nees.tolist() == pytest.approx([0.0])


def test_per_node_indexes_the_scans_by_node() -> None:
    scans = np.arange(30, dtype=float).reshape(10, 3)
    table = per_node([0, 1, 3], [0, 4, 9], scans)
    assert table.shape == (4, 3)
    np.testing.assert_array_equal(table[[0, 1, 3]], scans[[0, 4, 9]])
    assert np.isnan(table[2]).all()
    stamps = per_node([0, 2], [1, 3], [10.0, 10.1, 10.2, 10.3])  # a (S,) array: (N,)
    np.testing.assert_array_equal(stamps[[0, 2]], [10.1, 10.3])
    assert stamps.shape == (3,) and np.isnan(stamps[1])


def test_relations_score_the_factors_joining_their_scans_either_way() -> None:
    stamps = np.array([10.0, 10.2, 10.4, 10.6])
    delta = np.array([0.05, 0.1, -0.02])
    rel01 = se2.between(TRUTH[0], TRUTH[1])
    rel32 = se2.between(TRUTH[3], TRUTH[2])
    relations = Relations(
        np.array([[10.0, 10.2], [10.4, 10.6]]), np.array([rel01, se2.inverse(rel32)])
    )
    cov = np.diag([0.01, 0.01, 0.01])
    factors = [
        _factor(0, FactorKind.SCAN_MATCH, 0, 1, _off_by(rel01, delta), cov),
        _factor(1, FactorKind.ODOMETRY, 1, 2, np.zeros(3), cov),  # no relation spans it
        _factor(2, FactorKind.SCAN_MATCH, 3, 2, _off_by(rel32, delta), cov),  # reversed
    ]
    out = relation_factor_nees(factors, stamps, relations)
    assert out.i.tolist() == [0, 3]
    np.testing.assert_allclose(out.nees, [float(delta @ delta / 0.01)] * 2, rtol=1e-9)
    np.testing.assert_allclose(out.nees, factor_nees([factors[0], factors[2]], TRUTH).nees)
    with pytest.raises(EvaluationError, match="no factor joins the two scans"):
        relation_factor_nees([factors[1]], stamps, relations)


def test_pose_nees_compares_in_the_frame_of_the_first_node() -> None:
    # The truth lives in another world frame; aligned on the first node, node 2's estimate
    # is off by delta, two standard deviations on x alone: NEES 4.
    world = np.array([5.0, -3.0, 0.7])
    truth = se2.compose(world, TRUTH[:3])
    delta = np.array([0.2, 0.0, 0.0])
    est = TRUTH[:3].copy()
    est[2] = _off_by(TRUTH[2], delta)
    covs = np.stack([np.eye(3) * 1e-9, np.eye(3), np.diag([0.01, 1.0, 1.0])])
    out = pose_nees(est, covs, truth)
    assert np.isnan(out[0])
    assert out[1:] == pytest.approx([0.0, 4.0], abs=1e-9)


@pytest.mark.parametrize(
    ("call", "message"),
    [
        (lambda: factor_nees([], np.zeros((3, 2))), "node_truth must be"),
        (
            lambda: factor_nees(
                [_factor(0, FactorKind.ODOMETRY, 0, 1, np.zeros(3), -np.eye(3))], TRUTH
            ),
            "not positive definite",
        ),
        (lambda: pose_nees(TRUTH, np.zeros((2, 3, 3)), TRUTH), "node_covariances"),
        (lambda: summarize_nees([np.nan]), "no finite NEES"),
        (lambda: summarize_nees([1.0], confidence=1.0), "confidence"),
    ],
)
def test_bad_input_is_refused(call: object, message: str) -> None:
    with pytest.raises(EvaluationError, match=message):
        call()  # type: ignore[operator]


def test_mit_csail_relations_score_its_sequential_factors() -> None:
    # Real benchmark data: the first 300 scans of MIT CSAIL. Every relation there joins
    # consecutive scans, so the scored factors are odometry and scan-match factors, each
    # recomputed here with the closed-form logarithm.
    scans = list(open_log(shared_file("mit-csail/mit-csail.clf")))[:300]
    relations = read_relations(shared_file("mit-csail/mit-csail.relations"))
    result = run_scans(scans)
    stamps = per_node(result.node_ids, result.node_scan_index, result.stamps_s)
    out = relation_factor_nees(result.factors, stamps, relations)
    assert set(out.kind.tolist()) == {"odometry", "scan_match"}
    assert out.nees.size >= 40
    by_stamps = {
        tuple(np.round(t, 3)): d for t, d in zip(relations.stamps_s, relations.deltas, strict=True)
    }
    factors = {(f.i, f.j, f.kind.value): f for f in result.factors}
    for i, j, kind, nees in zip(out.i, out.j, out.kind, out.nees, strict=True):
        f = factors[(int(i), int(j), str(kind))]
        truth = by_stamps[(round(stamps[i], 3), round(stamps[j], 3))]
        e = se2_log(se2.between(f.measured, truth))
        assert nees == pytest.approx(float(e @ np.linalg.solve(f.cov, e)), rel=1e-6)
