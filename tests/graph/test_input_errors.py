"""Bad input to the graph library is a GraphError with a clear message (issue 12)."""

from __future__ import annotations

from pathlib import Path

import pytest

from graph import PoseGraph, load_g2o
from iceg_common.errors import GraphError


def test_binary_g2o_file(tmp_path: Path) -> None:
    path = tmp_path / "graph.g2o"
    path.write_bytes(b"VERTEX_SE2 0 0 0 0\n\x89PNG\x00\xff\xfe")
    with pytest.raises(GraphError, match="not a text g2o file"):
        load_g2o(path)
    with pytest.raises(GraphError, match="not a text g2o file"):
        PoseGraph.read_g2o(path)


@pytest.mark.parametrize("node_id", [2**70, 2**63, -1])
def test_node_id_outside_gtsam_keys(node_id: int) -> None:
    g = PoseGraph()
    with pytest.raises(GraphError, match=r"non-negative and below 2\*\*63"):
        g.add_node(node_id, [0.0, 0.0, 0.0])
    g.add_node(2**63 - 1, [0.0, 0.0, 0.0])  # the largest id works
    assert g.update().new_factors == 1
