"""Reused nodes (``slam.reuse_nodes``, a reduced pose graph): a revisit hangs from the old
nodes instead of adding new ones, against the simulated truth; a session split while a
revisit hangs from an old node continues bit for bit, and two workers, or searches decided at
the next keyframe, give the same run."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.simulate import office_world, simulate
from graph import FactorKind
from iceg import session
from iceg.config import config_from_dict
from iceg.evaluation import position_errors
from iceg.feature_map import FeatureMap, MapCheckpoint
from iceg.match_pool import MatchPool
from iceg.pipeline import run_scans
from iceg.results import SlamResult
from iceg.slam import Anchor, Slam
from iceg_common import se2

REUSE = {"slam": {"reuse_nodes": True}}


@pytest.fixture(scope="module")
def two_laps():  # type: ignore[no-untyped-def]
    """The office loop driven twice along the same true poses (1401 scans, 5 Hz)."""
    world = office_world()
    lap = simulate(world, seed=1).true_poses
    return simulate(world, trajectory=np.concatenate([lap, lap[1:]]), seed=1), lap.shape[0]


def _run(scans, config: dict) -> tuple[Slam, SlamResult]:  # type: ignore[no-untyped-def]
    slam = Slam(config_from_dict(config))
    for scan in scans:
        slam.process(scan)
    return slam, slam.finish()


@pytest.fixture(scope="module")
def reused(two_laps):  # type: ignore[no-untyped-def]
    run, _ = two_laps
    return _run(run.scans, REUSE)


def _leaving_nodes(result: SlamResult) -> list[int]:
    """The nodes that end a revisit: no odometry factor from the node before them."""
    sequential = {f.j for f in result.factors if f.kind is FactorKind.ODOMETRY and f.j == f.i + 1}
    return [j for j in result.node_ids.tolist()[1:] if j not in sequential]


def test_the_second_lap_hangs_from_the_first_laps_nodes(two_laps, reused) -> None:  # type: ignore[no-untyped-def]
    run, lap_scans = two_laps
    slam, result = reused
    first_lap_nodes = int(np.sum(result.node_scan_index < lap_scans))
    second_lap_nodes = len(result.node_ids) - first_lap_nodes
    # without reused nodes the second lap adds as many nodes as the first (about 500); with
    # them most of its keyframes hang from the first lap's (where a match does not pin the
    # pose to one keyframe spacing, e.g. along a bare wall, the keyframe is a node)
    assert slam.export_state().reused_keyframes > 2 * second_lap_nodes
    assert result.summary()["reused_keyframes"] == slam.export_state().reused_keyframes
    assert second_lap_nodes < 0.5 * first_lap_nodes
    # every scan of the second lap still gets its pose, as close to the truth as the first's
    first = position_errors(result.poses[:lap_scans], run.true_poses[:lap_scans])
    second = position_errors(result.poses[lap_scans:], run.true_poses[lap_scans:])
    assert first.rmse_m < 0.02
    assert second.rmse_m < 0.02
    assert second.max_m < 0.1


def test_a_revisit_that_leaves_the_old_nodes_is_linked_to_them(two_laps, reused) -> None:  # type: ignore[no-untyped-def]
    """A node that ends a revisit has no odometry factor from the node before it: it is
    linked to the old node it hung from by its match (or by the odometry where that failed),
    and the link agrees with the truth."""
    run, _ = two_laps
    _, result = reused
    leaving = _leaving_nodes(result)
    assert leaving, "the second lap never left the old nodes"
    truth = run.true_poses[result.node_scan_index]
    for j in leaving:
        # the first factor into the node: the link, added before any loop-closure search
        link = next(f for f in result.factors if f.j == j)
        assert link.kind in (FactorKind.LOOP_CLOSURE, FactorKind.ODOMETRY)
        assert link.i < j - 1
        error = se2.between(se2.between(truth[link.i], truth[j]), link.measured)
        assert np.hypot(error[0], error[1]) < 0.05
        assert abs(np.degrees(error[2])) < 1.0


def test_anchor_round_trips_through_its_array() -> None:
    a = Anchor(7, np.array([0.1, -0.2, 0.03]), np.diag([1e-4, 2e-4, 3e-5]), np.ones(3), 4.5, 12.25)
    b = Anchor.from_array(a.as_array())
    assert (b.node, b.stamp_s, b.path_m) == (7, 4.5, 12.25)
    for x, y in ((a.offset, b.offset), (a.offset_cov, b.offset_cov), (a.odom, b.odom)):
        assert np.array_equal(x, y)


def test_a_session_split_while_hanging_from_an_old_node_continues_bit_for_bit(  # type: ignore[no-untyped-def]
    two_laps, reused, tmp_path
) -> None:
    run, lap_scans = two_laps
    _, whole = reused
    first = Slam(config_from_dict(REUSE))
    k = lap_scans + 200
    for scan in run.scans[:k]:
        first.process(scan)
    assert first.export_state().anchor is not None  # the split falls inside a revisit
    first.finish()
    session.save(first, tmp_path / "s")
    second = session.load(tmp_path / "s")
    assert second.export_state().anchor is not None
    for scan in run.scans[k:]:
        second.process(scan)
    split = second.finish()
    assert np.array_equal(split.poses, whole.poses)  # bit for bit, not approximately
    assert np.array_equal(split.node_poses, whole.node_poses)
    assert [(f.kind, f.i, f.j) for f in split.factors] == [
        (f.kind, f.i, f.j) for f in whole.factors
    ]
    assert second.export_state().reused_keyframes == whole.slam.export_state().reused_keyframes


def test_two_workers_give_the_same_run_bit_for_bit(two_laps, reused) -> None:  # type: ignore[no-untyped-def]
    run, _ = two_laps
    _, one = reused
    two = run_scans(run.scans, config_from_dict({"slam": {"reuse_nodes": True, "workers": 2}}))
    assert two.reused_keyframes == one.reused_keyframes
    assert two.poses.tobytes() == one.poses.tobytes()


@pytest.fixture
def restores(monkeypatch: pytest.MonkeyPatch) -> list[MapCheckpoint]:
    """The checkpoints ``FeatureMap.restore`` is given during the test: one per search that
    accepted closures after its node's map update ran."""
    given: list[MapCheckpoint] = []
    restore = FeatureMap.restore

    def counted(self: FeatureMap, checkpoint: MapCheckpoint) -> None:
        given.append(checkpoint)
        restore(self, checkpoint)

    monkeypatch.setattr(FeatureMap, "restore", counted)
    return given


def test_searches_decided_at_the_next_keyframe_give_the_same_run_bit_for_bit(  # type: ignore[no-untyped-def]
    two_laps, reused, restores
) -> None:
    # With a match pool, a node's loop-closure search stays open while the node's map update
    # and the next keyframe's local match run; a closure it then accepts undoes that map
    # update, updates it again on the corrected estimates, and the keyframe starts again
    # (revisits hang from old nodes here). The run is the one that decides each search at
    # its node, bit for bit. A pool without a helper takes the same steps in one process.
    run, _ = two_laps
    _, one = reused
    slam = Slam(config_from_dict(REUSE))
    with MatchPool(slam.matcher, helper=False) as pool:
        slam.loop_closer.match_pool = pool
        for scan in run.scans:
            slam.process(scan)
        deferred = slam.finish()
    assert len(restores) >= 3 and pool.local > 0  # closures accepted after their map update ran
    assert deferred.reused_keyframes == one.reused_keyframes
    assert deferred.poses.tobytes() == one.poses.tobytes()
    assert deferred.node_poses.tobytes() == one.node_poses.tobytes()
    assert [(f.kind, f.i, f.j) for f in deferred.factors] == [
        (f.kind, f.i, f.j) for f in one.factors
    ]


def test_the_feature_map_read_while_a_search_is_open_is_the_map_after_its_decision(  # type: ignore[no-untyped-def]
    two_laps, reused, restores
) -> None:
    # Read between two keyframes, ``Slam.feature_map`` decides the open search first: where
    # the search accepts a closure, the node's map update that ran before is redone on the
    # corrected estimates, so the map read is the map of the run that decides each search
    # at its node, at the same scan (compared where that run accepted a closure).
    run, _ = two_laps
    _, one = reused
    direct, deferred = Slam(config_from_dict(REUSE)), Slam(config_from_dict(REUSE))
    compared = 0
    with MatchPool(deferred.matcher, helper=False) as pool:
        deferred.loop_closer.match_pool = pool
        for scan in run.scans:
            accepted = direct.loop_stats.accepted
            direct.process(scan)
            deferred.process(scan)
            if direct.loop_stats.accepted == accepted:
                continue
            compared += 1
            fmap = deferred.feature_map
            # the read decided the open search (the closure is in, not pending)
            assert deferred.loop_closer.stats.accepted == direct.loop_stats.accepted
            want, got = direct.feature_map.export_state(), fmap.export_state()
            assert want.keys() == got.keys()
            for k in want:  # NaN where equal (an Intersection has no directions)
                np.testing.assert_array_equal(got[k], want[k], err_msg=f"{k} {scan.source}")
        result = deferred.finish()
    assert compared >= 3 and len(restores) >= 3  # updates redone at the read
    assert result.poses.tobytes() == one.poses.tobytes()


def test_a_closure_a_revisit_hangs_from_is_forbidden_in_a_new_run_not_removed(  # type: ignore[no-untyped-def]
    two_laps, reused, tmp_path
) -> None:
    """``iceg optimize --remove-factor`` cannot undo a closure that a revisit hangs from (the
    hung scans stay in the old nodes' frames), so it refuses and names the configuration
    that runs the logs again without it; that run is the same up to the closure's node, does
    not match the place again there, and still follows the truth."""
    from iceg.edit import edit_and_optimize
    from iceg_common.errors import SessionError

    run, _ = two_laps
    slam, result = reused
    session.save(slam, tmp_path / "s")
    leaving = _leaving_nodes(result)
    # the closure into the node before a revisit's first leaving node started the revisit
    # (factor indices: the session's, loop_closures.csv column "factor")
    started = [
        k
        for k, c in enumerate(result.factors)
        if c.kind is FactorKind.LOOP_CLOSURE and c.j + 1 in leaving
    ]
    assert started, "no revisit began at a loop closure"
    f = started[0]
    old, node = result.factors[f].i, result.factors[f].j
    with pytest.raises(SessionError, match=rf"forbidden_closures: \[\[{old}, {node}\]\]"):
        edit_and_optimize(session.read(tmp_path / "s"), remove=[f])

    _, rerun = _run(run.scans, {**REUSE, "loop_closure": {"forbidden_closures": [[old, node]]}})
    # the factors added before the closure's search are the same, bit for bit
    for a, b in zip(result.factors[:f], rerun.factors[:f], strict=True):
        assert (a.kind, a.i, a.j, a.measured.tobytes()) == (b.kind, b.i, b.j, b.measured.tobytes())
    # no closure at that node with the place the forbidden one matched (its old nodes)
    place = config_from_dict(REUSE).loop_closure.reference_nodes
    assert not any(
        c.kind is FactorKind.LOOP_CLOSURE and c.j == node and abs(c.i - old) <= place
        for c in rerun.factors
    )
    assert position_errors(rerun.poses, run.true_poses).rmse_m < 0.02


def test_the_matching_stage_times_the_local_matches_only(reused) -> None:  # type: ignore[no-untyped-def]
    # benchmarks/bench_pipeline.py pairs each local match's time with its reference's: a
    # match against an old place is its own stage (it has no local-map reference)
    slam, result = reused
    leaving = _leaving_nodes(result)
    samples = slam.timer.samples
    assert len(samples["matching"]) == len(result.node_ids) - 1 - len(leaving)
    assert len(samples["old_place"]) >= slam.export_state().reused_keyframes + len(leaving)
