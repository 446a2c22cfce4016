"""An odometry that holds one pose while the robot drives on is left out where it holds
(``iceg.odometry_stalls``), on every path that reads a log; a robot that stands still keeps
its odometry."""

from __future__ import annotations

import dataclasses
import logging
import re
from pathlib import Path

import numpy as np
import pytest

from frontends import LaserScan, open_log
from frontends.carmen import write_carmen
from frontends.registry import adjust_scan
from frontends.simulate import office_world, simulate
from frontends.simulate.trajectory import default_trajectory
from frontends.simulate.worlds import with_pedestrians
from iceg.batch import expand, spec_from_dict
from iceg.batch_run import execute_run, load_input
from iceg.config import IcegConfig
from iceg.evaluation import position_errors
from iceg.log_checks import reading_adjustments
from iceg.odometry_stalls import held_runs, odometry_stalls
from iceg.pipeline import read_log_scans, run_log
from iceg.scan_store import ScanStore
from iceg_common import se2
from tests.conftest import shared_file

#: The office world's scans whose odometry is held at scan 199's pose.
HELD = range(200, 350)


def _held(scans: list[LaserScan], held: range, offset: bool) -> list[LaserScan]:
    """``scans`` with the odometry of ``held`` at the pose of the scan before it; after it, the
    recorded odometry (a stalled topic that comes back) or, with ``offset``, the recorded
    odometry moved so that it continues from the held pose (encoders that lost the motion)."""
    pose = scans[held.start - 1].odom_pose
    assert pose is not None
    last = scans[held.stop - 1].odom_pose
    assert last is not None
    shift = se2.compose(pose, se2.inverse(last))
    out = []
    for k, scan in enumerate(scans):
        if k in held:
            scan = dataclasses.replace(scan, odom_pose=pose.copy())
        elif offset and k >= held.stop and scan.odom_pose is not None:
            scan = dataclasses.replace(scan, odom_pose=se2.compose(shift, scan.odom_pose))
        out.append(scan)
    return out


@pytest.fixture(scope="module")
def office() -> tuple[list[LaserScan], np.ndarray]:
    run = simulate(office_world(), seed=0)
    return list(run.scans), np.asarray(run.true_poses)


def test_held_runs_by_hand() -> None:
    a, b = [0.0, 0.0, 0.0], [1.0, 0.0, 0.5]
    nan = [np.nan] * 3
    poses = np.array([a, a, a, b, b, nan, nan, a, a, a, a, b], dtype=np.float64)
    breaks = np.zeros(len(poses), dtype=bool)
    assert held_runs(poses, breaks) == [(0, 3), (3, 5), (7, 11)]
    breaks[9] = True  # a new odometry frame that happens to give the same pose
    assert held_runs(poses, breaks) == [(0, 3), (3, 5), (7, 9), (9, 11)]
    assert held_runs(np.zeros((0, 3)), np.zeros(0, dtype=bool)) == []


@pytest.mark.parametrize("offset", [False, True])
def test_a_held_odometry_over_the_office_loop_is_found(
    office: tuple[list[LaserScan], np.ndarray], offset: bool
) -> None:
    # 150 scans (30 s) of a robot driving 10 cm a scan: every pair compared moved, far beyond
    # its match's covariance; the held run starts one scan early, at the pose it holds.
    scans, _ = office
    (stall,) = odometry_stalls(_held(scans, HELD, offset), IcegConfig())
    assert (stall.first, stall.stop) == (HELD.start, HELD.stop)
    assert (stall.start_s, stall.end_s) == (scans[200].stamp_s, scans[349].stamp_s)
    assert (stall.moved, stall.stood) == (24, 0) and stall.p == 0.5**24
    assert stall.held_s == scans[349].stamp_s - scans[199].stamp_s
    assert odometry_stalls(scans, IcegConfig()) == []  # as simulated: nothing held


def test_an_odometry_that_updates_every_tenth_scan_does_not_stall(
    office: tuple[list[LaserScan], np.ndarray],
) -> None:
    # It holds each pose for ten scans while the robot drives on (a 2 Hz odometry beside a
    # 20 Hz laser): that is its rate, not a stall, and it catches up every time; each of its
    # runs, 9 of 9 pairs moved, would pass the sign test alone. A hold of 30 s in it is one.
    scans = office[0]
    low_rate = [
        dataclasses.replace(scan, odom_pose=scans[k - k % 10].odom_pose)
        for k, scan in enumerate(scans)
    ]
    assert odometry_stalls(low_rate, IcegConfig()) == []
    (stall,) = odometry_stalls(_held(low_rate, HELD, offset=False), IcegConfig())
    assert (stall.first, stall.stop) == (191, HELD.stop)  # held since scan 190's update


def test_a_robot_standing_still_keeps_its_odometry(
    office: tuple[list[LaserScan], np.ndarray],
) -> None:
    # The same scan 40 times over with fresh noise on its ranges (1 cm, the scanner's): the
    # odometry holds its pose and the scans do not move.
    scan = office[0][0]
    rng = np.random.default_rng(3)
    standing = [
        dataclasses.replace(
            scan,
            stamp_s=scan.stamp_s + 0.2 * k,
            ranges_m=scan.ranges_m + rng.normal(0.0, 0.01, scan.ranges_m.shape),
        )
        for k in range(40)
    ]
    assert held_runs(ScanStore(standing).odometry[1], np.zeros(40, dtype=bool)) == [(0, 40)]
    assert odometry_stalls(standing, IcegConfig()) == []


def test_a_robot_standing_among_walking_people_keeps_its_odometry() -> None:
    # The office with 30 people walking it; the robot stands 30 s (150 scans) at its 100th
    # pose: its odometry holds, the legs move, the walls do not.
    world = with_pedestrians(office_world(), 30, seed=1)
    route = default_trajectory(world)[:200]
    trajectory = np.concatenate([route[:100], np.repeat(route[100:101], 150, axis=0), route[101:]])
    scans = ScanStore(simulate(world, trajectory, seed=0).scans)
    _, poses, breaks = scans.odometry
    assert held_runs(poses, breaks) == [(100, 250)]
    assert odometry_stalls(scans, IcegConfig()) == []


@pytest.mark.parametrize(
    ("stand", "drive", "first"),
    [(100, 100, 279), (50, 150, 200), (150, 50, 348)],
)
def test_a_hold_over_a_robot_that_stands_then_drives_is_found_where_it_drives(
    stand: int, drive: int, first: int
) -> None:
    # The office's robot stands at its 200th pose, then drives on; its odometry holds from
    # the stop for stand + drive scans. Where the standing scans outnumber the driving ones
    # the run as a whole does not pass, and the span of the moves is tested alone: the
    # scans from the last compared standing one on are read without odometry.
    world = office_world()
    route = default_trajectory(world)[:600]
    trajectory = np.concatenate(
        [route[:200], np.repeat(route[200:201], stand, axis=0), route[200:]]
    )
    scans = _held(list(simulate(world, trajectory, seed=0).scans), range(200, 400), False)
    (stall,) = odometry_stalls(scans, IcegConfig())
    assert (stall.first, stall.stop) == (first, 400)
    assert stall.p < 0.01


def test_a_hold_over_a_robot_that_drives_then_stops_is_found_from_where_it_drove() -> None:
    # Driving 50 scans, then standing 150 at a pose the odometry does not know: every scan
    # from the hold's start is read without odometry.
    world = office_world()
    route = default_trajectory(world)[:600]
    trajectory = np.concatenate([route[:250], np.repeat(route[250:251], 150, axis=0), route[250:]])
    scans = _held(list(simulate(world, trajectory, seed=0).scans), range(200, 400), False)
    (stall,) = odometry_stalls(scans, IcegConfig())
    assert (stall.first, stall.stop) == (200, 400)


def test_the_turtlebot4_standing_at_its_start_keeps_its_odometry() -> None:
    # Its RPLIDAR's scans of a robot standing still match 2-4 mm apart, beyond their
    # covariances (0.6-0.7 mm across the beams) but within the range noise: no scan moved.
    scans = ScanStore(open_log(shared_file("rosbag/turtlebot4-ros2")))
    _, poses, breaks = scans.odometry
    assert [r for r in held_runs(poses, breaks) if r[1] - r[0] >= 8] == [(2, 80)]
    assert odometry_stalls(scans, IcegConfig()) == []


def test_mit_csail_stands_and_holds_briefly_but_never_stalls() -> None:
    # It stands at its start and end (33 and 31 scans); three times its odometry holds for
    # 4-5 scans while the robot drives (too short to tell at 1 %, and it catches up).
    scans = ScanStore(open_log(shared_file("mit-csail/mit-csail.clf")))
    _, poses, breaks = scans.odometry
    runs = held_runs(poses, breaks)
    assert [r for r in runs if r[1] - r[0] >= 5] == [
        (0, 33), (39, 45), (320, 325), (797, 802), (1579, 1584), (1957, 1988)
    ]  # fmt: skip
    assert odometry_stalls(scans, IcegConfig()) == []


@pytest.fixture(scope="module")
def held_log(
    tmp_path_factory: pytest.TempPathFactory, office: tuple[list[LaserScan], np.ndarray]
) -> Path:
    log = tmp_path_factory.mktemp("held") / "held.clf"
    write_carmen(log, _held(office[0], HELD, offset=False))
    return log


def test_every_path_reads_the_held_scans_without_odometry(
    tmp_path: Path, held_log: Path, caplog: pytest.LogCaptureFixture
) -> None:
    with caplog.at_level(logging.WARNING, logger="iceg.log_checks"):
        scans, record, options = read_log_scans(held_log, IcegConfig())
    assert (
        f"{held_log}: the odometry holds one pose over 151 scans ({held_log}:202 to "
        f"{held_log}:352, 30.0 s) while the scans move (in 24 of 24 pairs of its scans matched, "
        "p = 6e-08): those scans are read without odometry" in caplog.text
    )
    (stall,) = options["odometry_stalls_s"]
    assert stall == [scans[200].stamp_s, scans[349].stamp_s] and record == {"applied_s": 0.0}
    without = [k for k, s in enumerate(scans) if s.odom_pose is None]
    assert without == list(HELD)
    (task,) = expand(spec_from_dict({"logs": [{"path": str(held_log)}]}), tmp_path, tmp_path)
    data = load_input(task)
    assert data.adjusted == options
    assert [k for k, s in enumerate(data.scans) if s.odom_pose is None] == list(HELD)
    reopened = list(open_log(held_log, **options))  # as a session reads it again
    assert [k for k, s in enumerate(reopened) if s.odom_pose is None] == list(HELD)
    assert adjust_scan(reopened[199], **options).odom_pose is not None


def test_a_batch_row_counts_the_scans_read_without_odometry(tmp_path: Path, held_log: Path) -> None:
    spec = spec_from_dict({"logs": [{"path": str(held_log)}], "outputs": "metrics"})
    (task,) = expand(spec, tmp_path, tmp_path)
    row = execute_run(task)
    assert row["status"] == "ok", row["error"]
    assert row["metrics"]["scans_without_odometry"] == len(HELD)
    assert row["metrics"]["beams_mirrored"] == 0


def test_a_run_through_the_held_odometry_keeps_to_the_truth(
    held_log: Path, office: tuple[list[LaserScan], np.ndarray]
) -> None:
    # Read as recorded the run loses the robot for the 30 s: a node at the held pose after
    # the keyframe interval, a 6.6 m jump where the odometry comes back, ATE 7 m. Tracked by
    # the laser alone there, it stays within 2 cm (1.1 cm as simulated, without the hold).
    result = run_log(held_log)
    truth = office[1][result.node_scan_index]
    assert position_errors(result.node_poses, truth).rmse_m < 0.02
    assert [(s["first"], s["stop"]) for s in result.metrics["odometry_stalls"]] == [(200, 350)]


def test_info_says_where_the_odometry_held(held_log: Path) -> None:
    from typer.testing import CliRunner

    from iceg.cli import app

    result = CliRunner().invoke(app, ["info", str(held_log)])
    assert result.exit_code == 0, result.output
    row = r"odometry held while moving +scans 199-349 \(30.0 s, 24 of 24 pairs moved\): a run "
    assert re.search(row + "reads them without odometry", result.output)


def test_reading_adjustments_of_a_log_read_without_odometry_find_no_stall(
    office: tuple[list[LaserScan], np.ndarray],
) -> None:
    scans = _held(office[0], HELD, offset=False)
    reading = reading_adjustments("x.clf", [s.without_odometry() for s in scans], IcegConfig())
    assert reading.options == {} and reading.stalls == ()
