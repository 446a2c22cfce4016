"""ROS bag reader and writer: numbers, round trips from CARMEN, real bags, bad bags, the CLI."""

from __future__ import annotations

import json
import logging
import math
import re
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest
from scipy.spatial.transform import Rotation
from typer.testing import CliRunner

pytest.importorskip("rosbags", reason="the ROS bag reader needs the 'ros' extra (rosbags)")

from rosbags.interfaces import MessageDefinitionFormat, Nodetype

from frontends import LaserScan, open_log
from frontends.rosbag import (
    READ_TYPES,
    TF_TYPE,
    RosbagReader,
    Transform3,
    _Bag,
    _read_types,
    interpolate_se2,
    project_mounting,
    quaternion_yaw,
    stamp_ns,
    widen_angle,
    widen_decimal,
    write_rosbag,
    yaw_quaternion,
)
from iceg.cli import app
from iceg_common import se2
from iceg_common.errors import ConfigError, LogFormatError
from tests.conftest import SHARED_DATA, shared_file

runner = CliRunner()
FORMATS = {"ros1": "x.bag", "sqlite3": "x_sqlite3", "mcap": "x_mcap"}


def _bag_dir(name: str) -> Path:
    path = SHARED_DATA / "rosbag" / name
    if not path.exists():
        pytest.skip(f"real bag {path} is absent (it lives in ../shared/data beside the repo)")
    return path


# ---------------------------------------------------------------------------------------------
# Numbers
# ---------------------------------------------------------------------------------------------


def test_stamps_round_trip_exactly_through_nanoseconds() -> None:
    rng = np.random.default_rng(0)
    # Epoch stamps (float ulp >= 2 ns: exact), and sim-time stamps with at most 9 decimals.
    stamps = np.concatenate([rng.uniform(1.0e9, 1.8e9, 2000), rng.uniform(0, 100, 200).round(9)])
    for t in stamps.tolist():
        assert stamp_ns(t) / 10**9 == t
    # Truth by hand: the float nearest 1134864629.923456 is 1134864629.92345595359802246...
    # (ulp 2**-22 s = 238 ns), so its nearest nanosecond is ...923455954.
    assert stamp_ns(1134864629.923456) == 1134864629923455954
    assert stamp_ns(0.565) == 565_000_000


def test_widen_decimal_recovers_the_decimal_a_float32_was_rounded_from() -> None:
    decimals = np.array([3.45, 81.91, 0.02, 12.0, 0.15, 5.0, 1234.567, 0.001])
    out = widen_decimal(decimals.astype(np.float32))
    np.testing.assert_array_equal(out, decimals)  # bit for bit
    # 8 significant digits are more than a float32 holds: the shortest decimal is another one.
    assert widen_decimal(np.array([1234.5678], dtype=np.float32))[0] == 1234.5677
    special = widen_decimal(np.array([np.nan, np.inf, -np.inf, 0.0], dtype=np.float32))
    assert np.isnan(special[0]) and special[1] == np.inf and special[2] == -np.inf
    assert special[3] == 0.0


def test_widen_angle_recovers_multiples_of_pi_then_decimals() -> None:
    for angle in (-math.pi / 2, math.pi / 360, -3 * math.pi / 4, math.pi / 720, math.pi):
        assert widen_angle(float(np.float32(angle))) == angle
    assert widen_angle(float(np.float32(-1.5708))) == -1.5708  # not k*pi/q: the decimal
    assert widen_angle(0.0) == 0.0


def test_yaw_quaternion_reads_back_the_exact_heading() -> None:
    rng = np.random.default_rng(1)
    for yaw in rng.uniform(-math.pi, math.pi, 3000).tolist():
        q = yaw_quaternion(yaw)
        assert quaternion_yaw(*q) == yaw
        assert math.isclose(math.hypot(q[2], q[3]), 1.0, abs_tol=1e-15)


def test_se2_interpolation_follows_a_constant_twist_arc() -> None:
    # Truth: a robot at constant twist (v=1 m/s, omega=0.5 rad/s) from the origin moves on a
    # circle of radius 2: pose(t) = (2 sin(t/2), 2 (1 - cos(t/2)), t/2). The SE(2) geodesic
    # between pose(0) and pose(2) passes through pose(1) at f = 0.5.
    def arc(t: float) -> np.ndarray:
        return np.array([2 * math.sin(t / 2), 2 * (1 - math.cos(t / 2)), t / 2])

    p0 = se2.compose([1.0, -2.0, 0.3], arc(0.0))
    p1 = se2.compose([1.0, -2.0, 0.3], arc(2.0))
    mid = interpolate_se2(p0, p1, 0.5)
    np.testing.assert_allclose(mid, se2.compose([1.0, -2.0, 0.3], arc(1.0)), atol=1e-12)
    quarter = interpolate_se2(p0, p1, 0.25)
    np.testing.assert_allclose(quarter, se2.compose([1.0, -2.0, 0.3], arc(0.5)), atol=1e-12)
    assert np.array_equal(interpolate_se2(p0, p1, 0.0), p0)
    assert np.array_equal(interpolate_se2(p0, p1, 1.0), p1)


def test_mounting_projection_rotated_flipped_and_tilted() -> None:
    rot90 = Transform3(np.array([0.004, 0.0, 0.2]), Rotation.from_euler("z", 90, degrees=True))
    m = project_mounting(rot90, "bag", math.radians(5))
    np.testing.assert_allclose(m.offset, [0.004, 0.0, math.pi / 2], atol=1e-12)
    assert not m.flipped
    # Upside down (roll 180 deg) and facing backwards (yaw 180 deg): the bearing-0 beam points
    # along base -x; a beam at laser bearing +a points to base heading pi - a (mirrored).
    flip = Transform3(np.zeros(3), Rotation.from_euler("ZYX", [180, 0, 180], degrees=True))
    m = project_mounting(flip, "bag", math.radians(5))
    assert m.flipped
    assert abs(abs(m.offset[2]) - math.pi) < 1e-12
    tilt = Transform3(np.zeros(3), Rotation.from_euler("y", 10, degrees=True))
    with pytest.raises(LogFormatError, match=r"bag: the laser is tilted 10\.0 deg"):
        project_mounting(tilt, "bag", math.radians(5))


# ---------------------------------------------------------------------------------------------
# Hand-made bags: every format, interpolation, invalid ranges, a flipped laser
# ---------------------------------------------------------------------------------------------

ANGLES = np.asarray(-math.pi / 4 + np.arange(5) * (math.pi / 8), dtype=np.float64)


def _scans(n: int = 4, odom: bool = True) -> list[LaserScan]:
    return [
        LaserScan(
            stamp_s=100.0 + i,
            ranges_m=np.array([1.25 + i, 0.0, np.nan, 4.0 + i, 81.91]),
            angles_rad=ANGLES,
            range_min_m=0.1,
            range_max_m=81.91,
            odom_pose=np.array([0.5 * i, 0.0, 0.1 * i]) if odom else None,
            laser_offset=np.array([0.2, -0.1, 0.3]),
            source=f"hand:{i}",
        )
        for i in range(n)
    ]


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_hand_made_bag_reads_back(tmp_path: Path, fmt: str) -> None:
    path = tmp_path / FORMATS[fmt]
    assert write_rosbag(path, _scans(), fmt) == 4  # type: ignore[arg-type]
    reader = open_log(path)
    assert isinstance(reader, RosbagReader)
    assert reader.count_scans() == 4
    got = list(reader)
    assert [s.stamp_s for s in got] == [100.0, 101.0, 102.0, 103.0]
    for i, s in enumerate(got):
        # 0 is below range_min and NaN is invalid: both become +inf (no return); 81.91 is
        # at range_max and is kept as it is (already a no-return beam).
        np.testing.assert_array_equal(s.ranges_m, [1.25 + i, np.inf, np.inf, 4.0 + i, 81.91])
        np.testing.assert_array_equal(s.angles_rad, ANGLES)
        np.testing.assert_array_equal(s.odom_pose, [0.5 * i, 0.0, 0.1 * i])
        np.testing.assert_allclose(s.laser_offset, [0.2, -0.1, 0.3], atol=1e-12)
        assert (s.range_min_m, s.range_max_m) == (0.1, 81.91)
        assert s.source == f"{path}:/scan#{i}"
    np.testing.assert_array_equal(got[0].valid_mask(), [True, False, False, True, False])


def test_odometry_is_interpolated_on_se2_and_scans_outside_get_none(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # Odometry at t = 100.5, 101.5, 102.5 on a constant-twist arc (v = 1, omega = 0.5); scans at
    # 100..103: the first and last lie outside the odometry's span. Truth: the arc itself.
    def arc(t: float) -> np.ndarray:
        return np.array([2 * math.sin(t / 2), 2 * (1 - math.cos(t / 2)), t / 2])

    odometry = [(100.5 + k, arc(float(k))) for k in range(3)]
    path = tmp_path / "interp.bag"
    write_rosbag(path, _scans(odom=False), "ros1", odometry=odometry)
    reader = RosbagReader(path)
    with caplog.at_level(logging.WARNING, logger="frontends.rosbag"):
        got = list(reader)
    assert got[0].odom_pose is None and got[3].odom_pose is None
    assert got[1].odom_pose is not None and got[2].odom_pose is not None
    np.testing.assert_allclose(got[1].odom_pose, arc(0.5), atol=1e-12)  # t = 101.0
    np.testing.assert_allclose(got[2].odom_pose, arc(1.5), atol=1e-12)  # t = 102.0
    assert reader.scans_without_odometry == 2
    assert "2 of 4 scans lie outside the odometry's time span" in caplog.text
    dropped = list(RosbagReader(path, outside_odometry="drop"))
    assert [s.stamp_s for s in dropped] == [101.0, 102.0]


def test_upside_down_laser_mirrors_the_bearings(tmp_path: Path) -> None:
    # Laser upside down (roll 180 deg), 0.3 m ahead of the base, facing forward. A wall 2 m
    # ahead and a point 1 m to the laser's own left (+y in the laser frame) must land at
    # base (2.3, 0) and base (0.3, -1): the upside-down laser's left is the robot's right.
    scan = LaserScan(
        stamp_s=5.0,
        ranges_m=np.array([2.0, 1.0]),
        angles_rad=np.array([0.0, math.pi / 2]),
        range_min_m=0.1,
        range_max_m=10.0,
        odom_pose=None,
    )
    mount = Transform3(np.array([0.3, 0.0, 0.1]), Rotation.from_euler("x", 180, degrees=True))
    path = tmp_path / "flip.bag"
    write_rosbag(path, [scan], "ros1", laser_mount=mount)
    (got,) = list(RosbagReader(path, base_frame="base_link"))
    np.testing.assert_allclose(
        got.points_xy()[np.argsort(got.points_xy()[:, 1])], [[0.3, -1.0], [2.3, 0.0]], atol=1e-12
    )
    assert np.all(np.diff(got.angles_rad) > 0)


# ---------------------------------------------------------------------------------------------
# Round trips from the MIT CSAIL CARMEN log (acceptance: exact scans, odometry and stamps)
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def csail_scans() -> list[LaserScan]:
    return list(open_log(shared_file("mit-csail/mit-csail.clf")))


@pytest.mark.parametrize("fmt", sorted(FORMATS))
def test_csail_round_trip_is_exact(csail_scans: list[LaserScan], tmp_path: Path, fmt: str) -> None:
    path = tmp_path / FORMATS[fmt].replace("x", "csail")
    write_rosbag(path, csail_scans, fmt)  # type: ignore[arg-type]
    got = list(open_log(path))
    assert len(got) == len(csail_scans) == 1988
    for a, b in zip(csail_scans, got, strict=True):
        assert a.stamp_s == b.stamp_s
        assert np.array_equal(a.ranges_m, b.ranges_m)
        assert np.array_equal(a.angles_rad, b.angles_rad)
        assert np.array_equal(a.odom_pose, b.odom_pose)  # type: ignore[arg-type]
        assert np.array_equal(a.laser_offset, b.laser_offset)
        assert (a.range_min_m, a.range_max_m) == (b.range_min_m, b.range_max_m)


@pytest.mark.slow
def test_iceg_run_on_the_csail_bag_equals_the_clf_run(
    csail_scans: list[LaserScan], tmp_path: Path
) -> None:
    # One end-to-end run on a converted bag: the first 350 scans of the CSAIL log (190 of its
    # relations) as a CARMEN prefix and as a ROS 2 mcap bag.
    # The pipeline is deterministic, so the trajectories must be byte-identical and the
    # relation errors equal. (The full log as a ROS 1 bag gives 0.0381 m / 0.610 deg, as .clf.)
    clf = shared_file("mit-csail/mit-csail.clf")
    rel = shared_file("mit-csail/mit-csail.relations")
    lines = [ln for ln in clf.read_text().splitlines(keepends=True) if ln.startswith("FLASER")]
    prefix = tmp_path / "prefix.clf"
    prefix.write_text("".join(lines[:350]))
    bag = tmp_path / "prefix_mcap"
    write_rosbag(bag, open_log(prefix), "mcap")
    outs = {}
    for name, log in (("clf", prefix), ("bag", bag)):
        outs[name] = tmp_path / f"out_{name}"
        args = ["run", str(log), "--relations", str(rel), "--out", str(outs[name])]
        result = runner.invoke(app, [*args, "--no-progress"])
        assert result.exit_code == 0, result.output
    traj = [(outs[k] / "trajectory.tum").read_bytes() for k in ("clf", "bag")]
    assert traj[0] == traj[1]
    assert len(traj[0].splitlines()) == 350
    metrics = [json.loads((outs[k] / "metrics.json").read_text()) for k in ("clf", "bag")]
    assert metrics[0]["relations"] == metrics[1]["relations"]
    assert metrics[0]["relations"]["n_matched"] > 100


# ---------------------------------------------------------------------------------------------
# Real bags (../shared/data/rosbag; figures from its README.md)
# ---------------------------------------------------------------------------------------------


def _path_and_turn(scans: list[LaserScan]) -> tuple[float, float]:
    odom = np.array([s.odom_pose for s in scans if s.odom_pose is not None])
    path = float(np.hypot(*np.diff(odom[:, :2], axis=0).T).sum())
    return path, float(np.abs(se2.wrap_angle(np.diff(odom[:, 2]))).sum())


def test_turtlebot4_ros2_rotated_laser() -> None:
    reader = open_log(_bag_dir("turtlebot4-ros2"))
    scans = list(reader)
    # README: 357 x 720 beams, +-180 deg, 0.15-12 m, 76 % valid, laser yaw +90 deg at x 0.004 m.
    assert len(scans) == 357 and {s.n_beams for s in scans} == {720}
    assert (scans[0].range_min_m, scans[0].range_max_m) == (0.15, 12.0)
    np.testing.assert_allclose(scans[0].laser_offset, [0.004, 0.0, math.pi / 2], atol=5e-4)
    valid = np.mean(np.concatenate([s.valid_mask() for s in scans]))
    assert valid == pytest.approx(0.76, abs=0.01)
    assert math.degrees(scans[0].angles_rad[0]) == pytest.approx(-179.0, abs=1e-4)
    # README: an 8.4 m path and 6.7 rad of turning (at the 354 scans inside the odometry span).
    path, turn = _path_and_turn(scans)
    assert reader.scans_without_odometry == 3  # type: ignore[attr-defined]
    assert path == pytest.approx(8.4, abs=0.1) and turn == pytest.approx(6.7, abs=0.15)
    # Odometry from /tf (odom -> base_link) agrees with /odom at the same scans.
    by_tf = list(open_log(_bag_dir("turtlebot4-ros2"), odom_frame="odom", base_frame="base_link"))
    pairs = [
        (a.odom_pose, b.odom_pose)
        for a, b in zip(scans, by_tf, strict=True)
        if a.odom_pose is not None and b.odom_pose is not None
    ]
    diff = np.array([se2.between(a, b) for a, b in pairs])
    assert len(pairs) == 354
    assert np.abs(diff[:, :2]).max() < 0.01 and np.abs(diff[:, 2]).max() < 0.01


def _misalignment(scans: list[LaserScan], yaw: float, mirror: bool) -> float:
    """Median nearest-neighbour distance (m) between scans 3 apart placed by odometry, with
    the laser mounted at heading ``yaw`` (bearings mirrored if ``mirror``)."""
    from scipy.spatial import cKDTree

    def points(s: LaserScan) -> np.ndarray:
        m = s.valid_mask()
        a = (-s.angles_rad[m] if mirror else s.angles_rad[m]) + yaw
        r = s.ranges_m[m]
        return np.c_[r * np.cos(a), r * np.sin(a)] + s.laser_offset[:2]

    odom = [s for s in scans if s.odom_pose is not None]
    errs = []
    for a, b in zip(odom[:-3:3], odom[3::3], strict=False):
        assert a.odom_pose is not None and b.odom_pose is not None
        moved = se2.transform_points(se2.between(a.odom_pose, b.odom_pose), points(b))
        errs.append(np.median(cKDTree(points(a)).query(moved)[0]))
    return float(np.median(errs))


@pytest.mark.parametrize(
    ("folder", "file", "options"),
    [
        ("turtlebot4-ros2", "", {}),
        ("neato-ros1", "neato-obstacle-avoid.bag", {"scan_topic": "/scan"}),
        ("turtlebot3-gazebo-ros2", "", {}),
    ],
)
def test_the_tf_mounting_aligns_scans_best(folder: str, file: str, options: dict[str, str]) -> None:
    # Truth from the data itself: with the mounting read from tf (yaw +90, 180 and 0 deg),
    # scans placed by odometry overlap better than with any other of the 8 right-angle or
    # mirrored mountings (measured: 1.6 cm vs >= 2.8 cm, 4.1 vs >= 15.6, 1.2 vs >= 1.4).
    bag = _bag_dir(folder) / file if file else _bag_dir(folder)
    scans = list(open_log(bag, **options))
    yaw = float(scans[0].laser_offset[2])
    best = _misalignment(scans, yaw, False)
    for k in range(4):
        for mirror in (False, True):
            if k == 0 and not mirror:
                continue
            assert best < _misalignment(scans, yaw + k * math.pi / 2, mirror)


def test_neato_ros1_needs_a_scan_topic_and_reads_a_flipped_mount_from_dynamic_tf() -> None:
    bag = _bag_dir("neato-ros1") / "neato-obstacle-avoid.bag"
    with pytest.raises(LogFormatError, match=r"2 laser scan topics .*/scan, /stable_scan"):
        list(open_log(bag))
    scans = list(open_log(bag, scan_topic="/scan"))
    # README: 362 x 361, 0.02-5 m, 33 % valid (0 = no return), laser x -0.102 m yaw 180 deg,
    # 17.6 m path and 21 rad turning.
    assert len(scans) == 362 and scans[0].n_beams == 361
    assert (scans[0].range_min_m, scans[0].range_max_m) == (0.02, 5.0)
    np.testing.assert_allclose(scans[0].laser_offset[:2], [-0.1016, 0.0], atol=1e-9)
    assert abs(abs(scans[0].laser_offset[2]) - math.pi) < 1e-5
    valid = np.mean(np.concatenate([s.valid_mask() for s in scans]))
    assert valid == pytest.approx(0.33, abs=0.01)
    assert not np.any(np.concatenate([s.ranges_m for s in scans]) == 0.0)  # zeros -> +inf
    path, turn = _path_and_turn(scans)
    assert path == pytest.approx(17.6, abs=0.3) and turn == pytest.approx(21.0, abs=0.2)


def test_rc_car_without_odometry_or_laser_tf_runs_in_the_laser_frame(
    caplog: pytest.LogCaptureFixture,
) -> None:
    # No Odometry topic and no tf names frame 'laser' (README): the laser frame is the only
    # frame there is, so it is the base, with a warning naming the options for the robot's.
    bag = _bag_dir("rc-car-mocap-ros1") / "overtakes.bag"
    with caplog.at_level(logging.WARNING, logger="frontends.rosbag"):
        own = list(open_log(bag))
    assert "no tf names laser frame 'laser': the trajectory is the laser's" in caplog.text
    assert "--laser-frame-offset" in caplog.text
    assert len(own) == 339 and all(s.odom_pose is None for s in own)
    np.testing.assert_array_equal(own[0].laser_offset, [0.0, 0.0, 0.0])
    rows = dict(open_log(bag).describe())  # type: ignore[attr-defined]
    assert rows["base frame"].startswith("laser (the laser's own")
    caplog.clear()
    with caplog.at_level(logging.WARNING, logger="frontends.rosbag"):
        scans = list(open_log(bag, laser_frame_offset=(-0.12, 0.0, 0.0)))
    assert "no tf names laser frame" not in caplog.text  # the mounting was given
    for a, b in zip(own, scans, strict=True):  # the same scans, mounted as asked
        assert a.stamp_s == b.stamp_s
        np.testing.assert_array_equal(a.ranges_m, b.ranges_m)
    assert len(scans) == 339 and scans[0].n_beams == 360
    assert all(s.odom_pose is None for s in scans)
    np.testing.assert_array_equal(scans[0].laser_offset, [-0.12, 0.0, 0.0])
    assert (scans[0].range_min_m, scans[0].range_max_m) == (0.15, 8.0)
    valid = np.mean(np.concatenate([s.valid_mask() for s in scans]))
    assert valid == pytest.approx(0.46, abs=0.01)


def test_no_odometry_with_the_laser_in_tf_needs_a_base_frame(tmp_path: Path) -> None:
    # The writer records /odom without a message: no odometry. tf links the laser to
    # base_link: which frame of the tree is the robot's is not the reader's guess, so the
    # bag is refused with the options that say it.
    path = tmp_path / "no_odom.bag"
    write_rosbag(path, _scans(odom=False), "ros1")
    with pytest.raises(LogFormatError, match=r"no_odom\.bag: topic /scan: no odometry .*--base"):
        list(open_log(path))
    got = list(open_log(path, base_frame="base_link"))
    assert len(got) == 4 and all(s.odom_pose is None for s in got)
    with pytest.raises(LogFormatError, match=r"topic /odom holds no messages"):
        list(open_log(path, odom_topic="/odom"))  # named: the user asked for that one
    np.testing.assert_allclose(got[0].laser_offset, [0.2, -0.1, 0.3], atol=1e-12)


@pytest.mark.parametrize("ros1", [True, False])
def test_the_read_types_are_the_typestores_definitions(ros1: bool) -> None:
    # Truth: rosbags' own Noetic / Humble typestore. Every type the reader deserializes, and
    # every type those hold, is there with the store's definition, and nothing else is.
    from rosbags.typesys import Stores, get_typestore

    store = get_typestore(Stores.ROS1_NOETIC if ros1 else Stores.ROS2_HUMBLE)
    types = _read_types(ros1)
    known = {name for name in READ_TYPES if name in store.fielddefs}
    assert known == set(READ_TYPES) - ({TF_TYPE} if ros1 else set())  # Noetic lacks tf2's
    assert all(types[name] == store.fielddefs[name] for name in types)

    def named(desc: tuple) -> str | None:  # a field's type name; arrays' their elements'
        kind, detail = desc
        if kind in (Nodetype.ARRAY, Nodetype.SEQUENCE):
            return named(detail[0])
        return detail if kind == Nodetype.NAME else None

    held = {named(desc) for _, fields in types.values() for _, desc in fields} - {None}
    assert held <= set(types) | {"builtin_interfaces/msg/Time"}  # the store's own builtin
    assert set(types) - held == known  # the read types and what they hold, only


def test_a_bag_without_definitions_registers_the_read_types_only() -> None:
    bag = _Bag(_bag_dir("turtlebot4-ros2"))  # a ROS 2 sqlite3 bag that defines no type
    with bag:
        assert {c.msgdef.format for c in bag.connections} == {MessageDefinitionFormat.NONE}
        registered = set(bag.reader.typestore.fielddefs)
        assert set(_read_types(False)) <= registered
        unread = {c.msgtype for c in bag.connections} - set(_read_types(False))
        assert unread == {"std_msgs/msg/String"}  # /robot_description: never deserialized
        assert not unread & registered


def test_turtlebot3_sim_time_and_chained_static_tf() -> None:
    scans = list(open_log(_bag_dir("turtlebot3-gazebo-ros2")))
    # README: 100 x 360, 0-360 deg, 0.12-3.5 m, sim-time stamps 0.4-20 s, base_footprint ->
    # base_link -> base_scan at x -0.064 m, a 1.7 m path, 90 % valid.
    assert len(scans) == 100 and scans[0].n_beams == 360
    stamps = np.array([s.stamp_s for s in scans])
    assert stamps[0] >= 0.4 and stamps[-1] <= 20.5 and np.all(np.diff(stamps) > 0)
    assert all(s.odom_pose is not None for s in scans)  # odometry uses the same sim clock
    np.testing.assert_allclose(scans[0].laser_offset, [-0.064, 0.0, 0.0], atol=1e-9)
    assert scans[0].angles_rad[0] == 0.0
    assert _path_and_turn(scans)[0] == pytest.approx(1.7, abs=0.05)
    # Odometry from /tf odom -> base_footprint, composed with the static base_footprint ->
    # base_link (a vertical offset only), equals /odom (base_footprint) at every scan.
    by_tf = list(
        open_log(_bag_dir("turtlebot3-gazebo-ros2"), odom_frame="odom", base_frame="base_link")
    )
    for a, b in zip(scans, by_tf, strict=True):
        assert a.odom_pose is not None and b.odom_pose is not None
        np.testing.assert_allclose(a.odom_pose, b.odom_pose, atol=1e-3)
        np.testing.assert_allclose(b.laser_offset, [-0.064, 0.0, 0.0], atol=1e-9)


def test_iceg_info_on_a_bag_and_on_a_carmen_log() -> None:
    result = runner.invoke(app, ["info", str(_bag_dir("turtlebot4-ros2"))])
    assert result.exit_code == 0, result.output
    out = result.output
    assert "ROS 2 sqlite3" in out and "sensor_msgs/msg/LaserScan × 357" in out
    assert "nav_msgs/Odometry on /odom" in out and "720, -179.0 to 180.0 deg" in out
    assert "0.15 to 12 m" in out and "yaw 90.0 deg" in out
    # its scans read for the odometry checks, as a run reads them
    assert re.search(r"walls and odometry +they turn and move together \(7 of 7 turns", out)
    assert re.search(r"odometry held while moving +nowhere", out)
    # An ambiguous bag: info still lists the topics and says which option reading needs.
    neato = _bag_dir("neato-ros1") / "neato-obstacle-avoid.bag"
    result = runner.invoke(app, ["info", str(neato)])
    assert result.exit_code == 0, result.output
    assert "/stable_scan" in result.output and "sensor_msgs/msg/LaserScan × 364" in result.output
    assert "reading needs an option" in result.output and "--scan-topic" in result.output
    assert "walls and odometry" not in result.output  # no scans to check without the option
    result = runner.invoke(app, ["info", str(neato), "--scan-topic", "/scan"])
    assert result.exit_code == 0, result.output
    assert re.search(r"walls and odometry +they turn and move together", result.output)
    result = runner.invoke(app, ["info", str(shared_file("mit-csail/mit-csail.clf"))])
    assert result.exit_code == 0, result.output
    assert "1988" in result.output and "361" in result.output and "0 to 81.91 m" in result.output


# ---------------------------------------------------------------------------------------------
# Bad bags: one-line LogFormatErrors naming the bag and topic
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("fmt", ["ros1", "mcap"])
def test_truncated_bag(tmp_path: Path, fmt: str) -> None:
    full = tmp_path / FORMATS[fmt]
    write_rosbag(full, _scans(40), fmt)  # type: ignore[arg-type]
    target = full if full.is_file() else next(full.glob("*.mcap"))
    data = target.read_bytes()
    target.write_bytes(data[: len(data) // 2])
    with pytest.raises(LogFormatError, match=rf"{target.name if fmt == 'ros1' else full.name}"):
        list(open_log(full))


def test_broken_ros2_metadata(tmp_path: Path) -> None:
    bag = tmp_path / "x_sqlite3"
    write_rosbag(bag, _scans(), "sqlite3")
    (bag / "metadata.yaml").write_text("rosbag2_bagfile_information: [not, a, mapping\n")
    with pytest.raises(LogFormatError, match=r"x_sqlite3: cannot read the bag"):
        list(open_log(bag))
    missing = tmp_path / "gone.bag"
    with pytest.raises(LogFormatError, match=r"gone\.bag: no such log file"):
        open_log(missing)


def test_wrong_type_on_the_chosen_topic_lists_candidates(tmp_path: Path) -> None:
    path = tmp_path / "x.bag"
    write_rosbag(path, _scans(), "ros1")
    msg = r"x\.bag: topic /odom carries nav_msgs/msg/Odometry, not a laser scan.*scan topics: /scan"
    with pytest.raises(LogFormatError, match=msg):
        list(open_log(path, scan_topic="/odom"))
    with pytest.raises(LogFormatError, match=r"x\.bag: no topic /lidar; scan topics: /scan"):
        list(open_log(path, scan_topic="/lidar"))


def test_an_option_the_reader_does_not_take_lists_those_it_does(tmp_path: Path) -> None:
    path = tmp_path / "x.bag"
    write_rosbag(path, _scans(), "ros1")
    message = (
        r"x\.bag: the rosbag reader does not take these options \(.*'strict'\); it takes "
        r"scan_topic, odom_topic, .* \(strict: --skip-malformed, for CARMEN logs\)"
    )
    with pytest.raises(ConfigError, match=message):
        open_log(path, strict=False)
    log = tmp_path / "x.clf"
    log.write_text("FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 1.0 h 1.0\n")
    with pytest.raises(
        ConfigError, match=r"carmen reader .*'scan_topic'\); it takes strict, "
    ) as info:
        open_log(log, scan_topic="/scan")
    assert "--skip-malformed" not in str(info.value)


def test_bag_without_scans(tmp_path: Path) -> None:
    path = tmp_path / "empty.bag"
    write_rosbag(path, [], "ros1")
    with pytest.raises(LogFormatError, match=r"empty\.bag: topic /scan holds no messages"):
        list(open_log(path))


def test_no_tf_for_the_laser_frame(tmp_path: Path) -> None:
    path = tmp_path / "x.bag"
    write_rosbag(path, _scans(), "ros1")
    msg = r"x\.bag: topic /scan: no tf .* links base frame 'base_footprint' to laser frame 'laser'"
    with pytest.raises(LogFormatError, match=msg):
        list(open_log(path, base_frame="base_footprint"))


def test_cli_prints_one_line_and_exits_1_on_a_bad_bag(tmp_path: Path) -> None:
    path = tmp_path / "x.bag"
    write_rosbag(path, _scans(40), "ros1")
    result = runner.invoke(app, ["run", str(path), "--scan-topic", "/odom", "--no-progress"])
    assert result.exit_code == 1
    lines = result.output.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("iceg: error: ")
    assert "x.bag: topic /odom carries nav_msgs/msg/Odometry" in lines[0]
    data = path.read_bytes()
    path.write_bytes(data[: len(data) // 2])
    for command in ("info", "run"):
        result = runner.invoke(app, [command, str(path)])
        assert result.exit_code == 1
        lines = result.output.strip().splitlines()
        assert len(lines) == 1 and lines[0].startswith(f"iceg: error: {path}: cannot read")


def test_bad_options(tmp_path: Path) -> None:
    with pytest.raises(ConfigError, match="laser_frame_offset"):
        RosbagReader(tmp_path / "x.bag", laser_frame_offset=(1.0, 2.0))
    log = tmp_path / "x.clf"
    log.write_text("")
    with pytest.raises(ConfigError, match="carmen reader does not take"):
        open_log(log, scan_topic="/scan")
    result = runner.invoke(app, ["info", str(log), "--laser-frame-offset", "1,2"])
    assert result.exit_code == 1 and "X_M,Y_M,YAW_DEG" in result.output


def test_ros2_bag_folder_copy_is_found_by_its_metadata(tmp_path: Path) -> None:
    src = _bag_dir("turtlebot3-gazebo-ros2")
    dst = tmp_path / "bag_without_suffix"
    shutil.copytree(src, dst)
    assert isinstance(open_log(dst), RosbagReader)
    assert open_log(dst).count_scans() == 100


def test_without_rosbags_opening_a_bag_names_the_extra(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = tmp_path / "x.bag"
    write_rosbag(path, _scans(), "ros1")
    for name in ("rosbags", "rosbags.highlevel", "rosbags.typesys"):
        monkeypatch.setitem(sys.modules, name, None)
    with pytest.raises(LogFormatError, match=r"the 'ros' extra: pip install 'iceg\[ros\]'"):
        list(open_log(path))


def test_a_folder_holding_a_log_names_it(tmp_path: Path) -> None:
    # A ROS 1 bag's folder (the shared data's RC car) is no log: the error names the logs
    # it holds, not its other files.
    write_rosbag(tmp_path / "overtakes.bag", _scans(), "ros1")
    (tmp_path / "LICENSE.upstream").write_text("license\n")
    with pytest.raises(LogFormatError, match=r"it holds overtakes\.bag: pass the log file itself"):
        open_log(tmp_path)
    empty = tmp_path / "empty"
    empty.mkdir()
    with pytest.raises(LogFormatError, match=r"metadata\.yaml\)$"):  # nothing to name
        open_log(empty)
