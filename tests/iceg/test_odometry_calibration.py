"""Online odometry calibration (iceg.odometry_calibration) against known biases."""

from __future__ import annotations

import json
import logging
import math
from pathlib import Path

import numpy as np
import pytest
from typer.testing import CliRunner

from frontends import open_log
from frontends.carmen import write_carmen
from frontends.simulate import (
    OdometryModel,
    default_trajectory,
    simulate,
    simulate_scenario,
    synthetic_odometry,
)
from graph import FactorKind, odometry_covariance
from iceg.cli import app
from iceg.config import IcegConfig, config_from_dict
from iceg.evaluation import position_errors
from iceg.odometry_calibration import (
    OdometryCalibrationConfig,
    OdometryCalibrator,
    signed_distance,
    systematic_errors,
)
from iceg.pipeline import run_log
from iceg.slam import Slam
from iceg_common import se2
from iceg_common.errors import ConfigError
from tests.conftest import shared_file

#: The office_biased scenario's odometry: 1.5 % scale error, 0.4 deg/m heading drift.
SCALE_ERROR = 0.015
DRIFT_RAD_PER_M = math.radians(0.4)
MATCH_COV = np.diag([0.003**2, 0.003**2, math.radians(0.05) ** 2])


def _steps(rng: np.random.Generator, n: int) -> np.ndarray:
    """True keyframe increments: forward 0.05-0.6 m (10 % reversing), turns up to 20 deg."""
    dist = rng.uniform(0.05, 0.6, n) * np.where(rng.random(n) < 0.1, -1.0, 1.0)
    turn = np.radians(rng.uniform(-20.0, 20.0, n))
    return np.column_stack([dist * np.cos(turn / 2), dist * np.sin(turn / 2), turn])


def test_recovers_known_scale_turn_scale_and_drift_from_noisy_matches() -> None:
    rng = np.random.default_rng(3)
    # White noise of a well-built base: 1 % of the distance, 1 % of the turn, 0.1 deg/m.
    model = OdometryModel(
        translation_sigma_per_m=0.01, rotation_sigma_per_rad=0.01, rotation_sigma_per_m=0.002
    )
    true = _steps(rng, 400)
    # Unequal wheel radii turn the other way when reversing (Borenstein & Feng 1996): the
    # drift goes with the signed distance (the simulator's model drives forward only).
    signed = np.array([signed_distance(u) for u in true])
    odo = true * np.array([1.02, 1.02, 1.03])  # 2 % distance scale, 3 % turn scale
    odo[:, 2] += 1.03 * math.radians(0.5) * signed
    odo += rng.standard_normal(odo.shape) * model.increment_sigmas(true)
    cal = OdometryCalibrator()
    for u_true, u_odo in zip(true, odo, strict=True):
        z = u_true + rng.standard_normal(3) * np.sqrt(np.diag(MATCH_COV))
        if rng.random() < 0.05:  # wrong matches: the Huber weight must hold
            z[:2] += rng.normal(0.0, 0.5, 2)
        cal.observe(u_odo, odometry_covariance(u_odo), z, MATCH_COV)
    # Truth: true = odo / 1.02 in distance; odo turn = 1.03 (turn + 0.5 deg/m * true
    # distance), so turn = odo turn / 1.03 - 0.5 / 1.02 deg per odometry metre.
    assert cal.scale == pytest.approx(1 / 1.02, abs=0.002)
    assert cal.turn_scale == pytest.approx(1 / 1.03, abs=0.01)
    assert math.degrees(cal.heading_drift_rad_per_m) == pytest.approx(0.5 / 1.02, abs=0.06)
    # The corrected increment of a 1 m straight step is right within the parameter errors,
    # and its covariance covers the remaining error.
    u_odo = np.array([1.02, 0.0, 1.03 * math.radians(0.5)])
    corrected, cov = cal.correct(u_odo, odometry_covariance(u_odo))
    err = corrected - np.array([1.0, 0.0, 0.0])
    assert abs(err[0]) < 0.003 and abs(err[2]) < math.radians(0.06)
    assert err @ np.linalg.solve(cov, err) < 11.3  # chi-square 3 dof, 99 %


def test_identity_odometry_stays_identity() -> None:
    rng = np.random.default_rng(0)
    cal = OdometryCalibrator()
    for u in _steps(rng, 200):
        z = u + rng.standard_normal(3) * np.sqrt(np.diag(MATCH_COV))
        cal.observe(u, odometry_covariance(u), z, MATCH_COV)
    assert cal.scale == pytest.approx(1.0, abs=0.002)
    assert cal.turn_scale == pytest.approx(1.0, abs=0.005)
    assert abs(math.degrees(cal.heading_drift_rad_per_m)) < 0.05
    assert signed_distance([-0.3, 0.4, 0.0]) == pytest.approx(-0.5)


def _numpy_estimate(
    deltas: np.ndarray, measured: np.ndarray
) -> tuple[np.ndarray, np.ndarray, list[float], list[float]]:
    """The estimator's recursion in numpy matrix algebra (``np.linalg.inv`` / ``solve``), as
    the module describes it: the parameters ``(kappa,)`` and ``(gamma, beta)`` after every
    observation of ``deltas`` / ``measured`` ``(n, 3)`` with ``MATCH_COV``, the two variance
    factors, and the Huber weights of the two equations' observations."""
    c = OdometryCalibrationConfig()
    s_info = np.array([[1 / c.prior_scale_sigma**2]])
    s_vec = s_info[0].copy()
    h_info = np.diag(
        [1 / c.prior_turn_scale_sigma**2, 1 / c.prior_heading_drift_sigma_rad_per_m**2]
    )
    h_vec = np.array([h_info[0, 0], 0.0])
    chi_t = dof_t = chi_r = dof_r = 0.0
    w_t: list[float] = []
    w_r: list[float] = []
    for d, z in zip(deltas, measured, strict=True):
        cov = odometry_covariance(d) + MATCH_COV
        info = np.linalg.inv(cov[:2, :2])
        r = z[:2] - np.linalg.solve(s_info, s_vec)[0] * d[:2]
        chi2 = float(r @ info @ r)
        s2 = (c.prior_dof + chi_t) / (c.prior_dof + dof_t)
        z_n = math.sqrt(chi2 / (2.0 * s2))
        w = 1.0 if z_n <= c.huber_k else c.huber_k / z_n
        chi_t, dof_t = chi_t + w * chi2, dof_t + 2.0 * w
        w_t.append(w)
        h = d[:2].reshape(2, 1)
        s_info = s_info + h.T @ (w * info) @ h
        s_vec = s_vec + h.T @ (w * info) @ z[:2]
        var = float(cov[2, 2])
        dtheta = float(np.arctan2(np.sin(z[2] - d[2]), np.cos(z[2] - d[2]))) + d[2]
        hr = np.array([d[2], -signed_distance(d)])
        r_h = dtheta - float(hr @ np.linalg.solve(h_info, h_vec))
        s2 = (c.prior_dof + chi_r) / (c.prior_dof + dof_r)
        z_n = abs(r_h / math.sqrt(var * s2))
        w = 1.0 if z_n <= c.huber_k else c.huber_k / z_n
        chi_r, dof_r = chi_r + w * r_h * r_h / var, dof_r + w
        w_r.append(w)
        h_info = h_info + (w / var) * np.outer(hr, hr)
        h_vec = h_vec + (w / var) * hr * dtheta
    factors = [
        (c.prior_dof + chi_t) / (c.prior_dof + dof_t),
        (c.prior_dof + chi_r) / (c.prior_dof + dof_r),
    ]
    return np.linalg.solve(s_info, s_vec), np.linalg.solve(h_info, h_vec), factors, w_t + w_r


def test_the_float_recursion_equals_the_matrix_algebra_to_rounding() -> None:
    """The per-observation arithmetic is written out in floats (a keyframe's observation in
    microseconds): the same estimate as the matrix algebra, to rounding, with outliers
    down-weighted on both equations."""
    rng = np.random.default_rng(7)
    true = _steps(rng, 300)
    odo = true * np.array([1.02, 1.02, 1.03])
    measured = true + rng.standard_normal(true.shape) * np.sqrt(np.diag(MATCH_COV))
    measured[::20] += rng.normal(0.0, 0.3, (15, 3))  # outliers: Huber weights below 1
    cal = OdometryCalibrator()
    for d, z in zip(odo, measured, strict=True):
        cal.observe(d, odometry_covariance(d), z, MATCH_COV)
    scale, heading, factors, weights = _numpy_estimate(odo, measured)
    assert min(weights) < 0.5  # the outliers were down-weighted
    assert cal.scale == pytest.approx(scale[0], rel=1e-12)
    assert [cal.turn_scale, cal.heading_drift_rad_per_m] == pytest.approx(heading, rel=1e-10)
    assert list(cal.variance_factors()) == pytest.approx(factors, rel=1e-10)


@pytest.fixture(scope="module")
def biased_office():  # type: ignore[no-untyped-def]
    run = simulate_scenario("office_biased", seed=2)
    slam = Slam(IcegConfig(odometry_calibration=OdometryCalibrationConfig(enabled=True)))
    for scan in run.scans:
        slam.process(scan)
    return run, slam, slam.finish()


def test_simulated_biased_office_calibration_and_ate(biased_office) -> None:  # type: ignore[no-untyped-def]
    run, slam, result = biased_office
    cal = slam.odometry_calibrator
    assert cal.scale == pytest.approx(1 / (1 + SCALE_ERROR), abs=0.003)
    assert cal.heading_drift_rad_per_m == pytest.approx(
        DRIFT_RAD_PER_M / (1 + SCALE_ERROR), abs=math.radians(0.05)
    )
    assert position_errors(result.poses, run.true_poses).rmse_m <= 0.05
    # The odometry factors no longer carry the drift: the mean heading error of the
    # (calibrated) odometry factors against the truth is within 3 standard errors of zero
    # (the white noise) and below half the raw drift per step.
    truth = run.true_poses[result.node_scan_index]
    errs, drift = [], []
    for f in result.factors:
        if f.kind == FactorKind.ODOMETRY:
            u = se2.between(truth[f.i], truth[f.j])
            errs.append(se2.wrap_angle(f.measured[2] - u[2]))
            drift.append(DRIFT_RAD_PER_M * math.hypot(u[0], u[1]))
    e = np.asarray(errs)
    standard_error = e.std() / math.sqrt(e.size)
    assert abs(e.mean()) < min(3.0 * standard_error, 0.5 * np.mean(drift)), (e.mean(), drift)


@pytest.mark.parametrize(
    ("scale_error", "drift_deg_per_m", "beyond"),
    [
        (0.015, 0.3, []),  # an uncalibrated base's (issue 11): within the noise model
        (0.04, 2.0, ["distance_scale_error", "heading_drift_deg_per_m"]),
    ],
)
def test_systematic_errors_against_the_noise_model_by_hand(
    scale_error: float, drift_deg_per_m: float, beyond: list[str]
) -> None:
    # Exact matches of the true steps, the odometry's distances scaled and its heading
    # drifting per metre: the estimates are the biases (odometry over truth, less 1; the
    # drift per odometry metre), and the default noise model allows 2 % of the distance,
    # 5 % of a turn and 0.5 deg per metre.
    rng = np.random.default_rng(5)
    true = _steps(rng, 300)
    signed = np.array([signed_distance(u) for u in true])
    odo = true * np.array([1 + scale_error, 1 + scale_error, 1.0])
    odo[:, 2] += math.radians(drift_deg_per_m) * (1 + scale_error) * signed
    cal = OdometryCalibrator()
    for u_true, u_odo in zip(true, odo, strict=True):
        cal.observe(u_odo, odometry_covariance(u_odo), u_true, MATCH_COV)
    errors = systematic_errors(cal, IcegConfig().odometry_noise)
    assert errors["distance_scale_error"].value == pytest.approx(scale_error, abs=1e-3)
    assert errors["turn_scale_error"].value == pytest.approx(0.0, abs=1e-3)
    assert errors["heading_drift_deg_per_m"].value == pytest.approx(drift_deg_per_m, abs=0.02)
    assert [e.allowed for e in errors.values()] == [0.02, 0.05, 0.5]
    assert all(e.std > 0.0 for e in errors.values())
    assert [name for name, e in errors.items() if e.beyond_noise_model] == beyond


@pytest.mark.parametrize(
    ("enabled", "drift_deg_per_m", "correcting_after"),
    [
        ("auto", 2.0, [False, False, True]),  # beyond the model once the matches show it
        ("auto", 0.3, [False, False, False]),  # within the model: the raw odometry
        (True, 0.3, [True, True, True]),
        (False, 2.0, [False, False, False]),
    ],
)
def test_auto_corrects_while_an_error_is_beyond_the_noise_model(
    enabled: bool | str, drift_deg_per_m: float, correcting_after: list[bool]
) -> None:
    # Exact matches of the true steps, the odometry's heading drifting per metre (1 %
    # scale): after no match, 5 and 300. With "auto" the calibrator corrects once the
    # drift's estimate exceeds the 0.5 deg/m the default noise model allows by three
    # standard deviations: not after 5 steps of 0.05-0.6 m (the prior's 2 deg/m still
    # dominates), after 300; a drift of 0.3 deg/m never. A restored state gives the same
    # answer.
    rng = np.random.default_rng(7)
    true = _steps(rng, 300)
    signed = np.array([signed_distance(u) for u in true])
    odo = true * np.array([1.01, 1.01, 1.0])
    odo[:, 2] += math.radians(drift_deg_per_m) * 1.01 * signed
    config = OdometryCalibrationConfig(enabled=enabled)  # type: ignore[arg-type]
    cal = OdometryCalibrator(config)
    seen = [cal.correcting]
    for k, (u_true, u_odo) in enumerate(zip(true, odo, strict=True), start=1):
        cal.observe(u_odo, odometry_covariance(u_odo), u_true, MATCH_COV)
        if k in (5, 300):
            seen.append(cal.correcting)
    assert seen == correcting_after
    restored = OdometryCalibrator(config)
    restored.restore_state(cal.export_state())
    assert restored.correcting == cal.correcting


def test_a_wrong_setting_names_its_three_choices() -> None:
    with pytest.raises(ConfigError, match=r"enabled': .*true, false or 'auto', not 'sometimes'"):
        config_from_dict({"odometry_calibration": {"enabled": "sometimes"}})
    config = config_from_dict({"odometry_calibration": {"enabled": "false"}})
    assert config.odometry_calibration.enabled is False


def test_a_run_corrects_an_odometry_drift_beyond_its_noise_model(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # The office loop with its heading drifting 2 deg/m (four times what the noise model
    # allows): by default the run measures it, corrects it and reports both (metrics.json,
    # and a line of iceg run's summary); told never to correct, it warns with the setting.
    # The office as simulated (0.4 deg/m) is within the model: not corrected, no warning.
    office = simulate_scenario("office_biased", seed=0)
    drifting = OdometryModel.biased(scale_error=0.01, heading_drift_deg_per_m=2.0)
    route = default_trajectory(office.world)
    runs = {"biased": office, "drift": simulate(office.world, route, seed=0, odometry=drifting)}
    logs = {name: tmp_path / f"{name}.clf" for name in runs}
    for name, run in runs.items():
        write_carmen(logs[name], run.scans[:400])
    never = IcegConfig(odometry_calibration=OdometryCalibrationConfig(enabled=False))
    with caplog.at_level(logging.WARNING, logger="iceg.pipeline"):
        uncorrected = run_log(logs["drift"], never)
    report = uncorrected.metrics["odometry_calibration"]
    drift = report["heading_drift_deg_per_m"]
    assert drift["value"] == pytest.approx(2.0, abs=0.2) and drift["beyond_noise_model"]
    assert not report["corrected"]
    assert "the scans' matches measure the odometry's heading drift +" in caplog.text
    assert "set odometry_calibration.enabled: auto (the default) or true" in caplog.text
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="iceg.pipeline"):
        biased = run_log(logs["biased"])
        out = tmp_path / "corrected"
        args = ["run", str(logs["drift"]), "--out", str(out), "--no-progress"]
        cli = CliRunner().invoke(app, args)
    assert cli.exit_code == 0, cli.output
    assert "odometry_calibration" not in caplog.text
    found = biased.metrics["odometry_calibration"]
    assert found["heading_drift_deg_per_m"]["value"] == pytest.approx(0.4, abs=0.2)
    assert not found["heading_drift_deg_per_m"]["beyond_noise_model"] and not found["corrected"]
    corrected = json.loads((out / "metrics.json").read_text())["odometry_calibration"]
    assert corrected["corrected"] and corrected["enabled"] == "auto"
    assert "odometry corrected  heading drift +" in cli.output


def test_aces_with_a_strong_heading_drift_keeps_its_chain() -> None:
    # ACES's corrected poses as the truth, synthetic odometry with 1 % scale error and a
    # 2 deg/m heading drift (the default noise, seed 0). Never corrected, the chain breaks
    # in a cascade of failed matches (docs/design.md, "Walls of nodes the odometry placed":
    # 4.38 m ATE); by default the run corrects the drift once its matches show it beyond
    # the noise model, 19-37 keyframes in, and ends 0.20 m off.
    scans = list(open_log(shared_file("aces/aces-corrected.log.gz")))
    model = OdometryModel.biased(scale_error=0.01, heading_drift_deg_per_m=2.0)
    synth = synthetic_odometry(scans, model, seed=0)
    truth = np.array(synth.reference_poses)
    ate = {}
    for enabled in (False, "auto"):
        config = IcegConfig(odometry_calibration=OdometryCalibrationConfig(enabled=enabled))
        slam = Slam(config)
        for scan in synth.scans:
            slam.process(scan)
        ate[enabled] = position_errors(slam.finish().poses, truth).rmse_m
    assert ate[False] > 1.0  # the failure is reproduced
    assert ate["auto"] < 0.3
