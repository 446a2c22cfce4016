"""The robot's own body in its scans: turns chosen by hand, posts on a simulated robot found
at their bearings and range (and nothing found without them), and a run that warns with the
value that leaves them out of its points, features and map."""

from __future__ import annotations

import logging
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from frontends import LaserScan
from frontends.carmen import write_carmen
from frontends.simulate import LaserModel, office_world, simulate
from iceg.batch_run import RunTask, execute_run
from iceg.config import IcegConfig
from iceg.grid import render
from iceg.pipeline import run_log
from iceg.robot_body import (
    BIN_DEG,
    DARK_BIN_DEG,
    READ_THROUGH_SCANS,
    ComparedBeams,
    body_reach,
    robot_body_range,
    turn_pairs,
)
from iceg.scan_store import ScanStore

POSTS_DEG = (45.0, 135.0, -135.0, -45.0)
#: A 360° lidar under a plate on four standoffs, 0.18 m from it.
AMONG_POSTS = LaserModel(
    n_beams=361, fov_deg=360.0, range_max_m=8.0, range_sigma_m=0.02, body_posts_deg=POSTS_DEG
)
#: The range that leaves out every return of the posts: their faces lie 0.18-0.1825 m from
#: the laser (0.03 m half width), and of the thousands of returns compared (about 38 bins of
#: a few hundred scans) the farthest lies 3-5 sigma of the 2 cm noise beyond; rounded up to
#: the centimetre.
POSTS_REACH_M = (0.18 + 3 * 0.02, 0.1825 + 5 * 0.02 + 0.01)


def test_turn_pairs_by_hand() -> None:
    # Ten scans turning 0.2 rad (11.5 deg) a step in place, then five driving 0.5 m a step
    # straight on. A pair needs 30-90 deg of turn within 1 m of travel: scan k pairs with
    # k + 3 (0.6 rad = 34 deg) up to scan 6 -> 9; scans 7 and 8 reach at most 0.4 rad
    # before the turn ends, and the drive does not turn.
    spin = [[0.0, 0.0, 0.2 * k] for k in range(10)]
    drive = [[0.5 * k, 0.0, 1.8] for k in range(1, 6)]
    pairs = turn_pairs(np.array(spin + drive))
    np.testing.assert_array_equal(pairs, [[k, k + 3] for k in range(7)])
    # A turn of more than three times 30 deg between two scans is not taken (the world may
    # have come round to look the same); neither is one across more than 1 m of travel.
    assert turn_pairs(np.array([[0.0, 0.0, 0.0], [0.0, 0.0, 1.7]])).shape == (0, 2)
    assert turn_pairs(np.array([[0.0, 0.0, 0.0], [1.1, 0.0, 0.6]])).shape == (0, 2)
    # A scan without a pose pairs with nothing, nor does a turn across it (its travel is
    # unknown); the headings after it are unwrapped as before.
    hole = np.array(spin + drive)
    hole[4] = np.nan
    np.testing.assert_array_equal(turn_pairs(hole), [[0, 3], [5, 8], [6, 9]])
    far = np.array([[0.0, 0.0, 0.0], [np.nan] * 3, [0.0, 0.0, 0.0], [5.0, 0.0, 0.6]])
    assert turn_pairs(far).shape == (0, 2)  # 5 m of travel after the hole
    # An odometry break just before scan 4: the pairs that span it, (1, 4) to (3, 6), go.
    breaks = np.zeros(15, dtype=bool)
    breaks[4] = True
    np.testing.assert_array_equal(
        turn_pairs(np.array(spin + drive), breaks), [[0, 3], [4, 7], [5, 8], [6, 9]]
    )


def test_compared_beams_are_the_compared_scans_beams_across_near_and_far_gaps() -> None:
    # Scans of 3-5 beams with their own range limits and laser yaws; the compared ones come
    # back to back, a few scans apart (read along with the scans between) and farther apart
    # than READ_THROUGH_SCANS (read on their own). Each beam is its scan's own, in order.
    rng = np.random.default_rng(5)
    scans = [
        LaserScan(
            float(k),
            np.r_[rng.uniform(0.05, 9.0, 2 + k % 3), np.inf],
            np.sort(rng.uniform(-3.0, 3.0, 3 + k % 3)),
            0.1 + 0.01 * (k % 2),
            8.0,
            np.zeros(3),
            laser_offset=np.array([0.1, 0.0, 0.05 * (k % 4)]),
        )
        for k in range(70)
    ]
    store = ScanStore(scans)
    compared = np.array([0, 1, 2, 6, 7, 7 + READ_THROUGH_SCANS + 2, 60, 69])
    beams = ComparedBeams.of(store, compared)
    expect = [scans[k] for k in compared.tolist()]
    assert beams.n_scans == len(expect)
    np.testing.assert_array_equal(
        beams.row, np.repeat(np.arange(len(expect)), [s.n_beams for s in expect])
    )
    np.testing.assert_array_equal(beams.range_m, np.concatenate([s.ranges_m for s in expect]))
    np.testing.assert_array_equal(
        beams.bearing_rad, np.concatenate([s.angles_rad + s.laser_offset[2] for s in expect])
    )
    valid = [(s.ranges_m > s.range_min_m) & (s.ranges_m < s.range_max_m) for s in expect]
    np.testing.assert_array_equal(beams.ok, np.concatenate(valid))
    np.testing.assert_array_equal(
        beams.none, np.concatenate([s.ranges_m >= s.range_max_m for s in expect])
    )


def test_the_body_s_reach_is_its_farthest_return_by_hand() -> None:
    # Two scans of five beams 0.5 deg apart, in the bin ahead (bearings 0 to 2 deg). A body
    # return is any from the nearest up to the first gap of more than 5 cm in range order:
    # scan 0 holds 0.18, 0.20, 0.24 (the body's noisy face), then 0.60 (a wall past its
    # edge); scan 1 holds 0.19 and 0.23, then 0.29 (6 cm on: the world) and beyond. The
    # farthest body return is 0.24 m. The nearest of each scan alone (0.18, 0.19) would fall
    # short of the face's noise.
    angles = np.radians([0.25, 0.75, 1.25, 1.75, 90.0])
    ranges = [[0.20, 0.18, 0.60, 0.24, 3.0], [0.29, 0.23, 0.19, 2.0, 0.21]]
    store = ScanStore(
        [
            LaserScan(float(k), np.array(r), angles, 0.01, 8.0, np.zeros(3))
            for k, r in enumerate(ranges)
        ]
    )
    ahead = round(180.0 / BIN_DEG)  # the bin from 0 to 2 deg
    both = ComparedBeams.of(store, np.array([0, 1]))
    assert body_reach(both, np.array([ahead])) == pytest.approx(0.24)
    # The bin at 90 deg holds 3.0 and 0.21: its own nearest runs.
    side = round(270.0 / BIN_DEG)
    assert body_reach(both, np.array([side])) == pytest.approx(3.0)
    second = ComparedBeams.of(store, np.array([1]))
    assert body_reach(second, np.array([ahead, side])) == pytest.approx(0.23)


@pytest.fixture(scope="module")
def among_posts() -> tuple[list[LaserScan], np.ndarray]:
    run = simulate(office_world(), laser=AMONG_POSTS, seed=0)
    return run.scans, run.true_poses


def test_posts_on_the_robot_are_found_and_a_world_alone_is_not(among_posts) -> None:  # type: ignore[no-untyped-def]
    scans, poses = among_posts
    est = robot_body_range(ScanStore(scans), poses)
    assert est is not None and est.pairs >= 100
    # Every post is found, and every bin found lies on a post (a face 6 cm wide at 0.18 m
    # spans 19 deg: its 2-deg bins lie within 9.5 + 2 deg of its bearing).
    found = np.array(est.bearings_deg)
    gap = np.abs((found[:, None] - np.array(POSTS_DEG)[None] + 180.0) % 360.0 - 180.0)
    assert np.all(gap.min(axis=1) <= 11.5)
    assert np.all(gap.min(axis=0) <= 2.0)
    # The value to set: the farthest return of the posts' faces.
    assert POSTS_REACH_M[0] <= est.range_m <= POSTS_REACH_M[1]
    # The same world and route without posts: many turns compared, no body.
    plain = simulate(office_world(), laser=AMONG_POSTS.model_copy(update={"body_posts_deg": ()}))
    none = robot_body_range(ScanStore(plain.scans), plain.true_poses)
    assert none is not None and none.range_m is None and none.pairs == est.pairs
    # Scans without a single return (open ground) are compared too, and show no body.
    dark = [replace(s, ranges_m=np.full(s.n_beams, np.inf)) for s in plain.scans]
    empty = robot_body_range(ScanStore(dark), plain.true_poses)
    assert empty is not None and empty.range_m is None


def _dark(scans: list[LaserScan]) -> list[LaserScan]:
    """The posts as a driver reports a body inside its range_min: no return (+inf)."""
    return [replace(s, ranges_m=np.where(s.ranges_m < 0.3, np.inf, s.ranges_m)) for s in scans]


def test_posts_read_as_no_return_are_found_by_their_dark_bearings(among_posts) -> None:  # type: ignore[no-untyped-def]
    scans, poses = among_posts
    est = robot_body_range(ScanStore(_dark(scans)), poses)
    assert est is not None and est.range_m is None  # no return of the posts is left
    # Four intervals, one per post, each within its shadow (a face 6 cm wide at 0.18 m hides
    # 9.5 deg either side of its bearing) and covering most of it.
    assert len(est.dark_deg) == 4
    for (lo, hi), post in zip(sorted(est.dark_deg), sorted(POSTS_DEG), strict=True):
        assert post - 9.5 - DARK_BIN_DEG <= lo < hi <= post + 9.5 + DARK_BIN_DEG
        assert hi - lo >= 15.0
    # Open ground is dark in both scans of a turn: no evidence. Without posts, nothing.
    plain = simulate(office_world(), laser=AMONG_POSTS.model_copy(update={"body_posts_deg": ()}))
    none = robot_body_range(ScanStore(plain.scans), plain.true_poses)
    assert none is not None and none.dark_deg == ()
    dark = [replace(s, ranges_m=np.full(s.n_beams, np.inf)) for s in plain.scans]
    empty = robot_body_range(ScanStore(dark), plain.true_poses)
    assert empty is not None and empty.dark_deg == ()


def test_a_run_among_dark_posts_reads_them_as_too_close(
    among_posts,  # type: ignore[no-untyped-def]
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
) -> None:
    scans, _ = among_posts
    log = tmp_path / "dark.clf"
    write_carmen(log, _dark(scans[:300]), laser_record="ROBOTLASER1")
    cfg = IcegConfig.model_validate({"slam": {"workers": 2}})
    with caplog.at_level(logging.WARNING, logger="iceg.pipeline"):
        auto = run_log(log, cfg)
    body = auto.metrics["robot_body"]
    assert len(body["dark_deg"]) == 4 and body["range_m"] == 0.0
    assert "hold no return where the turned scans see the world" in caplog.text
    assert "features.robot_body_dark_deg: [[" in caplog.text
    # the run of those bearings set by hand, bit for bit
    features = cfg.features.model_copy(
        update={"robot_body_dark_deg": auto.config.features.robot_body_dark_deg}
    )
    by_hand = run_log(log, cfg.model_copy(update={"features": features}))
    assert by_hand.poses.tobytes() == auto.poses.tobytes()


@pytest.mark.parametrize("workers", [1, 2])
def test_a_run_among_posts_leaves_them_out_as_if_the_value_were_set(
    among_posts,  # type: ignore[no-untyped-def]
    tmp_path: Path,
    caplog: pytest.LogCaptureFixture,
    workers: int,
) -> None:
    scans, _ = among_posts
    log = tmp_path / "posts.clf"
    write_carmen(log, scans[:300], laser_record="ROBOTLASER1")
    cfg = IcegConfig.model_validate({"slam": {"workers": workers}})
    # Measured along the odometry before the first scan, the posts are left out, with a
    # warning that names the value; the trajectory shows the same posts (its farthest
    # return, in other scans, within a centimetre), and no second warning.
    with caplog.at_level(logging.WARNING, logger="iceg.pipeline"):
        auto = run_log(log, cfg)
    body = auto.metrics["robot_body"]
    value = body["range_m"]
    assert value == body["on_odometry"]["range_m"] == auto.config.features.robot_body_range_m
    assert POSTS_REACH_M[0] <= value <= POSTS_REACH_M[1]
    assert f"they are left out (features.robot_body_range_m: {value:.2f}" in caplog.text
    assert abs(body["on_trajectory"]["range_m"] - value) <= 0.01 + 1e-9
    assert "to leave them out" not in caplog.text
    # The run is the one of that value set by hand (the helpers restarted with it): the
    # same trajectory, bit for bit, and no warning.
    caplog.clear()
    features = cfg.features.model_copy(update={"robot_body_range_m": value})
    with caplog.at_level(logging.WARNING, logger="iceg.pipeline"):
        by_hand = run_log(log, cfg.model_copy(update={"features": features}))
    assert "robot_body_range_m" not in caplog.text
    assert by_hand.poses.tobytes() == auto.poses.tobytes()
    # Not measured, the posts stay in: the run differs, and its trajectory warns with the
    # value to set.
    caplog.clear()
    kept = cfg.features.model_copy(update={"measure_robot_body": False})
    with caplog.at_level(logging.WARNING, logger="iceg.pipeline"):
        off = run_log(log, cfg.model_copy(update={"features": kept}))
    assert off.metrics["robot_body"]["range_m"] == 0.0
    assert off.metrics["robot_body"]["on_odometry"] is None
    found = off.metrics["robot_body"]["on_trajectory"]["range_m"]
    assert f"to leave them out, set features.robot_body_range_m: {found:.2f}" in caplog.text
    assert off.poses.tobytes() != auto.poses.tobytes()


def test_the_map_of_one_scan_draws_the_posts_unless_left_out(among_posts) -> None:  # type: ignore[no-untyped-def]
    scans, poses = among_posts
    # The map of one scan: the posts' faces are occupied cells 0.18 m from the robot, unless
    # the option's range leaves them out (over a run, the rays of the next scans clear them).
    for floor_m, drawn in ((0.0, True), (0.25, False)):
        grid = render(scans[:1], poses[:1], range_min_m=floor_m)
        xy = grid.cell_to_world(np.argwhere(grid.binary()))
        near = np.linalg.norm(xy - poses[0, :2], axis=1) < 0.25
        assert (np.count_nonzero(near) >= 4) == drawn


def test_a_batch_run_among_posts_measures_them_too(among_posts, tmp_path: Path) -> None:  # type: ignore[no-untyped-def]
    scans, _ = among_posts
    log = tmp_path / "posts.clf"
    write_carmen(log, scans[:300], laser_record="ROBOTLASER1")
    rows = {}
    for variant, features in (("auto", {}), ("kept", {"measure_robot_body": False})):
        task = RunTask(
            run_id=variant,
            key=variant,
            log_name="posts",
            variant=variant,
            seed=None,
            source=str(log),
            config={"features": features},
            folder=str(tmp_path / variant),
            outputs="metrics",
        )
        rows[variant] = execute_run(task)
    # the same range as iceg run measures on the same log (the test above), and none kept
    assert rows["auto"]["status"] == rows["kept"]["status"] == "ok"
    body_m = rows["auto"]["metrics"]["robot_body_range_m"]
    assert POSTS_REACH_M[0] <= body_m <= POSTS_REACH_M[1]
    assert rows["kept"]["metrics"]["robot_body_range_m"] == 0.0
