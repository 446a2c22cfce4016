"""Localization in a saved map and ``--continue`` on simulated worlds with exact truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from typer.testing import CliRunner

from frontends.carmen import write_carmen
from frontends.simulate import office_world, simulate, simulate_scenario
from iceg import session
from iceg.cli import app
from iceg.continuation import continue_scans, fixed_map_of, place_start
from iceg.evaluation import position_errors
from iceg.features import extract
from iceg.localize import LocalizeSettings, Status, fixed_map_of_session, localize_scans
from iceg.slam import Slam
from iceg_common import se2
from iceg_common.errors import SessionError

K, N = 260, 450  # the session covers scans [0, K); the second "log" is [K, N)
OTHER_FRAME = np.array([3.0, -7.0, 1.0])  # the second log's odometry frame


def _reframe(scans):  # type: ignore[no-untyped-def]
    return [dataclasses.replace(s, odom_pose=se2.compose(OTHER_FRAME, s.odom_pose)) for s in scans]


@pytest.fixture(scope="module")
def office(tmp_path_factory):  # type: ignore[no-untyped-def]
    run = simulate(office_world(), seed=1)
    folder = tmp_path_factory.mktemp("loc") / "first"
    slam = Slam()
    for scan in run.scans[:K]:
        slam.process(scan)
    slam.finish()
    session.save(slam, folder)
    return run, folder


def _err(poses, truth):  # type: ignore[no-untyped-def]
    return np.hypot(*(poses[:, :2] - truth[:, :2]).T)


def test_localize_without_initial_pose_tracks_the_map(office) -> None:  # type: ignore[no-untyped-def]
    run, folder = office
    s = session.read(folder)
    result = localize_scans(fixed_map_of_session(s), _reframe(run.scans[120:K]))
    assert result.status[0] == Status.PLACED
    assert np.all(result.status > Status.LOST)
    assert _err(result.poses, run.true_poses[120:K]).max() < 0.05
    assert np.all(np.linalg.eigvalsh(result.covs) > 0)
    assert s.arrays["g_kind"].shape == session.read(folder).arrays["g_kind"].shape  # untouched


def test_repeated_global_placement_reuses_places_and_gives_the_same_pose(office) -> None:  # type: ignore[no-untyped-def]
    # The second placement matches the places' references built by the first: the same
    # answers bit for bit as a fresh map, and each at the scan's true pose.
    run, folder = office
    fixed = fixed_map_of_session(session.read(folder))
    settings = LocalizeSettings()
    for i in (120, 180, 240):
        feats = extract(run.scans[i], fixed.config.features)
        first, again = fixed.place(feats, settings), fixed.place(feats, settings)
        fresh = fixed_map_of_session(session.read(folder)).place(feats, settings)
        assert first is not None and again is not None and fresh is not None
        for p in (again, fresh):
            assert p.anchor == first.anchor
            assert p.pose.tobytes() == first.pose.tobytes()
            assert p.match.cov.tobytes() == first.match.cov.tobytes()
        e = se2.between(run.true_poses[i], first.pose)
        assert np.hypot(e[0], e[1]) < 0.05 and abs(e[2]) < np.radians(1.0)
    assert 0 < len(fixed._places) <= fixed.candidates(settings.candidate_spacing_m).shape[0]


def test_localize_from_a_wrong_initial_pose(office) -> None:  # type: ignore[no-untyped-def]
    run, folder = office
    fixed = fixed_map_of_session(session.read(folder))
    wrong = run.true_poses[120] + np.array([4.0, -3.0, 1.0])
    result = localize_scans(fixed, run.scans[120:200], initial_pose=wrong)
    assert result.relocalizations >= 1
    ok = result.status > Status.LOST
    assert ok[:5].all()
    assert _err(result.poses[ok], run.true_poses[120:200][ok]).max() < 0.05


def test_localize_recovers_after_a_kidnapping(office) -> None:  # type: ignore[no-untyped-def]
    run, folder = office
    fixed = fixed_map_of_session(session.read(folder))
    # carried from scan 170 to scan 220: the odometry does not see it
    before, after = list(run.scans[120:170]), list(run.scans[220:K])
    jump = se2.between(after[0].odom_pose, before[-1].odom_pose)
    carried = [dataclasses.replace(s, odom_pose=se2.compose(jump, s.odom_pose)) for s in after]
    result = localize_scans(fixed, before + carried)
    truth = np.concatenate([run.true_poses[120:170], run.true_poses[220:K]])
    assert result.relocalizations >= 2  # the start, and after the kidnapping
    tail = slice(len(before) + 30, None)  # recovered within 30 scans (corridor aliasing)
    assert np.all(result.status[tail] > Status.LOST)
    assert _err(result.poses[tail], truth[tail]).max() < 0.05


def test_a_log_of_another_building_is_refused(office) -> None:  # type: ignore[no-untyped-def]
    _, folder = office
    other = simulate_scenario("outdoor", seed=2).scans[:40]
    later = [dataclasses.replace(s, stamp_s=s.stamp_s + 1000.0) for s in other]
    with pytest.raises(SessionError, match="cannot be placed"):
        continue_scans(folder, later)
    result = localize_scans(fixed_map_of_session(session.read(folder)), later)
    assert np.all(result.status == Status.LOST)


def test_continue_extends_the_graph_as_well_as_one_run(office) -> None:  # type: ignore[no-untyped-def]
    run, folder = office
    whole = Slam()
    for scan in run.scans[:N]:
        whole.process(scan)
    w = whole.finish()
    c = continue_scans(folder, _reframe(run.scans[K:N]))
    n_old = session.read(folder).arrays["g_node_ids"].shape[0]
    assert c.node_ids.shape[0] > n_old
    link = [f for f in c.factors if f.j == n_old]
    assert [f.kind.value for f in link] == ["loop_closure"]  # placed, no odometry across
    assert c.slam is not None and c.slam.export_state().segment_start == n_old  # own local map
    # every node is a place the global loop-closure search can find, the placed one included
    places = c.slam.loop_closer.places.export_state()["ids"]
    np.testing.assert_array_equal(places, c.node_ids)
    e_cont = position_errors(c.poses[K:], run.true_poses[K:N]).mean_m
    e_whole = position_errors(w.poses[K:], run.true_poses[K:N]).mean_m
    assert e_cont < 1.1 * e_whole + 0.005


def test_cli_continue_and_localize(office, tmp_path) -> None:  # type: ignore[no-untyped-def]
    run, folder = office
    log = tmp_path / "second.clf"
    write_carmen(log, _reframe(run.scans[K:N]))
    runner = CliRunner()
    r = runner.invoke(
        app, ["localize", str(log), "--map", str(folder), "--out", str(tmp_path / "l")]
    )
    assert r.exit_code == 0, r.output
    assert {"trajectory.tum", "localization.csv", "map.png", "metrics.json"} <= {
        p.name for p in (tmp_path / "l").iterdir()
    }
    r = runner.invoke(
        app,
        ["run", str(log), "--continue", str(folder), "--out", str(tmp_path / "c"), "--no-progress"],
    )
    assert r.exit_code == 0, r.output
    cont = session.read(tmp_path / "c")
    assert cont.arrays["s_stamp"].shape[0] == N
    assert len(cont.manifest["logs"]) == 1  # the first half came from memory (inline)
    # the new log's first node, found again from the graph when the session is loaded
    assert session.segment_start(cont.arrays) == session.read(folder).manifest["nodes"]


def test_scans_before_the_placed_one_are_tracked_backwards(office) -> None:  # type: ignore[no-untyped-def]
    # Truth: the simulator's poses (the session's map frame is the world frame). The new log
    # starts with the robot turning 72 deg in place; its first 8 scans carry a frozen
    # odometry, all equal to that of scan 8, the one placed: odometry lagging behind the
    # robot, as in MIT CSAIL's fast turns. Carried by odometry they would all take scan 8's
    # heading; tracked backwards from it (each matched against the scan after it), each
    # lands on its true pose.
    run, folder = office
    new = list(run.scans[K : K + 9])
    new[:8] = [dataclasses.replace(s, odom_pose=new[8].odom_pose) for s in new[:8]]
    truth = run.true_poses[K : K + 9]
    assert abs(np.degrees(truth[8, 2] - truth[0, 2])) > 60.0  # the robot did turn
    slam = session.load(folder)
    k, placement = place_start(fixed_map_of(slam), new[8:], initial_pose=truth[8])
    assert k == 0
    slam.start_segment(new[8], placement.anchor, placement.match, before=new[:8])
    _, poses = slam.trajectory()
    assert _err(poses[-9:], truth).max() < 0.05
    heading = np.degrees(np.abs(np.angle(np.exp(1j * (poses[-9:, 2] - truth[:, 2])))))
    assert heading.max() < 1.0
