"""``iceg merge``: two sessions of one building become one graph and one map."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from typer.testing import CliRunner

from frontends.simulate import office_world, simulate, simulate_scenario
from iceg import session
from iceg.cli import app
from iceg.evaluation import position_errors
from iceg.slam import Slam
from iceg_common import se2

B_FRAME = np.array([3.0, -7.0, 1.0])  # session B's odometry (hence map) frame


def _session(scans, folder):  # type: ignore[no-untyped-def]
    slam = Slam()
    for scan in scans:
        slam.process(scan)
    slam.finish()
    return session.save(slam, folder)


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):  # type: ignore[no-untyped-def]
    run = simulate(office_world(), seed=1)
    root = tmp_path_factory.mktemp("merge")
    b_scans = [
        dataclasses.replace(s, odom_pose=se2.compose(B_FRAME, s.odom_pose))
        for s in run.scans[200:450]
    ]
    return run, root, _session(run.scans[:260], root / "A"), _session(b_scans, root / "B")


def test_merge_links_the_sessions_in_one_frame(sessions) -> None:  # type: ignore[no-untyped-def]
    run, root, a, b = sessions
    r = CliRunner().invoke(app, ["merge", str(a), str(b), "--out", str(root / "C")])
    assert r.exit_code == 0, r.output
    merged = session.read(root / "C")
    n_a = session.read(a).manifest["nodes"]
    assert merged.manifest["nodes"] == n_a + session.read(b).manifest["nodes"]
    kinds = merged.arrays["g_kind"].tolist()
    assert kinds.count(0) == 1  # one prior: A's
    inter = [
        r
        for r in session.read_closures_csv(root / "C" / "session" / "loop_closures.csv")
        if int(r["node_i"]) < n_a <= int(r["node_j"])
    ]
    assert len(inter) >= 2
    _, poses = merged.trajectory()
    truth = np.concatenate([run.true_poses[:260], run.true_poses[200:450]])
    # A's map frame is the truth frame: B lands in it without any alignment
    assert position_errors(poses, truth, align=False).max_m < 0.06
    slam = session.load(root / "C")  # the merged session continues
    assert slam.graph.n_nodes == merged.manifest["nodes"]


def test_merge_refuses_another_building(sessions, tmp_path) -> None:  # type: ignore[no-untyped-def]
    _, _, a, _ = sessions
    other = _session(simulate_scenario("outdoor", seed=2).scans[:120], tmp_path / "O")
    r = CliRunner().invoke(app, ["merge", str(a), str(other), "--out", str(tmp_path / "C")])
    assert r.exit_code == 1
    assert "same building" in r.output
