"""Sessions: save, load and continue bit for bit; scans by reference; loop_closures.csv."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from frontends import LaserScan
from frontends.simulate import OdometryModel, office_world, simulate
from graph import GraphConfig, PoseGraph
from graph.pose_graph import STEP_BATCH_CORRECTION
from iceg import session
from iceg.config import config_from_dict
from iceg.pipeline import run_log
from iceg.scan_store import ScanStore
from iceg.slam import Slam
from iceg.types import MatchResult
from iceg_common.errors import SessionError
from tests.iceg.test_scan_store import scan_lists

N_SCANS = 260  # office prefix: enough for nodes, matches and map pruning, a few seconds


@pytest.fixture(scope="module")
def office_scans():  # type: ignore[no-untyped-def]
    return simulate(office_world(), seed=1).scans[:N_SCANS]


@pytest.fixture(scope="module")
def whole(office_scans):  # type: ignore[no-untyped-def]
    slam = Slam()
    for scan in office_scans:
        slam.process(scan)
    return slam.finish()


def _split_run(scans, k, folder):  # type: ignore[no-untyped-def]
    first = Slam()
    for scan in scans[:k]:
        first.process(scan)
    first.finish()  # the batch refinement of the first run must not leak into the second
    session.save(first, folder)
    second = session.load(folder)
    for scan in scans[k:]:
        second.process(scan)
    return second.finish()


@pytest.mark.parametrize("k", [1, 97, 200])
def test_split_run_equals_the_whole_run_bit_for_bit(office_scans, whole, tmp_path, k) -> None:  # type: ignore[no-untyped-def]
    split = _split_run(office_scans, k, tmp_path / "s")
    assert np.array_equal(split.stamps_s, whole.stamps_s)
    assert np.array_equal(split.poses, whole.poses)  # bit for bit, not approximately
    assert np.array_equal(split.node_poses, whole.node_poses)
    assert [f.kind for f in split.factors] == [f.kind for f in whole.factors]
    assert split.graph.steps == whole.graph.steps
    fa, fb = split.feature_map.export_state(), whole.feature_map.export_state()
    assert fa.keys() == fb.keys()
    for key in fa:
        assert np.array_equal(fa[key], fb[key], equal_nan=True), key
    pa, pb = split.slam.loop_closer.places, whole.slam.loop_closer.places
    for key, value in pa.export_state().items():
        assert np.array_equal(value, pb.export_state()[key]), key
    assert np.array_equal(
        split.slam.odometry_calibrator.export_state(),
        whole.slam.odometry_calibrator.export_state(),
    )


def test_disputed_steps_are_saved_and_restored(office_scans, tmp_path) -> None:  # type: ignore[no-untyped-def]
    # A disputed keyframe step (a failed tracking match's unverified hypothesis, which a
    # later closure may confirm) is state a continued run decides with: saved and loaded
    # as it was, every bit; a session without them (saved before) loads with none.
    first = Slam()
    for scan in office_scans[:97]:
        first.process(scan)
    hypothesis = MatchResult(
        True, np.array([0.21, -0.013, -0.37]), np.diag([4e-4, 1e-4, 2e-5]), 0.31
    )
    first.export_state().disputed[12] = hypothesis
    session.save(first, tmp_path / "s")
    got = session.load(tmp_path / "s").export_state().disputed
    assert list(got) == [12]
    assert np.array_equal(got[12].pose, hypothesis.pose)
    assert np.array_equal(got[12].cov, hypothesis.cov)
    assert got[12].correlation == hypothesis.correlation
    first.export_state().disputed.clear()
    session.save(first, tmp_path / "none")
    assert session.load(tmp_path / "none").export_state().disputed == {}


def test_split_run_with_odometry_calibration_is_bit_identical(office_scans, tmp_path) -> None:  # type: ignore[no-untyped-def]
    config = config_from_dict({"odometry_calibration": {"enabled": True}})
    whole = Slam(config)
    for scan in office_scans:
        whole.process(scan)
    w = whole.finish()
    first = Slam(config)
    for scan in office_scans[:120]:
        first.process(scan)
    first.finish()
    session.save(first, tmp_path / "s")
    second = session.load(tmp_path / "s")
    assert second.odometry_calibrator.n_observations > 0
    for scan in office_scans[120:]:
        second.process(scan)
    assert np.array_equal(second.finish().poses, w.poses)


def test_a_session_saved_while_auto_corrects_continues_bit_for_bit(tmp_path) -> None:  # type: ignore[no-untyped-def]
    # The office with its heading drifting 2 deg/m: by default (odometry_calibration
    # "auto") the run starts correcting once its matches show the drift beyond the noise
    # model. Saved after that, the loaded session corrects from its first scan on, as the
    # whole run does.
    drifting = OdometryModel.biased(scale_error=0.01, heading_drift_deg_per_m=2.0)
    scans = simulate(office_world(), seed=1, odometry=drifting).scans[:N_SCANS]
    whole = Slam()
    for scan in scans:
        whole.process(scan)
    w = whole.finish()
    first = Slam()
    k = 0
    while not first.odometry_calibrator.correcting:
        first.process(scans[k])
        k += 1
    assert k < N_SCANS - 20
    for scan in scans[k : k + 10]:
        first.process(scan)
    first.finish()
    session.save(first, tmp_path / "s")
    second = session.load(tmp_path / "s")
    assert second.odometry_calibrator.correcting
    for scan in scans[k + 10 :]:
        second.process(scan)
    assert np.array_equal(second.finish().poses, w.poses)


def test_split_run_between_deferred_isam2_updates_is_bit_identical(office_scans, tmp_path) -> None:  # type: ignore[no-untyped-def]
    # A long run defers its iSAM2 updates (here from 40 nodes on): saved while keyframes wait
    # for the next update, the session buffers them again.
    config = config_from_dict({"slam": {"isam2_defer_from_nodes": 40}})
    whole = Slam(config)
    for scan in office_scans:
        whole.process(scan)
    w = whole.finish()
    first = Slam(config)
    k = 97
    for scan in office_scans[:k]:
        first.process(scan)
    while first.graph.n_pending[0] == 0:
        first.process(office_scans[k])
        k += 1
    buffered = first.graph.n_pending
    first.finish()
    session.save(first, tmp_path / "s")
    second = session.load(tmp_path / "s")
    assert second.graph.n_pending == buffered
    for scan in office_scans[k:]:
        second.process(scan)
    split = second.finish()
    assert np.array_equal(split.poses, w.poses)
    assert split.graph.steps == w.graph.steps


def test_session_files_are_documented_formats_without_pickle(whole, tmp_path) -> None:  # type: ignore[no-untyped-def]
    folder = session.save(whole.slam, tmp_path / "s")
    assert sorted(p.name for p in folder.iterdir()) == sorted(session.SESSION_FILES)
    manifest = json.loads((folder / "manifest.json").read_text())
    assert manifest["format"] == "iceg-session" and manifest["version"] == 1
    assert manifest["nodes"] == whole.node_ids.shape[0]
    with np.load(folder / "state.npz", allow_pickle=False) as npz:
        assert all(npz[k].dtype != object for k in npz.files)
        assert np.array_equal(npz["g_node_final"], whole.node_poses)
    g2o = (folder / "graph.g2o").read_text().splitlines()
    assert sum(line.startswith("VERTEX_SE2") for line in g2o) == whole.node_ids.shape[0]
    stamps, poses = session.read(folder).trajectory()
    assert np.array_equal(poses, whole.poses) and np.array_equal(stamps, whole.stamps_s)


def test_scans_are_re_read_from_the_log_by_reference_and_checked(office_scans, tmp_path) -> None:  # type: ignore[no-untyped-def]
    log = tmp_path / "office.clf"
    simulate(office_world(), seed=1).write_carmen(log)
    result = run_log(log)
    out = result.save(tmp_path / "run")
    folder = out / session.SESSION_DIR
    a = session.read(folder).arrays
    assert np.all(a["s_log"] == 0) and a["inline_meta"].shape[0] == 0
    slam = session.load(out)  # the run folder works too
    rescans = slam.export_state().scans
    assert [s.source.rpartition(":")[2] for s in rescans] == [
        s.source.rpartition(":")[2] for s in result.scans
    ]
    assert [session.scan_hash(s) for s in rescans] == [session.scan_hash(s) for s in result.scans]
    # a changed log is refused, not silently used
    lines = log.read_text().splitlines(keepends=True)
    k = next(i for i, line in enumerate(lines) if line.startswith("FLASER"))
    fields = lines[k].split(" ")
    fields[5] = "7.777"
    lines[k] = " ".join(fields)
    log.write_text("".join(lines))
    with pytest.raises(SessionError, match="content hash"):
        session.load(folder)


@settings(max_examples=40, deadline=None)
@given(scans=scan_lists(), from_log=st.lists(st.booleans(), min_size=40, max_size=40))
def test_a_store_s_scan_references_are_its_scans(
    scans: list[LaserScan], from_log: list[bool], tmp_path_factory: pytest.TempPathFactory
) -> None:
    """A store's references and hashes, taken from its arrays without building its scans
    (a few scans' beams at a time), are those of the scans it gives back."""
    folder = tmp_path_factory.mktemp("refs")
    log = folder / "run.clf"
    log.write_text("")
    # some scans from a log on disk (by reference), the others inline
    scans = [
        replace(s, source=f"{log}:{k + 1}") if f else s
        for k, (s, f) in enumerate(zip(scans, from_log, strict=False))
    ]
    store = ScanStore(scans)
    session._HASH_CHUNK_SCANS, chunk = 3, session._HASH_CHUNK_SCANS
    try:
        arrays, logs = session.scan_arrays(store, folder)
    finally:
        session._HASH_CHUNK_SCANS = chunk
    expected, expected_logs = session.scan_arrays(list(store), folder)
    assert logs == expected_logs
    assert arrays.keys() == expected.keys()
    for key, value in expected.items():
        np.testing.assert_array_equal(arrays[key], value)
    assert arrays["s_hash"].tolist() == [session.scan_hash(s) for s in scans]


def test_unknown_version_and_non_session_are_refused(whole, tmp_path) -> None:  # type: ignore[no-untyped-def]
    with pytest.raises(SessionError, match="not a readable"):
        session.read(tmp_path)
    folder = session.save(whole.slam, tmp_path / "s")
    manifest = json.loads((folder / "manifest.json").read_text())
    manifest["version"] = 99
    (folder / "manifest.json").write_text(json.dumps(manifest))
    with pytest.raises(SessionError, match="version 99"):
        session.read(folder)


def test_loop_closures_csv_lists_each_closure_with_its_chi2(whole, tmp_path) -> None:  # type: ignore[no-untyped-def]
    folder = session.save(whole.slam, tmp_path / "s")
    rows = session.read_closures_csv(folder / "loop_closures.csv")
    lc = [f for f in whole.factors if f.kind.value == "loop_closure"]
    accepted = [r for r in rows if r["status"] == "accepted"]
    held = [r for r in rows if r["status"] == "held_back"]
    assert len(accepted) == len(lc)
    assert len(held) == len(whole.slam.loop_closer.pending)
    for r, f in zip(accepted, lc, strict=True):
        assert int(r["factor"]) == f.index and (int(r["node_i"]), int(r["node_j"])) == (f.i, f.j)
        assert float(r["x_m"]) == f.measured[0]
        assert 0.0 <= float(r["chi2"]) < 16.27  # accepted closures agree with the optimum
        assert r["why"]


def test_a_state_without_a_needed_array_is_refused(whole, tmp_path) -> None:  # type: ignore[no-untyped-def]
    folder = session.save(whole.slam, tmp_path / "s")
    with np.load(folder / "state.npz", allow_pickle=False) as npz:
        arrays = {k: npz[k] for k in npz.files if k != "cal_state"}
    np.savez(folder / "state.npz", **arrays)
    with pytest.raises(SessionError, match="lacks cal_state"):
        session.load(folder)


def test_the_solver_log_replays_a_correction_solve_bit_for_bit() -> None:
    # A mid-run correction solve (optimize_batch(correction=True), its own tolerance) is logged
    # as its own step; replaying the log rebuilds the same estimates bit for bit, and an
    # update after it gives the same iSAM2 state in both.
    cov = np.diag([1e-3, 1e-3, 1e-4])
    g = PoseGraph()
    for k in range(8):
        g.add_node(k, [1.05 * k, 0.02 * k * k, 0.01 * k])
        if k:
            g.add_between(k - 1, k, [1.0, 0.0, 0.0], cov)
        if k == 4:
            g.update()
    g.add_between(7, 0, [-7.0, 0.3, 0.0], cov, kind="loop_closure", robust="cauchy")
    g.optimize_batch(correction=True)
    g.add_node(8, [8.0, 0.0, 0.0])
    g.add_between(7, 8, [1.0, 0.0, 0.0], cov)
    g.update()
    assert STEP_BATCH_CORRECTION in [s[0] for s in g.steps]
    again = session.replay_graph(session.graph_arrays(g), GraphConfig())
    assert again.steps == g.steps
    assert np.array_equal(again.estimates()[1], g.estimates()[1])
