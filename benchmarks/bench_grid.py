"""Benchmark: render the occupancy grid of all 1988 MIT CSAIL scans (361 beams) at 5 cm.

Prints: log read time (not part of the figure), numba compile time (no cache), the first
``render`` call in this process (numba cache load, or a compile if the cache is cold), the
steady-state render time (median and best of 5) for ``range_max_m`` 30 m (the default) and
the sensor's full range, and, for comparison, a pure-numpy variant (rays sampled every half
cell, ``np.unique`` per scan, same per-scan once-per-cell rule) on the first 200 scans.

The steady-state renders run with one thread and with two (``GridConfig.threads``: each
traces the beams through its own band of rows; the map is the same bit for bit).

Also prints the storage of the sparse tiled grid (``render_tiled``) against the dense one.
Odometry poses are used (timing only; the map is not meaningful). Target: <= 1.5 s.

Run: ``/work/venv/bin/python benchmarks/bench_grid.py [path/to/mit-csail.clf]``
"""

from __future__ import annotations

import statistics
import sys
import time
from pathlib import Path

import numba
import numpy as np

from frontends import LaserScan, open_log
from iceg import grid as grid_mod
from iceg.grid import TILE_SIZE, GridConfig, OccupancyGrid, render, render_tiled
from iceg_common.se2 import compose

DEFAULT_LOG = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "mit-csail" / "mit-csail.clf"
)


def render_numpy(
    scans: list[LaserScan], poses: np.ndarray, config: GridConfig, like: OccupancyGrid
) -> OccupancyGrid:
    """Vectorized numpy variant on the grid frame of ``like``: per scan, sample every ray each
    half cell, count each cell once per scan (``np.unique``), hits take precedence."""
    h, w = like.shape
    res = like.resolution_m
    lo = np.zeros(h * w, dtype=np.float32)
    step = 0.5 * res
    for scan, pose in zip(scans, poses, strict=True):
        laser = compose(pose, scan.laser_offset)
        rmax = min(scan.range_max_m, config.range_max_m or np.inf)
        r = scan.ranges_m
        ok = np.isfinite(r) & (r > scan.range_min_m) & (r < rmax)
        r = r[ok]
        bearing = laser[2] + scan.angles_rad[ok]
        d = np.stack([np.cos(bearing), np.sin(bearing)], 1)
        end = laser[:2] + r[:, None] * d
        g_end = np.floor((end - like.origin_xy) / res).astype(np.int64)
        hit = np.unique(g_end[:, 1] * w + g_end[:, 0])
        n = np.ceil(r / step).astype(np.int64)
        ray = np.repeat(np.arange(r.size), n)
        k = np.arange(n.sum()) - np.repeat(np.cumsum(n) - n, n)
        pts = laser[:2] + (k * step)[:, None] * d[ray]
        g = np.floor((pts - like.origin_xy) / res).astype(np.int64)
        free = np.setdiff1d(np.unique(g[:, 1] * w + g[:, 0]), hit, assume_unique=True)
        lo[hit] = np.minimum(lo[hit] + config.l_occ, config.l_max)
        lo[free] = np.maximum(lo[free] + config.l_free, config.l_min)
    return OccupancyGrid(lo.reshape(h, w), res, like.origin_xy)


def timed(fn, repeats: int) -> list[float]:
    out = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        out.append(time.perf_counter() - t0)
    return out


def main() -> None:
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_LOG
    if not path.is_file():
        print(f"skipped: {path} is absent (../shared/data)")
        return
    t0 = time.perf_counter()
    scans = list(open_log(path))
    poses = np.stack([s.odom_pose for s in scans])  # type: ignore[misc]
    print(
        f"log: {path.name}: {len(scans)} scans x {scans[0].n_beams} beams, read in "
        f"{time.perf_counter() - t0:.2f} s (not timed below)"
    )
    cfg = GridConfig(resolution_m=0.05)

    t0 = time.perf_counter()
    render(scans[:1], poses[:1], cfg)
    t_load = time.perf_counter() - t0
    stats = grid_mod._trace_scans.stats
    hits = sum(stats.cache_hits.values())
    what = "numba cache load" if hits else "numba compile (cold cache)"
    print(f"first call in this process (1 scan): {t_load:.3f} s, i.e. the {what}")
    t0 = time.perf_counter()
    first = render(scans, poses, cfg)
    print(f"then the first full render: {time.perf_counter() - t0:.3f} s")
    fresh = numba.njit(nogil=True)(grid_mod._trace_scans.py_func)
    t0 = time.perf_counter()
    fresh.compile(grid_mod._trace_scans.signatures[0])
    print(f"numba compile time without cache: {time.perf_counter() - t0:.3f} s")

    for label, c in [
        ("range_max_m=30 (default), 1 thread", cfg.model_copy(update={"threads": 1})),
        ("range_max_m=30 (default), 2 threads", cfg.model_copy(update={"threads": 2})),
        ("range_max_m=None (80 m), 1 thread", GridConfig(range_max_m=None, threads=1)),
        ("range_max_m=None (80 m), 2 threads", GridConfig(range_max_m=None, threads=2)),
    ]:
        times = timed(lambda c=c: render(scans, poses, c), 5)
        g = render(scans, poses, c)
        updates = int(g.hits.sum() + g.misses.sum())
        print(
            f"render {len(scans)} scans at 5 cm, {label}: median {statistics.median(times):.3f} s,"
            f" best {min(times):.3f} s; grid {g.shape[0]}x{g.shape[1]}, {updates / 1e6:.1f} M "
            f"cell updates ({updates / min(times) / 1e6:.0f} M/s)"
        )

    tiled = render_tiled(scans, poses, cfg)
    h, w = tiled.shape
    print(
        f"tiled storage (render_tiled, what the pipeline renders): {tiled.n_tiles} tiles of "
        f"{TILE_SIZE}x{TILE_SIZE} = {tiled.allocated_cells / 1e6:.1f} M cells of the "
        f"{h * w / 1e6:.1f} M dense ({tiled.allocated_cells / (h * w):.0%})"
    )

    n_cmp = 200
    sub, sub_poses = scans[:n_cmp], poses[:n_cmp]
    t_numba = min(timed(lambda: render(sub, sub_poses, cfg), 3))
    t_numpy = min(timed(lambda: render_numpy(sub, sub_poses, cfg, first), 1))
    print(
        f"first {n_cmp} scans: numba {t_numba:.3f} s, numpy sampling {t_numpy:.3f} s "
        f"(x{t_numpy / t_numba:.0f}; numpy extrapolated to {len(scans)} scans: "
        f"{t_numpy * len(scans) / n_cmp:.1f} s)"
    )
    print("target: <= 1.5 s for all scans")


if __name__ == "__main__":
    main()
