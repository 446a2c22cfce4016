"""Benchmark: two versions of the code on one log, alternated, so that a change smaller than
the machine's own spread can still be seen (issue 13's speed work).

On the shared benchmark machine one run of MIT CSAIL moves by 10-20 % from one run to the
next with the other jobs' load, more than most single changes save. This compares two
versions the way ``docs/design.md`` ("Speed") does by hand: each sample is a fresh process
that runs the log once untimed (numba's kernels loaded, the caches warm) and once timed
(``run_log`` and the map's render, as ``bench_pipeline.py``'s whole run), and the samples
alternate in pairs whose order turns every pair (A B, B A, A B, ...), so that a drift of the
machine's speed through the session falls on both versions alike. It prints every sample
(wall time, CPU of the main process, CPU of the helper processes, the 1-minute load), each
pair's ratio B / A, their median, range and how many pairs B was faster in, and whether the
two versions gave the same trajectory bits (a hash of the poses).

A version is a git revision (checked out into a temporary worktree, removed at the end) or
a directory holding the project's packages (used as it is: a working tree with uncommitted
changes, or a copy built another way). The child processes put it first on ``PYTHONPATH``
and check that ``iceg`` is imported from it. A new worktree has no numba cache: its first
process compiles every kernel (a minute or two, untimed and printed as such).

Run: ``python benchmarks/bench_compare.py A [B] [--pairs N] [--workers N]
[--log path/to/log | --log demo]`` (``B`` defaults to this checkout; ``--pairs`` 4,
``--workers`` 2, the log MIT CSAIL; ``demo``: the built-in simulated demo, 701 scans, about
a fifth of MIT CSAIL's time, for more pairs in the same time).
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
DATA = ROOT.parent / "shared" / "data" / "mit-csail" / "mit-csail.clf"

#: What a sample runs in its child process (argv: the tree, the log, the workers). It is
#: self-contained rather than importing ``bench_pipeline``'s ``_config`` and
#: ``_helpers_cpu_s``: it runs inside the version under test, whose benchmarks may differ
#: or predate them; it uses only ``IcegConfig``, ``run_log`` and ``run_simulated_demo``.
CHILD = """
import hashlib, json, os, resource, sys, time
tree, log, workers = sys.argv[1], sys.argv[2], int(sys.argv[3])
import iceg
if not os.path.abspath(iceg.__file__).startswith(os.path.abspath(tree) + os.sep):
    sys.exit(f"iceg was imported from {iceg.__file__}, not from {tree}")
from iceg.config import IcegConfig
from iceg.pipeline import run_log, run_simulated_demo

cfg = IcegConfig()
cfg = cfg.model_copy(update={"slam": cfg.slam.model_copy(update={"workers": workers})})
cfg = cfg.model_copy(update={"grid": cfg.grid.model_copy(update={"threads": workers})})

def helpers_cpu():
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime

def run():
    return run_simulated_demo(cfg) if log == "demo" else run_log(log, cfg)

run().render_map()
h0, t0, c0 = helpers_cpu(), time.perf_counter(), time.process_time()
result = run()
result.render_map()
wall, cpu = time.perf_counter() - t0, time.process_time() - c0
print(json.dumps({
    "wall": wall, "cpu": cpu, "helpers_cpu": helpers_cpu() - h0, "load": os.getloadavg()[0],
    "poses": hashlib.sha256(result.poses.tobytes()).hexdigest()[:12],
}))
"""


@dataclass(frozen=True)
class PairedSummary:
    """Ratios B / A of paired samples: their median, least and largest, and the number of
    pairs in which B took less."""

    ratios: list[float]
    median: float
    low: float
    high: float
    b_less: int


def paired_summary(a: list[float], b: list[float]) -> PairedSummary:
    """Summary of the paired samples ``a[i]``, ``b[i]`` (seconds, same length, positive).

    Raises:
        ValueError: the two lists differ in length or are empty.
    """
    if len(a) != len(b) or not a:
        raise ValueError(f"paired samples need the same nonzero count, got {len(a)} and {len(b)}")
    ratios = [y / x for x, y in zip(a, b, strict=True)]
    return PairedSummary(
        ratios,
        statistics.median(ratios),
        min(ratios),
        max(ratios),
        sum(y < x for x, y in zip(a, b, strict=True)),
    )


def run_order(pairs: int) -> list[str]:
    """The versions' order over ``pairs`` pairs: ``A B``, then ``B A``, and so on."""
    order: list[str] = []
    for i in range(pairs):
        order += ["A", "B"] if i % 2 == 0 else ["B", "A"]
    return order


def _tree(version: str, scratch: Path) -> tuple[Path, bool]:
    """The directory of a version and whether it is a worktree made here."""
    path = Path(version)
    if path.is_dir() and (path / "iceg").is_dir():
        return path.resolve(), False
    found = subprocess.run(
        ["git", "-C", str(ROOT), "rev-parse", "--verify", "--quiet", f"{version}^{{commit}}"],
        capture_output=True,
        text=True,
    )
    if found.returncode != 0:
        raise SystemExit(f"{version}: neither a git revision nor a folder holding iceg/")
    sha = found.stdout.strip()
    where = scratch / sha[:12]
    if not where.exists():
        subprocess.run(
            ["git", "-C", str(ROOT), "worktree", "add", "--detach", str(where), sha],
            check=True,
            capture_output=True,
        )
    return where, True


def _sample(tree: Path, log: str, workers: int) -> dict[str, float | str]:
    paths = [str(tree), *filter(None, os.environ.get("PYTHONPATH", "").split(os.pathsep))]
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(paths))
    env.pop("PYTHONDONTWRITEBYTECODE", None)  # as after pip install: bytecode cached
    done = subprocess.run(
        [sys.executable, "-c", CHILD, str(tree), log, str(workers)],
        env=env,
        cwd=tree,  # the child's first path entry is its working directory
        capture_output=True,
        text=True,
    )
    if done.returncode != 0:
        raise SystemExit(f"the run in {tree} failed:\n{done.stderr[-2000:]}")
    sample: dict[str, float | str] = json.loads(done.stdout.strip().splitlines()[-1])
    return sample


def _print_summary(name: str, a: list[float], b: list[float]) -> None:
    s = paired_summary(a, b)
    med_a, med_b = statistics.median(a), statistics.median(b)
    print(
        f"  {name:<12} A median {med_a:7.2f} s, B median {med_b:7.2f} s;"
        f" B / A median {s.median:.3f} (pairs {s.low:.3f}-{s.high:.3f}), B less in "
        f"{s.b_less} of {len(a)} pairs"
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("a", help="git revision or directory of version A")
    ap.add_argument("b", nargs="?", default=str(ROOT), help="version B (default: this checkout)")
    ap.add_argument("--pairs", type=int, default=4)
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--log", default=str(DATA), help="a log (file or bag folder), or 'demo'")
    args = ap.parse_args()
    if args.pairs < 1:
        ap.error("--pairs must be at least 1")
    if args.log != "demo":
        if not Path(args.log).exists():  # a file, or a ROS 2 bag's folder
            ap.error(f"--log {args.log}: no such file or folder")
        args.log = str(Path(args.log).resolve())  # the children run in the versions' folders
    with tempfile.TemporaryDirectory(prefix="iceg-compare-") as tmp:
        made: list[Path] = []
        trees: dict[str, Path] = {}
        try:
            for key, version in (("A", args.a), ("B", args.b)):
                trees[key], new = _tree(version, Path(tmp))
                if new:
                    made.append(trees[key])
                print(f"{key}: {version} ({trees[key]})")
            for key, tree in trees.items():
                print(f"warming {key} (numba's cache; untimed) ...", flush=True)
                _sample(tree, args.log, args.workers)
            samples: dict[str, list[dict[str, float | str]]] = {"A": [], "B": []}
            print(
                f"{'run':>4} {'version':>7} {'wall s':>7} {'CPU s':>7} {'helpers s':>9} "
                f"{'load':>5}  poses"
            )
            for i, key in enumerate(run_order(args.pairs)):
                s = _sample(trees[key], args.log, args.workers)
                samples[key].append(s)
                print(
                    f"{i + 1:4d} {key:>7} {s['wall']:7.2f} {s['cpu']:7.2f} "
                    f"{s['helpers_cpu']:9.2f} {s['load']:5.2f}  {s['poses']}",
                    flush=True,
                )
        finally:
            for where in made:
                subprocess.run(
                    ["git", "-C", str(ROOT), "worktree", "remove", "--force", str(where)],
                    check=False,
                    capture_output=True,
                )
    print(f"{Path(args.log).name}, {args.pairs} pairs, {args.workers} workers:")
    for metric, name in (("wall", "wall"), ("cpu", "main CPU")):
        _print_summary(
            name,
            [float(s[metric]) for s in samples["A"]],
            [float(s[metric]) for s in samples["B"]],
        )
    hashes = {key: {str(s["poses"]) for s in runs} for key, runs in samples.items()}
    same = hashes["A"] == hashes["B"] and len(hashes["A"]) == 1
    print(
        "  trajectory   the same bits in every run"
        if same
        else f"  trajectory   differs: A {sorted(hashes['A'])}, B {sorted(hashes['B'])}"
    )


if __name__ == "__main__":
    main()
