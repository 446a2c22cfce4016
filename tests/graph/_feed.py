"""Helpers shared by the graph tests and benchmarks: feed a g2o edge list node by node."""

from __future__ import annotations

import time

import numpy as np

from graph import G2oGraph, GraphConfig, PoseGraph
from iceg_common.se2 import compose, inverse


def feed_node_by_node(
    data: G2oGraph, config: GraphConfig | None = None, times_s: list[float] | None = None
) -> PoseGraph:
    """Build a PoseGraph from a g2o edge list the way a SLAM front-end would: nodes in id order,
    each initialized by composing an edge from an existing node's current estimate (the
    odometry edge ``(n-1, n)`` when there is one), all edges whose endpoints both exist added,
    then one ``update()`` per node. ``times_s`` receives the duration of each update()."""
    graph = PoseGraph(config)
    later = np.maximum(data.edge_ij[:, 0], data.edge_ij[:, 1])
    order = np.argsort(later, kind="stable")
    bounds = np.searchsorted(later[order], data.node_ids, side="left")
    ends = np.searchsorted(later[order], data.node_ids, side="right")
    for k, n in enumerate(data.node_ids.tolist()):
        edges = order[bounds[k] : ends[k]].tolist()
        init = data.poses[k] if k == 0 else None
        # prefer the odometry edge from the previous node, then any edge to an existing node
        for m in sorted(edges, key=lambda m: data.edge_ij[m, 0] != n - 1):
            i, j = data.edge_ij[m].tolist()
            if j == n and i != n:
                init = compose(graph.estimate(i), data.edge_measured[m])
                break
            if i == n and j != n:
                init = compose(graph.estimate(j), inverse(data.edge_measured[m]))
                break
        if init is None:
            init = data.poses[k]
        graph.add_node(n, init)
        for m in edges:
            i, j = data.edge_ij[m].tolist()
            graph.add_between(i, j, data.edge_measured[m], data.edge_cov[m], kind=data.edge_kind[m])
        start = time.perf_counter()
        graph.update()
        if times_s is not None:
            times_s.append(time.perf_counter() - start)
    return graph
