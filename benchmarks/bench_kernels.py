"""Benchmark: the compiled kernels the main process calls in a MIT CSAIL run, in the run and
alone (issue 13).

Runs the log once to load every kernel and count its calls, then once more with each numba
kernel that the pipeline's modules import wrapped by a timer (``time.perf_counter``, about
0.3 µs a call), and prints each kernel's calls, total and mean time in the run, the sum over
all kernels and the run's wall time. For the matching kernels (pure functions of their
arguments), the arguments of about ``--replay`` calls spread evenly over the run are copied
as they come, and each kernel is then replayed alone on them: the minimum over ``--passes``
passes of the mean time a call, and the ratio of the run's mean to it.

The replayed figure is the kernel's own work with its code and data in the caches; the run's
adds numba's dispatch and the cache misses of code and data that the rest of each keyframe
displaced (on this 2-core virtual machine the two differ by up to three times; docs/design.md,
"Kernels that touch each value once"). The replayed figure hardly moves with the machine's
load, so it is the one to compare when a kernel's code changes; the run's says what the
change is worth. The same calls are then replayed once more with a sum over ``--sweep-mb``
megabytes of other data before each call (each call timed alone): the kernel with its code
and data evicted from the core's caches, as the rest of a keyframe leaves them. Where that
figure is near the run's, the kernel's loss in the run is the caches' (docs/design.md, "More
levers measured, none landed"); the last line sums it over the replayed kernels' calls.

Run: ``python benchmarks/bench_kernels.py [log] [--workers N] [--replay N] [--passes N]
[--sweep-mb MB]``
(``--replay 0``: the run's figures only, nothing replayed).
"""

from __future__ import annotations

import argparse
import copy
import functools
import importlib
import os
import time
from collections import defaultdict
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
from numba.core.registry import CPUDispatcher

from iceg.config import IcegConfig
from iceg.pipeline import run_log

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "mit-csail"

#: The modules whose imported kernels are wrapped (every caller of ``_kernels`` and of the
#: feature map's, visibility's and grid's kernels).
MODULES = (
    "iceg.matching.hypotheses",
    "iceg.matching.refine",
    "iceg.matching.correlation",
    "iceg.matching.matcher",
    "iceg.matching.geometry",
    "iceg.matching.plicp",
    "iceg.slam",
    "iceg.feature_map",
    "iceg.landmark_association",
    "iceg.landmark_frames",
    "iceg.visibility",
    "iceg.node_index",
    "iceg.loop_closure",
    "iceg.grid",
)

#: Kernels that only read their arguments, so that a call can be replayed on a copy of them.
REPLAYED = frozenset(
    {
        "refine_pose",
        "segment_rotation_peak",
        "final_covariances",
        "correlation_scores",
        "ray_wall_check",
        "finite_points_within",
        "points_explained",
        "sorted_cells",
        "vote_clusters",
        "segment_grid",
        "segment_arrays",
        "feature_angles",
        "directed_poses",
        "intersection_pair_poses",
        "feasible_pair_indices",
    }
)


class _Timings:
    """Each wrapped kernel's calls and time in the run, in this process only (not in the
    helpers a run forks), and the copied arguments of about ``keep`` of its calls spread
    evenly over the run (replayed kernels only; every ``stride[name]``-th call, the strides
    from the calls of a first run)."""

    def __init__(self, keep: int) -> None:
        self.keep = keep
        self.pid = os.getpid()
        self.recording = False
        self.total_s: dict[str, float] = defaultdict(float)
        self.calls: dict[str, int] = defaultdict(int)
        self.stride: dict[str, int] = {}
        self.args: dict[str, list[tuple[Any, ...]]] = defaultdict(list)
        self.kernels: dict[str, Callable[..., Any]] = {}

    def wrap(self, name: str, kernel: Callable[..., Any]) -> Callable[..., Any]:
        self.kernels[name] = kernel

        @functools.wraps(kernel)
        def timed(*args: Any, **kwargs: Any) -> Any:
            if os.getpid() != self.pid:
                return kernel(*args, **kwargs)
            if not self.recording:
                self.calls[name] += 1
                return kernel(*args, **kwargs)
            t0 = time.perf_counter()
            try:
                return kernel(*args, **kwargs)
            finally:
                self.total_s[name] += time.perf_counter() - t0
                # copied after the call, so that the copy does not warm the caches for it
                stride = self.stride.get(name, 0)
                if stride and not kwargs and self.calls[name] % stride == 0:
                    self.args[name].append(copy.deepcopy(args))
                self.calls[name] += 1

        return timed

    def start_recording(self) -> None:
        """Strides from the calls counted so far (the first run), then time and record."""
        self.stride = {
            name: max(1, n // self.keep)
            for name, n in self.calls.items()
            if name in REPLAYED and self.keep > 0
        }
        self.calls.clear()
        self.recording = True


def _install(timings: _Timings) -> None:
    for module_name in MODULES:
        module = importlib.import_module(module_name)
        for name, value in list(vars(module).items()):
            if isinstance(value, CPUDispatcher):
                setattr(module, name, timings.wrap(name, value))


def _replayed_us(kernel: Callable[..., Any], calls: list[tuple[Any, ...]], passes: int) -> float:
    """Minimum over ``passes`` of the mean time (µs) of replaying ``calls``."""
    best = float("inf")
    for _ in range(passes):
        t0 = time.perf_counter()
        for args in calls:
            kernel(*args)
        best = min(best, (time.perf_counter() - t0) / len(calls))
    return 1e6 * best


def _swept_us(
    kernel: Callable[..., Any], calls: list[tuple[Any, ...]], passes: int, sweep: np.ndarray
) -> float:
    """Minimum over ``passes`` of the mean time (µs) of the calls replayed each after a sum
    over ``sweep`` (not timed), so that each starts with its code and data out of the core's
    caches."""
    best = float("inf")
    for _ in range(passes):
        total = 0.0
        for args in calls:
            sweep.sum()
            t0 = time.perf_counter()
            kernel(*args)
            total += time.perf_counter() - t0
        best = min(best, total / len(calls))
    return 1e6 * best


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", nargs="?", type=Path, default=DATA / "mit-csail.clf")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--replay", type=int, default=300, help="calls kept per replayed kernel (0: none)"
    )
    ap.add_argument("--passes", type=int, default=7)
    ap.add_argument("--top", type=int, default=25)
    ap.add_argument(
        "--sweep-mb", type=float, default=8.0, help="data swept before each call (0: none)"
    )
    args = ap.parse_args()
    cfg = IcegConfig()
    cfg = cfg.model_copy(update={"slam": cfg.slam.model_copy(update={"workers": args.workers})})
    timings = _Timings(args.replay)
    _install(timings)
    run_log(args.log, config=cfg)  # loads every kernel, counts the calls
    timings.start_recording()
    t0 = time.perf_counter()
    run_log(args.log, config=cfg)
    wall = time.perf_counter() - t0
    timings.recording = False
    in_kernels = sum(timings.total_s.values())
    print(
        f"{args.log.name}, {args.workers} worker(s): run {wall:.2f} s, of which the main "
        f"process's kernels {in_kernels:.2f} s ({100 * in_kernels / wall:.0f} %)"
    )
    sweep = np.ones(max(1, int(args.sweep_mb * 2**20) // 8)) if args.sweep_mb > 0 else None
    header = f"{'kernel':26s} {'calls':>6s} {'run s':>7s} {'run µs':>8s}"
    if args.replay > 0:
        header += f" {'alone µs':>9s} {'ratio':>6s} {'swept µs':>9s} {'ratio':>6s}"
    print(header)
    evicted_s = 0.0
    for name in sorted(timings.total_s, key=lambda k: -timings.total_s[k])[: args.top]:
        run_us = 1e6 * timings.total_s[name] / timings.calls[name]
        replayed = ""
        if timings.args[name]:
            kernel, calls = timings.kernels[name], timings.args[name]
            alone_us = _replayed_us(kernel, calls, args.passes)
            replayed = f"{alone_us:9.1f} {run_us / alone_us:6.2f}"
            if sweep is not None:
                swept_us = _swept_us(kernel, calls, args.passes, sweep)
                replayed += f" {swept_us:9.1f} {run_us / swept_us:6.2f}"
                evicted_s += 1e-6 * max(0.0, swept_us - alone_us) * timings.calls[name]
        print(
            f"{name:26s} {timings.calls[name]:6d} {timings.total_s[name]:7.3f} "
            f"{run_us:8.1f} {replayed}"
        )
    if sweep is not None and args.replay > 0:
        print(
            f"the replayed kernels above, swept against alone, times their calls: "
            f"{evicted_s:.2f} s of the run ({args.sweep_mb:g} MB swept before each call)"
        )


if __name__ == "__main__":
    main()
