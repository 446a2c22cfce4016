"""What every path that reads a log (a run, a continuation or localization through
``read_log_scans``, a batch run's ``load_input``) checks of it before a run
(``iceg.log_checks``): a log without a single return is refused (``check_returns``), a log
whose odometry is one pose throughout is read without it, as ``--laser-only`` reads it
(``motionless_odometry``; the run itself is compared bit for bit with ``--laser-only`` in
``test_cli.py``), a log whose walls turn against its odometry is read with its beams
mirrored, and one whose walls do not turn or move where its odometry turns or moves is read
without the odometry (``iceg.odometry_check``)."""

from __future__ import annotations

import dataclasses
import logging
import re
from pathlib import Path

import numpy as np
import pytest

from frontends import LaserScan, open_log
from frontends.carmen import write_carmen
from frontends.simulate import office_world, simulate
from iceg.batch import expand, spec_from_dict
from iceg.batch_run import execute_run, load_input
from iceg.config import IcegConfig
from iceg.log_checks import (
    MAX_MEDIAN_SCAN_INTERVAL_S,
    check_returns,
    describe_odometry_checks,
    describe_stamps,
    motionless_odometry,
    reading_adjustments,
    warn_sparse_stamps,
)
from iceg.odometry_check import OdometryCheck, move_pairs, odometry_check, sign_test_p
from iceg.pipeline import read_log_scans, run_log
from iceg.scan_store import ScanStore
from iceg_common.errors import LogFormatError
from tests.conftest import shared_file


@pytest.fixture(scope="module")
def office_scans() -> list[LaserScan]:
    return simulate(office_world(), seed=2).scans[:40]


def _with_odometry(scans: list[LaserScan], poses: list[np.ndarray | None]) -> list[LaserScan]:
    return [dataclasses.replace(s, odom_pose=p) for s, p in zip(scans, poses, strict=True)]


def test_one_pose_throughout_carries_no_motion(
    office_scans: list[LaserScan], caplog: pytest.LogCaptureFixture
) -> None:
    n = len(office_scans)
    pose = np.array([1.5, -2.0, np.radians(30.0)])
    stuck = _with_odometry(office_scans, [pose] * n)
    with caplog.at_level(logging.WARNING, logger="iceg.log_checks"):
        assert motionless_odometry("stuck.clf", stuck)
    assert caplog.messages == [
        f"stuck.clf: the odometry is the same pose (1.500 m, -2.000 m, 30.0 deg) in all {n} "
        "scans: it carries no motion, so the log is read without it, as with --laser-only"
    ]
    assert motionless_odometry("stuck.clf", ScanStore(stuck))  # the store's arrays agree


def test_odometry_that_moves_or_is_missing_is_kept(office_scans: list[LaserScan]) -> None:
    n = len(office_scans)
    zero = np.zeros(3)
    one_step = [zero] * (n - 1) + [np.array([0.0, 0.0, 1e-9])]  # a nanoradian is a motion
    for poses in (one_step, [zero] * (n - 1) + [None], [None] * n):
        scans = _with_odometry(office_scans, poses)
        assert not motionless_odometry("x.clf", scans)
        assert not motionless_odometry("x.clf", ScanStore(scans))
    assert not motionless_odometry("x.clf", office_scans[:1])  # one scan shows no motion
    assert not motionless_odometry("x.clf", office_scans)  # the simulated odometry moves


@pytest.fixture(scope="module")
def stuck_log(tmp_path_factory: pytest.TempPathFactory, office_scans: list[LaserScan]) -> Path:
    log = tmp_path_factory.mktemp("stuck") / "stuck.clf"
    write_carmen(log, _with_odometry(office_scans, [np.zeros(3)] * len(office_scans)))
    return log


@pytest.mark.parametrize("offset", [0.0, -0.1, "auto"])
def test_read_log_scans_reads_it_as_laser_only(stuck_log: Path, offset: float | str) -> None:
    # An offset reads the odometry at other stamps: with none to read it is moot (0 applied).
    scans, record, options = read_log_scans(
        stuck_log,
        IcegConfig(),
        odometry_time_offset_s=offset,  # type: ignore[arg-type]
    )
    assert len(scans) == 40 and all(s.odom_pose is None and not s.odom_break for s in scans)
    assert record == {"applied_s": 0.0} and options == {"laser_only": True}


def test_a_batch_run_reads_it_as_laser_only(tmp_path: Path, stuck_log: Path) -> None:
    spec = spec_from_dict({"logs": [{"path": str(stuck_log)}]})
    (task,) = expand(spec, tmp_path, tmp_path)
    data = load_input(task)
    assert data.adjusted == {"laser_only": True}
    assert len(data.scans) == 40 and all(s.odom_pose is None for s in data.scans)


def test_a_log_without_a_return_is_refused(tmp_path: Path, office_scans: list[LaserScan]) -> None:
    # The office scans written in millimetres: every range beyond the 20 m maximum.
    mm = [dataclasses.replace(s, ranges_m=s.ranges_m * 1000.0) for s in office_scans]
    log = tmp_path / "mm.clf"
    write_carmen(log, mm)
    low = min(float(np.min(s.ranges_m)) for s in mm)
    high = max(float(np.max(s.ranges_m)) for s in mm)
    message = re.escape(
        f"mm.clf: none of its 40 scans has a return: every range lies outside the scan's "
        f"limits (0..20 m; the ranges read: from {low:.4g} to {high:.4g}); are the ranges in "
        "metres"
    )
    with pytest.raises(LogFormatError, match=message):
        run_log(log)
    with pytest.raises(LogFormatError, match=message):
        read_log_scans(log, IcegConfig())
    (task,) = expand(spec_from_dict({"logs": [{"path": str(log)}]}), tmp_path, tmp_path)
    with pytest.raises(LogFormatError, match=message):
        load_input(task)


def test_one_return_in_the_log_is_enough(office_scans: list[LaserScan]) -> None:
    blind = [
        dataclasses.replace(s, ranges_m=np.full_like(s.ranges_m, np.inf)) for s in office_scans
    ]
    with pytest.raises(LogFormatError, match=r"blind: none of its 40 .*ranges read: none finite"):
        check_returns("blind", blind)
    check_returns("last", [*blind[:-1], office_scans[-1]])  # one scan with returns: no error
    check_returns("empty", [])  # no scans: refused where the run starts


def test_mirrored_beams_are_told_by_the_turns(office_scans: list[LaserScan]) -> None:
    # The office's first 150 scans turn 61 times by 30-90 deg within a metre: in every one
    # the walls turn as the odometry does (the test stops at the seventh, p = 2^-7 < 1 %),
    # and in every one against it with the beams mirrored (p = 2^-61).
    scans = simulate(office_world(), seed=2).scans[:150]
    config = IcegConfig()
    as_read = odometry_check(scans, config)
    assert as_read == OdometryCheck(7, 7, 0, 1.0, 7, 0, 1.0, 7, 7, 0, 1.0)
    assert not as_read.beams_mirrored and not as_read.heading_unusable
    mirrored = odometry_check([s.mirrored() for s in scans], config)
    assert mirrored is not None and (mirrored.as_read, mirrored.mirrored) == (0, 61)
    assert mirrored.p_mirrored == pytest.approx(0.5**61) and mirrored.beams_mirrored
    assert not mirrored.heading_unusable  # the walls do turn, the other way
    assert odometry_check(ScanStore([s.mirrored() for s in scans]), config) == mirrored
    early = odometry_check(office_scans[:20], config)  # no turn of 30 deg yet; moves
    assert early == OdometryCheck(0, 0, 0, 1.0, 0, 0, 1.0, 7, 7, 0, 1.0)
    assert odometry_check([s.without_odometry() for s in scans], config) is None


def test_move_pairs_by_hand() -> None:
    # Scans 0.2 m apart: each pairs with the first one 0.5 m or more along the path (three
    # steps on, 0.6 m). No pair spans a scan without a pose, nor a break.
    poses = np.array([[0.2 * k, 0.0, 0.0] for k in range(8)])
    np.testing.assert_array_equal(move_pairs(poses), [[k, k + 3] for k in range(5)])
    hole = poses.copy()
    hole[4] = np.nan
    np.testing.assert_array_equal(move_pairs(hole), [[0, 3]])  # 5-7: 0.4 m after the hole
    breaks = np.zeros(8, dtype=bool)
    breaks[5] = True
    np.testing.assert_array_equal(move_pairs(poses, breaks), [[0, 3], [1, 4]])
    # Scans metres apart (a sparse log, or centimetres read as metres): each with the next.
    far = np.array([[0.0, 0.0, 0.0], [1.2, 0.0, 0.0], [9.0, 0.0, 0.0], [9.3, 0.0, 0.0]])
    np.testing.assert_array_equal(move_pairs(far), [[0, 1], [1, 2]])  # 9.3 is 0.3 m on
    far[1] = np.nan
    np.testing.assert_array_equal(move_pairs(far), np.zeros((0, 2)))


def test_a_jump_of_the_odometry_at_a_break_is_no_turn(office_scans: list[LaserScan]) -> None:
    # A robot standing still whose odometry jumps by 45 deg every ten scans: across the
    # jumps the walls stay put. Flagged as breaks (as a reader flags a reset), no pair
    # spans one; unflagged, the jumps read as turns the walls do not follow.
    still = office_scans[0]
    scans = [
        dataclasses.replace(
            still,
            odom_pose=np.array([0.0, 0.0, np.radians(45.0) * (i // 10)]),
            odom_break=i > 0 and i % 10 == 0,
        )
        for i in range(40)
    ]
    assert odometry_check(scans, IcegConfig()) is None
    unflagged = [dataclasses.replace(s, odom_break=False) for s in scans]
    unflagged_check = odometry_check(unflagged, IcegConfig())
    assert unflagged_check is not None and unflagged_check.heading_unusable


@pytest.mark.parametrize(("wins", "losses"), [(0, 0), (7, 0), (0, 10), (49, 15), (3, 2), (60, 4)])
def test_the_sign_test_is_the_binomial_tail(wins: int, losses: int) -> None:
    from scipy.stats import binomtest

    expected = binomtest(wins, wins + losses, 0.5, "greater").pvalue if wins + losses else 1.0
    assert sign_test_p(wins, losses) == pytest.approx(expected, rel=1e-12)


def _in_degrees(scans: list[LaserScan]) -> list[LaserScan]:
    """The scans with their odometry heading written in degrees."""
    return [
        dataclasses.replace(s, odom_pose=np.array([*s.odom_pose[:2], np.degrees(s.odom_pose[2])]))
        for s in scans
        if s.odom_pose is not None
    ]


def test_a_heading_the_walls_do_not_follow_is_told(caplog: pytest.LogCaptureFixture) -> None:
    # The whole office with the odometry's heading in degrees: a turn of 30-90 "degrees" as
    # radians is one of 0.5-1.6 deg, and in every such turn the walls line up unturned.
    scans = _in_degrees(simulate(office_world(), seed=2).scans)
    test = odometry_check(scans, IcegConfig())
    assert test is not None and test.heading_unusable and not test.beams_mirrored
    assert test.turned == 0 and test.unturned >= 7 and test.p_unturned == 0.5**test.unturned
    with caplog.at_level(logging.WARNING, logger="iceg.log_checks"):
        reading = reading_adjustments("deg.clf", scans, IcegConfig())
    assert reading.options == {"laser_only": True} and reading.check == test
    assert "deg.clf: the walls do not turn where the odometry turns" in caplog.text
    assert "(in degrees instead of radians? another column?)" in caplog.text


def test_the_median_scan_interval_by_hand(caplog: pytest.LogCaptureFixture) -> None:
    with caplog.at_level(logging.WARNING, logger="iceg.log_checks"):
        assert warn_sparse_stamps("s", [0.0, 0.1, 0.3, 0.6]) == pytest.approx(0.2)
        assert warn_sparse_stamps("one", [5.0]) is None
        assert not caplog.text
        # any order; intervals 100, 200, 300 (milliseconds read as seconds)
        assert warn_sparse_stamps("ms", [600.0, 0.0, 300.0, 100.0]) == pytest.approx(200.0)
    assert "ms: its scans are 200 s apart at the median" in caplog.text
    assert "are the stamps in seconds? Read as seconds" in caplog.text
    assert describe_stamps([600.0, 0.0, 300.0, 100.0]) == [
        (
            "scan interval",
            "200 s at the median; a laser scanner sends 1 to 100 scans a second: are the "
            "stamps in seconds?",
        )
    ]
    assert describe_stamps([0.0, 0.1, 0.3, 0.6]) == [("scan interval", "0.2 s at the median")]
    assert describe_stamps([5.0]) == []


def test_stamps_in_milliseconds_are_told(
    tmp_path: Path, office_scans: list[LaserScan], caplog: pytest.LogCaptureFixture
) -> None:
    # The office scans are 0.2 s apart (5 Hz); written in milliseconds, 200 units apart.
    log = tmp_path / "ms.clf"
    write_carmen(log, [dataclasses.replace(s, stamp_s=s.stamp_s * 1000.0) for s in office_scans])
    told = "ms.clf: its scans are 200 s apart at the median"
    with caplog.at_level(logging.WARNING, logger="iceg.log_checks"):
        run_log(log)
    assert caplog.text.count(told) == 1
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="iceg.log_checks"):
        read_log_scans(log, IcegConfig())
        (task,) = expand(spec_from_dict({"logs": [{"path": str(log)}]}), tmp_path, tmp_path)
        load_input(task)
    assert caplog.text.count(told) == 2


@pytest.mark.parametrize(
    ("name", "median_s"),
    [("mit-csail/mit-csail.clf", 0.21), ("aces/aces-corrected.log.gz", 2.159)],
)
def test_real_logs_stamps_read_as_seconds(
    name: str, median_s: float, caplog: pytest.LogCaptureFixture
) -> None:
    # MIT CSAIL's scanner at about 5 Hz; ACES thinned to the scans where the robot moved,
    # still well under the bound.
    stamps = [s.stamp_s for s in open_log(shared_file(name))]
    with caplog.at_level(logging.WARNING, logger="iceg.log_checks"):
        median = warn_sparse_stamps(name, stamps)
    assert median == pytest.approx(median_s, abs=0.001)
    assert median is not None and median < MAX_MEDIAN_SCAN_INTERVAL_S / 4
    assert not caplog.text


def test_mirroring_twice_gives_the_scan_back(office_scans: list[LaserScan]) -> None:
    scan = office_scans[3]
    once = scan.mirrored()
    np.testing.assert_array_equal(once.ranges_m, scan.ranges_m[::-1])
    np.testing.assert_array_equal(once.angles_rad, -scan.angles_rad[::-1])
    assert np.all(np.diff(once.angles_rad) > 0)  # bearings still increase
    twice = once.mirrored()
    np.testing.assert_array_equal(twice.ranges_m, scan.ranges_m)
    np.testing.assert_array_equal(twice.angles_rad, scan.angles_rad)
    assert twice.odom_pose is scan.odom_pose and twice.stamp_s == scan.stamp_s


@pytest.mark.parametrize("name", ["mit-csail/mit-csail.clf", "mit-csail/csail.log"])
def test_real_logs_read_as_they_are_and_broken_ones_are_told(name: str) -> None:
    # As read: the walls follow the odometry in most turns (MIT CSAIL 12 of the 14 it takes
    # to decide, csail.log 7 of 7; the others turn near 45 or 90 deg, where a building's
    # right angles cannot tell). Beams reversed: mirrored; heading in degrees: unturned.
    scans = list(open_log(shared_file(name)))
    config = IcegConfig()
    as_read = odometry_check(scans, config)
    assert as_read is not None and as_read.finding() is None
    assert as_read.as_read > 3 * as_read.mirrored and as_read.turned > 3 * as_read.unturned
    assert as_read.moved > 3 * as_read.unmoved  # MIT CSAIL 7 of 7, csail.log 10 of 11
    mirrored = odometry_check([s.mirrored() for s in scans], config)
    assert mirrored is not None and mirrored.beams_mirrored and mirrored.p_mirrored < 1e-4
    degrees = odometry_check(_in_degrees(scans), config)
    assert degrees is not None and degrees.heading_unusable and degrees.p_unturned < 1e-3


def test_an_odometry_in_centimetres_is_told_by_the_moves() -> None:
    # MIT CSAIL with its odometry's x and y in centimetres: its moves of 0.5 "m" or more are
    # the robot's centimetres from one scan to the next, and in each the walls line up
    # better unmoved (64 of 64, p = 2^-64).
    scans = list(open_log(shared_file("mit-csail/mit-csail.clf")))
    centimetres = [
        dataclasses.replace(s, odom_pose=s.odom_pose * np.array([100.0, 100.0, 1.0]))
        for s in scans
        if s.odom_pose is not None
    ]
    check = odometry_check(centimetres, IcegConfig())
    assert check is not None and check.translation_unusable and not check.heading_unusable
    assert (check.moved, check.unmoved) == (0, 64) and check.p_unmoved == 0.5**64
    finding = check.finding()
    assert finding is not None and finding[0] == "laser_only"


@pytest.mark.parametrize("log", ["mit-csail/csail.log", "aces/aces-corrected.log.gz"])
def test_an_odometry_in_centimetres_is_told_on_a_sparse_log(log: str) -> None:
    # csail.log's scans lie 0.4-0.7 m apart and ACES's about 1 m: read in centimetres, their
    # odometry moves tens of "m" between consecutive scans, and only a robot standing
    # nearly still gave a move of 0.5-1 "m" (one or two pairs: not told). Each scan pairs
    # with the first later one 0.5 "m" or more on, its neighbour: in all 64 compared the
    # walls line up better unmoved (p = 2^-64). Read in metres, the moves follow the
    # odometry (csail.log 7 of 7, ACES 12 of 14).
    scans = list(open_log(shared_file(log)))
    as_read = odometry_check(scans, IcegConfig())
    assert as_read is not None and as_read.finding() is None
    assert as_read.moved > 3 * as_read.unmoved
    centimetres = [
        dataclasses.replace(s, odom_pose=s.odom_pose * np.array([100.0, 100.0, 1.0])) for s in scans
    ]
    check = odometry_check(centimetres, IcegConfig())
    assert check is not None and check.translation_unusable
    assert (check.moved, check.unmoved) == (0, 64) and check.p_unmoved == 0.5**64
    finding = check.finding()
    assert finding is not None and finding[0] == "laser_only"


@pytest.fixture(scope="module")
def mirrored_log(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, list[LaserScan]]:
    scans = simulate(office_world(), seed=2).scans[:150]
    log = tmp_path_factory.mktemp("mirrored") / "mirrored.clf"
    write_carmen(log, [s.mirrored() for s in scans])
    return log, scans


def test_read_log_scans_reads_mirrored_beams_back(
    mirrored_log: tuple[Path, list[LaserScan]], caplog: pytest.LogCaptureFixture
) -> None:
    log, truth = mirrored_log
    with caplog.at_level(logging.WARNING, logger="iceg.log_checks"):
        scans, record, options = read_log_scans(log, IcegConfig())
    assert "the walls turn against the odometry (in 61 of 61 turns" in caplog.text
    assert options == {"mirror_beams": True} and record == {"applied_s": 0.0}
    _assert_read_back(scans, truth)
    again, _, options_again = read_log_scans(log, IcegConfig(), reader_options=options)
    assert options_again == options  # read mirrored, the test finds nothing more to do
    _assert_read_back(again, truth)


def test_a_batch_run_reads_mirrored_beams_back(
    tmp_path: Path, mirrored_log: tuple[Path, list[LaserScan]]
) -> None:
    log, truth = mirrored_log
    (task,) = expand(spec_from_dict({"logs": [{"path": str(log)}]}), tmp_path, tmp_path)
    data = load_input(task)
    assert data.adjusted == {"mirror_beams": True}
    _assert_read_back(data.scans, truth)
    row = execute_run(dataclasses.replace(task, outputs="metrics"))
    assert row["status"] == "ok", row["error"]
    assert (row["metrics"]["beams_mirrored"], row["metrics"]["scans_without_odometry"]) == (1, 0)


def test_a_log_with_its_heading_in_degrees_is_read_as_laser_only(tmp_path: Path) -> None:
    log = tmp_path / "degrees.clf"
    write_carmen(log, _in_degrees(simulate(office_world(), seed=2).scans))
    scans, record, options = read_log_scans(log, IcegConfig(), odometry_time_offset_s="auto")
    assert options == {"laser_only": True} and record == {"applied_s": 0.0}
    assert len(scans) == 701 and all(s.odom_pose is None for s in scans)
    (task,) = expand(spec_from_dict({"logs": [{"path": str(log)}]}), tmp_path, tmp_path)
    data = load_input(task)
    assert data.adjusted == {"laser_only": True} and all(s.odom_pose is None for s in data.scans)


def test_info_says_how_the_walls_turn_with_the_odometry(
    mirrored_log: tuple[Path, list[LaserScan]],
) -> None:
    from typer.testing import CliRunner

    from iceg.cli import app

    log, scans = mirrored_log
    config = IcegConfig()
    assert describe_odometry_checks(scans, config) == [
        ("walls and odometry", "they turn and move together (7 of 7 turns, 7 of 7 moves)"),
        ("odometry held while moving", "nowhere"),
    ]
    assert describe_odometry_checks([s.without_odometry() for s in scans], config) == []
    result = CliRunner().invoke(app, ["info", str(log)])
    assert result.exit_code == 0, result.output
    row = r"walls and odometry +the walls turn against the odometry \(in 61 of 61 turns they "
    assert re.search(row + r"follow .*: a run reads the log with its beams mirrored", result.output)


def _assert_read_back(scans: list[LaserScan], truth: list[LaserScan]) -> None:
    """The simulated scans as CARMEN stores them: ranges to the centimetre, bearings within
    rounding of the 180 deg fan (written mirrored, read mirrored back)."""
    assert len(scans) == len(truth)
    for got, want in zip(scans, truth, strict=True):
        np.testing.assert_allclose(got.ranges_m, want.ranges_m, atol=0.005)
        np.testing.assert_allclose(got.angles_rad, want.angles_rad, atol=1e-12)
        assert got.odom_pose is not None and want.odom_pose is not None
        np.testing.assert_allclose(got.odom_pose, want.odom_pose, atol=1e-3)
