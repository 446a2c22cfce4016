"""Benchmark: ICE feature extraction time per MIT CSAIL scan (361 beams) and feature counts.

Prints the median and 95th-percentile wall time of ``iceg.features.extract`` per scan over
the whole log (target from issue 3: median <= 1.0 ms), and the mean number of segments,
Corners, ends of wall and Intersections per scan. Reads ``../shared/data/mit-csail``.

With ``--large-beams N`` it also times one noise-free synthetic 360° scan of N beams in a
star-shaped room of 500 faces (issue 12: feature extraction is linear in beams and segments).

Usage: ``python benchmarks/bench_features.py [path/to/mit-csail.clf] [--repeat N]
[--large-beams N]``
"""

from __future__ import annotations

import argparse
import math
import os
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
DEFAULT_LOG = (
    Path(os.environ.get("ICEG_SHARED_DATA", REPO.parent / "shared" / "data"))
    / "mit-csail"
    / "mit-csail.clf"
)


def time_large_scan(n_beams: int, n_teeth: int = 250, radius_m: float = 15.0) -> None:
    """Time ``extract`` on a noise-free scan from the centre of a star-shaped room whose
    vertices alternate between ``radius_m`` and ``radius_m`` plus half a tooth's arc (faces
    at about 45° to the beams, ``2 n_teeth`` segments) and print the figures."""
    from frontends.scan import LaserScan
    from frontends.simulate import ray_ranges
    from iceg.features import extract
    from iceg.features.prefetch import warm_up_scan

    step = 2.0 * math.pi / n_teeth
    k = np.arange(2 * n_teeth)
    radius = np.where(k % 2 == 0, radius_m, radius_m * (1.0 + step / 2.0))
    verts = np.c_[radius * np.cos(k * step / 2.0), radius * np.sin(k * step / 2.0)]
    walls = np.stack([verts, np.roll(verts, -1, axis=0)], axis=1)
    angles = np.linspace(-math.pi, math.pi, n_beams, endpoint=False)
    chunks = np.array_split(angles, max(1, n_beams // 20_000))
    ranges = np.concatenate([ray_ranges(np.zeros(2), c, walls) for c in chunks])
    scan = LaserScan(0.0, ranges, angles, 0.0, 20.0, None, source="sawtooth")
    extract(warm_up_scan())  # load the compiled kernels first: the time is the extraction's
    t0 = time.perf_counter()
    f = extract(scan)
    dt = time.perf_counter() - t0
    print(
        f"large scan: {n_beams} beams, {f.n_segments} segments, {f.n_features} features, {dt:.2f} s"
    )


def main() -> None:
    """Time ``extract`` on every scan of the log and print the figures."""
    from frontends import open_log
    from iceg.features import FeatureConfig, extract
    from iceg.types import FeatureKind

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("log", nargs="?", type=Path, default=DEFAULT_LOG)
    parser.add_argument("--repeat", type=int, default=3, help="timed passes over the log")
    parser.add_argument("--large-beams", type=int, default=0, help="also time a synthetic scan")
    args = parser.parse_args()
    if args.large_beams:
        time_large_scan(args.large_beams)
    if not args.log.is_file():
        print(f"skipped: {args.log} is absent (it lives in ../shared/data beside the repo)")
        return
    scans = list(open_log(args.log))
    config = FeatureConfig()
    extract(scans[0], config)  # compile the numba kernels (cached on disk after the 1st run)

    times = np.empty((args.repeat, len(scans)))
    for rep in range(args.repeat):
        for i, scan in enumerate(scans):
            t0 = time.perf_counter()
            extract(scan, config)
            times[rep, i] = time.perf_counter() - t0
    per_scan = times.min(axis=0) * 1e3  # best of the passes per scan: less scheduler noise
    all_runs = times.ravel() * 1e3

    counts = np.zeros(3)
    n_segments = 0
    for scan in scans:
        f = extract(scan, config)
        counts += np.bincount(f.kind, minlength=3)
        n_segments += f.n_segments
    n = len(scans)
    beams = scans[0].n_beams
    print(f"log: {args.log} ({n} scans, {beams} beams)")
    print(
        f"extract per scan, best of {args.repeat}: median {np.median(per_scan):.3f} ms, "
        f"p95 {np.percentile(per_scan, 95):.3f} ms, max {per_scan.max():.3f} ms"
    )
    print(
        f"extract per scan, all {all_runs.size} runs: median {np.median(all_runs):.3f} ms, "
        f"p95 {np.percentile(all_runs, 95):.3f} ms"
    )
    print(f"target: median <= 1.0 ms -> {'met' if np.median(all_runs) <= 1.0 else 'MISSED'}")
    print(f"segments per scan: {n_segments / n:.2f}")
    for kind in FeatureKind:
        print(
            f"{kind.name.lower():>12} per scan: {counts[kind] / n:.2f} (total {int(counts[kind])})"
        )


if __name__ == "__main__":
    main()
