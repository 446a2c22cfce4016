"""The laser-odometry time offset measured from matched rotations (iceg.odometry_timing)."""

from __future__ import annotations

import logging
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from frontends.odometry_shift import shift_odometry
from frontends.simulate.scenarios import simulate_scenario
from graph import FactorKind
from iceg.config import IcegConfig
from iceg.odometry_timing import (
    OFFSET_RESOLUTION_S,
    _signed_rank_p,
    estimate_odometry_time_offset,
    odometry_time_offset,
    scan_pairs_time_offset,
)
from iceg.pipeline import run_log
from iceg.results import SlamResult
from iceg.slam import Slam
from iceg_common.errors import ConfigError
from tests.conftest import shared_file


def _heading(t: np.ndarray) -> np.ndarray:
    """A robot that turns back and forth (rad)."""
    return 1.5 * np.sin(0.7 * t) + 0.2 * t


def _synthetic(latency_s: float, noise_deg: float = 0.2, seed: int = 0) -> dict[str, Any]:
    """Scans measured at ``tau``, stamped ``tau + latency_s``, with the odometry read at
    the stamp; the matched turn between consecutive keyframes is the true one plus noise."""
    rng = np.random.default_rng(seed)
    tau = np.arange(0.0, 60.0, 0.05)
    stamps = tau + latency_s
    keyframes = np.arange(0, tau.shape[0], 4)
    turn = np.diff(_heading(tau[keyframes])) + np.radians(noise_deg) * rng.standard_normal(
        keyframes.shape[0] - 1
    )
    return {
        "stamps_s": stamps,
        "odom_heading_rad": np.angle(np.exp(1j * _heading(stamps))),  # wrapped, as logged
        "segment": np.zeros(tau.shape[0], dtype=np.int64),
        "step_from": keyframes[:-1],
        "step_to": keyframes[1:],
        "step_turn_rad": turn,
    }


@pytest.mark.parametrize("latency_s", [0.12, 0.2, -0.07])
def test_recovers_a_known_latency(latency_s: float) -> None:
    est = estimate_odometry_time_offset(**_synthetic(latency_s))
    assert est is not None
    assert est.offset_s == pytest.approx(-latency_s, abs=OFFSET_RESOLUTION_S)
    assert est.significant
    assert est.heading_error_at_offset_deg < est.heading_error_at_zero_deg


def test_no_latency_gives_zero_and_no_warning() -> None:
    est = estimate_odometry_time_offset(**_synthetic(0.0))
    assert est is not None
    assert abs(est.offset_s) <= OFFSET_RESOLUTION_S
    assert not est.significant


def test_steps_across_a_segment_or_without_odometry_are_left_out() -> None:
    data = _synthetic(0.1)
    n = data["stamps_s"].shape[0]
    data["segment"] = np.where(np.arange(n) < n // 2, 0, 1)
    data["segment"][:40] = -1  # the first two seconds without odometry
    est = estimate_odometry_time_offset(**data)
    assert est is not None
    a, b, seg = data["step_from"], data["step_to"], data["segment"]
    stamps, lo = data["stamps_s"], 0.5  # MAX_OFFSET_S: shifted times stay in the segment
    inside = [
        (seg[i] >= 0 and seg[i] == seg[j])
        and stamps[i] - lo >= stamps[seg == seg[i]][0]
        and stamps[j] + lo <= stamps[seg == seg[i]][-1]
        for i, j in zip(a.tolist(), b.tolist(), strict=True)
    ]
    assert est.steps == sum(inside)
    assert est.offset_s == pytest.approx(-0.1, abs=OFFSET_RESOLUTION_S)
    data["segment"][:] = -1
    assert estimate_odometry_time_offset(**data) is None


def test_signed_rank_p_value_by_hand() -> None:
    # |gains| ranked 0.5 -> 1, 1 -> 2, 2 -> 3, 3 -> 4; W+ = 2 + 3 + 4 = 9, n = 4:
    # mean 5, sd sqrt(4 * 5 * 9 / 24) = sqrt(7.5); p = Phi(-(9 - 5) / sqrt(7.5)) = 0.07206
    assert _signed_rank_p(np.array([1.0, 2.0, -0.5, 3.0, 0.0])) == pytest.approx(0.07206, abs=1e-5)
    assert _signed_rank_p(np.zeros(3)) == 1.0


def test_signed_rank_p_value_is_scipys_normal_tail() -> None:
    # The tail from libm's erfc against scipy's ndtr, from p near 1 to p near 1e-106.
    from scipy.special import ndtr

    rng = np.random.default_rng(3)
    for n, shift in [(5, 0.0), (40, -1.0), (200, 0.3), (60, 1.5), (2000, 0.5)]:
        gain = rng.normal(shift, 1.0, n)
        d = gain[gain != 0.0]
        ranks = np.empty(d.shape[0])
        ranks[np.argsort(np.abs(d), kind="stable")] = np.arange(1, d.shape[0] + 1)
        m = d.shape[0]
        z = (ranks[d > 0].sum() - m * (m + 1) / 4) / np.sqrt(m * (m + 1) * (2 * m + 1) / 24)
        assert _signed_rank_p(gain) == pytest.approx(float(ndtr(-z)), rel=1e-10, abs=0.0)


def test_a_simulated_robot_has_no_latency() -> None:
    """The Gazebo TurtleBot 3 bag stamps scans and odometry with the simulation's clock."""
    result = run_log(shared_file("rosbag/turtlebot3-gazebo-ros2"), IcegConfig())
    measured = result.metrics["odometry_time_offset"]["measured"]
    assert measured["offset_s"] == 0.0 and not measured["significant"]


def test_the_measured_latency_of_a_real_robot_makes_its_scans_match() -> None:
    """The TurtleBot 4 bag's scans match its odometry about 0.1 s before their stamps; read
    there, more keyframes get a scan-match factor and the run measures no offset left."""
    cfg = IcegConfig.model_validate({"slam": {"workers": 1}})
    first = run_log(shared_file("rosbag/turtlebot4-ros2"), cfg)
    est = odometry_time_offset(first)
    assert est is not None and est.significant and est.offset_s < 0
    again = run_log(shared_file("rosbag/turtlebot4-ros2"), cfg, odometry_time_offset_s=est.offset_s)
    left = again.metrics["odometry_time_offset"]

    def unmatched(result: SlamResult) -> int:
        """Keyframes after the first without a scan-match factor."""
        matched = sum(f.kind == FactorKind.SCAN_MATCH for f in result.factors)
        return int(result.node_ids.shape[0]) - 1 - matched

    # Read at its latency, the keyframes left without a scan-match factor are at least
    # halved: 17 of 102 -> 6 of 101 (with its blind wedges read as the robot's body; before
    # that, 53 of 102 -> 6 of 101).
    assert unmatched(again) <= unmatched(first) / 2
    assert left["applied_s"] == est.offset_s and not left["measured"]["significant"]


def test_a_latency_injected_into_a_simulated_run_is_measured() -> None:
    """The simulated office run with its odometry read 0.1 s after each scan was taken: the
    run's matched rotations put it back at -0.1 s."""
    run = simulate_scenario("office", seed=0)
    slam = Slam(IcegConfig.model_validate({"slam": {"workers": 1}}))
    for scan in shift_odometry(run.scans, 0.1):
        slam.process(scan)
    est = odometry_time_offset(slam.finish())
    assert est is not None and est.significant
    assert est.offset_s == pytest.approx(-0.1, abs=OFFSET_RESOLUTION_S)


@pytest.mark.parametrize("scenario", ["corridor", "open_loops"])
def test_odometry_noise_alone_is_no_delay(scenario: str) -> None:
    """Simulated runs without delay: reading noisy odometry between its samples averages the
    noise and lowers the errors off 0 (the corridor's best fit is -0.11 s, p 0.0006 against
    0), but on both sides alike, so no offset is significant."""
    run = simulate_scenario(scenario, seed=0)
    slam = Slam(IcegConfig.model_validate({"slam": {"workers": 1}}))
    for scan in run.scans:
        slam.process(scan)
    est = odometry_time_offset(slam.finish())
    assert est is not None and not est.significant


def test_consecutive_scans_measure_a_simulated_latency() -> None:
    """Before any run: the simulated office's scans with their odometry read 0.2 s after
    each was taken; the consecutive scans' matched rotations put it back at -0.2 s, the
    same estimate with the log's second half matched in a forked process."""
    run = simulate_scenario("office", seed=0)
    late = list(shift_odometry(run.scans, 0.2))
    est = scan_pairs_time_offset(late, IcegConfig())
    assert est == scan_pairs_time_offset(late, IcegConfig(), processes=2)
    assert est is not None and est.significant
    assert est.offset_s == pytest.approx(-0.2, abs=OFFSET_RESOLUTION_S)
    assert est.steps >= 0.95 * (len(run.scans) - 1)  # nearly every pair matched


@pytest.mark.parametrize("scenario", ["corridor", "open_loops"])
def test_consecutive_scans_without_a_delay_measure_none(scenario: str) -> None:
    run = simulate_scenario(scenario, seed=0)
    est = scan_pairs_time_offset(run.scans, IcegConfig())
    assert est is not None and not est.significant


def test_consecutive_scans_measure_the_turtlebot_4_bag_s_offset() -> None:
    """The real TurtleBot 4 bag: its run's keyframe steps measure -0.10 s (mean heading
    error per step 0.43 -> 0.13 deg), and so do its consecutive scans, before any run."""
    from frontends import open_log

    est = scan_pairs_time_offset(
        list(open_log(shared_file("rosbag/turtlebot4-ros2"))), IcegConfig()
    )
    assert est is not None and est.significant
    assert est.offset_s == pytest.approx(-0.10, abs=OFFSET_RESOLUTION_S)
    assert est.heading_error_at_offset_deg < 0.5 * est.heading_error_at_zero_deg


def test_auto_reads_the_odometry_at_a_simulated_latency(tmp_path: Path) -> None:
    """``odometry_time_offset_s="auto"`` on a log whose odometry is read 0.2 s after each scan
    was taken (the simulated office, written as a CARMEN log): measured before the run at
    -0.2 s, the odometry read there, the run measures nothing left; the poses are those of a
    run given that offset, bit for bit."""
    from frontends.carmen import write_carmen

    run = simulate_scenario("office", seed=0)
    log = tmp_path / "late.clf"
    write_carmen(log, shift_odometry(run.scans, 0.2))
    cfg = IcegConfig.model_validate({"slam": {"workers": 1}})
    result = run_log(log, cfg, odometry_time_offset_s="auto")
    offset = result.metrics["odometry_time_offset"]
    assert offset["before_run"]["significant"]
    assert offset["applied_s"] == offset["before_run"]["offset_s"]
    assert offset["applied_s"] == pytest.approx(-0.2, abs=OFFSET_RESOLUTION_S)
    assert not offset["measured"]["significant"]
    given = run_log(log, cfg, odometry_time_offset_s=offset["applied_s"])
    assert result.poses.tobytes() == given.poses.tobytes()


def test_the_warning_names_the_offset_from_the_stamps(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    """The simulated office's odometry read 0.2 s late, run with half of it given: the run
    measures the -0.1 s left and names the whole -0.2 s to pass (not ``auto``, as an offset
    was given)."""
    from frontends.carmen import write_carmen

    log = tmp_path / "late.clf"
    write_carmen(log, shift_odometry(simulate_scenario("office", seed=0).scans, 0.2))
    cfg = IcegConfig.model_validate({"slam": {"workers": 1}})
    with caplog.at_level(logging.WARNING, logger="iceg.pipeline"):
        result = run_log(log, cfg, odometry_time_offset_s=-0.1)
    measured = result.metrics["odometry_time_offset"]["measured"]
    assert measured["significant"]
    assert measured["offset_s"] == pytest.approx(-0.1, abs=OFFSET_RESOLUTION_S)
    assert "match the odometry -0.20 s from their stamps" in caplog.text
    assert "pass --odometry-time-offset -0.20" in caplog.text
    assert "or auto" not in caplog.text


def test_auto_reads_a_log_without_a_latency_at_its_stamps() -> None:
    """The Gazebo TurtleBot 3 bag shows no offset: ``"auto"`` reads its odometry at the
    stamps, the same poses as a plain run, bit for bit."""
    cfg = IcegConfig.model_validate({"slam": {"workers": 1}})
    bag = shared_file("rosbag/turtlebot3-gazebo-ros2")
    auto = run_log(bag, cfg, odometry_time_offset_s="auto")
    plain = run_log(bag, cfg)
    assert not auto.metrics["odometry_time_offset"]["before_run"]["significant"]
    assert auto.metrics["odometry_time_offset"]["applied_s"] == 0.0
    assert auto.poses.tobytes() == plain.poses.tobytes()


def test_an_odometry_time_offset_is_seconds_or_auto() -> None:
    bag = shared_file("rosbag/turtlebot3-gazebo-ros2")
    with pytest.raises(ConfigError, match="seconds or 'auto'"):
        run_log(bag, odometry_time_offset_s="later")  # type: ignore[arg-type]
