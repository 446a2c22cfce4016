"""Benchmark: per-scan cost and memory against log length (issue 12, long logs).

Builds long logs in memory from the MIT CSAIL log (1988 scans) driven forward, then backward
along the same path, then forward again, ... (a backward pass is the log in reverse order with
increasing stamps: the same odometry poses and ranges, so odometry stays consistent and every
pass revisits the same building). Each size runs the library pipeline (:class:`iceg.slam.Slam`
scan by scan, :meth:`Slam.finish`, then the occupancy grid of the result) in a fresh
subprocess and prints:

- the wall time of each successive block of 1000 scans (growth with the map is visible),
- the time of the final step (batch refinement, result) and of the grid rendering,
- the time per stage (the pipeline's own stage timer),
- the peak RSS (``resource.getrusage`` ``ru_maxrss``) after each block, after the final step
  and after the grid, and the peak RSS per 1000 scans: above the process's start, and above
  the first block's peak per 1000 scans after it (the first block holds one-time costs, about
  85 MB, most of it the compiled kernels; the time figures leave it out for the same reason).

Every generated scan owns fresh range and bearing arrays (nothing is shared with the source
log), so what the pipeline keeps is what the measurement sees.

``--source corridor`` runs an exploring log instead: the simulated long corridor with door
recesses (``frontends.simulate.long_corridor_world``, accurate odometry, 0.1 m per scan)
made as long as the log, so no place is seen twice; what still grows there is what grows
with the number of nodes, not with the passes through a place.

The summary ends with issue 12's criteria (time and memory per 1000 scans flat within 20 %):
per size the mean wall and CPU seconds per 1000 scans over the whole blocks after the first
and the peak RSS added per 1000 scans after the first block, and their largest over smallest
across sizes; with ``--repeats R`` every size runs R times (sizes
interleaved) and the median over its runs counts, since one 1000-scan block moves by up to
20 % between two runs on this machine (the 2k size has one such block). Within each run of
the largest size, the last ten blocks over the first ten show growth with the log's length
free of that run-to-run spread, and the same two means per stage of the pipeline's timer
show which stages the growth is in.

``--workers 2`` runs each size as ``iceg run`` does on a machine with a free core: with the
feature worker and the loop closer's match helper (:func:`iceg.pipeline.helper_processes`;
the same result). CPU times are the main process's.

``--check-closures`` (the CSAIL source) scores, after the timed run, every accepted loop
closure against the relative pose of its two source scans in a single pass through the log
(two copies of one scan are the same pose) and prints how many are off by more than 0.3 m or
3 degrees (``iceg.batch_run.check_loop_closures``).

``--no-reuse-nodes`` turns ``slam.reuse_nodes`` off (every keyframe a node, as before it):
the back-and-forth log then adds a set of nodes and landmarks per pass.

Run: ``python benchmarks/bench_scaling.py [--sizes 2000,10000,50000] [--repeats R]
[--log path.clf] [--source csail|corridor] [--no-grid] [--check-closures] [--workers N]
[--no-reuse-nodes]``
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import NDArray

if TYPE_CHECKING:
    from iceg.results import SlamResult

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "mit-csail" / "mit-csail.clf"
BLOCK = 1000
FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


def peak_rss_mb() -> float:
    """Peak resident set size of this process so far (MB; Linux reports KB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def back_and_forth_plan(stamps: FloatArray, n: int) -> tuple[IntArray, FloatArray]:
    """The source scan and the stamp (s) of each of ``n`` scans driven forward, backward,
    forward, ... through a log with ``stamps`` ``(m,)`` (s, non-decreasing): ``(n,)`` int64
    indices into the log and ``(n,)`` float64 increasing stamps.

    The turnaround scan is not repeated; the stamp step across a turnaround is the log's
    median step.
    """
    m = stamps.shape[0]
    step = float(np.median(np.diff(stamps)))
    index: list[int] = []
    stamp: list[float] = []
    base = float(stamps[0])
    forward = True
    while len(index) < n:
        order: Sequence[int] = range(m) if forward else range(m - 1, -1, -1)
        if index:
            order = order[1:]
        t0 = base
        for i in order:
            rel = (stamps[i] - stamps[0]) if forward else (stamps[-1] - stamps[i])
            base = float(t0 + rel)
            index.append(i)
            stamp.append(base)
            if len(index) >= n:
                break
        base += step
        forward = not forward
    return np.array(index, dtype=np.int64), np.array(stamp, dtype=np.float64)


def back_and_forth(scans: Sequence, n: int) -> Iterator:
    """``n`` scans: ``scans`` forward, backward, forward, ... with increasing stamps
    (:func:`back_and_forth_plan`). Each yielded scan is a new :class:`frontends.LaserScan`
    with its own arrays."""
    from frontends import LaserScan

    index, stamps = back_and_forth_plan(np.array([s.stamp_s for s in scans]), n)
    for i, stamp in zip(index.tolist(), stamps.tolist(), strict=True):
        s = scans[i]
        yield LaserScan(
            stamp_s=stamp,
            ranges_m=np.array(s.ranges_m, dtype=np.float64),
            angles_rad=np.array(s.angles_rad, dtype=np.float64),
            range_min_m=s.range_min_m,
            range_max_m=s.range_max_m,
            odom_pose=None if s.odom_pose is None else np.array(s.odom_pose),
            laser_offset=np.array(s.laser_offset),
            source=s.source,
        )


def exploring_corridor(n: int) -> list:
    """``n`` scans driven along a simulated corridor of ``0.1 n`` metres (seed 0)."""
    from frontends.simulate import simulate
    from frontends.simulate.odometry import ACCURATE_ODOMETRY
    from frontends.simulate.trajectory import DEFAULT_RATE_HZ, DEFAULT_SPEED_MPS
    from frontends.simulate.worlds import long_corridor_world

    step_m = DEFAULT_SPEED_MPS / DEFAULT_RATE_HZ
    world = long_corridor_world(length_m=n * step_m + 3.0)
    return simulate(world, odometry=ACCURATE_ODOMETRY, seed=0).scans[:n]


def run_one(
    n: int,
    log: Path,
    grid: bool,
    source_name: str = "csail",
    check_closures: bool = False,
    workers: int = 1,
    reuse_nodes: bool = True,
) -> dict:
    """Run the pipeline over ``n`` scans in this process (with its helper processes when
    ``workers`` > 1, :func:`iceg.pipeline.helper_processes`); return the figures. With
    ``check_closures`` (the CSAIL source), after the timed run: the accepted loop closures
    whose measurement is off by more than ``iceg.batch_run.FALSE_LC_TRANS_M`` or
    ``FALSE_LC_ROT_DEG`` from the relative pose of their two source scans in a single pass
    through the log (its own run, relation error about 3 cm; two copies of the same scan
    are the same pose)."""
    from frontends import open_log
    from iceg.config import config_from_dict
    from iceg.pipeline import helper_processes
    from iceg.slam import Slam

    if source_name == "corridor":
        source = exploring_corridor(n)
        scans = iter(source)
    else:
        source = list(open_log(log))
        scans = back_and_forth(source, n)
    rss_start = peak_rss_mb()
    slam = Slam(config_from_dict({"slam": {"reuse_nodes": reuse_nodes}}))
    blocks: list[float] = []
    cpu_blocks: list[float] = []
    rss_blocks: list[float] = []
    stage_blocks: list[dict[str, float]] = []
    c_block = time.process_time()
    stages_before: dict[str, float] = {}
    t_block = time.perf_counter()
    t_start = t_block
    with helper_processes(slam, workers) as prefetch:
        for k, (scan, features) in enumerate(prefetch.scans(scans), start=1):
            slam.process(scan, features=features)
            if k % BLOCK == 0 or k == n:
                now = time.perf_counter()
                blocks.append(now - t_block)
                cpu_blocks.append(time.process_time() - c_block)
                rss_blocks.append(peak_rss_mb())
                t_block, c_block = now, time.process_time()
                stages = dict(slam.timer.seconds)
                grown = {s: v - stages_before.get(s, 0.0) for s, v in stages.items()}
                stages_before = stages
                stage_blocks.append(grown)
                print(
                    f"  [{n}] scans {k}: block {blocks[-1]:.1f} s (CPU {cpu_blocks[-1]:.1f} s), "
                    f"peak RSS {rss_blocks[-1]:.0f} MB, nodes {slam.graph.n_nodes}, "
                    f"landmarks {len(slam.feature_map)}, reused keyframes "
                    f"{slam.export_state().reused_keyframes}, global closures "
                    f"{slam.loop_stats.global_accepted}, node-index rebuilds "
                    f"{slam.loop_closer.index_rebuilds}; stage s: "
                    + ", ".join(
                        f"{s} {v:.1f}" for s, v in sorted(grown.items(), key=lambda x: -x[1])
                    ),
                    file=sys.stderr,
                    flush=True,
                )
    # the CSAIL log (small) is kept for the closure check; a simulated log is let go
    kept = source if check_closures and source_name != "corridor" else None
    del source
    t0 = time.perf_counter()
    result = slam.finish()
    t_finish = time.perf_counter() - t0
    rss_finish = peak_rss_mb()
    t_grid = float("nan")
    if grid:
        t0 = time.perf_counter()
        result.render_map()
        t_grid = time.perf_counter() - t0
    fig = {
        "n": n,
        "blocks_s": blocks,
        "cpu_blocks_s": cpu_blocks,
        "rss_blocks_mb": rss_blocks,
        "stage_blocks_s": stage_blocks,
        "process_s": time.perf_counter() - t_start - t_finish - (0.0 if not grid else t_grid),
        "finish_s": t_finish,
        "grid_s": t_grid,
        "rss_start_mb": rss_start,
        "rss_finish_mb": rss_finish,
        "rss_peak_mb": peak_rss_mb(),
        "nodes": len(result.node_ids),
        "loop_closures": result.loop_closures.accepted,
        "reused_keyframes": result.reused_keyframes,
        "stages_s": dict(sorted(result.stage_seconds.items(), key=lambda kv: -kv[1])),
    }
    # after the timing: a second run of the whole log
    fig["lc_false"] = None if kept is None else _false_against_single_pass(result, kept, n)
    return fig


def _false_against_single_pass(result: SlamResult, source: Sequence, n: int) -> int:
    """Loop closures of a back-and-forth run off the single pass through ``source``."""
    from iceg.batch_run import check_loop_closures
    from iceg.slam import Slam

    single = Slam()
    for scan in source:
        single.process(scan)
    index, _ = back_and_forth_plan(np.array([s.stamp_s for s in source]), n)
    return check_loop_closures(result, single.finish().poses[index]).n_false


def _grown(fig: dict) -> float:
    """Peak RSS above the process's RSS before the first scan (MB)."""
    return float(fig["rss_peak_mb"] - fig["rss_start_mb"])


def _grown_per_k_after_first(fig: dict) -> float:
    """Peak RSS (final step and grid included) above the peak after the first block, per 1000
    scans after it (MB): the memory each scan adds, without the first block's one-time costs
    (about 85 MB on MIT CSAIL, most of it the compiled kernels loaded at the first scan), as
    the time figures leave the first block out. NaN for a single block."""
    if fig["n"] <= BLOCK:
        return float("nan")
    return float(fig["rss_peak_mb"] - fig["rss_blocks_mb"][0]) / ((fig["n"] - BLOCK) / BLOCK)


def report(fig: dict) -> None:
    n = fig["n"]
    k = n / BLOCK
    print(
        f"\n== {n} scans: {fig['nodes']} nodes, {fig['loop_closures']} loop closures, "
        f"{fig.get('reused_keyframes', 0)} keyframes hung from old nodes"
    )
    if fig.get("lc_false") is not None:
        print(f"  loop closures off the single pass by more than 0.3 m or 3 deg: {fig['lc_false']}")
    print("  block (scans)   wall (s)  CPU (s)  wall s/1000  CPU s/1000  peak RSS after (MB)")
    rows = zip(fig["blocks_s"], fig["cpu_blocks_s"], fig["rss_blocks_mb"], strict=True)
    for i, (t, c, r) in enumerate(rows):
        lo, hi = i * BLOCK, min((i + 1) * BLOCK, n)
        per = BLOCK / (hi - lo)
        print(f"  {lo:6d}-{hi:<6d}  {t:8.2f} {c:8.2f}  {t * per:11.2f} {c * per:11.2f}  {r:10.0f}")
    per_k = fig["process_s"] / k
    print(f"  scans processed: {fig['process_s']:.1f} s ({per_k:.2f} s per 1000 scans)")
    print(f"  finish (batch refinement, result): {fig['finish_s']:.1f} s")
    print(f"  grid: {fig['grid_s']:.1f} s")
    print(
        f"  peak RSS: {fig['rss_peak_mb']:.0f} MB; above the start (imports and source log, "
        f"{fig['rss_start_mb']:.0f} MB): {_grown(fig) / k:.1f} MB per 1000 scans; after "
        f"the scans {fig['rss_blocks_mb'][-1]:.0f} MB, after finish {fig['rss_finish_mb']:.0f} MB; "
        f"above the first block's peak: {_grown_per_k_after_first(fig):.1f} MB per 1000 scans "
        "after it"
    )
    print("  stages (s): " + ", ".join(f"{s} {v:.1f}" for s, v in fig["stages_s"].items()))


def _steady_blocks(fig: dict) -> tuple[list[float], list[float]]:
    """Wall and CPU seconds of the whole blocks after the first (which includes JIT
    compilation and the empty map's first scans)."""
    last = (fig["n"] - 1) % BLOCK + 1
    whole = slice(1, len(fig["blocks_s"]) - (1 if last < BLOCK else 0))
    return fig["blocks_s"][whole], fig["cpu_blocks_s"][whole]


def print_summary(summary: Sequence[dict]) -> None:
    """The table over runs and the issue-12 flatness figures: per size the median over its
    runs of the mean time per 1000 scans (whole blocks after the first), their largest over
    smallest, and within each run of the largest size its last ten blocks over its first ten."""
    print("\nsummary (s per 1000 scans; blocks after the first, which includes JIT compilation)")
    print(
        "  size   wall first/last/mean   CPU first/last/mean   CPU max/min   peak RSS MB, per 1000"
        " scans above the start, above the first block"
    )
    steady: dict[int, list[tuple[float, float, float]]] = {}
    for fig in summary:
        k = fig["n"] / BLOCK
        last = (fig["n"] - 1) % BLOCK + 1
        b = fig["blocks_s"]
        c = fig["cpu_blocks_s"]
        wall, cpu = _steady_blocks(fig)
        spread = max(cpu) / min(cpu) if cpu else float("nan")
        print(
            f"  {fig['n']:6d}  {b[0]:6.1f} {b[-1] * BLOCK / last:6.1f} {fig['process_s'] / k:6.1f}"
            f"   {c[0]:6.1f} {c[-1] * BLOCK / last:6.1f} {sum(c) / k:6.1f}   {spread:8.2f}"
            f"      {fig['rss_peak_mb']:6.0f}, {_grown(fig) / k:5.1f}, "
            f"{_grown_per_k_after_first(fig):5.1f}"
        )
        if wall:
            steady.setdefault(fig["n"], []).append(
                (float(np.mean(wall)), float(np.mean(cpu)), _grown_per_k_after_first(fig))
            )
    if len(steady) > 1:
        print(
            "\nflatness across sizes (issue 12: within 20 %): per size, the median over its runs "
            "of the mean s per 1000 scans over the whole blocks after the first, and of the peak "
            "RSS added per 1000 scans after the first block (MB)"
        )
        for col, name in enumerate(("wall", "CPU ", "MB  ")):
            per_size = {n: [r[col] for r in runs] for n, runs in steady.items()}
            med = np.array([np.median(v) for v in per_size.values()])
            runs = "; ".join(
                f"{n}: " + ", ".join(f"{v:.2f}" for v in vals) for n, vals in per_size.items()
            )
            print(f"  {name} {runs}; largest / smallest median {med.max() / med.min():.2f}")
    n_max = max((f["n"] for f in summary), default=0)
    for fig in (f for f in summary if f["n"] == n_max):
        wall, cpu = _steady_blocks(fig)
        if len(wall) >= 20:
            print(
                f"  within a {n_max}-scan run, last 10 blocks / first 10 after the first: "
                f"wall {np.mean(wall[-10:]) / np.mean(wall[:10]):.2f}, "
                f"CPU {np.mean(cpu[-10:]) / np.mean(cpu[:10]):.2f}"
            )
            print_stage_growth(fig, len(wall))


def print_stage_growth(fig: dict, steady: int) -> None:
    """Per stage of the pipeline's timer, the mean seconds per block over the first ten and
    the last ten of the ``steady`` whole blocks after the first, and their difference: which
    stages the growth along the log is in."""
    blocks = fig["stage_blocks_s"][1 : 1 + steady]
    first, last = blocks[:10], blocks[-10:]
    stages = sorted({s for b in blocks for s in b})
    mean_first = {s: float(np.mean([b.get(s, 0.0) for b in first])) for s in stages}
    mean_last = {s: float(np.mean([b.get(s, 0.0) for b in last])) for s in stages}
    print("    stage            first 10   last 10   difference  (s per block of 1000 scans)")
    for s in sorted(stages, key=lambda s: mean_first[s] - mean_last[s]):
        d = mean_last[s] - mean_first[s]
        print(f"    {s:16s} {mean_first[s]:8.2f}  {mean_last[s]:8.2f}  {d:+10.2f}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="2000,10000,50000", help="comma-separated scan counts")
    ap.add_argument("--log", type=Path, default=DATA, help="source CARMEN log")
    ap.add_argument("--no-grid", action="store_true", help="skip the occupancy grid")
    ap.add_argument(
        "--source",
        choices=("csail", "corridor"),
        default="csail",
        help="csail: the log driven back and forth; corridor: a simulated exploring corridor",
    )
    ap.add_argument(
        "--repeats",
        type=int,
        default=1,
        help="runs of each size (sizes interleaved), to average out the machine's spread",
    )
    ap.add_argument(
        "--check-closures",
        action="store_true",
        help="csail: count loop closures off the single pass through the log (after timing)",
    )
    ap.add_argument(
        "--workers",
        type=int,
        default=1,
        help="processes of each run (as slam.workers): 2 adds the feature worker and the "
        "loop closer's match helper (iceg.pipeline.helper_processes)",
    )
    ap.add_argument(
        "--no-reuse-nodes",
        action="store_true",
        help="slam.reuse_nodes off: every keyframe of a revisit adds a node (as before it)",
    )
    ap.add_argument("--child", type=int, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if not args.log.exists():
        sys.exit(f"{args.log}: not found (the MIT CSAIL log lives in ../shared/data)")
    if args.child is not None:
        fig = run_one(
            args.child,
            args.log,
            not args.no_grid,
            args.source,
            args.check_closures,
            args.workers,
            not args.no_reuse_nodes,
        )
        print(json.dumps(fig))
        return
    summary = []
    sizes = [int(s) for s in args.sizes.split(",")]
    for n in sizes * max(1, args.repeats):
        cmd = [sys.executable, __file__, "--child", str(n), "--log", str(args.log)]
        cmd += ["--source", args.source, "--workers", str(args.workers)]
        if args.no_grid:
            cmd.append("--no-grid")
        if args.check_closures:
            cmd.append("--check-closures")
        if args.no_reuse_nodes:
            cmd.append("--no-reuse-nodes")
        out = subprocess.run(cmd, check=True, stdout=subprocess.PIPE, text=True).stdout
        fig = json.loads(out.strip().splitlines()[-1])
        report(fig)
        summary.append(fig)
        sys.stdout.flush()
    print_summary(summary)


if __name__ == "__main__":
    main()
