"""g2o write/read: exact round trip, compatibility with gtsam's own writer, foreign files.

Truth: the graph that was written (round trip), the numbers printed in the data file itself
(parsed here with plain Python), and gtsam.readG2o of a file written by gtsam.writeG2o.
"""

from __future__ import annotations

from pathlib import Path

import gtsam
import numpy as np
import pytest

from graph import GraphConfig, PoseGraph, load_g2o
from iceg_common.errors import GraphError
from iceg_common.se2 import compose
from tests.conftest import shared_file


def _mixed_graph() -> PoseGraph:
    rng = np.random.default_rng(3)
    g = PoseGraph(GraphConfig(prior_sigma_xy_m=0.002))
    pose = np.array([10.123456789012345, -3.3, 0.4])
    g.add_node(0, pose)
    for k in range(1, 8):
        z = np.array([1.0 + 0.1 * k, 0.05 * k, 0.3 - 0.07 * k])
        pose = compose(pose, z)
        g.add_node(k, pose + rng.normal(scale=0.01, size=3))
        a = rng.normal(size=(3, 3)) * 0.1
        kind = "scan_match" if k % 2 else "odometry"
        g.add_between(k - 1, k, z, a @ a.T + np.diag([1e-3, 1e-3, 1e-4]), kind=kind)
    g.add_between(0, 5, [4.0, 2.5, -0.9], np.diag([0.04, 0.04, 0.01]), "loop_closure", "huber")
    g.add_between(
        2, 7, [4.8, -1.0, -1.1], np.diag([0.04, 0.09, 0.02]), "loop_closure", "cauchy", 3.5
    )
    g.add_prior(3, [13.0, 0.2, 0.5], np.array([[0.5, 0.1, 0.0], [0.1, 0.4, 0.0], [0, 0, 0.3]]))
    return g


def _assert_same_factors(a: PoseGraph, b: PoseGraph) -> None:
    assert a.n_factors == b.n_factors
    for fa, fb in zip(a.factors, b.factors, strict=True):
        assert (fa.kind, fa.i, fa.j, fa.robust, fa.robust_k) == (
            fb.kind,
            fb.i,
            fb.j,
            fb.robust,
            fb.robust_k,
        )
        # exact up to one ulp: gtsam stores the heading as (cos, sin) and returns atan2
        np.testing.assert_allclose(fa.measured, fb.measured, rtol=0, atol=1e-15)
        np.testing.assert_allclose(fa.cov, fb.cov, rtol=1e-10, atol=0)


def test_round_trip_keeps_factors_and_values(tmp_path: Path) -> None:
    g = _mixed_graph()
    g.update()
    g.add_node(8, [20.0, 1.0, 0.1])  # a pending node is written at its initial value
    g.add_between(7, 8, [1.0, 0.0, 0.1], np.diag([0.01, 0.01, 0.001]))
    path = tmp_path / "mixed.g2o"
    g.write_g2o(path)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["mixed.g2o"]  # no temp file left

    back = PoseGraph.read_g2o(path)
    _assert_same_factors(g, back)
    ids, poses = g.estimates()
    ids_back, poses_back = back.estimates()
    np.testing.assert_array_equal(ids, ids_back)
    np.testing.assert_allclose(poses, poses_back, rtol=0, atol=1e-15)

    # both graphs optimize to the same place
    g.optimize_batch()
    back.optimize_batch()
    np.testing.assert_allclose(g.estimates()[1], back.estimates()[1], atol=1e-9)


def test_written_information_is_the_inverse_of_each_covariance(tmp_path: Path) -> None:
    # The writer inverts every edge's covariance in one stacked call: each EDGE_SE2 line
    # holds the upper triangle of inv(cov) of its own factor, symmetrized, to the bit.
    g = _mixed_graph()
    path = tmp_path / "mixed.g2o"
    g.write_g2o(path)
    edges = [ln.split() for ln in path.read_text().splitlines() if ln.startswith("EDGE_SE2")]
    between = [f for f in g.factors if f.j is not None]
    assert len(edges) == len(between) == 9
    for line, f in zip(edges, between, strict=True):
        assert (int(line[1]), int(line[2])) == (f.i, f.j)
        info = np.linalg.inv(f.cov)
        info = 0.5 * (info + info.T)
        assert [float(x) for x in line[6:]] == info[np.triu_indices(3)].tolist()


def test_written_file_reads_like_gtsams_own_writer(tmp_path: Path) -> None:
    # Same graph written by gtsam.writeG2o (6 significant digits) and by write_g2o: gtsam reads
    # both to the same edges within gtsam's printing precision, ours exactly.
    g = _mixed_graph()
    ours = tmp_path / "ours.g2o"
    g.write_g2o(ours)
    graph = gtsam.NonlinearFactorGraph()
    values = gtsam.Values()
    ids, poses = g.estimates()
    for n, p in zip(ids.tolist(), poses, strict=True):
        values.insert(n, gtsam.Pose2(*p))
    for f in g.factors:
        if f.j is not None:
            model = gtsam.noiseModel.Gaussian.Covariance(f.cov)
            graph.add(gtsam.BetweenFactorPose2(f.i, f.j, gtsam.Pose2(*f.measured), model))
    theirs = tmp_path / "theirs.g2o"
    gtsam.writeG2o(graph, values, str(theirs))
    a, b = load_g2o(ours), load_g2o(theirs)
    np.testing.assert_array_equal(a.edge_ij, b.edge_ij)
    np.testing.assert_allclose(a.edge_measured, b.edge_measured, rtol=1e-5, atol=1e-5)
    np.testing.assert_allclose(a.poses, b.poses, rtol=1e-5, atol=1e-5)
    # the information matrices are what both write (6 digits for gtsam)
    info_a, info_b = np.linalg.inv(a.edge_cov), np.linalg.inv(b.edge_cov)
    scale = np.abs(info_a).max(axis=(1, 2), keepdims=True)
    assert np.all(np.abs(info_a - info_b) <= 1e-5 * scale)
    # gtsam's file loses digits (x0 = 10.123456789012345 is printed as 10.1235), ours does not
    assert abs(b.poses[0, 0] - 10.123456789012345) > 1e-6
    assert a.poses[0, 0] == 10.123456789012345


def test_load_intel_matches_the_file_text() -> None:
    path = shared_file("g2o/input_INTEL_g2o.g2o")
    data = load_g2o(path)
    lines = path.read_text().splitlines()
    vertices = [ln.split() for ln in lines if ln.startswith("VERTEX_SE2")]
    edges = [ln.split() for ln in lines if ln.startswith("EDGE_SE2")]
    assert (len(data.node_ids), data.n_edges) == (len(vertices), len(edges)) == (1228, 1483)
    # first edge parsed by hand: information upper triangle I11 I12 I13 I22 I23 I33
    f = [float(x) for x in edges[0][3:]]
    info = np.array([[f[3], f[4], f[5]], [f[4], f[6], f[7]], [f[5], f[7], f[8]]])
    np.testing.assert_allclose(data.edge_measured[0], f[:3])
    np.testing.assert_allclose(data.edge_cov[0], np.linalg.inv(info), rtol=1e-9)
    k = int(vertices[500][1])
    np.testing.assert_allclose(
        data.poses[np.searchsorted(data.node_ids, k)], [float(x) for x in vertices[500][2:]]
    )
    # kinds of a foreign file: consecutive ids are odometry, the rest loop closures
    consecutive = data.edge_ij[:, 1] == data.edge_ij[:, 0] + 1
    assert data.edge_kind.count("odometry") == int(consecutive.sum())
    g = PoseGraph.read_g2o(path)
    assert g.n_factors == 1483 + 1  # the edges plus the automatic prior on node 0
    assert g.factors[0].kind.value == "prior" and g.factors[0].i == 0


@pytest.mark.parametrize(
    ("text", "message"),
    [
        ("VERTEX_SE2 0 0 0 0\nFIX 0\nVERTEX_SE2 1 1 0 0\n", r"bad.g2o:2: record 'FIX'"),
        (
            "VERTEX_SE2 0 0 0 0\n# note\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\n",
            r"bad.g2o:2: comment line before the last record",
        ),
        ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n", "gtsam.readG2o"),
    ],
)
def test_malformed_files_raise_graph_error(tmp_path: Path, text: str, message: str) -> None:
    path = tmp_path / "bad.g2o"
    path.write_text(text)
    with pytest.raises(GraphError, match=message):
        load_g2o(path)


def test_a_byte_order_mark_is_refused(tmp_path: Path) -> None:
    # gtsam.readG2o reads the BOM as part of the first tag and loses that vertex's pose
    # (node 0 at the origin, not at (5, 5, 0.5)): refused rather than read wrong.
    path = tmp_path / "bom.g2o"
    path.write_bytes(b"\xef\xbb\xbfVERTEX_SE2 0 5 5 0.5\nVERTEX_SE2 1 1 0 0\n")
    with pytest.raises(GraphError, match=r"bom\.g2o:1: the file starts with a UTF-8 byte order"):
        load_g2o(path)


def test_missing_file_and_unwritable_destination(tmp_path: Path) -> None:
    with pytest.raises(GraphError, match="no such g2o file"):
        PoseGraph.read_g2o(tmp_path / "absent.g2o")
    g = _mixed_graph()
    with pytest.raises(GraphError, match="cannot write"):
        g.write_g2o(tmp_path / "no_dir" / "out.g2o")
