"""Benchmark: time to simulate the default office run; prints scans per second.

Run: ``python benchmarks/bench_simulate.py [--repeats N]``.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from frontends.simulate import LaserModel, cast_rays, office_world, simulate


def main(repeats: int = 5) -> None:
    """Simulate the default office run ``repeats`` times and print the best timing."""
    world = office_world()
    simulate(world, seed=0)  # warm-up (imports, caches)
    best = float("inf")
    n_scans = 0
    for seed in range(repeats):
        t0 = time.perf_counter()
        run = simulate(world, seed=seed)
        best = min(best, time.perf_counter() - t0)
        n_scans = len(run)
    print(f"world: {world!r}")
    print(f"run: {run!r}")
    print(
        f"simulate(office): {n_scans} scans x {LaserModel().n_beams} beams x "
        f"{world.walls.shape[0]} walls in {best * 1e3:.1f} ms (best of {repeats}) -> "
        f"{n_scans / best:,.0f} scans/s"
    )
    # Ray casting alone, per scan.
    rng = np.random.default_rng(0)
    poses = run.true_poses
    t0 = time.perf_counter()
    for p in poses:
        cast_rays(world, p, rng=rng)
    dt = time.perf_counter() - t0
    print(f"cast_rays alone: {dt / len(poses) * 1e6:.0f} us/scan -> {len(poses) / dt:,.0f} scans/s")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--repeats", type=int, default=5)
    main(parser.parse_args().repeats)
