"""Benchmark: iSAM2 update time per node and batch time of graph.PoseGraph.

Two runs, each fed node by node with one ``update()`` per node and the default GraphConfig:

1. M3500b (``../shared/data/g2o/input_M3500b_g2o.g2o``, 3500 nodes, 5453 edges), through
   ``graph.replay.replay_node_by_node``;
2. a simulated Manhattan world of 10,000 nodes (``graph.simulate.simulate_manhattan``);
3. with ``--chain N``: a chain of N nodes without loop closures (dead reckoning along a
   straight corridor, two between factors per step as the pipeline adds them), printing the
   mean ``update()`` time per 1000 nodes. Nothing in a chain grows but the tree itself, so a
   growing time per update is the solver's own per-update cost in the size of the graph.

For each: median, 99th percentile and maximum wall time of ``update()`` per node, the total,
the time of ``optimize_batch()`` started from the incremental estimate (offline refinement),
and, for M3500b, Levenberg–Marquardt from the file's initial values for comparison (time,
iterations and the error it reaches). The simulated run also reports the mean position error
against ground truth.

Run: ``/work/venv/bin/python benchmarks/bench_graph.py [--nodes 10000] [--skip-m3500]``
"""

from __future__ import annotations

import argparse
import os
import sys
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    from graph import PoseGraph

REPO = Path(__file__).resolve().parents[1]
if str(REPO) not in sys.path:  # run as a script from anywhere
    sys.path.insert(0, str(REPO))
SHARED = Path(os.environ.get("ICEG_SHARED_DATA", REPO.parent / "shared" / "data"))


def _summary(label: str, times_s: list[float]) -> None:
    t = np.asarray(times_s) * 1000.0
    print(
        f"  {label}: {len(t)} updates, median {np.median(t):.3f} ms, "
        f"p99 {np.percentile(t, 99):.3f} ms, max {t.max():.1f} ms, total {t.sum() / 1000:.1f} s"
    )


def _converge(graph: PoseGraph) -> int:
    """Three relinearization checks after the last node (as tests/graph/test_g2o_datasets.py)."""
    extra = 3 * graph.config.relinearize_skip
    for _ in range(extra):
        graph.update()
    return extra


def _aligned_error(est: np.ndarray, truth: np.ndarray) -> float:
    """Mean position error after least-squares rigid alignment (Umeyama 1991), metres."""
    a = est[:, :2] - est[:, :2].mean(axis=0)
    b = truth[:, :2] - truth[:, :2].mean(axis=0)
    u, _, vt = np.linalg.svd(a.T @ b)
    d = np.diag([1.0, np.sign(np.linalg.det(u @ vt))])
    return float(np.mean(np.linalg.norm(a @ (u @ d @ vt) - b, axis=1)))


def bench_m3500(path: Path) -> None:
    """Replay M3500b node by node, then refine in batch; LM from the raw initial values too."""
    from graph import PoseGraph, load_g2o
    from graph.replay import replay_node_by_node

    print(f"M3500b: {path}")
    data = load_g2o(path)
    times: list[float] = []
    graph = replay_node_by_node(data, times_s=times)
    _summary(f"iSAM2 update per node ({graph.factorization})", times)
    start = time.perf_counter()
    extra = _converge(graph)
    print(f"  {extra} extra update() to converge: {time.perf_counter() - start:.2f} s")
    error_inc = sum(graph.residual_errors().values())
    start = time.perf_counter()
    stats = graph.optimize_batch()
    print(
        f"  batch LM from the iSAM2 estimate: {time.perf_counter() - start:.2f} s, "
        f"{stats.iterations} iterations, error {error_inc:.4f} -> {stats.error_after:.4f}"
    )
    raw = PoseGraph.read_g2o(path)
    start = time.perf_counter()
    stats = raw.optimize_batch(max_iterations=100)
    print(
        f"  batch LM from the file's initial values: {time.perf_counter() - start:.2f} s, "
        f"{stats.iterations} iterations, error {stats.error_before:.1f} -> "
        f"{stats.error_after:.4f} (converged: {stats.converged})"
    )


def bench_simulated(n_nodes: int) -> None:
    """Incremental run on a simulated Manhattan world with ground truth."""
    from graph import OdometryNoiseConfig, PoseGraph, odometry_covariance
    from graph.simulate import simulate_manhattan
    from iceg_common.se2 import compose

    # wheel odometry of 1.5 cm and 0.1 deg + 1 % of the rotation per 1 m step, loop closures
    # of 2 cm and 0.3 deg (the noise of tests/graph/test_robust.py)
    odometry = OdometryNoiseConfig(
        sigma_xy_base_m=0.005,
        sigma_xy_per_distance_m_per_m=0.01,
        sigma_theta_base_deg=0.1,
        sigma_theta_per_rotation_deg_per_deg=0.01,
        sigma_theta_per_distance_deg_per_m=0.1,
    )
    sim = simulate_manhattan(
        n_nodes, seed=0, grid_cells=40, odometry=odometry, loop_sigma_theta_deg=0.3
    )
    print(
        f"Simulated Manhattan world: {n_nodes} nodes, {n_nodes - 1} odometry factors, "
        f"{len(sim.loop_ij)} loop closures"
    )
    loops_at: dict[int, list[int]] = {}
    for idx, k in enumerate(sim.loop_ij[:, 1].tolist()):
        loops_at.setdefault(k, []).append(idx)
    graph = PoseGraph()
    graph.add_node(0, sim.true_poses[0])
    times: list[float] = []
    for k in range(1, n_nodes):
        z = sim.odometry_measured[k - 1]
        graph.add_node(k, compose(graph.estimate(k - 1), z))
        graph.add_between(k - 1, k, z, odometry_covariance(z, odometry))
        for idx in loops_at.get(k, []):
            m = int(sim.loop_ij[idx, 0])
            graph.add_between(m, k, sim.loop_measured[idx], sim.loop_cov, kind="loop_closure")
        start = time.perf_counter()
        graph.update()
        times.append(time.perf_counter() - start)
    _summary(f"iSAM2 update per node ({graph.factorization})", times)
    extra = _converge(graph)
    _, inc = graph.estimates()
    start = time.perf_counter()
    stats = graph.optimize_batch()
    batch_s = time.perf_counter() - start
    _, batch = graph.estimates()
    print(
        f"  batch LM from the iSAM2 estimate: {batch_s:.2f} s, {stats.iterations} iterations "
        f"(after {extra} extra updates)"
    )
    err_inc = np.linalg.norm(inc[:, :2] - sim.true_poses[:, :2], axis=1)
    err_batch = np.linalg.norm(batch[:, :2] - sim.true_poses[:, :2], axis=1)
    print(
        f"  mean position error vs truth: anchored at node 0 {err_inc.mean():.4f} m, after "
        f"SE(2) alignment {_aligned_error(inc, sim.true_poses):.4f} m; max |iSAM2 - batch| "
        f"{np.linalg.norm(inc[:, :2] - batch[:, :2], axis=1).max() * 1000:.2f} mm "
        f"(batch anchored {err_batch.mean():.4f} m)"
    )


def bench_chain(n_nodes: int) -> None:
    """Incremental run on a loop-free chain: mean update time per block of 1000 nodes."""
    from graph import PoseGraph
    from iceg_common.se2 import compose

    rng = np.random.default_rng(0)
    step_cov = np.diag([0.01, 0.01, 0.002]) ** 2
    graph = PoseGraph()
    graph.add_node(0, np.zeros(3))
    pose = np.zeros(3)
    per_block: list[float] = []
    block_s = 0.0
    for k in range(1, n_nodes):
        z = np.array([0.1, 0.0, 0.0]) + rng.normal(0.0, [0.005, 0.005, 0.002])
        pose = compose(pose, z)
        graph.add_node(k, pose)
        graph.add_between(k - 1, k, z, step_cov)
        graph.add_between(k - 1, k, z + rng.normal(0.0, [0.01, 0.0, 0.0]), step_cov)
        start = time.perf_counter()
        graph.update()
        block_s += time.perf_counter() - start
        if k % 1000 == 0:
            per_block.append(block_s)
            block_s = 0.0
    print(
        f"Chain without loop closures: {n_nodes} nodes ({graph.factorization}); mean update() "
        "per block of 1000 nodes, ms: " + ", ".join(f"{t:.3f}" for t in per_block)
    )


def main() -> None:
    """Parse arguments, run the benchmarks, print the figures."""
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--nodes", type=int, default=10_000, help="simulated run size")
    parser.add_argument("--skip-m3500", action="store_true", help="only the simulated run")
    parser.add_argument("--chain", type=int, default=0, help="also a loop-free chain this long")
    args = parser.parse_args()
    from graph import GraphConfig

    cfg = GraphConfig()
    print(
        f"GraphConfig: relinearize_threshold {cfg.relinearize_threshold}, relinearize_skip "
        f"{cfg.relinearize_skip}, factorization {cfg.factorization}"
    )
    m3500 = SHARED / "g2o" / "input_M3500b_g2o.g2o"
    if args.skip_m3500:
        pass
    elif m3500.is_file():
        bench_m3500(m3500)
    else:
        print(f"M3500b skipped: {m3500} is absent")
    bench_simulated(args.nodes)
    if args.chain:
        bench_chain(args.chain)


if __name__ == "__main__":
    main()
