"""Tests of the issue-11 worlds and scenarios: each world's defining property against exact
truth (corridor length and recesses, two-loop drift at the return, outdoor beam hits on
trees), and the biased odometry model against its closed form."""

from __future__ import annotations

import math

import numpy as np
import pytest

from frontends.simulate import (
    ACCURATE_ODOMETRY,
    SCENARIOS,
    LaserModel,
    OdometryModel,
    Pedestrian,
    World,
    cast_rays,
    corridor_recesses,
    default_trajectory,
    long_corridor_world,
    outdoor_layout,
    outdoor_world,
    ray_ranges,
    rectangle,
    simulate_scenario,
    tree_walls,
    two_loop_world,
    with_pedestrians,
    world_by_name,
)
from frontends.simulate.worlds import (
    LEG_RADIUS_M,
    LEG_SPACING_M,
    POST_HALF_SIDE_M,
    RECESS_DEPTH_RANGE_M,
    RECESS_SPACING_RANGE_M,
    TREE_RADIUS_RANGE_M,
    _distance_to_route,
)
from iceg_common.errors import ConfigError
from iceg_common.se2 import between, wrap_angle

EXACT = LaserModel(range_sigma_m=0.0)


def _path_length(poses: np.ndarray) -> float:
    return float(np.hypot(*np.diff(poses[:, :2], axis=0).T).sum())


# ------------------------------------------------------------------------ long corridor


def test_long_corridor_is_200_m_with_recesses_on_both_sides() -> None:
    # Truth: the layout drawn from corridor_recesses (0.9 m wide, 0.2-0.3 m deep, every
    # 3-8 m per side, irregular). Each recess adds 4 right-angle corners; the corridor's two
    # ends add 4 more; nothing else is a corner.
    w = world_by_name("long_corridor")
    rec = corridor_recesses()
    np.testing.assert_allclose(w.bounds()[:, 0], [0.0, 200.0])
    lo, hi = RECESS_DEPTH_RANGE_M
    np.testing.assert_allclose(
        w.bounds()[:, 1], [-rec[rec[:, 0] == 0, 2].max(), 2.0 + rec[rec[:, 0] == 1, 2].max()]
    )
    for side in (0, 1):
        centres = rec[rec[:, 0] == side, 1]
        assert centres.size >= 200.0 / RECESS_SPACING_RANGE_M[1]
        gaps = np.diff(centres)
        assert np.all((gaps >= RECESS_SPACING_RANGE_M[0]) & (gaps <= RECESS_SPACING_RANGE_M[1]))
        assert gaps.std() > 0.5  # irregular spacing
    assert np.all((rec[:, 2] >= lo) & (rec[:, 2] <= hi))
    assert w.corners().shape[0] == 4 * rec.shape[0] + 4
    assert w.wall_ends().shape[0] == 0


def test_long_corridor_ranges_into_recesses() -> None:
    # Truth: from the centre line (y = 1) a beam straight down reads 1 m to the wall, or
    # 1 m + depth at a recess centre; straight up likewise on the north side.
    w = long_corridor_world()
    rec = corridor_recesses()
    for side, centre, depth in rec[:10]:
        down = ray_ranges([centre, 1.0], np.array([-math.pi / 2, math.pi / 2]), w.walls)
        assert down[0 if side == 0 else 1] == pytest.approx(1.0 + depth, abs=1e-12)
    clear = [x for x in np.arange(5.0, 195.0, 0.37) if np.all(np.abs(rec[:, 1] - x) > 0.5)]
    r = np.array(
        [ray_ranges([x, 1.0], np.array([-math.pi / 2, math.pi / 2]), w.walls) for x in clear]
    )
    np.testing.assert_allclose(r, 1.0, atol=1e-12)


def test_long_corridor_route_end_to_end_with_accurate_odometry() -> None:
    # Truth: the route runs x 1 -> 199 on y = 1 (198 m); ACCURATE_ODOMETRY has no bias, so
    # the odometry path length is within its 0.5 % per-step noise of the true one.
    run = simulate_scenario("long_corridor", seed=0)
    t = run.true_poses
    np.testing.assert_allclose(t[[0, -1], :2], [[1.0, 1.0], [199.0, 1.0]], atol=1e-9)
    assert _path_length(t) == pytest.approx(198.0, abs=1e-9)
    assert run.odometry == ACCURATE_ODOMETRY
    assert _path_length(run.odom_poses) / 198.0 == pytest.approx(1.0, abs=2e-3)
    assert np.hypot(*(run.odom_poses[-1, :2] - t[-1, :2])) < 1.0


def test_long_corridor_rejects_bad_size() -> None:
    with pytest.raises(ConfigError):
        long_corridor_world(length_m=5.0)


# ------------------------------------------------------------------------ biased odometry


def test_biased_odometry_closed_form_on_straight_line() -> None:
    # Truth: n steps of length d along +x with scale error s and heading drift k (rad/m):
    # each odometry increment is (d (1+s), 0, k d); composing gives heading n k d and the
    # position d (1+s) sin(n k d / 2) / sin(k d / 2) (cos, sin)((n - 1) k d / 2).
    s, k_deg, d, n = 0.015, 0.4, 0.1, 500
    k = math.radians(k_deg)
    model = OdometryModel.biased(scale_error=s, heading_drift_deg_per_m=k_deg, noise=False)
    truth = np.column_stack([np.arange(n + 1) * d, np.zeros(n + 1), np.zeros(n + 1)])
    odom = model.simulate(truth, np.random.default_rng(0))
    a = k * d
    chord = d * (1 + s) * math.sin(n * a / 2) / math.sin(a / 2)
    expect = [chord * math.cos((n - 1) * a / 2), chord * math.sin((n - 1) * a / 2)]
    np.testing.assert_allclose(odom[-1, :2], expect, atol=1e-9)
    assert wrap_angle(odom[-1, 2] - n * a) == pytest.approx(0.0, abs=1e-12)
    assert model.rotation_bias_rad_per_m == pytest.approx(k, rel=1e-15)
    assert model.translation_sigma_per_m == 0.0


def test_office_biased_scenario_scale_and_heading_drift() -> None:
    # Truth: OdometryModel.biased(0.015, 0.4): each odometry increment is the true one with
    # its (dx, dy) scaled by 1.015 and 0.4 deg per metre added to dtheta, plus zero-mean
    # noise of known std (model.increment_sigmas). The along-track sum and the heading-error
    # sum must match the bias within 4 standard deviations of that noise.
    run = simulate_scenario("office_biased", seed=0)
    model = run.odometry
    assert model.translation_scale_bias == 0.015
    assert model.rotation_bias_rad_per_m == pytest.approx(math.radians(0.4), rel=1e-15)
    true_u = between(run.true_poses[:-1], run.true_poses[1:])
    odom_u = between(run.odom_poses[:-1], run.odom_poses[1:])
    sig = model.increment_sigmas(true_u)
    d = np.hypot(true_u[:, 0], true_u[:, 1])
    along = (odom_u[:, 0] * true_u[:, 0] + odom_u[:, 1] * true_u[:, 1]).sum() / (d**2).sum()
    sd_along = np.sqrt((sig[:, 0] ** 2 * d**2).sum()) / (d**2).sum()
    assert abs(along - 1.015) < 4 * sd_along
    heading_err = wrap_angle(odom_u[:, 2] - true_u[:, 2]).sum()
    sd_heading = np.sqrt((sig[:, 2] ** 2).sum())
    assert abs(heading_err - math.radians(0.4) * d.sum()) < 4 * sd_heading
    assert math.radians(0.4) * d.sum() > 4 * sd_heading  # the bias stands out of the noise
    assert np.linalg.norm(run.odom_poses[-1, :2] - run.true_poses[-1, :2]) > 1.0


# ------------------------------------------------------------------------ two loops


def test_two_loop_route_has_two_loops_back_at_start() -> None:
    # Truth: the route (1,1) -> round the west block (104 m) -> round the building (152 m).
    w = two_loop_world()
    t = default_trajectory(w)
    assert _path_length(t) == pytest.approx(256.0, abs=1e-9)
    at_start = np.hypot(t[:, 0] - 1.0, t[:, 1] - 1.0) < 1e-9
    visits = np.flatnonzero(np.diff(at_start.astype(int)) == 1) + 1
    assert visits.size == 2  # the return after loop 1 and after loop 2
    assert _path_length(t[: visits[0] + 1]) == pytest.approx(104.0, abs=1e-9)
    assert w.wall_ends().shape[0] > 20  # door frames break up the long walls


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_two_loop_odometry_drift_at_return_exceeds_20_m(seed: int) -> None:
    # Truth: the true final pose is the start; with 1 % scale error and 0.3 deg/m heading
    # drift over 256 m the odometry ends 26-32 m away (seeds 0-2): beyond any 10 m search.
    run = simulate_scenario("two_loop", seed=seed)
    np.testing.assert_allclose(run.true_poses[-1, :2], run.true_poses[0, :2], atol=1e-9)
    drift = float(np.hypot(*(run.odom_poses[-1, :2] - run.true_poses[-1, :2])))
    assert drift > 20.0


def test_two_loop_drift_without_noise_matches_bias() -> None:
    # Truth: with the bias only, the drift is deterministic; it also exceeds 20 m, so the
    # noise does not create the property.
    w = two_loop_world()
    t = default_trajectory(w)
    model = OdometryModel.biased(scale_error=0.01, heading_drift_deg_per_m=0.3, noise=False)
    odom = model.simulate(t, np.random.default_rng(0))
    assert np.hypot(*(odom[-1, :2] - t[-1, :2])) > 20.0
    total_turn = math.radians(0.3) * 256.0  # heading error at the end, rad
    assert wrap_angle(odom[-1, 2] - t[-1, 2]) == pytest.approx(wrap_angle(total_turn), abs=1e-9)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_open_loops_drift_beyond_search_and_laser_blind_between(seed: int) -> None:
    # Truth: the route passes the start (5, 5) after 160 m and ends there after 320 m. The
    # odometry (1 %, 0.3 deg/m) is > 15 m off at the first return and > 30 m at the second
    # (36-40 m for seeds 0-2). Only scans within ~20 m of the start area see anything: the
    # others have no valid beam, so scan matching cannot correct the drift.
    run = simulate_scenario("open_loops", seed=seed)
    t, o = run.true_poses, run.odom_poses
    at_start = np.flatnonzero(np.hypot(t[:, 0] - 5.0, t[:, 1] - 5.0) < 1e-9)
    first_return = at_start[np.flatnonzero(np.diff(at_start) > 1)[0] + 1]
    assert _path_length(t[: first_return + 1]) == pytest.approx(160.0, abs=1e-9)
    assert _path_length(t) == pytest.approx(320.0, abs=1e-9)
    assert np.hypot(*(o[first_return, :2] - t[first_return, :2])) > 15.0
    assert np.hypot(*(o[-1, :2] - t[-1, :2])) > 30.0
    n_valid = np.array([s.valid_mask().sum() for s in run.scans])
    blind = n_valid == 0
    assert blind.mean() > 0.75
    near_start = np.hypot(t[:, 0] - 5.0, t[:, 1] - 5.0) < 10.0
    assert np.all(n_valid[near_start] > 50)  # the start area is seen on every return


# ------------------------------------------------------------------------ outdoor


def test_outdoor_layout_trees_posts_and_clearance() -> None:
    lay = outdoor_layout()
    r = lay.trees[:, 2]
    assert lay.trees.shape == (70, 3) and lay.posts.shape == (20, 2)
    assert np.all((r >= TREE_RADIUS_RANGE_M[0]) & (r <= TREE_RADIUS_RANGE_M[1]))
    w = outdoor_world()
    t = default_trajectory(w)
    # Every object is at least 1.2 m from every true pose (clearance minus its radius).
    d_tree = np.hypot(*(t[:, None, :2] - lay.trees[None, :, :2]).transpose(2, 0, 1))
    assert np.all(d_tree - lay.trees[None, :, 2] > 1.2 - TREE_RADIUS_RANGE_M[1])
    lengths = np.linalg.norm(w.walls[:, 1] - w.walls[:, 0], axis=1)
    assert int((lengths > 5.0).sum()) == 2  # the few long walls
    # Tree polygons are inscribed: vertices exactly on the circle.
    v = tree_walls(lay.trees[:1])[:, 0]
    np.testing.assert_allclose(np.hypot(*(v - lay.trees[0, :2]).T), lay.trees[0, 2], atol=1e-12)


def test_outdoor_beam_hits_mostly_on_trees_and_posts() -> None:
    # Truth: a beam's hit is on a tree or post iff the range against trees and posts alone
    # equals the range against the whole world. Over the route most hits are on them.
    lay = outdoor_layout()
    w = outdoor_world()
    posts = np.array(
        [
            rectangle(
                x - POST_HALF_SIDE_M,
                y - POST_HALF_SIDE_M,
                x + POST_HALF_SIDE_M,
                y + POST_HALF_SIDE_M,
            )
            for x, y in lay.posts
        ]
    ).reshape(-1, 2, 2)
    objects = np.concatenate([tree_walls(lay.trees), posts])
    t = default_trajectory(w)[::10]
    angles = EXACT.angles_rad()
    n_hits = n_obj = 0
    for pose in t:
        r_all = cast_rays(w, pose, EXACT)
        r_obj = ray_ranges(pose[:2], pose[2] + angles, objects)
        hit = r_all < EXACT.range_max_m
        n_hits += int(hit.sum())
        n_obj += int((hit & (np.abs(r_obj - r_all) < 1e-9)).sum())
    assert n_hits > 0
    assert n_obj / n_hits > 0.6


# ------------------------------------------------------------------------ scenarios


def test_scenarios_registered_and_deterministic() -> None:
    names = {"office", "corridor", "office_biased", "long_corridor", "two_loop", "open_loops"}
    assert names | {"outdoor"} <= set(SCENARIOS)
    a = simulate_scenario("outdoor", seed=4)
    b = simulate_scenario("outdoor", seed=4)
    np.testing.assert_array_equal(a.odom_poses, b.odom_poses)
    np.testing.assert_array_equal(a.scans[7].ranges_m, b.scans[7].ranges_m)
    with pytest.raises(ConfigError, match="unknown scenario"):
        simulate_scenario("moon")


def test_a_scenario_driven_with_another_laser() -> None:
    # The same route and odometry seen through a 270-degree, 0.25-degree, 30 m scanner: its
    # bearings span 270 degrees in 1081 beams; from the first pose (10, 1), on the axis of
    # the 2 m wide corridor, the beams at -90 and +90 degrees meet the walls at 1 m (within
    # 5 sigmas of the 1 cm noise), and the beam straight ahead, 30 m to the corridor's end,
    # returns nothing.
    utm = LaserModel(n_beams=1081, fov_deg=270.0, range_max_m=30.0)
    default = simulate_scenario("corridor", seed=2)
    run = simulate_scenario("corridor", seed=2, laser=utm)
    np.testing.assert_array_equal(run.odom_poses, default.odom_poses)
    np.testing.assert_array_equal(run.true_poses[0], [10.0, 1.0, 0.0])
    scan = run.scans[0]
    assert default.scans[0].n_beams == 181 and scan.n_beams == 1081
    assert math.degrees(scan.angles_rad[-1] - scan.angles_rad[0]) == pytest.approx(270.0)
    np.testing.assert_allclose(np.degrees(scan.angles_rad[[180, 900]]), [-90.0, 90.0])
    np.testing.assert_allclose(scan.ranges_m[[180, 900]], 1.0, atol=0.05)
    assert scan.ranges_m[540] >= scan.range_max_m == 30.0


# ------------------------------------------------------------------------ pedestrians


def test_a_pedestrian_walks_its_path_back_and_forth() -> None:
    # A 7 m path (4 m east, then 3 m north) at 1 m/s from its start: at 2 s 2 m along the
    # first leg heading east, at 5.5 s 1.5 m up the second heading north, at 8 s on the way
    # back (14 - 8 = 6 m along: 2 m up the second leg) heading south, and at 14 s back at
    # the start heading east again; a start of -1 m is 13 m along the there-and-back walk.
    walker = Pedestrian(np.array([[0.0, 0.0], [4.0, 0.0], [4.0, 3.0]]), speed_mps=1.0)
    for t, xy, heading in (
        (2.0, [2.0, 0.0], [1.0, 0.0]),
        (5.5, [4.0, 1.5], [0.0, 1.0]),
        (8.0, [4.0, 2.0], [0.0, -1.0]),
        (14.0, [0.0, 0.0], [1.0, 0.0]),
    ):
        p, u = walker.pose_at(t)
        np.testing.assert_allclose(p, xy, atol=1e-12)
        np.testing.assert_allclose(u, heading, atol=1e-12)
    back = Pedestrian(walker.path_xy, speed_mps=1.0, start_m=-1.0)
    np.testing.assert_allclose(back.pose_at(0.0)[0], [1.0, 0.0], atol=1e-12)


def test_a_pedestrian_is_two_legs_a_beam_hits() -> None:
    # Walking north along x = 2 and at (2, 0) at 0 s, with no swing: the legs' centres are
    # LEG_SPACING_M / 2 either side across the walk, at x = 1.87 and 2.13. The 16-gon of the
    # nearer leg has a vertex pointing at the laser, so the beam along +x from the origin
    # ends exactly LEG_RADIUS_M before its centre; without the time (static walls only) it
    # reaches the wall at x = 10.
    walker = Pedestrian(
        np.array([[2.0, -1.0], [2.0, 1.0]]), speed_mps=1.0, start_m=1.0, stride_m=0.0
    )
    legs = walker.legs_at(0.0).reshape(2, -1, 2, 2)
    centres = legs[:, :, 0].mean(axis=1)
    np.testing.assert_allclose(
        centres, [[2.0 - LEG_SPACING_M / 2, 0.0], [2.0 + LEG_SPACING_M / 2, 0.0]], atol=1e-12
    )
    world = World("lane", np.array([[[10.0, -5.0], [10.0, 5.0]]]), pedestrians=(walker,))
    ahead = int(np.flatnonzero(EXACT.angles_rad() == 0.0)[0])
    assert world.is_dynamic
    assert cast_rays(world, [0.0, 0.0, 0.0], EXACT, stamp_s=0.0)[ahead] == pytest.approx(
        2.0 - LEG_SPACING_M / 2 - LEG_RADIUS_M, abs=1e-12
    )
    assert cast_rays(world, [0.0, 0.0, 0.0], EXACT)[ahead] == pytest.approx(10.0, abs=1e-12)


def test_a_pedestrian_needs_a_path_and_a_speed() -> None:
    with pytest.raises(ConfigError, match="consecutive waypoints"):
        Pedestrian(np.array([[0.0, 0.0], [0.0, 0.0], [1.0, 0.0]]))
    with pytest.raises(ConfigError, match="shape"):
        Pedestrian(np.array([[0.0, 0.0]]))
    with pytest.raises(ConfigError, match="speed_mps"):
        Pedestrian(np.array([[0.0, 0.0], [1.0, 0.0]]), speed_mps=0.0)
    with pytest.raises(ConfigError, match="default route"):
        with_pedestrians(World("bare", np.array([[[0.0, 0.0], [1.0, 0.0]]])), 2)


def test_people_walk_the_route_within_their_offset() -> None:
    # Each person walks the route moved by at most 0.6 m in x and in y: at any time within
    # 0.6 * sqrt(2) of the route; the same seed gives the same people.
    world = with_pedestrians(world_by_name("office"), 6, seed=3)
    again = with_pedestrians(world_by_name("office"), 6, seed=3)
    route = world.route_xy
    assert route is not None and len(world.pedestrians) == 6
    for walker, twin in zip(world.pedestrians, again.pedestrians, strict=True):
        np.testing.assert_array_equal(walker.legs_at(12.3), twin.legs_at(12.3))
        where = np.array([walker.pose_at(float(t))[0] for t in np.linspace(0.0, 200.0, 41)])
        assert np.all(_distance_to_route(where, route) <= 0.6 * math.sqrt(2.0) + 1e-9)
    assert "office_people" in SCENARIOS
    assert len(simulate_scenario("office_people", seed=0).world.pedestrians) == 10


def test_a_scanner_drops_beams_in_runs() -> None:
    # dropout_fraction 0.05 in runs of 3: run starts drawn with probability 0.05 / 3 per
    # beam, so about 5 % of the beams of a closed room (every beam hits a wall) read no
    # return, and no dropped beam inside the scan stands alone (runs of three; only a run
    # cut by the scan's end can be shorter). Without dropouts nothing is dropped.
    room = World("room", np.array(rectangle(-3.0, -3.0, 3.0, 3.0)))
    laser = LaserModel(dropout_fraction=0.05, dropout_run_beams=3)
    rng = np.random.default_rng(4)
    drops = [cast_rays(room, np.zeros(3), laser, rng) >= laser.range_max_m for _ in range(200)]
    assert np.mean(drops) == pytest.approx(0.05, abs=0.01)
    for d in drops:
        inner = d[1:-1] & ~d[:-2] & ~d[2:]
        assert not inner.any()
    clean = cast_rays(room, np.zeros(3), LaserModel(), np.random.default_rng(4))
    assert np.all(clean < LaserModel().range_max_m)
