"""Replay a g2o graph node by node through :class:`graph.PoseGraph`, as a SLAM front-end would.

Used to check and time the incremental back-end against a batch solution on published graphs
(INTEL, M3500): nodes arrive in id order, each initialized from an existing node's current
estimate composed with a measured edge, then one ``update()``.
"""

from __future__ import annotations

import time

import numpy as np

from graph.config import GraphConfig
from graph.g2o import G2oGraph
from graph.pose_graph import PoseGraph
from iceg_common.se2 import compose, inverse


def replay_node_by_node(
    data: G2oGraph, config: GraphConfig | None = None, times_s: list[float] | None = None
) -> PoseGraph:
    """Feed a g2o edge list to a new PoseGraph one node at a time.

    For each vertex in ascending id order: add it with an initial value composed from the
    current estimate of an existing neighbour (the odometry edge ``(n-1, n)`` when the file has
    it, else any edge to an existing node, else the file's vertex pose), add every edge whose
    two endpoints now exist (each edge exactly once, with the file's kind), then ``update()``.

    Args:
        data: the raw graph (:func:`graph.load_g2o`).
        config: graph settings; defaults to ``GraphConfig()``.
        times_s: if given, receives the wall time (s) of each ``update()`` call.

    Returns:
        The graph after the last node's update (newest nodes have had one iSAM2 step: call
        ``update()`` again to converge them).

    Raises:
        GraphError: from the graph (e.g. an indeterminant system, naming the node).
    """
    graph = PoseGraph(config)
    later = np.maximum(data.edge_ij[:, 0], data.edge_ij[:, 1])
    order = np.argsort(later, kind="stable")
    first = np.searchsorted(later[order], data.node_ids, side="left")
    last = np.searchsorted(later[order], data.node_ids, side="right")
    for k, n in enumerate(data.node_ids.tolist()):
        edges = order[first[k] : last[k]].tolist()
        init = data.poses[k]
        # the odometry edge from the previous node first, then any edge to an existing node
        for m in sorted(edges, key=lambda m: data.edge_ij[m, 0] != n - 1):
            i, j = data.edge_ij[m].tolist()
            if j == n and i != n:
                init = compose(graph.estimate(i), data.edge_measured[m])
                break
            if i == n and j != n:
                init = compose(graph.estimate(j), inverse(data.edge_measured[m]))
                break
        graph.add_node(n, init)
        for m in edges:
            i, j = data.edge_ij[m].tolist()
            graph.add_between(i, j, data.edge_measured[m], data.edge_cov[m], data.edge_kind[m])
        start = time.perf_counter()
        graph.update()
        if times_s is not None:
            times_s.append(time.perf_counter() - start)
    return graph
