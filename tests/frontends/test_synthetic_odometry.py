"""Tests of synthetic odometry for corrected logs: identity without bias and noise, the
closed-form drift on a straight line, and the written CARMEN + TUM files read back."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

from frontends import open_log
from frontends.scan import LaserScan
from frontends.simulate import (
    OdometryModel,
    pillar_world,
    simulate,
    synthetic_odometry,
    write_synthetic_log,
)
from frontends.simulate.synthetic_odometry import main, reference_path
from frontends.tum import read_tum
from iceg_common.errors import ConfigError, LogFormatError
from iceg_common.se2 import wrap_angle
from tests.conftest import shared_file

EXACT = OdometryModel.biased(scale_error=0.0, heading_drift_deg_per_m=0.0, noise=False)
TOL_POSE = 5e-7 + 1e-12  # write_carmen prints poses with %.6f


def _straight_scans(n: int, step_m: float, heading: float) -> list[LaserScan]:
    """Scans whose poses run straight from (2, -1) at ``heading``, ``step_m`` apart."""
    u = np.array([math.cos(heading), math.sin(heading)])
    return [
        LaserScan(
            stamp_s=0.2 * k,
            ranges_m=np.full(5, 3.0),
            angles_rad=np.linspace(-1.0, 1.0, 5),
            range_min_m=0.0,
            range_max_m=20.0,
            odom_pose=np.array([2.0 + k * step_m * u[0], -1.0 + k * step_m * u[1], heading]),
        )
        for k in range(n)
    ]


def test_zero_bias_and_noise_reproduces_the_poses() -> None:
    # Truth: with no bias and no noise each increment is composed back unchanged, so the
    # odometry is the reference (to float rounding of between/compose).
    run = simulate(pillar_world(), seed=2)
    synth = synthetic_odometry(run.scans, EXACT, seed=9)
    np.testing.assert_allclose(synth.odom_poses[:, :2], run.odom_poses[:, :2], atol=1e-9)
    dtheta = wrap_angle(synth.odom_poses[:, 2] - run.odom_poses[:, 2])
    np.testing.assert_allclose(dtheta, 0.0, atol=1e-9)
    np.testing.assert_array_equal(synth.reference_poses, run.odom_poses)
    for a, b in zip(synth.scans, run.scans, strict=True):
        np.testing.assert_array_equal(a.ranges_m, b.ranges_m)
        np.testing.assert_array_equal(a.odom_pose, synth.odom_poses[synth.scans.index(a)])
        assert a.stamp_s == b.stamp_s and a.source == b.source
    assert synth.end_drift_m() < 1e-9


def test_bias_on_straight_line_matches_closed_form() -> None:
    # Truth: n steps of d along heading h with scale error s and drift k rad/m: increments
    # (d (1+s), 0, k d), so after n steps heading h + n k d and displacement
    # d (1+s) sin(n k d / 2) / sin(k d / 2) along h + (n - 1) k d / 2.
    n, d, h = 400, 0.25, 0.7
    s, k_deg = 0.012, 0.45
    k = math.radians(k_deg)
    scans = _straight_scans(n + 1, d, h)
    model = OdometryModel.biased(scale_error=s, heading_drift_deg_per_m=k_deg, noise=False)
    synth = synthetic_odometry(scans, model)
    a = k * d
    chord = d * (1 + s) * math.sin(n * a / 2) / math.sin(a / 2)
    phi = h + (n - 1) * a / 2
    expect = np.array([2.0, -1.0]) + chord * np.array([math.cos(phi), math.sin(phi)])
    np.testing.assert_allclose(synth.odom_poses[-1, :2], expect, atol=1e-9)
    assert wrap_angle(synth.odom_poses[-1, 2] - (h + n * a)) == pytest.approx(0.0, abs=1e-12)
    # Continuous limit (an arc of curvature k): lateral drift (1+s)(1 - cos(k L)) / k over
    # L = 100 m; the discrete steps differ from it by O(k d).
    dx, dy = synth.odom_poses[-1, :2] - [2.0, -1.0]
    lateral = math.cos(h) * dy - math.sin(h) * dx
    assert lateral == pytest.approx((1 + s) * (1 - math.cos(k * n * d)) / k, rel=5e-3)


def test_noise_is_seeded_and_zero_mean() -> None:
    # Truth: the default white noise has zero mean, so 200 seeds of a 100 m straight line
    # with no bias end, on average, at the true end (within 4 standard errors).
    scans = _straight_scans(201, 0.5, 0.0)
    model = OdometryModel.biased(scale_error=0.0, heading_drift_deg_per_m=0.0)
    a = synthetic_odometry(scans, model, seed=3)
    b = synthetic_odometry(scans, model, seed=3)
    np.testing.assert_array_equal(a.odom_poses, b.odom_poses)
    ends = np.array([synthetic_odometry(scans, model, i).odom_poses[-1, 0] for i in range(200)])
    assert abs(ends.mean() - 102.0) < 4 * ends.std() / math.sqrt(200)
    assert ends.std() > 0.1


def test_written_log_reads_back(tmp_path: Path) -> None:
    # Truth: the synthetic odometry and scans in memory; the CARMEN log reads back to the
    # writer's precision and the TUM beside it holds the reference poses.
    run = simulate(pillar_world(), seed=1, start_stamp_s=100.0)
    src = tmp_path / "corrected.clf"
    run.write_carmen(src)
    model = OdometryModel.biased(scale_error=0.02, heading_drift_deg_per_m=0.5)
    out = tmp_path / "synthetic.log"
    synth = write_synthetic_log(src, out, model, seed=4)
    back = list(open_log(out))
    assert len(back) == len(run)
    for r, s in zip(back, synth.scans, strict=True):
        np.testing.assert_allclose(r.odom_pose, s.odom_pose, rtol=0, atol=TOL_POSE)
        np.testing.assert_allclose(r.ranges_m, s.ranges_m, rtol=0, atol=5e-4 + 1e-12)
        np.testing.assert_allclose(r.angles_rad, s.angles_rad, rtol=0, atol=1e-12)
    assert reference_path(out) == tmp_path / "synthetic.reference.tum"
    stamps, poses = read_tum(reference_path(out))
    np.testing.assert_allclose(stamps, run.stamps_s, atol=1e-9)
    # The source log's odometry (the run's odom_poses, written at %.6f) is the reference.
    np.testing.assert_allclose(poses[:, :2], run.odom_poses[:, :2], atol=TOL_POSE)
    np.testing.assert_allclose(wrap_angle(poses[:, 2] - run.odom_poses[:, 2]), 0.0, atol=2e-6)
    assert synth.end_drift_m() > 0.5


def test_real_corrected_log_round_trip(tmp_path: Path) -> None:
    # Truth: aces-corrected.log.gz (440 scans, GMapping-corrected poses). Zero bias and noise
    # reproduce its poses; the written log reads back with the same scans.
    src = shared_file("aces/aces-corrected.log.gz")
    original = list(open_log(src))
    out = tmp_path / "aces-synthetic.log.gz"
    synth = write_synthetic_log(src, out, EXACT)
    ref = np.array([s.odom_pose for s in original])
    np.testing.assert_allclose(synth.odom_poses[:, :2], ref[:, :2], atol=1e-8)
    back = list(open_log(out))
    assert len(back) == len(original) == 440
    odom_back = np.array([s.odom_pose for s in back])
    np.testing.assert_allclose(odom_back[:, :2], ref[:, :2], atol=TOL_POSE + 1e-8)
    np.testing.assert_array_equal(back[10].valid_mask(), original[10].valid_mask())


def test_restamp_and_errors() -> None:
    scans = _straight_scans(5, 0.1, 0.0)
    synth = synthetic_odometry(scans, EXACT, restamp_hz=2.0)
    np.testing.assert_allclose(synth.stamps_s, [0.0, 0.5, 1.0, 1.5, 2.0])
    assert [s.stamp_s for s in synth.scans] == [0.0, 0.5, 1.0, 1.5, 2.0]
    with pytest.raises(ConfigError):
        synthetic_odometry(scans, EXACT, restamp_hz=0.0)
    with pytest.raises(ConfigError):
        synthetic_odometry(scans, OdometryModel(start="zero"))
    with pytest.raises(LogFormatError):
        synthetic_odometry([], EXACT)
    with pytest.raises(LogFormatError):
        synthetic_odometry([dataclasses.replace(scans[0], odom_pose=None)], EXACT)


def test_command_line(tmp_path: Path) -> None:
    run = simulate(pillar_world(), seed=0)
    src = tmp_path / "in.clf"
    run.write_carmen(src)
    out = tmp_path / "out.clf"
    assert main([str(src), str(out), "--no-noise", "--heading-drift-deg-per-m", "0.3"]) == 0
    back = np.array([s.odom_pose for s in open_log(out)])
    model = OdometryModel.biased(0.01, 0.3, noise=False)
    expect = model.simulate(np.array([s.odom_pose for s in open_log(src)]), np.random.default_rng())
    np.testing.assert_allclose(back[:, :2], expect[:, :2], atol=TOL_POSE + 1e-9)
    assert reference_path(out).is_file()
