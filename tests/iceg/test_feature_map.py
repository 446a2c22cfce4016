"""Tests of the feature map: anchored landmarks, references, association and time-validity
(paper §III-C3, docs/design.md "Feature map and time-validity").

Truth: exact SE(2) algebra for frames; the simulator's ground truth (true poses, the box's
geometry and removal time) for time-validity.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Iterator
from typing import NamedTuple

import numpy as np
import pytest

from frontends import LaserScan
from frontends.simulate import SimulatedRun, box_world, office_world, simulate
from iceg import feature_map
from iceg.feature_map import (
    PRUNED_VALIDITY,
    FeatureMap,
    FeatureMapConfig,
    MapReference,
    MapUpdate,
    PrunedLandmarks,
    _Landmarks,
    _Points,
    _Segments,
    _Touched,
)
from iceg.features import extract
from iceg.landmark_association import (
    associate_scan,
    is_ascending,
    lookup_sorted,
    nearest_free_pairs,
    reference_geometry,
    rows_of_nodes,
    rows_taking_part,
    sorted_union,
    within_gate_of_any,
)
from iceg.landmark_frames import (
    FeatureRows,
    frame_inverse,
    keep_better,
    move_features,
    move_lines,
    move_point_blocks,
    move_points,
    poses_in_frame,
)
from iceg.matching import IceMatcher, MatchBounds
from iceg.matching.geometry import PolarProfile
from iceg.matching.matcher import walls_seen_through
from iceg.types import FeatureKind, MatchResult, ScanFeatures
from iceg.visibility import count_observations, expected_landmarks, pruned_landmarks
from iceg_common import se2
from iceg_common.errors import FeatureMapError
from iceg_common.se2 import between, rotation_matrix, transform_points, wrap_angle
from tests.iceg.test_matching import hand_scan, point_features, room_walls


def _unit(deg: float) -> list[float]:
    return [math.cos(math.radians(deg)), math.sin(math.radians(deg))]


def test_reference_is_in_the_frame_pose_frame() -> None:
    rng = np.random.default_rng(0)
    w = room_walls()
    pa, pb = np.array([2.0, 2.0, 0.3]), np.array([3.0, 2.5, 0.6])
    fa = hand_scan(w, pa, rng)
    fm = FeatureMap()
    up = fm.update(0, fa, 0.0)
    assert up.added_ids.tolist() == list(range(fa.n_features))
    poses = {0: pa, 1: pb}
    snapshot = fm.reference(poses, [0], pb)
    ref = snapshot.features
    # The reference carries the pose snapshot it was built from (sorted by node id).
    np.testing.assert_array_equal(snapshot.node_ids, [0, 1])
    np.testing.assert_array_equal(snapshot.node_poses, np.stack([pa, pb]))
    np.testing.assert_array_equal(snapshot.frame_pose, pb)
    np.testing.assert_array_equal(snapshot.landmark_ids, ref.ids)
    # Landmarks of node 0 seen from pb: exact SE(2) algebra.
    rel = between(pb, pa)
    np.testing.assert_allclose(ref.xy, transform_points(rel, fa.xy), atol=1e-12)
    np.testing.assert_allclose(
        ref.seg_endpoints,
        transform_points(rel, fa.seg_endpoints.reshape(-1, 2)).reshape(-1, 2, 2),
        atol=1e-12,
    )
    # Segment endpoints lie on their transformed lines (rho >= 0 form).
    n = np.stack([np.cos(ref.seg_lines[:, 0]), np.sin(ref.seg_lines[:, 0])], axis=1)
    for k in (0, 1):
        np.testing.assert_allclose(
            np.einsum("ma,ma->m", n, ref.seg_endpoints[:, k]), ref.seg_lines[:, 1], atol=0.02
        )
    assert np.all(ref.seg_lines[:, 1] >= 0)
    np.testing.assert_array_equal(ref.ids, np.arange(fa.n_features))
    assert ref.points_xy.shape == (0, 2)
    # The same landmarks in the world frame, from a dict or an (ids, poses) tuple.
    v1 = fm.world_landmarks(poses)
    v2 = fm.world_landmarks((np.array([1, 0]), np.stack([pb, pa])))
    np.testing.assert_allclose(v1.xy, transform_points(pa, fa.xy), atol=1e-12)
    np.testing.assert_allclose(v2.xy, v1.xy)
    # A node without landmarks gives an empty reference; unknown anchors are left out.
    assert fm.reference(poses, [1], pb).features.n_features == 0
    assert fm.reference({1: pb}, [0], pb).features.n_features == 0


def test_update_checks_its_inputs() -> None:
    fm = FeatureMap()
    f = point_features([FeatureKind.INTERSECTION], [[1.0, 1.0]])
    fm.update(0, f, 0.0)
    with pytest.raises(FeatureMapError, match="already added"):
        fm.update(0, f, 1.0)
    ok = MatchResult(True, np.zeros(3), np.eye(3), 0.9)
    with pytest.raises(FeatureMapError, match="reference"):
        fm.update(1, f, 1.0, match=ok)
    with pytest.raises(FeatureMapError, match="reference"):
        fm.update(1, f, 1.0, match=ok, reference=f)  # type: ignore[arg-type]  # not a MapReference
    other = FeatureMap()
    other.update(0, f, 0.0)
    with pytest.raises(FeatureMapError, match="reference"):
        fm.update(
            1, f, 1.0, match=ok, reference=other.reference({0: np.zeros(3)}, [0], np.zeros(3))
        )
    # A failed match is no evidence: every feature becomes a landmark of the new node.
    bad = MatchResult(False, np.zeros(3), np.full((3, 3), np.nan), 0.0, reason="x")
    up = fm.update(1, f, 1.0, match=bad)
    assert up.added_ids.tolist() == [1]


def test_matched_features_update_landmarks_instead_of_duplicating_them() -> None:
    rng = np.random.default_rng(4)
    w = room_walls()
    poses = {0: np.array([2.0, 2.0, 0.3]), 1: np.array([2.4, 2.3, 0.4])}
    fa = hand_scan(w, poses[0], rng)
    fb = hand_scan(w, poses[1], rng)
    fm = FeatureMap()
    fm.update(0, fa, 0.0)
    ref = fm.reference(poses, [0], poses[0])
    res = IceMatcher().match(
        fb, ref.features, between(poses[0], poses[1]), MatchBounds.local(0.3, 10)
    )
    assert res.success, res.reason
    up = fm.update(1, fb, 0.2, reference=ref, match=res, node_poses=poses)
    # Every feature of the second scan is a landmark of the first seen again (the two
    # views of the room share all corners and door ends): nothing new is added.
    assert up.added_ids.shape[0] == fb.n_features - up.matched_ids.shape[0]
    assert up.matched_ids.shape[0] >= len(res.inlier_pairs)
    v = fm.world_landmarks(poses)
    m = np.isin(v.ids, up.matched_ids)
    assert np.all(v.n_matched[m] == 1)
    # Matched landmarks stay within 3 cm of the true room geometry.
    corners = np.array([[0, 0], [10, 0], [10, 7], [0, 7], [6, 3], [7, 3], [7, 4.5], [6, 4.5]])
    ends = np.array([[3, 0], [4, 0], [10, 4.5], [10, 5.4]])
    truth = np.concatenate([corners, ends])
    d = np.min(np.linalg.norm(v.xy[:, None] - truth[None], axis=2), axis=1)
    assert np.all(d[v.kind != FeatureKind.INTERSECTION] < 0.03)


def test_an_eow_seen_as_a_corner_becomes_a_corner() -> None:
    # Paper §III-C2 (Fig. 1-2): point A is an EOW from P1 and a Corner from P2.
    p0, p1 = np.array([0.0, 0.0, 0.0]), np.array([1.0, -1.0, 0.5])
    corner_world = np.array([3.0, 1.0])
    eow = point_features([FeatureKind.EOW], [corner_world], [[_unit(180), [np.nan, np.nan]]])
    xy1 = transform_points(between(p1, p0), corner_world[None])[0]
    corner = point_features(
        [FeatureKind.CORNER], [xy1], [[_unit(180 - 28.6479), _unit(270 - 28.6479)]]
    )
    fm = FeatureMap()
    fm.update(0, eow, 0.0)
    poses = {0: p0, 1: p1}
    ref = fm.reference(poses, [0], p0)
    res = MatchResult(True, between(p0, p1), np.eye(3) * 1e-4, 0.9, np.array([[0, 0]]))
    up = fm.update(1, corner, 0.2, reference=ref, match=res, node_poses=poses)
    assert up.added_ids.shape[0] == 0
    v = fm.world_landmarks(poses)
    assert v.kind.tolist() == [FeatureKind.CORNER]
    np.testing.assert_allclose(v.xy[0], corner_world, atol=1e-9)
    # Its two walls in the world frame: the corner's edges rotated by the pose of node 1.
    np.testing.assert_allclose(
        v.directions[0, 0], _unit(180 - 28.6479 + math.degrees(0.5)), atol=1e-9
    )


def _run_map(
    world,
    seed: int,
    config: FeatureMapConfig,
    after_update: Callable[[FeatureMap, dict[int, np.ndarray], int], None] | None = None,
):
    """Feature map along a simulated run with true node poses: keyframes every 0.3 m or
    10 deg, each matched against the landmarks of the last four nodes (``after_update``
    called with the map, the poses and the node after each matched node's update)."""
    fm = FeatureMap(config)
    m = IceMatcher()
    poses: dict[int, np.ndarray] = {}
    expected_at: dict[int, list[float]] = {}
    for s, truth in _keyframes(simulate(world, seed=seed)):
        f = extract(s)
        node = len(poses)
        poses[node] = truth
        if node == 0:
            fm.update(0, f, s.stamp_s, scan=s)
        else:
            ref = fm.reference(poses, range(max(0, node - 4), node), poses[node - 1])
            res = m.match(
                f, ref.features, between(poses[node - 1], truth), MatchBounds.local(0.3, 10)
            )
            up = fm.update(node, f, s.stamp_s, reference=ref, match=res, scan=s, node_poses=poses)
            for i in up.expected_ids:
                expected_at.setdefault(int(i), []).append(s.stamp_s)
            if after_update is not None:
                after_update(fm, poses, node)
    return fm, poses, expected_at


def _keyframes(run: SimulatedRun) -> Iterator[tuple[LaserScan, np.ndarray]]:
    """The run's scans and true poses every 0.3 m or 10 deg of true motion."""
    last = None
    for s, truth in zip(run.scans, run.true_poses, strict=True):
        if last is not None:
            d = between(last, truth)
            if math.hypot(d[0], d[1]) < 0.3 and abs(d[2]) < math.radians(10):
                continue
        last = truth
        yield s, truth


def _pruned_world(
    fm: FeatureMap, poses: dict[int, np.ndarray]
) -> tuple[np.ndarray, PrunedLandmarks]:
    p = fm.pruned
    xy = np.array(
        [transform_points(poses[int(a)], p.xy[i][None])[0] for i, a in enumerate(p.anchor)]
    ).reshape(-1, 2)
    return xy, p


def test_time_validity_prunes_the_removed_box_and_no_static_wall_feature() -> None:
    # Issue 4 acceptance: the box (x 5.5-6.5, y 3.5-4.5) is removed halfway through the run;
    # its features are pruned within the validity window once the robot looks at where
    # they were, and no feature of a static wall is ever pruned.
    cfg = FeatureMapConfig()
    world = box_world()
    removed_s = world.dynamic_walls[0].present_until_s
    fm, poses, expected_at = _run_map(world, 3, cfg)
    xy, p = _pruned_world(fm, poses)
    near_box = (np.abs(xy[:, 0] - 6.0) < 1.0) & (np.abs(xy[:, 1] - 4.0) < 1.0)
    assert np.all(near_box), xy[~near_box]  # nothing static pruned
    assert np.all(p.reason == PRUNED_VALIDITY)
    # All four box corners went, and no landmark is left at the box.
    box_corners = np.array([[5.5, 3.5], [6.5, 3.5], [6.5, 4.5], [5.5, 4.5]])
    assert np.all(np.min(np.linalg.norm(box_corners[:, None] - xy[None], axis=2), axis=1) < 0.05)
    v = fm.world_landmarks(poses)
    assert not np.any((np.abs(v.xy[:, 0] - 6.0) < 1.0) & (np.abs(v.xy[:, 1] - 4.0) < 1.0))
    for i in range(p.ids.shape[0]):
        # Pruned only after the box was gone for longer than validity_s since the last match,
        # and as soon as the misses since the first look after the last match are confirmed
        # (miss_confirm_s), give or take one keyframe.
        assert p.last_matched_s[i] <= removed_s + 0.2
        assert p.stamp_s[i] - p.last_matched_s[i] >= cfg.validity_s
        looks = np.array(expected_at[int(p.ids[i])])
        first_miss = looks[looks > p.last_matched_s[i]].min()
        due = max(p.last_matched_s[i] + cfg.validity_s, first_miss + cfg.miss_confirm_s)
        assert due <= p.stamp_s[i] <= due + 1.0


def test_no_landmark_of_a_static_office_is_pruned() -> None:
    # A static world: nothing may be pruned along the office route (which passes every
    # room again on its way back); duplicates of one corner are merged, not pruned.
    fm, poses, _ = _run_map(office_world(), 0, FeatureMapConfig())
    assert fm.pruned.ids.shape[0] == 0
    assert len(fm) > 20
    v = fm.world_landmarks(poses)
    # Corners and wall ends of the map are the office's own (simulator ground truth).
    truth = np.concatenate([office_world().corners(), office_world().wall_ends()])
    d = np.min(np.linalg.norm(v.xy[:, None] - truth[None], axis=2), axis=1)
    assert np.median(d[v.kind != FeatureKind.INTERSECTION]) < 0.03


def test_reference_points_follow_their_nodes() -> None:
    # With reference_points the nodes' scan points come along, in the frame of frame_pose,
    # and each segment's point range still selects the points of that segment.
    rng = np.random.default_rng(2)
    w = room_walls()
    poses = {0: np.array([2.0, 2.0, 0.3]), 1: np.array([3.0, 3.0, -0.4])}
    fa, fb = hand_scan(w, poses[0], rng), hand_scan(w, poses[1], rng)
    fm = FeatureMap(FeatureMapConfig(reference_points=True))
    fm.update(0, fa, 0.0)
    fm.update(1, fb, 0.2)  # no match: added as a new node
    frame = np.array([1.0, -1.0, 0.2])
    ref = fm.reference(poses, [0, 1], frame).features
    expect = np.concatenate(
        [
            transform_points(between(frame, poses[0]), fa.points_xy),
            transform_points(between(frame, poses[1]), fb.points_xy),
        ]
    )
    np.testing.assert_allclose(ref.points_xy, expect, atol=1e-12)
    n = np.stack([np.cos(ref.seg_lines[:, 0]), np.sin(ref.seg_lines[:, 0])], axis=1)
    for m in range(ref.n_segments):
        a, b = ref.seg_point_range[m]
        res = ref.points_xy[a:b] @ n[m] - ref.seg_lines[m, 1]
        assert np.abs(res).max() < 0.05  # 1 cm range noise, TLS lines
    # Without the option the reference carries no points.
    assert FeatureMap().reference({}, [], frame).features.points_xy.shape == (0, 2)


def test_reference_of_any_node_subset_equals_a_brute_force_selection() -> None:
    # Segments and points are found through a per-node block index (no scan of every row):
    # for random subsets of nodes (some unknown, some without a pose) the reference holds
    # exactly the rows a full scan of the stored arrays selects, in the same order.
    rng = np.random.default_rng(5)
    w = room_walls()
    fm = FeatureMap(FeatureMapConfig(reference_points=True))
    poses: dict[int, np.ndarray] = {}
    for node in range(30):
        pose = np.array([2.0 + 0.05 * node, 2.0 + 0.03 * node, 0.02 * node])
        poses[node] = pose
        fm.update(node, hand_scan(w, pose, rng), 0.1 * node)
    state = fm.export_state()
    frame = np.array([0.5, -0.2, 0.3])
    for _ in range(20):
        want = rng.choice(35, size=int(rng.integers(0, 8)), replace=False)
        posed = {k: v for k, v in poses.items() if rng.random() > 0.2}
        ref = fm.reference(posed, want, frame).features
        keep = np.isin(state["seg_node"], [k for k in want if k in posed])
        rows = np.flatnonzero(keep)
        ep = np.array(
            [
                transform_points(
                    between(frame, posed[int(state["seg_node"][r])]), state["seg_ep"][r]
                )
                for r in rows
            ]
        ).reshape(-1, 2, 2)
        np.testing.assert_allclose(ref.seg_endpoints, ep, rtol=0, atol=1e-12)
        pkeep = np.isin(state["pts_node"], [k for k in want if k in posed])
        pts = [
            transform_points(between(frame, posed[int(n)]), state["pts_xy"][state["pts_node"] == n])
            for n in np.unique(state["pts_node"][pkeep])
        ]
        expect = np.concatenate(pts) if pts else np.zeros((0, 2))
        np.testing.assert_allclose(ref.points_xy, expect, rtol=0, atol=1e-12)
        # Each segment's point range selects points of its own node's block.
        for m in range(ref.n_segments):
            a, b = ref.seg_point_range[m]
            assert 0 <= a <= b <= ref.points_xy.shape[0]
    # A map rebuilt from its state selects the same rows.
    again = FeatureMap.from_state(state, FeatureMapConfig(reference_points=True))
    a = fm.reference(poses, [3, 7, 8], frame).features
    b = again.reference(poses, [3, 7, 8], frame).features
    np.testing.assert_array_equal(a.seg_endpoints, b.seg_endpoints)
    np.testing.assert_array_equal(a.points_xy, b.points_xy)
    np.testing.assert_array_equal(a.seg_point_range, b.seg_point_range)


@pytest.mark.parametrize("indexed", [True, False])
@pytest.mark.parametrize("world", ["box", "office"])
def test_reference_landmarks_equal_a_scan_of_every_landmark(
    world: str, indexed: bool, monkeypatch: pytest.MonkeyPatch
) -> None:
    # A reference's landmarks are found through the ids each node created or matched (no
    # scan of every landmark): along runs with matches, merges and pruning (the box world)
    # or revisits (the office), and in the map rebuilt from its state, every window selects
    # exactly the landmarks a scan of the whole table selects (anchored to or last matched
    # from a window node). A small map takes the pass over every landmark; both ways agree.
    monkeypatch.setattr(feature_map, "_TOUCHED_FROM_LANDMARKS", 0 if indexed else 10**9)
    if world == "box":
        fm, poses, _ = _run_map(box_world(), 3, FeatureMapConfig())
        assert fm.pruned.ids.shape[0] > 0
    else:
        fm, poses, _ = _run_map(office_world(), 0, FeatureMapConfig())
        assert len(fm) > 20
    state = fm.export_state()
    anchor, last, ids = state["lm_anchor"], state["lm_last_node"], state["lm_id"]
    assert np.count_nonzero(anchor != last) > 0 and fm.n_merged > 0
    again = FeatureMap.from_state(state)
    rng = np.random.default_rng(2)
    frame = np.array([0.5, -0.2, 0.3])
    n = len(poses)
    windows = [np.arange(n), *(rng.choice(n + 3, size=k, replace=False) for k in (1, 3, 9, 40))]
    for want in windows:
        expect = ids[np.isin(anchor, want) | np.isin(last, want)]
        for m in (fm, again):
            np.testing.assert_array_equal(m.reference(poses, want, frame).landmark_ids, expect)
            np.testing.assert_array_equal(
                m.reference_pose_nodes(want), np.union1d(want, anchor[np.isin(ids, expect)])
            )


def test_a_reference_after_an_update_is_that_of_the_map_rebuilt_from_its_state() -> None:
    # A map keeps the landmark rows it last chose for a window (a reference reads them twice):
    # an update that matches, merges and prunes landmarks (the box world) changes them. The
    # window of the last match, asked again after each update, and the next window give what
    # a map rebuilt from its state, which chose nothing yet, gives.
    def check(fm: FeatureMap, poses: dict[int, np.ndarray], node: int) -> None:
        fresh = FeatureMap.from_state(fm.export_state())
        for want in (range(max(0, node - 4), node), range(max(0, node - 3), node + 1)):
            a = fm.reference(poses, want, poses[node])
            b = fresh.reference(poses, want, poses[node])
            np.testing.assert_array_equal(a.landmark_ids, b.landmark_ids)
            np.testing.assert_array_equal(a.features.xy, b.features.xy)
            np.testing.assert_array_equal(
                fm.reference_pose_nodes(want), fresh.reference_pose_nodes(want)
            )

    fm, _, _ = _run_map(box_world(), 3, FeatureMapConfig(), check)
    assert fm.n_merged > 0 and fm.pruned.ids.shape[0] > 0


class _Step(NamedTuple):
    """A keyframe of :func:`_box_world_steps` to update both maps with."""

    node: int
    features: ScanFeatures
    scan: LaserScan
    poses: dict[int, np.ndarray]  # true poses of the nodes so far, this one included
    ref_a: MapReference
    ref_b: MapReference
    match: MatchResult  # against ref_a


def _box_world_steps(a: FeatureMap, b: FeatureMap) -> Iterator[_Step]:
    """Two maps along the box world (matches, merges, pruning) with true poses: node 0 is
    added to both, then every keyframe's scan is matched against ``a``'s landmarks of the
    last four nodes, each map's reference of them given (the caller updates both)."""
    m = IceMatcher()
    poses: dict[int, np.ndarray] = {}
    for s, truth in _keyframes(simulate(box_world(), seed=3)):
        f = extract(s)
        node = len(poses)
        poses[node] = truth
        if node == 0:
            a.update(0, f, s.stamp_s, scan=s)
            b.update(0, f, s.stamp_s, scan=s)
            continue
        window = range(max(0, node - 4), node)
        ref_a = a.reference(poses, window, poses[node - 1])
        ref_b = b.reference(poses, window, poses[node - 1])
        res = m.match(
            f, ref_a.features, between(poses[node - 1], truth), MatchBounds.local(0.3, 10)
        )
        yield _Step(node, f, s, poses, ref_a, ref_b, res)


def _update(
    fm: FeatureMap, step: _Step, ref: MapReference, poses: dict[int, np.ndarray]
) -> MapUpdate:
    return fm.update(
        step.node,
        step.features,
        step.scan.stamp_s,
        reference=ref,
        match=step.match,
        scan=step.scan,
        node_poses=poses,
    )


def _assert_same_state(a: FeatureMap, b: FeatureMap) -> dict[str, np.ndarray]:
    """Both maps' states hold the same arrays; returns ``a``'s."""
    x, y = a.export_state(), b.export_state()
    assert x.keys() == y.keys()
    for k in x:
        np.testing.assert_array_equal(x[k], y[k], err_msg=k)
    return x


def test_an_update_after_its_pose_nodes_were_asked_is_the_update_without() -> None:
    # A map keeps the rows of the landmarks taking part in a node's bookkeeping that its
    # update_pose_nodes chose (the update reads them again); the bookkeeping changes them.
    # Two maps along the box world (matches, merges, pruning), one asked for each update's
    # pose nodes first (as the SLAM loop does), the other not, hold the same state after
    # every update; asked again after it, the first answers as a map rebuilt from its state.
    asked, plain = FeatureMap(FeatureMapConfig()), FeatureMap(FeatureMapConfig())
    for step in _box_world_steps(asked, plain):
        want_nodes = asked.update_pose_nodes(step.node, step.ref_a)
        assert set(want_nodes.tolist()) <= set(step.poses)
        _update(asked, step, step.ref_a, step.poses)
        _update(plain, step, step.ref_b, step.poses)
        state = _assert_same_state(asked, plain)
        # asked again after the update: what a map rebuilt from the state answers
        fresh = FeatureMap.from_state(state)
        np.testing.assert_array_equal(
            asked.update_pose_nodes(step.node, step.ref_a),
            fresh.update_pose_nodes(step.node, step.ref_a),
        )
    assert asked.n_merged > 0 and asked.pruned.ids.shape[0] > 0


def test_a_restored_map_is_the_map_before_the_updates_it_undid() -> None:
    # The SLAM loop updates the map before the node's loop-closure search is decided, and
    # where a closure is accepted, restores the checkpoint taken before and updates again on
    # the corrected estimates (iceg.slam, Slam._finish_search). Along the box world
    # (matches, merges, pruning), one map runs every update that way, first on estimates a
    # closure would then correct (bent along the path), the other only the second update:
    # both hold the same state after every node. A reference built before the undone update
    # still holds the values it had (a loop-closure match built then may run after it).
    spec, plain = FeatureMap(FeatureMapConfig()), FeatureMap(FeatureMapConfig())
    restored_merges = restored_prunes = 0
    for step in _box_world_steps(spec, plain):
        ref = step.ref_a.features
        before = [np.array(a, copy=True) for a in (ref.xy, ref.cov)]
        checkpoint = spec.checkpoint()
        bent = {i: p + np.array([0.004 * i, -0.002 * i, 0.001 * i]) for i, p in step.poses.items()}
        undone = _update(spec, step, step.ref_a, bent)
        restored_merges += undone.merged_ids.shape[0]
        restored_prunes += undone.pruned_ids.shape[0]
        for a, b in zip(before, (ref.xy, ref.cov), strict=True):
            np.testing.assert_array_equal(a, b)
        spec.restore(checkpoint)
        _update(spec, step, step.ref_a, bent)  # once more undone: a checkpoint stays valid
        spec.restore(checkpoint)
        _update(spec, step, step.ref_a, step.poses)
        _update(plain, step, step.ref_b, step.poses)
        _assert_same_state(spec, plain)
        np.testing.assert_array_equal(spec._touched.id, plain._touched.id)
        assert spec._touched_rows == plain._touched_rows
        assert (spec._seg_rows, spec._pts_rows) == (plain._seg_rows, plain._pts_rows)
    assert restored_merges > 0 and restored_prunes > 0
    with pytest.raises(FeatureMapError, match="another map's"):
        plain.restore(checkpoint)


@pytest.mark.parametrize("removed", [True, False])
def test_walls_the_newest_scan_sees_through_are_dropped_from_a_reference(removed: bool) -> None:
    # Truth: box_world's box spans x 5.5-6.5, y 3.5-4.5 in a 12 m x 8 m room. Node 0 looks at
    # it from (2, 4) facing +x while it stands (stamp 0 s); node 1, 0.5 m further, looks at
    # the same place at 1 s, after the box was taken away at 0.5 s (or, as a control, while it
    # still stands). Node 1's beams then pass through where node 0 saw the box's west face.
    world = box_world(removed_at_s=0.5 if removed else 10.0)
    run = simulate(world, trajectory=[[2.0, 4.0, 0.0], [2.5, 4.0, 0.0]], rate_hz=1.0)
    fm = FeatureMap(FeatureMapConfig())
    poses = {0: run.true_poses[0], 1: run.true_poses[1]}
    feats = [extract(s) for s in run.scans]
    fm.update(0, feats[0], run.scans[0].stamp_s, scan=run.scans[0])
    fm.update(1, feats[1], run.scans[1].stamp_s, scan=run.scans[1], node_poses=poses)
    ref = fm.reference(poses, [0, 1], poses[1])
    kept = ref.without_walls_seen_through(feats[1].points_xy, tolerance_m=0.3)
    dropped = ref.features.seg_endpoints.shape[0] - kept.features.seg_endpoints.shape[0]
    walls = transform_points(poses[1], ref.features.seg_endpoints.reshape(-1, 2)).reshape(-1, 2, 2)
    on_box = np.all((np.abs(walls[..., 0] - 6.0) < 0.6) & (np.abs(walls[..., 1] - 4.0) < 0.6), 1)
    assert on_box.any()  # node 0 saw the box
    if not removed:
        assert dropped == 0 and kept is ref
        return
    # Exactly the box's walls went (node 1 sees through them); every wall of the room stayed.
    assert dropped == int(on_box.sum())
    left = transform_points(poses[1], kept.features.seg_endpoints.reshape(-1, 2)).reshape(-1, 2, 2)
    np.testing.assert_array_equal(left, walls[~on_box])
    assert kept.features.ids is ref.features.ids  # landmarks untouched
    # The matcher's profile of the same points gives the same walls; one of another range
    # (which would judge other walls) is not used.
    right = PolarProfile.from_points(feats[1].points_xy, ref.features.range_max_m)
    wrong = PolarProfile.from_points(feats[1].points_xy, 3.0)
    ep = ref.features.seg_endpoints
    assert not np.array_equal(
        walls_seen_through(ep, right, 0.3), walls_seen_through(ep, wrong, 0.3)
    )
    for profile in (right, wrong):
        given = ref.without_walls_seen_through(feats[1].points_xy, 0.3, profile)
        np.testing.assert_array_equal(given.features.seg_endpoints, kept.features.seg_endpoints)


@pytest.mark.parametrize("n_drop", [0, 1, 3, 40])
def test_dropping_rows_keeps_the_others_in_order_and_the_spare_capacity(n_drop: int) -> None:
    # Dropping landmark rows (merged, pruned) leaves the rows a mask would keep, in order,
    # moved down within the buffers (none, one, a few or many kept blocks); the container
    # keeps its buffers and capacity, so appending after it writes into them.
    rng = np.random.default_rng(n_drop)
    cols = _Points(np.arange(100, dtype=np.int64), rng.normal(size=(100, 2)))
    cols.append(_Points(np.arange(100, 150, dtype=np.int64), rng.normal(size=(50, 2))))
    gone = rng.choice(150, n_drop, replace=False)
    keep = np.ones(150, dtype=bool)
    keep[gone] = False
    node, xy = cols.node[keep], cols.xy[keep]
    buffer, cap = cols._bufs["xy"], cols._cap
    cols.drop(gone)
    np.testing.assert_array_equal(cols.node, node)
    np.testing.assert_array_equal(cols.xy, xy)
    assert cols._bufs["xy"] is buffer and cols._cap == cap >= 150
    cols.append(_Points(np.array([7], dtype=np.int64), np.array([[1.5, -2.5]])))
    assert cols._bufs["xy"] is buffer and len(cols) == 151 - n_drop
    np.testing.assert_array_equal(cols.xy[-1], [1.5, -2.5])


def test_dropping_landmark_rows_moves_every_column_of_the_table() -> None:
    # The landmark table's columns: int64 and float64, rows of shape (), (2,), (2, 2) and
    # (3, 2). Drops one after another (the first row, the last, a run, scattered rows,
    # none) leave the rows a mask keeps, bit for bit.
    rng = np.random.default_rng(5)
    n = 300
    table = _Landmarks.empty()
    table.extend(
        n,
        **{name: rng.normal(size=(n, *shape)) for name, (_, shape) in _Landmarks.SPEC.items()},
    )
    table.first_miss_s[::7] = np.nan  # NaN and a NaN with a payload keep their bits
    table.created_s[::11] = np.array([0x7FF4000000000123], dtype=np.int64).view(np.float64)[0]
    want = {name: getattr(table, name).copy() for name in _Landmarks.SPEC}
    for gone in ([0], [n - 2], list(range(10, 20)), [3, 4, 99, 150, 151, 200], []):
        rows = np.array(gone, dtype=np.int64)
        keep = np.ones(len(table), dtype=bool)
        keep[rows] = False
        want = {name: col[keep] for name, col in want.items()}
        table.drop(rows)
        for name in _Landmarks.SPEC:
            assert getattr(table, name).tobytes() == want[name].tobytes(), name
    assert len(table) == n - 18


def test_every_table_column_holds_eight_byte_values() -> None:
    # A drop moves each column's rows as 8-byte words (iceg.table_rows).
    for table in (_Landmarks, _Segments, _Points, _Touched):
        for name, (dtype, _) in table.SPEC.items():
            assert np.dtype(dtype).itemsize == 8, (table.__name__, name)


def test_dropping_rows_never_writes_the_arrays_a_container_was_made_of() -> None:
    # A map read back from its state holds the state's arrays until it changes: a drop
    # (pruning, merging) copies them first, so the caller's state stays as it was.
    node, xy = np.arange(10, dtype=np.int64), np.arange(20.0).reshape(10, 2)
    cols = _Points(node, xy)
    cols.drop(np.array([0, 4]))
    np.testing.assert_array_equal(node, np.arange(10))
    np.testing.assert_array_equal(xy, np.arange(20.0).reshape(10, 2))
    np.testing.assert_array_equal(cols.xy, xy[[1, 2, 3, 5, 6, 7, 8, 9]])


def _numpy_expected(
    rows, anchor_in_new, support, wall_p, wall_d, wall_side, kind,
    bearing, range_m, spacing, sensor_pose, margin, max_range, tol, sin_min,
):  # fmt: skip
    """The visibility test written as numpy expressions over ``(n, k, 2)`` arrays: the
    reference the compiled :func:`iceg.visibility.expected_landmarks` must equal bit for
    bit."""

    def rot(t: np.ndarray) -> np.ndarray:
        c, s = np.cos(t), np.sin(t)
        return np.stack([np.stack([c, -s], -1), np.stack([s, c], -1)], -2)

    r, t = rot(anchor_in_new[:, 2]), anchor_in_new[:, :2]
    sup = np.einsum("nab,nkb->nka", r, support[rows]) + t[:, None, :]
    has = np.all(np.isfinite(sup), axis=2)
    pts = sup
    if sensor_pose is not None:
        pts = np.einsum("ba,nkb->nka", rot(np.array(sensor_pose[2])), sup - sensor_pose[:2])
    b = np.arctan2(pts[..., 1], pts[..., 0])
    dist = np.hypot(pts[..., 0], pts[..., 1])
    k = np.clip(np.searchsorted(bearing, b), 1, bearing.shape[0] - 1)
    gap = (bearing[k] - bearing[k - 1]) > 1.6 * spacing
    with np.errstate(invalid="ignore"):
        clear = (np.fmin(range_m[k - 1], range_m[k]) >= dist - tol) & ~gap
    ok = (b >= bearing[0] + margin) & (b <= bearing[-1] - margin) & (dist <= max_range) & clear
    visible = np.all(ok | ~has, axis=1) & np.any(has, axis=1)
    wp = np.einsum("nab,nkb->nka", r, wall_p[rows]) + t[:, None, :]
    wd = np.einsum("nab,nkb->nka", r, wall_d[rows])
    with np.errstate(invalid="ignore"):
        side = np.sign(wd[..., 1] * wp[..., 0] - wd[..., 0] * wp[..., 1])
        ray = wp / np.maximum(np.hypot(wp[..., 0], wp[..., 1]), 1e-9)[..., None]
        sin_inc = np.abs(ray[..., 0] * wd[..., 1] - ray[..., 1] * wd[..., 0])
        wall_ok = (side == wall_side[rows]) & (sin_inc >= sin_min)
    has_wall = np.isfinite(wall_side[rows])
    all_seen = np.all(wall_ok | ~has_wall, axis=1) & np.any(has_wall, axis=1)
    any_seen = np.any(wall_ok & has_wall, axis=1)
    return visible & np.where(kind[rows] == int(FeatureKind.INTERSECTION), all_seen, any_seen)


@pytest.mark.parametrize("offset", [None, (0.12, -0.03, 0.05)])
def test_expected_landmarks_equal_the_numpy_expressions_bit_for_bit(offset) -> None:
    # Random landmarks around a 270-degree scan with occluders, invalid (0) and max-range
    # (inf) beams and a gap of missing beams; support points and walls partly missing.
    rng = np.random.default_rng(11)
    n_lm = 3000
    anchor_in_new = np.column_stack([rng.uniform(-3, 3, (n_lm, 2)), rng.uniform(-4, 4, n_lm)])
    support = rng.uniform(-6, 6, (n_lm, 3, 2))
    support[rng.uniform(size=(n_lm, 3)) < 0.5] = np.nan
    wall_p = rng.uniform(-8, 8, (n_lm, 2, 2))
    ang = rng.uniform(-np.pi, np.pi, (n_lm, 2))
    wall_d = np.stack([np.cos(ang), np.sin(ang)], -1)
    wall_side = rng.choice([-1.0, 1.0, np.nan], (n_lm, 2))
    kind = rng.choice([int(k) for k in FeatureKind], n_lm).astype(np.int64)
    bearing = np.linspace(-2.35, 2.35, 540)
    bearing = np.delete(bearing, np.s_[200:215])  # missing beams
    range_m = rng.uniform(3.0, 25.0, bearing.shape[0])
    range_m[rng.uniform(size=bearing.shape[0]) < 0.02] = 0.0
    range_m[rng.uniform(size=bearing.shape[0]) < 0.5] = np.inf
    spacing = float(np.median(np.diff(bearing)))
    sensor = None if offset is None else np.array(offset)
    rows = rng.permutation(n_lm)[: n_lm // 2]
    args = (rows, anchor_in_new[rows], support, wall_p, wall_d, wall_side, kind)
    got = expected_landmarks(
        *args, int(FeatureKind.INTERSECTION), bearing, range_m, 1.6 * spacing,
        np.zeros(0) if sensor is None else sensor, 0.05, 10.0, 0.2, math.sin(math.radians(15)),
    )  # fmt: skip
    want = _numpy_expected(
        *args, bearing, range_m, spacing, sensor, 0.05, 10.0, 0.2, math.sin(math.radians(15))
    )
    assert 0.1 < want.mean() < 0.9, want.mean()  # both answers occur
    assert np.array_equal(got, want)


def test_pruned_landmarks_are_those_of_the_ratio_and_validity_expressions() -> None:
    # Paper §III-C3's two tests as numpy expressions over every landmark (what the map
    # computed before the compiled pass), on counters and times around each threshold,
    # never-missed landmarks (NaN first miss) included: the same rows and reasons.
    rng = np.random.default_rng(12)
    cfg = FeatureMapConfig()
    for _ in range(50):
        n = int(rng.integers(0, 300))
        n_expected = rng.integers(0, 2 * cfg.min_expected + 2, n)
        n_matched = rng.integers(0, n_expected + 1)
        misses = rng.integers(0, 2 * cfg.min_misses + 2, n)
        stamp = 100.0
        last_matched = stamp - rng.uniform(0, 2 * cfg.validity_s, n)
        first_miss = stamp - rng.uniform(0, 2 * cfg.miss_confirm_s, n)
        first_miss[rng.uniform(size=n) < 0.3] = np.nan
        ratio = (n_expected >= cfg.min_expected) & (n_matched < cfg.min_match_ratio * n_expected)
        with np.errstate(invalid="ignore"):
            stale = (
                (misses >= cfg.min_misses)
                & (stamp - last_matched >= cfg.validity_s)
                & (stamp - first_miss >= cfg.miss_confirm_s)
            )
        rows, got_stale = pruned_landmarks(
            n_expected,
            n_matched,
            misses,
            last_matched,
            first_miss,
            stamp,
            cfg.min_expected,
            cfg.min_match_ratio,
            cfg.min_misses,
            cfg.validity_s,
            cfg.miss_confirm_s,
        )
        np.testing.assert_array_equal(rows, np.flatnonzero(ratio | stale))
        np.testing.assert_array_equal(got_stale, stale[rows])


def test_association_kernels_equal_the_numpy_expressions() -> None:
    # Features and landmarks scattered over a few metres (gate 0.3 m): some features pair,
    # some landmarks are wanted by two features, ties in distance occur (repeated points).
    rng = np.random.default_rng(5)
    for _ in range(50):
        k, n = int(rng.integers(0, 30)), int(rng.integers(0, 40))
        feature_xy = np.round(rng.uniform(0, 3, (k, 2)), 1)
        landmark_xy = np.round(rng.uniform(0, 3, (n, 2)), 1)
        paired_f = rng.uniform(size=k) < 0.3
        paired_l = rng.uniform(size=n) < 0.3
        # numpy: the unpaired features' nearest unpaired landmark, one feature per landmark
        free_n, free_s = np.flatnonzero(~paired_f), np.flatnonzero(~paired_l)
        want_f, want_l = np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64)
        if free_n.shape[0] and free_s.shape[0]:
            d = np.linalg.norm(feature_xy[free_n][:, None, :] - landmark_xy[free_s][None], axis=2)
            jbest = np.argmin(d, axis=1)
            good = d[np.arange(free_n.shape[0]), jbest] <= 0.3
            cand_n, cand_s = free_n[good], free_s[jbest[good]]
            _, first = np.unique(cand_s, return_index=True)
            want_f, want_l = cand_n[first], cand_s[first]
        got_f, got_l = nearest_free_pairs(feature_xy, paired_f, landmark_xy, paired_l, 0.3)
        assert np.array_equal(got_f, want_f) and np.array_equal(got_l, want_l)
        # numpy: landmarks within the gate of any of the paired features
        paired = np.flatnonzero(paired_f)
        want = np.zeros(n, dtype=bool)
        if paired.shape[0] and n:
            dd = np.linalg.norm(feature_xy[paired][:, None, :] - landmark_xy[None], axis=2)
            want = np.any(dd <= 0.3, axis=0)
        assert np.array_equal(within_gate_of_any(feature_xy, paired, landmark_xy, 0.3), want)


def test_is_ascending_is_the_numpy_expression() -> None:
    rng = np.random.default_rng(9)
    for n in (0, 1, 2, 3, 10, 100):
        for ids in (np.sort(rng.integers(0, 5, n)), rng.integers(0, 5, n), np.arange(n)[::-1]):
            ids = np.ascontiguousarray(ids, dtype=np.int64)
            assert is_ascending(ids) == (n < 2 or bool((ids[1:] >= ids[:-1]).all()))


@pytest.mark.parametrize("seed", range(4))
def test_lookup_sorted_is_numpys_searchsorted(seed: int) -> None:
    # Rows of ids in a sorted table: numpy's left searchsorted clipped to the last row, and
    # whether that row holds the id; ids below, between, equal to and above the table's,
    # repeated queries, and an empty table or query.
    rng = np.random.default_rng(seed)
    for n, q in ((0, 5), (1, 6), (7, 0), (40, 300)):
        table = np.unique(rng.integers(-20, 60, n * 2))[:n].astype(np.int64)
        query = rng.integers(-25, 65, q).astype(np.int64)
        pos, found = lookup_sorted(table, query)
        if n == 0:
            assert not pos.any() and not found.any() and pos.shape == (q,)
            continue
        want = np.minimum(np.searchsorted(table, query), n - 1)
        np.testing.assert_array_equal(pos, want)
        np.testing.assert_array_equal(found, table[want] == query)
        assert set(query[found].tolist()) == set(query.tolist()) & set(table.tolist())


@pytest.mark.parametrize("seed", range(4))
def test_sorted_union_is_numpys_union1d(seed: int) -> None:
    # Ids in any order with repeats, negative ones, one side or both empty.
    rng = np.random.default_rng(seed)
    for n, m in ((0, 0), (0, 4), (5, 0), (1, 1), (20, 120), (300, 7)):
        a = rng.integers(-10, 50, n).astype(np.int64)
        b = rng.integers(-10, 50, m).astype(np.int64)
        got = sorted_union(a, b)
        assert got.dtype == np.int64
        np.testing.assert_array_equal(got, np.union1d(a, b))


def _keep_better_numpy(
    pair_new: np.ndarray,
    pair_row: np.ndarray,
    anchor_in_new: np.ndarray,
    rank: np.ndarray,
    ratio: float,
    obs: FeatureRows,
    lm: dict[str, np.ndarray],
) -> None:
    """The replacement in numpy expressions, as ``FeatureMap`` wrote it before it was
    compiled: the bits :func:`keep_better` must give."""
    tr_new = obs.cov[pair_new, 0, 0] + obs.cov[pair_new, 1, 1]
    tr_old = lm["cov"][pair_row, 0, 0] + lm["cov"][pair_row, 1, 1]
    upgrade = rank[obs.kind[pair_new]] > rank[lm["kind"][pair_row]]
    same = lm["kind"][pair_row] == obs.kind[pair_new]
    rep = np.flatnonzero(upgrade | (same & (tr_new < ratio * tr_old)))
    rr, fi = pair_row[rep], pair_new[rep]
    na = se2.inverse(anchor_in_new[rep])
    lm["xy"][rr], lm["cov"][rr], lm["dirs"][rr] = move_features(fi, na, obs.xy, obs.cov, obs.dirs)
    lm["opening"][rr] = obs.opening[fi]
    lm["kind"][rr] = obs.kind[fi]
    lm["support"][rr] = move_points(na, obs.support[fi], True)
    lm["wall_p"][rr] = move_points(na, obs.wall_p[fi], True)
    lm["wall_d"][rr] = move_points(na, obs.wall_d[fi], False)
    o = na[:, None, :2]
    wpa, wda = lm["wall_p"][rr], lm["wall_d"][rr]
    with np.errstate(invalid="ignore"):
        lm["wall_side"][rr] = np.sign(
            wda[..., 0] * (o[..., 1] - wpa[..., 1]) - wda[..., 1] * (o[..., 0] - wpa[..., 0])
        )


@pytest.mark.parametrize("seed", range(4))
def test_keep_better_is_the_numpy_replacement(seed: int) -> None:
    # Landmarks of three kinds, some paired twice (the last replacement wins), NaN directions
    # and walls (EOWs, Intersections), anchors at headings past +-pi, a wall through the new
    # node's origin (side 0): the compiled pass writes numpy's bits into the table.
    rng = np.random.default_rng(seed)
    k, n_lm, q = 12, 30, 20
    rank = np.array([2, 1, 0], dtype=np.int64)

    def cov(n: int) -> np.ndarray:
        a = rng.normal(size=(n, 2, 2))
        return a @ np.swapaxes(a, 1, 2) * rng.uniform(1e-4, 1e-2, (n, 1, 1))

    def geometry(n: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        support = rng.uniform(-8, 8, (n, 3, 2))
        wall_p = rng.uniform(-8, 8, (n, 2, 2))
        wall_d = rng.normal(size=(n, 2, 2))
        support[::3, 2] = np.nan
        wall_p[::3, 1] = wall_d[::3, 1] = np.nan
        return support, wall_p, wall_d

    dirs = rng.normal(size=(k, 2, 2))
    dirs[::4] = np.nan
    obs = FeatureRows(
        rng.uniform(-8, 8, (k, 2)),
        cov(k),
        dirs,
        rng.uniform(0, 3, k),
        rng.integers(0, 3, k).astype(np.int64),
        *geometry(k),
    )
    table = dict(
        xy=rng.uniform(-8, 8, (n_lm, 2)),
        cov=cov(n_lm),
        dirs=rng.normal(size=(n_lm, 2, 2)),
        opening=rng.uniform(0, 3, n_lm),
        kind=rng.integers(0, 3, n_lm).astype(np.int64),
    )
    table.update(zip(("support", "wall_p", "wall_d"), geometry(n_lm), strict=True))
    table["wall_side"] = np.sign(rng.normal(size=(n_lm, 2)))
    pair_new = rng.integers(0, k, q).astype(np.int64)
    pair_row = rng.integers(0, n_lm - 1, q).astype(np.int64)
    anchor_in_new = np.column_stack([rng.uniform(-5, 5, (q, 2)), rng.uniform(-4, 4, q)])
    # The first pair, an upgrade of the last row, puts the new node on the wall's line: the
    # side is -0.0 before the sign, +0.0 after (numpy's).
    pair_row[0] = n_lm - 1
    obs.kind[pair_new[0]], table["kind"][n_lm - 1] = 0, 2
    obs.wall_p[pair_new[0], 0] = 0.0
    obs.wall_d[pair_new[0], 0] = (1.0, -0.5)
    anchor_in_new[0] = 0.0
    want = {name: a.copy() for name, a in table.items()}
    _keep_better_numpy(pair_new, pair_row, anchor_in_new, rank, 0.5, obs, want)
    got = {name: a.copy() for name, a in table.items()}
    columns = FeatureRows(**{name: got[name] for name in FeatureRows._fields})
    keep_better(pair_new, pair_row, anchor_in_new, rank, 0.5, obs, columns, got["wall_side"])
    for name in table:
        assert np.array_equal(got[name], want[name], equal_nan=True), name
        zero = want[name] == 0.0  # +0.0 and -0.0 alike
        assert np.array_equal(np.signbit(got[name][zero]), np.signbit(want[name][zero])), name
    assert not np.array_equal(want["xy"], table["xy"])  # some replaced
    assert want["wall_side"][n_lm - 1, 0] == 0.0


def _associate_numpy(
    part: np.ndarray,
    lm_id: np.ndarray,
    lm_anchor: np.ndarray,
    lm_xy: np.ndarray,
    tab_ids: np.ndarray,
    tab_poses: np.ndarray,
    new_pose: np.ndarray,
    inlier_pairs: np.ndarray,
    ref_ids: np.ndarray,
    feature_xy: np.ndarray,
    gate: float,
) -> tuple[np.ndarray, ...]:
    """The association in numpy expressions and separate kernels, as ``FeatureMap`` wrote
    it before it was one compiled pass: the answers and bits :func:`associate_scan` must
    give."""
    apos, afound = lookup_sorted(tab_ids, lm_anchor[part])
    rows = part[afound]
    anchor_in_new = poses_in_frame(new_pose, tab_poses, apos[afound])
    xy_new = move_points(anchor_in_new, lm_xy[rows][:, None, :], True)[:, 0]
    slot = np.full(lm_id.shape[0], -1, dtype=np.int64)
    slot[rows] = np.arange(rows.shape[0])
    pairs = inlier_pairs[(inlier_pairs[:, 0] >= 0) & (inlier_pairs[:, 0] < feature_xy.shape[0])]
    pairs = pairs[(pairs[:, 1] >= 0) & (pairs[:, 1] < ref_ids.shape[0])]
    lpos, lfound = lookup_sorted(lm_id, ref_ids[pairs[:, 1]])
    ok = lfound & (slot[lpos] >= 0)
    pair_new, pair_row = pairs[ok, 0], lpos[ok]
    feature_paired = np.zeros(feature_xy.shape[0], dtype=bool)
    feature_paired[pair_new] = True
    slot_paired = np.zeros(rows.shape[0], dtype=bool)
    slot_paired[slot[pair_row]] = True
    new_f, new_s = nearest_free_pairs(feature_xy, feature_paired, xy_new, slot_paired, gate)
    pair_new = np.concatenate([pair_new, new_f])
    pair_row = np.concatenate([pair_row, rows[new_s]])
    merge = np.zeros(0, dtype=np.int64)
    if pair_new.shape[0] and rows.shape[0]:
        close = within_gate_of_any(feature_xy, pair_new, xy_new, gate)
        close[slot[pair_row]] = False
        merge = rows[close]
    return rows, anchor_in_new, xy_new, slot, pair_new, pair_row, merge


@pytest.mark.parametrize("seed", range(6))
def test_associate_scan_is_the_numpy_association(seed: int) -> None:
    # Landmarks clustered so that gates overlap (pairs, contested landmarks, duplicates),
    # anchors without a pose, the matcher's pairs with indices out of range and landmarks
    # that do not take part; headings past +-pi; an empty map or scan now and then.
    rng = np.random.default_rng(seed)
    n_lm = int(rng.choice([0, 5, 40]))
    k = int(rng.choice([0, 3, 15]))
    lm_id = np.unique(rng.integers(0, 200, n_lm * 2))[:n_lm].astype(np.int64)
    n_lm = lm_id.shape[0]
    lm_anchor = rng.integers(0, 12, n_lm).astype(np.int64)
    lm_xy = rng.uniform(-3, 3, (n_lm, 2))
    tab_ids = np.unique(rng.integers(0, 12, 9)).astype(np.int64)
    tab_poses = np.column_stack(
        [rng.uniform(-1, 1, (tab_ids.shape[0], 2)), rng.uniform(-4, 4, tab_ids.shape[0])]
    )
    part = np.flatnonzero(rng.uniform(size=n_lm) < 0.8).astype(np.int64)
    new_pose = np.array([0.2, -0.1, float(rng.uniform(-4, 4))])
    feature_xy = rng.uniform(-3, 3, (k, 2))
    ref_ids = np.concatenate([lm_id[rng.permutation(n_lm)[: n_lm // 2]], [999]]).astype(np.int64)
    inlier_pairs = np.column_stack(
        [rng.integers(-1, k + 1, 8), rng.integers(-1, ref_ids.shape[0] + 1, 8)]
    ).astype(np.int64)
    ax, ay, at = se2.inverse(new_pose).tolist()
    new_inverse = np.array([ax, ay, at, math.cos(at), math.sin(at)])
    table = (part, lm_id, lm_anchor, lm_xy, tab_ids, tab_poses)
    scan = (inlier_pairs, ref_ids, feature_xy, 1.0)
    got = associate_scan(*table, new_inverse, *scan)
    want = _associate_numpy(*table, new_pose, *scan)
    for a, b in zip(got, want, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert np.array_equal(a, b)


@pytest.mark.parametrize("seed", range(4))
def test_count_observations_is_the_numpy_update(seed: int) -> None:
    # Counters of landmarks taking part or not, matched ones repeated among the pairs,
    # expected ones already missing (their first miss kept) or not: the compiled update
    # gives the numpy expressions' counters and rows.
    rng = np.random.default_rng(seed)
    n_lm = 40
    rows = rng.permutation(n_lm)[: int(rng.integers(0, 30))].astype(np.int64)
    expected = rng.uniform(size=rows.shape[0]) < 0.6
    pair_row = rng.choice(rows, int(rng.integers(0, 12))) if rows.shape[0] else rows[:0]
    counters = dict(
        n_expected=rng.integers(0, 9, n_lm),
        n_matched=rng.integers(0, 9, n_lm),
        misses=rng.integers(0, 4, n_lm),
        first_miss_s=np.where(rng.uniform(size=n_lm) < 0.5, np.nan, rng.uniform(0, 9, n_lm)),
        last_matched_s=rng.uniform(0, 9, n_lm),
        last_node=rng.integers(0, 50, n_lm),
    )
    want = {name: a.copy() for name, a in counters.items()}
    matched = np.unique(pair_row)
    is_matched = np.zeros(n_lm, dtype=bool)
    is_matched[matched] = True
    exp_rows = rows[expected | is_matched[rows]]
    want["n_expected"][exp_rows] += 1
    want["n_matched"][matched] += 1
    want["last_matched_s"][matched] = 10.0
    want["misses"][matched] = 0
    want["first_miss_s"][matched] = np.nan
    want["last_node"][matched] = 77
    miss_rows = rows[expected & ~is_matched[rows]]
    want["misses"][miss_rows] += 1
    first = miss_rows[np.isnan(want["first_miss_s"][miss_rows])]
    want["first_miss_s"][first] = 10.0
    got = {name: a.copy() for name, a in counters.items()}
    got_matched, got_expected = count_observations(
        rows, expected, pair_row.astype(np.int64), 10.0, 77, *got.values()
    )
    assert np.array_equal(got_matched, matched) and np.array_equal(got_expected, exp_rows)
    for name in counters:
        assert np.array_equal(got[name], want[name], equal_nan=True), name


@pytest.mark.parametrize("seed", range(4))
def test_rows_of_nodes_are_the_lookups_rows(seed: int) -> None:
    # Wanted nodes as a run of consecutive ids (the range test) or with gaps (the binary
    # search), one node, none; rows anchored or last matched inside, outside and at the
    # run's ends.
    rng = np.random.default_rng(seed)
    anchor = rng.integers(0, 60, 300).astype(np.int64)
    last_node = np.maximum(anchor, rng.integers(0, 60, 300)).astype(np.int64)
    for want in (
        np.arange(20, 40, dtype=np.int64),
        np.unique(rng.integers(0, 60, 15)).astype(np.int64),
        np.array([33], dtype=np.int64),
        np.zeros(0, dtype=np.int64),
    ):
        expected = np.flatnonzero(
            lookup_sorted(want, anchor)[1] | lookup_sorted(want, last_node)[1]
        )
        assert np.array_equal(rows_of_nodes(want, anchor, last_node), expected)
    assert rows_of_nodes(np.arange(3, dtype=np.int64), anchor[:0], last_node[:0]).shape == (0,)


@pytest.mark.parametrize("seed", range(4))
def test_rows_taking_part_are_the_numpy_expressions(seed: int) -> None:
    # The bookkeeping's rows (one compiled pass): those last matched from a recent node, and
    # the rows of the reference's ids (in any order, some absent), as the numpy mask built
    # them; no table, no reference, a bound past every node.
    rng = np.random.default_rng(seed)
    ids = np.unique(rng.integers(0, 900, 300)).astype(np.int64)
    last_node = rng.integers(0, 60, ids.shape[0]).astype(np.int64)
    for first in (0, 45, 61):
        for ref in (
            rng.choice(ids, 25, replace=False),
            rng.integers(0, 900, 25).astype(np.int64),
            np.zeros(0, dtype=np.int64),
        ):
            part = last_node >= first
            pos, found = lookup_sorted(ids, ref)
            part[pos[found]] = True
            got = rows_taking_part(last_node, first, ids, ref)
            assert np.array_equal(got, np.flatnonzero(part))
    none = np.zeros(0, dtype=np.int64)
    assert rows_taking_part(none, 3, none, np.arange(3, dtype=np.int64)).shape == (0,)


def test_poses_in_frame_are_the_bits_of_se2_between() -> None:
    # The compiled gather-and-compose against se2.between on the gathered rows: the same
    # expressions in the same order, so the same bits (headings at +-pi and beyond wrap
    # alike); repeated and empty rows.
    rng = np.random.default_rng(5)
    poses = np.column_stack([rng.normal(0, 50, (400, 2)), rng.uniform(-7, 7, 400)])
    poses[:5, 2] = [np.pi, -np.pi, 0.0, 2 * np.pi, -3 * np.pi]
    for _ in range(50):
        frame = np.array([*rng.normal(0, 50, 2), rng.uniform(-4, 4)])
        rows = rng.integers(0, 400, 300)
        got = poses_in_frame(frame, poses, rows)
        assert np.array_equal(got.view(np.int64), se2.between(frame, poses[rows]).view(np.int64))
    assert poses_in_frame(poses[0], poses, np.zeros(0, dtype=np.int64)).shape == (0, 3)


def test_frame_inverse_is_se2_inverse_with_its_cosine_and_sine() -> None:
    # The frame's inverse as the compiled passes read it: se2.inverse's bits (headings at and
    # beyond +-pi, a non-finite one through numpy's path), then libm's cosine and sine.
    rng = np.random.default_rng(11)
    frames = [np.array([*rng.normal(0, 50, 2), t]) for t in rng.uniform(-9, 9, 40)]
    frames += [np.array([1.0, 2.0, t]) for t in (np.pi, -np.pi, 0.0, -0.0, np.inf, np.nan)]
    for frame in frames:
        with np.errstate(invalid="ignore"):  # the non-finite headings
            ax, ay, at = se2.inverse(frame).tolist()
            got = frame_inverse(frame)
        want = np.array([ax, ay, at, math.cos(at), math.sin(at)])
        assert np.array_equal(got.view(np.int64), want.view(np.int64))


@pytest.mark.parametrize("seed", range(4))
def test_reference_geometry_is_the_frame_changes_one_by_one(seed: int) -> None:
    # The reference's one compiled pass against the separate calls it fuses (the anchors'
    # and the segments' nodes placed by poses_in_frame, then move_features, move_lines and
    # move_points): the same bits. Landmarks whose anchor has no pose are left out; headings
    # past +-pi; no landmark or no segment now and then.
    rng = np.random.default_rng(seed)
    tab_ids = np.unique(rng.integers(0, 30, 20)).astype(np.int64)
    tab_poses = np.column_stack(
        [rng.normal(0, 30, (tab_ids.shape[0], 2)), rng.uniform(-5, 5, tab_ids.shape[0])]
    )
    frame = np.array([*rng.normal(0, 30, 2), rng.uniform(-5, 5)])
    n_lm, n_seg = (0, 12) if seed == 1 else (60, 0) if seed == 2 else (60, 40)
    lm_anchor = rng.integers(0, 30, n_lm).astype(np.int64)
    lm_xy = rng.uniform(-10, 10, (n_lm, 2))
    q = rng.normal(size=(n_lm, 2, 2))
    lm_cov = q @ np.swapaxes(q, 1, 2) * 1e-3
    lm_dirs = rng.normal(size=(n_lm, 2, 2))
    lm_dirs[::3] = np.nan
    lm_rows = np.flatnonzero(rng.uniform(size=n_lm) < 0.7).astype(np.int64)
    seg_node = np.sort(rng.choice(tab_ids, n_seg)).astype(np.int64)
    seg_ep = rng.uniform(-10, 10, (n_seg, 2, 2))
    seg_lines = np.column_stack([rng.uniform(-np.pi, np.pi, n_seg), rng.uniform(0, 8, n_seg)])
    w = rng.normal(size=(n_seg, 2, 2))
    seg_cov = w @ np.swapaxes(w, 1, 2) * 1e-4
    seg_rows = np.flatnonzero(rng.uniform(size=n_seg) < 0.6).astype(np.int64)
    got = reference_geometry(
        tab_ids,
        tab_poses,
        frame_inverse(frame),
        lm_rows,
        lm_anchor,
        lm_xy,
        lm_cov,
        lm_dirs,
        seg_rows,
        seg_node,
        seg_ep,
        seg_lines,
        seg_cov,
    )
    apos, afound = lookup_sorted(tab_ids, lm_anchor[lm_rows])
    rows = lm_rows[afound]
    anchors = poses_in_frame(frame, tab_poses, apos[afound])
    spos, _ = lookup_sorted(tab_ids, seg_node[seg_rows])
    nodes = poses_in_frame(frame, tab_poses, spos)
    want = (
        rows,
        *move_features(rows, anchors, lm_xy, lm_cov, lm_dirs),
        move_points(nodes, seg_ep[seg_rows], True),
        *move_lines(seg_rows, nodes, seg_lines, seg_cov),
    )
    assert 0 < rows.shape[0] < lm_rows.shape[0] or n_lm == 0
    for a, b in zip(got, want, strict=True):
        assert a.dtype == b.dtype and a.shape == b.shape
        assert np.array_equal(a, b, equal_nan=a.dtype.kind == "f")


def test_moved_geometry_equals_the_numpy_expressions() -> None:
    # The compiled frame changes of the feature map against the numpy expressions they
    # replaced (R p + t, R C R^T, R d, the line transform): equal to rounding, NaN directions
    # kept NaN, lines that flip (rho < 0 after the move) included.
    rng = np.random.default_rng(3)
    n_all, n = 50, 30
    rows = rng.choice(n_all, n, replace=False).astype(np.int64)
    poses = np.column_stack([rng.uniform(-20, 20, (n, 2)), rng.uniform(-np.pi, np.pi, n)])
    r = rotation_matrix(poses[:, 2])
    xy = rng.uniform(-10, 10, (n_all, 2))
    q = rng.normal(size=(n_all, 2, 2))
    cov = q @ np.swapaxes(q, 1, 2) * 1e-3
    dirs = rng.normal(size=(n_all, 2, 2))
    dirs[::4] = np.nan  # Intersections: no directions
    got = move_features(rows, poses, xy, cov, dirs)
    want = (
        np.einsum("nab,nb->na", r, xy[rows]) + poses[:, :2],
        r @ cov[rows] @ np.swapaxes(r, 1, 2),
        np.einsum("nab,nkb->nka", r, dirs[rows]),
    )
    for a, b in zip(got, want, strict=True):
        np.testing.assert_allclose(a, b, rtol=1e-13, atol=1e-13)
    pts = rng.uniform(-10, 10, (n, 3, 2))
    pts[::5, 2] = np.nan
    np.testing.assert_allclose(
        move_points(poses, pts, True),
        np.einsum("nab,nkb->nka", r, pts) + poses[:, None, :2],
        rtol=1e-13,
        atol=1e-13,
    )
    np.testing.assert_allclose(
        move_points(poses, pts, False), np.einsum("nab,nkb->nka", r, pts), rtol=1e-13, atol=1e-13
    )
    # blocks of points, some empty: the bits of move_points with each pose repeated
    counts = rng.integers(0, 4, n)
    block_pts = rng.uniform(-10, 10, (int(counts.sum()), 2))
    assert np.array_equal(
        move_point_blocks(poses, counts, block_pts),
        move_points(np.repeat(poses, counts, axis=0), block_pts[:, None, :], True)[:, 0],
    )
    lines = np.column_stack([rng.uniform(-np.pi, np.pi, n_all), rng.uniform(0, 8, n_all)])
    lcov = q @ np.swapaxes(q, 1, 2) * 1e-4
    got_lines, got_cov = move_lines(rows, poses, lines, lcov)
    # the numpy expressions: alpha' = alpha + theta, rho' = rho + n' . t, flipped to rho' >= 0,
    # the covariance by J = [[1, 0], [d rho' / d alpha, 1]] (second row negated by a flip)
    a = lines[rows, 0] + poses[:, 2]
    rho = lines[rows, 1] + np.cos(a) * poses[:, 0] + np.sin(a) * poses[:, 1]
    jac = np.zeros((n, 2, 2))
    jac[:, 0, 0] = jac[:, 1, 1] = 1.0
    jac[:, 1, 0] = -np.sin(a) * poses[:, 0] + np.cos(a) * poses[:, 1]
    flip = rho < 0
    jac[flip, 1, :] *= -1.0
    want_lines = np.column_stack([wrap_angle(np.where(flip, a + np.pi, a)), np.abs(rho)])
    np.testing.assert_allclose(got_lines, want_lines, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(got_cov, jac @ lcov[rows] @ np.swapaxes(jac, 1, 2), rtol=1e-12)
    assert 5 < np.count_nonzero(flip) < n - 5


def _numpy_visibility_geometry(features: ScanFeatures, offset_m: float) -> tuple[np.ndarray, ...]:
    """The numpy expressions ``visibility_geometry`` compiled (``feature_map._geometry``)."""
    k = features.n_features
    support, wall_p, wall_d = (np.full((k, n, 2), np.nan) for n in (3, 2, 2))
    xy, d = features.xy, features.directions
    direct = features.kind != int(FeatureKind.INTERSECTION)
    support[direct, 0] = xy[direct]
    support[direct, 1] = xy[direct] + offset_m * d[direct, 0]
    support[direct, 2] = xy[direct] + offset_m * d[direct, 1]
    wall_p[direct] = xy[direct, None, :]
    wall_d[direct] = d[direct]
    inter = np.flatnonzero(~direct)
    for slot in (0, 1):
        sid = features.segment_ids[inter, slot]
        ok = (sid >= 0) & (sid < features.n_segments)
        rows = inter[ok]
        ep = features.seg_endpoints[sid[ok]]
        near_k = np.argmin(np.linalg.norm(ep - xy[rows, None, :], axis=2), axis=1)
        ar = np.arange(rows.shape[0])
        near, far = ep[ar, near_k], ep[ar, 1 - near_k]
        u = far - near
        u /= np.maximum(np.linalg.norm(u, axis=1), 1e-9)[:, None]
        support[rows, slot] = near + offset_m * u
        wall_p[rows, slot] = near
        wall_d[rows, slot] = u
    with np.errstate(invalid="ignore"):
        side = np.sign(wall_d[..., 1] * wall_p[..., 0] - wall_d[..., 0] * wall_p[..., 1])
    return support, wall_p, wall_d, side


def test_visibility_geometry_equals_the_numpy_expressions_bit_for_bit() -> None:
    # The support points, walls and sides of every feature of a simulated office run (with
    # a laser off the robot's centre), compiled, against the numpy expressions they
    # replaced: the same bits, NaN rows included.
    run = simulate(office_world(), seed=6)
    n_inter = 0
    for scan in run.scans[::6]:
        for offset in (0.0, 0.3):
            f = extract(dataclasses.replace(scan, laser_offset=np.array([0.2, 0.1, 0.1])))
            got = feature_map._geometry(f, offset)
            want = _numpy_visibility_geometry(f, offset)
            for a, b in zip(got, want, strict=True):
                assert (a.shape, a.tobytes()) == (b.shape, b.tobytes())
            n_inter += int(np.count_nonzero(f.kind == int(FeatureKind.INTERSECTION)))
    assert n_inter > 100


def test_beam_profile_equals_the_numpy_expressions_bit_for_bit() -> None:
    # A scan's beams by bearing for the visibility test, compiled, against the numpy
    # expressions they replaced: valid returns keep their range, a finite return at or
    # beyond the maximum range is inf (it blocks nothing), other invalid beams 0; the
    # median step between bearings (odd and even counts of steps).
    run = simulate(office_world(), seed=7)
    n_inf = 0
    for scan in run.scans[::20]:
        blocked = np.where(np.arange(scan.n_beams) % 7 == 0, np.inf, 30.0)
        for ranges in (scan.ranges_m, blocked):
            for n in (scan.n_beams, scan.n_beams - 1):
                s = dataclasses.replace(
                    scan, ranges_m=np.array(ranges[:n]), angles_rad=scan.angles_rad[:n]
                )
                got = feature_map._BeamProfile.of_scan(s)
                order = np.argsort(s.angles_rad, kind="stable")
                rng = s.ranges_m[order]
                with np.errstate(invalid="ignore"):
                    beyond = np.isfinite(rng) & (rng >= s.range_max_m)
                want = np.where(s.valid_mask()[order], rng, np.where(beyond, np.inf, 0.0))
                assert got.bearing.tobytes() == s.angles_rad[order].tobytes()
                assert got.range_m.tobytes() == want.tobytes()
                step = float(np.median(np.diff(s.angles_rad[order])))
                assert np.float64(got.spacing_rad).tobytes() == np.float64(step).tobytes()
                n_inf += int(np.count_nonzero(np.isinf(got.range_m)))
    assert n_inf > 100
