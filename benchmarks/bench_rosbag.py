"""Benchmark: stream a large ROS bag that the benchmark writes itself; memory must stay flat.

Writes N synthetic scans (720 beams, 10 Hz, one Odometry message per scan, ``/tf_static``) as
a ROS 1 bag, a ROS 2 sqlite3 bag and a ROS 2 mcap bag in a temporary folder (streamed from a
generator: nothing is held in memory), then reads each back with ``open_log`` without keeping
the scans. Prints, per block of 1000 scans, the read rate (scans/s) and the process's peak
RSS so far (``getrusage``) and current RSS (``/proc/self/statm``): the reader streams message
by message, so the peak must not grow with the bag.

Run: ``PYTHONPATH=. python benchmarks/bench_rosbag.py [N_SCANS=20000] [ros1,sqlite3,mcap]``
"""

from __future__ import annotations

import math
import os
import resource
import sys
import tempfile
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np

from frontends import LaserScan, open_log
from frontends.rosbag import BagFormat, write_rosbag

BEAMS = 720
BLOCK = 1000


def synthetic_scans(n: int, seed: int = 0) -> Iterator[LaserScan]:
    """``n`` scans of 720 beams (0.5 deg, +-180 deg) at 10 Hz along a slow arc."""
    rng = np.random.default_rng(seed)
    angles = np.asarray(-math.pi + np.arange(BEAMS) * (2 * math.pi / BEAMS), dtype=np.float64)
    for i in range(n):
        t = 1.7e9 + 0.1 * i
        yield LaserScan(
            stamp_s=t,
            ranges_m=np.round(rng.uniform(0.2, 11.0, BEAMS), 3),
            angles_rad=angles,
            range_min_m=0.15,
            range_max_m=12.0,
            odom_pose=np.array([0.05 * i, 0.0, math.remainder(0.001 * i, 2 * math.pi)]),
            source=f"synthetic:{i}",
        )


def _rss_mb() -> tuple[float, float]:
    """Peak and current resident set size, MB (Linux)."""
    peak = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    with open("/proc/self/statm") as fh:
        current = int(fh.read().split()[1]) * os.sysconf("SC_PAGE_SIZE") / 1e6
    return peak, current


def _size_mb(path: Path) -> float:
    files = [path] if path.is_file() else list(path.iterdir())
    return sum(f.stat().st_size for f in files) / 1e6


def bench(fmt: BagFormat, n: int, folder: Path) -> None:
    path = folder / ("big.bag" if fmt == "ros1" else f"big_{fmt}")
    t0 = time.perf_counter()
    write_rosbag(path, synthetic_scans(n), fmt)
    t_write = time.perf_counter() - t0
    size = _size_mb(path)
    print(f"\n{fmt}: {n} scans x {BEAMS} beams, {size:.0f} MB, written in {t_write:.1f} s")
    print(f"{'scans':>8} {'scans/s':>9} {'peak RSS MB':>12} {'RSS MB':>8}")
    t_block = t_start = time.perf_counter()
    count = 0
    for _ in open_log(path):
        count += 1
        if count % BLOCK == 0:
            now = time.perf_counter()
            peak, current = _rss_mb()
            print(f"{count:8d} {BLOCK / (now - t_block):9.0f} {peak:12.1f} {current:8.1f}")
            t_block = now
    total = time.perf_counter() - t_start
    print(f"read {count} scans in {total:.1f} s ({count / total:.0f} scans/s)")


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    n = int(args[0]) if args else 20_000
    formats = args[1].split(",") if len(args) > 1 else ["ros1", "sqlite3", "mcap"]
    with tempfile.TemporaryDirectory() as tmp:
        for fmt in formats:
            bench(fmt, n, Path(tmp))  # type: ignore[arg-type]


if __name__ == "__main__":
    main()
