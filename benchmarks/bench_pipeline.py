"""Benchmark: the whole pipeline on the MIT CSAIL log (1988 scans, 361 beams) and on the
built-in simulated demo (what ``iceg run`` without a log runs).

For each run it prints the end-to-end wall time (log reading or simulation, SLAM, batch
refinement, grid), scans per second, the ratio of the wall time to the log's real duration
(424 s for CSAIL), per-stage totals and per-keyframe medians, and the relation (CSAIL) or
ground-truth (demo) errors. It also measures the cold start of a fresh process (import of
the pipeline, then the first scan and the first two matched keyframes, with the numba cache
and Python's bytecode cache warm, as after ``pip install``; the first figure of a process
that had to compile is printed too). The child processes write bytecode even where the
environment sets ``PYTHONDONTWRITEBYTECODE`` (this machine's does: every start would then
compile the project's ~60 modules from source, about 0.1 s).

Issue 13 budget (median per keyframe on CSAIL): features <= 0.4 ms; local-map match
<= 1.0 ms; feature-map update + reference <= 0.4 ms; iSAM2 update <= 0.3 ms; loop-closure
search (whole run) <= 1.0 s; grid (whole run) <= 0.4 s; cold start <= 1.0 s; whole run
<= 6 s.

Per-keyframe samples come from :class:`iceg.slam.StageTimer` (its ``samples``); the
reference build (inside the ``matching`` stage) is timed here by wrapping
``FeatureMap.reference`` during the local match only, and reported as its own row (the
``match`` row is ``matching`` minus it). Beside each wall figure the CPU time of the main
process (``time.process_time``, marked at the start of ``Slam.process`` / ``finish`` and at
each stage boundary; the grid's around ``render_map``): on a machine shared with other jobs,
compare CPU times of runs made back to back. The CPU time of the helper processes (feature
worker, match helper; ``RUSAGE_CHILDREN``, counted as they exit at the end of the run) is
printed with the run's CPU in all and half of it: the wall time two cores could reach if that
work were split evenly between them. With ``--profile`` the CSAIL run is profiled with
pyinstrument instead (wall figures then include the profiler's overhead): the HTML goes to
the printed path and the five largest self-time costs are listed.

Last, ``iceg run`` as a user types it (``python -m iceg run``), in a fresh process on
the log with its relations and on the demo: the wall time from start to exit, and how much of
it is not the run's stages (interpreter, imports, log reading, saving, exit); ``--no-cli``
skips it. ``--fresh-install`` first times a new user's first ``iceg run`` of the demo, with
numba's cache empty so that every kernel is compiled, and the same command once more (about
two and a half minutes on the benchmark machine).

``--workers N`` sets both ``slam.workers`` and ``grid.threads`` (left at 0, each takes 2
when the cores are idle enough, :func:`iceg.features.prefetch.auto_workers`).

Like the ``iceg`` command, the benchmark first starts itself again with mimalloc where it is
installed, else with glibc's malloc on transparent huge pages where the machine offers them
(:func:`iceg.malloc.exec_with_fast_malloc`), so that its in-process runs, its child processes
and its ``iceg run`` measure what the command gets; ``--glibc`` starts them on glibc's malloc
on huge pages (``ICEG_MALLOC=glibc``), ``--default-pages`` on glibc's default pages
(``glibc.malloc.hugetlb=0``). The first line says which.

Run: ``python benchmarks/bench_pipeline.py [--profile [HTML]] [--no-demo] [--no-cold]
[--no-cli] [--fresh-install] [--glibc | --default-pages] [--workers N] [path/to/mit-csail.clf
[path/to/relations]]``
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from collections import defaultdict
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from iceg.results import SlamResult

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "mit-csail"
ROOT = Path(__file__).resolve().parents[1]

#: Issue 13 budget: row -> (kind, limit). "median" rows are ms per keyframe, "total" rows s.
BUDGET: dict[str, tuple[str, float]] = {
    "features": ("median", 0.4),
    "match": ("median", 1.0),
    "map+reference": ("median", 0.4),
    "isam2": ("median", 0.3),
    "loop_closure": ("total", 1.0),
    "grid": ("total", 0.4),
}
#: Key prefix of the CPU-time samples (``time.process_time``) beside the wall-time ones.
CPU = "cpu:"


@contextmanager
def _instrument() -> Iterator[dict[str, list[float]]]:
    """Per-call samples of every stage (also on code whose StageTimer only sums) and of the
    reference built for the local match."""
    import iceg.slam as slam_mod
    from iceg.feature_map import FeatureMap

    samples: dict[str, list[float]] = defaultdict(list)
    orig_add = slam_mod.StageTimer.add
    orig_ref = FeatureMap.reference
    orig_local = slam_mod.Slam._match_local
    orig_process = slam_mod.Slam.process
    orig_finish = slam_mod.Slam.finish
    state = {"local": False, "finishing": False}
    # CPU time of this process per stage: every stage's t0 is the start of process() /
    # finish() or the previous add() of the same call, so the CPU clock is marked there.
    cpu_mark = [time.process_time()]

    def add(self: Any, stage: str, t0: float) -> float:
        now: float = orig_add(self, stage, t0)
        cpu = time.process_time()
        samples[stage].append(now - t0)
        samples[CPU + stage].append(cpu - cpu_mark[0])
        cpu_mark[0] = cpu
        return now

    def process(self: Any, *args: Any, **kwargs: Any) -> Any:
        cpu_mark[0] = time.process_time()
        return orig_process(self, *args, **kwargs)

    def finish(self: Any, *args: Any, **kwargs: Any) -> Any:
        # The second chance for keyframes unmatched online (Slam.finish) matches again: its
        # references belong to the finish, not to the keyframes' local matches.
        cpu_mark[0] = time.process_time()
        state["finishing"] = True
        try:
            return orig_finish(self, *args, **kwargs)
        finally:
            state["finishing"] = False

    def reference(self: Any, *args: Any, **kwargs: Any) -> Any:
        t0, c0 = time.perf_counter(), time.process_time()
        out = orig_ref(self, *args, **kwargs)
        if state["local"]:
            samples["reference"].append(time.perf_counter() - t0)
            samples[CPU + "reference"].append(time.process_time() - c0)
        return out

    def match_local(self: Any, *args: Any, **kwargs: Any) -> Any:
        state["local"] = not state["finishing"]
        try:
            return orig_local(self, *args, **kwargs)
        finally:
            state["local"] = False

    slam_mod.StageTimer.add = add  # type: ignore[method-assign]
    FeatureMap.reference = reference  # type: ignore[method-assign]
    slam_mod.Slam._match_local = match_local  # type: ignore[method-assign]
    slam_mod.Slam.process = process  # type: ignore[method-assign]
    slam_mod.Slam.finish = finish  # type: ignore[method-assign]
    try:
        yield samples
    finally:
        slam_mod.StageTimer.add = orig_add  # type: ignore[method-assign]
        FeatureMap.reference = orig_ref  # type: ignore[method-assign]
        slam_mod.Slam._match_local = orig_local  # type: ignore[method-assign]
        slam_mod.Slam.process = orig_process  # type: ignore[method-assign]
        slam_mod.Slam.finish = orig_finish  # type: ignore[method-assign]


def _config(workers: int | None) -> Any:
    from iceg.config import IcegConfig

    cfg = IcegConfig()
    if workers is not None and "workers" in type(cfg.slam).model_fields:
        cfg = cfg.model_copy(update={"slam": cfg.slam.model_copy(update={"workers": workers})})
    if workers is not None and "threads" in type(cfg.grid).model_fields:
        # the grid's threads too, rather than a choice by the machine's idleness of the moment
        cfg = cfg.model_copy(update={"grid": cfg.grid.model_copy(update={"threads": workers})})
    return cfg


def _derived_rows(rows: dict[str, list[float]], prefix: str) -> None:
    """Add the ``match`` and ``map+reference`` rows (of wall or, with ``prefix`` CPU, CPU
    samples) derived from ``matching``, ``feature_map`` and ``reference``."""
    matching, ref, fmap = (
        rows.get(prefix + k, []) for k in ("matching", "reference", "feature_map")
    )
    if matching and len(ref) == len(matching):
        rows[prefix + "match"] = [m - r for m, r in zip(matching, ref, strict=True)]
    if fmap and len(ref) == len(fmap) - 1:
        # The first scan's map update has no local match (no reference).
        rows[prefix + "map+reference"] = [f + r for f, r in zip(fmap[1:], ref, strict=True)]


def _helpers_cpu_s() -> float:
    """CPU seconds (user + system) of this process's children that have exited: a run's
    helper processes (feature worker, match helper) count once they are stopped, at the end
    of the run."""
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


@dataclass
class _Clock:
    """A timed block's wall time, CPU time of this process and of the helper processes that
    exited meanwhile (seconds; filled when the block ends)."""

    wall: float = 0.0
    cpu: float = 0.0
    helpers_cpu: float = 0.0


@contextmanager
def _clock() -> Iterator[_Clock]:
    clock = _Clock()
    h0, t0, c0 = _helpers_cpu_s(), time.perf_counter(), time.process_time()
    yield clock
    clock.wall, clock.cpu = time.perf_counter() - t0, time.process_time() - c0
    clock.helpers_cpu = _helpers_cpu_s() - h0


def _report(name: str, result: SlamResult, samples: dict[str, list[float]], clock: _Clock) -> None:
    wall, cpu, helpers_cpu = clock.wall, clock.cpu, clock.helpers_cpu
    n_scans, stage_seconds = result.n_scans, result.stage_seconds
    duration_s = float(result.stamps_s[-1] - result.stamps_s[0])
    print(f"== {name}")
    print(
        f"end to end: {wall:.2f} s for {n_scans} scans ({n_scans / wall:.1f} scans/s); "
        f"real duration {duration_s:.1f} s, wall/real = {wall / duration_s:.4f}; "
        f"CPU of the main process {cpu:.2f} s (workers excluded)"
    )
    # The floor two cores put under the wall time: the run's CPU in all, split evenly.
    print(
        f"CPU of the helper processes {helpers_cpu:.2f} s; in all {cpu + helpers_cpu:.2f} s, "
        f"{(cpu + helpers_cpu) / 2:.2f} s per core if split evenly over two"
    )
    rows = dict(samples)
    _derived_rows(rows, "")
    _derived_rows(rows, CPU)
    print(
        f"  {'stage':<18} {'total s':>8} {'calls':>6} {'median ms':>10} {'p90 ms':>8}"
        f" {'CPU s':>8} {'CPU med ms':>10}"
    )
    totals = dict(stage_seconds)
    for key in ("reference", "match", "map+reference"):
        if key in rows:
            totals[key] = sum(rows[key])
    for stage in sorted(totals, key=lambda k: -totals[k]):
        xs = sorted(rows.get(stage, []))
        cs = rows.get(CPU + stage, [])
        med = f"{1e3 * statistics.median(xs):10.3f}" if xs else f"{'':10}"
        p90 = f"{1e3 * xs[int(0.9 * (len(xs) - 1))]:8.3f}" if xs else f"{'':8}"
        ctot = f"{sum(cs):8.3f}" if cs else f"{'':8}"
        cmed = f"{1e3 * statistics.median(cs):10.3f}" if cs else f"{'':10}"
        print(f"  {stage:<18} {totals[stage]:8.3f} {len(xs):6d} {med} {p90} {ctot} {cmed}")
    print("  budget (issue 13; wall, and CPU of this process):")
    for row, (kind, limit) in BUDGET.items():
        if kind == "median":
            xs, cs = rows.get(row, []), rows.get(CPU + row, [])
            value = 1e3 * statistics.median(xs) if xs else float("nan")
            cpu_value = 1e3 * statistics.median(cs) if cs else float("nan")
            unit = "ms/keyframe (median)"
        else:
            value = totals.get(row, float("nan"))
            cs = rows.get(CPU + row, [])
            cpu_value = sum(cs) if cs else float("nan")
            unit = "s (whole run)"
        flag = "ok" if value <= limit else "OVER"
        print(
            f"    {row:<16} {value:8.3f} (CPU {cpu_value:8.3f}) {unit:<21} budget {limit:5.2f}"
            f"  {flag}"
        )
    flag = "ok" if wall <= 6.0 else "OVER"
    print(f"    {'whole run':<16} {wall:8.3f} (CPU {cpu:8.3f}) {'s':<21} budget  6.00  {flag}")


def _render_map(result: SlamResult, samples: dict[str, list[float]]) -> None:
    """Render the run's map, its CPU time (this process) kept as the grid row's."""
    c1 = time.process_time()
    result.render_map()
    samples[CPU + "grid"].append(time.process_time() - c1)


def run_csail(
    log: Path, rel: Path, workers: int | None, profile: Path | None, out: Path | None
) -> dict[str, Any]:
    """The CSAIL run, timed (or profiled), with relation errors."""
    from iceg.pipeline import run_log

    cfg = _config(workers)
    profiler = None
    if profile is not None:
        from pyinstrument import Profiler

        profiler = Profiler(interval=0.0005)
        profiler.start()
    with _instrument() as samples, _clock() as clock:
        result = run_log(log, cfg, relations=rel)
        _render_map(result, samples)
    if profiler is not None:
        profiler.stop()
        assert profile is not None
        profile.write_text(profiler.output_html())
        print(f"profile (pyinstrument HTML): {profile}")
        _print_top_costs(profiler, 5)
    _report(f"CSAIL {log.name}", result, samples, clock)
    r = result.metrics["relations"]
    print(
        f"relation error: {r['trans_mean_m']:.4f} ± {r['trans_std_m']:.4f} m, "
        f"{r['rot_mean_deg']:.3f} ± {r['rot_std_deg']:.3f} deg "
        f"({r['n_matched']}/{r['n_relations']} relations)"
    )
    print(repr(result))
    if out is not None:
        result.save(out)
        print(f"saved (untimed): {out}")
    return {"wall": clock.wall}


def run_demo(workers: int | None) -> None:
    """The built-in demo (``iceg run`` with no log): simulation + SLAM + grid."""
    from iceg.pipeline import run_simulated_demo

    cfg = _config(workers)
    with _instrument() as samples, _clock() as clock:
        result = run_simulated_demo(cfg)
        _render_map(result, samples)
    _report("built-in demo (simulated office)", result, samples, clock)
    gt = result.metrics["ground_truth"]
    print(f"ground truth: {json.dumps(gt, default=str)}")


_COLD = r"""
import sys, time, json
t0 = time.perf_counter()
from iceg.config import IcegConfig
from iceg.slam import Slam
import iceg.pipeline
t_import = time.perf_counter() - t0
from frontends import open_log
it = iter(open_log(sys.argv[1]))
scans = [next(it) for _ in range(400)]
slam = Slam(IcegConfig())
t1 = time.perf_counter()
slam.process(scans[0])
t_first = time.perf_counter() - t1
t2 = time.perf_counter()
for s in scans[1:]:
    slam.process(s)
    if len(slam.export_state().node_odom) >= 3:
        break
t_kf = time.perf_counter() - t2
print(json.dumps({"import": t_import, "first_scan": t_first, "first_keyframe": t_kf}))
"""


def cold_start(log: Path) -> None:
    """Fresh processes: import, first scan, first two matched keyframes (numba cache loads;
    the scans before them, the robot standing, are not keyframes)."""
    env = _cli_env()
    runs = []
    for _ in range(3):
        out = subprocess.run(
            [sys.executable, "-c", _COLD, str(log)],
            env=env,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        runs.append(json.loads(out.strip().splitlines()[-1]))
    first, warm = runs[0], min(runs[1:], key=lambda r: sum(r.values()))
    for label, r in (("first process (may compile)", first), ("warm cache (best of 2)", warm)):
        total = sum(r.values())
        print(
            f"cold start, {label}: {total:.3f} s = import {r['import']:.3f} + first scan "
            f"{r['first_scan']:.3f} + first two keyframes {r['first_keyframe']:.3f}"
        )
    print(f"  budget 1.00 s: {'ok' if sum(warm.values()) <= 1.0 else 'OVER'}")


def _cli_env() -> dict[str, str]:
    """The environment of a fresh ``iceg`` process: this checkout on the path, with Python's
    bytecode cache written (a user's install has it)."""
    env = dict(os.environ, PYTHONPATH=os.environ.get("PYTHONPATH", str(ROOT)))
    env.pop("PYTHONDONTWRITEBYTECODE", None)
    return env


def _iceg_run(args: list[str], out: Path, env: dict[str, str]) -> tuple[float, float]:
    """``python -m iceg run ARGS --out OUT`` in a fresh process: its wall time from start to
    exit and the run's stages (``total_seconds`` of its metrics.json), seconds."""
    cmd = [sys.executable, "-m", "iceg", "run", *args, "--out", str(out), "--no-progress"]
    t0 = time.perf_counter()
    subprocess.run(cmd, env=env, capture_output=True, check=True)
    wall = time.perf_counter() - t0
    return wall, float(json.loads((out / "metrics.json").read_text())["total_seconds"])


def cli_runs(log: Path, rel: Path, workers: int | None) -> None:
    """``iceg run`` as a user types it, in a fresh process each (bytecode and numba caches
    warm), on the log with its relations and on the built-in demo: the wall time from the
    command's start to its exit, and what of it is not the run's stages (``total_seconds``
    of its metrics.json): interpreter start, imports, reading the log, saving the results
    and the interpreter's exit."""
    import tempfile

    extra: list[str] = []
    with tempfile.TemporaryDirectory() as tmp:
        if workers is not None:
            cfg = Path(tmp) / "workers.yaml"
            cfg.write_text(f"slam:\n  workers: {workers}\ngrid:\n  threads: {workers}\n")
            extra = ["--config", str(cfg)]
        cases: tuple[tuple[str, list[str]], ...] = (
            ("MIT CSAIL", [str(log), "--relations", str(rel)]),
            ("built-in demo", []),
        )
        for label, args in cases:
            out = Path(tmp) / label.replace(" ", "_")
            wall, stages = _iceg_run([*args, *extra], out, _cli_env())
            print(
                f"iceg run, {label}: {wall:.2f} s from start to exit = the run's stages "
                f"{stages:.2f} s + {wall - stages:.2f} s of start, log reading, saving and exit"
            )


def fresh_install() -> None:
    """A new user's first ``iceg run`` (the built-in demo): numba's cache empty
    (``NUMBA_CACHE_DIR`` set to a new folder), so every kernel the run calls is compiled;
    then the same command again, loading them from that cache."""
    import tempfile

    with tempfile.TemporaryDirectory() as tmp:
        env = dict(_cli_env(), NUMBA_CACHE_DIR=str(Path(tmp) / "numba"))
        for label in ("first run, empty numba cache", "second run, cache written by the first"):
            out = Path(tmp) / label.split(",")[0].replace(" ", "_")
            wall, stages = _iceg_run([], out, env)
            print(f"fresh install, built-in demo, {label}: {wall:.2f} s (stages {stages:.2f} s)")


def _print_top_costs(profiler: Any, n: int) -> None:
    """The ``n`` functions with the largest self time (numba kernels count in their caller)."""
    self_time: dict[str, float] = defaultdict(float)
    session = profiler.last_session
    root = session.root_frame()

    def walk(frame: Any, visit: Callable[[Any], None]) -> None:
        stack = [frame]
        while stack:
            f = stack.pop()
            visit(f)
            stack.extend(f.children)

    def visit(f: Any) -> None:
        if f.identifier.startswith("[") or not f.file_path:
            return
        own = f.time - sum(c.time for c in f.children if c.file_path)
        where = f.file_path.replace(str(ROOT) + "/", "")
        self_time[f"{f.function} ({where}:{f.line_no})"] += max(own, 0.0)

    walk(root, visit)
    total = root.time
    print(f"top {n} self-time costs of {total:.2f} s profiled:")
    for name, t in sorted(self_time.items(), key=lambda kv: -kv[1])[:n]:
        print(f"  {t:7.3f} s  {100 * t / total:5.1f} %  {name}")


def _choose_malloc(glibc: bool, default_pages: bool) -> None:
    """Start again with the malloc the ``iceg`` command gets (mimalloc where installed), or
    with ``glibc`` glibc's on huge pages, or with ``default_pages`` glibc's on its default
    pages (this process's children too); print the choice in force."""
    from iceg.huge_pages import TUNABLE, sets_tunable
    from iceg.malloc import CHOICE_VARIABLE, exec_with_fast_malloc

    if glibc or default_pages:
        os.environ[CHOICE_VARIABLE] = "glibc"
    if default_pages and not sets_tunable(os.environ):
        tunables = os.environ.get("GLIBC_TUNABLES", "")
        os.environ["GLIBC_TUNABLES"] = f"{tunables}:{TUNABLE}=0".lstrip(":")
    exec_with_fast_malloc()
    preload = os.environ.get("LD_PRELOAD", "")
    if "libmimalloc" in preload:
        print(f"malloc: mimalloc (LD_PRELOAD={preload!r})")
    else:
        print(f"malloc: glibc (GLIBC_TUNABLES={os.environ.get('GLIBC_TUNABLES', '')!r})")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", nargs="?", type=Path, default=DATA / "mit-csail.clf")
    ap.add_argument("relations", nargs="?", type=Path, default=DATA / "mit-csail.relations")
    ap.add_argument("--profile", nargs="?", type=Path, const=Path("/tmp/iceg_profile.html"))
    ap.add_argument("--workers", type=int, default=None)
    ap.add_argument("--no-demo", action="store_true")
    ap.add_argument("--no-cold", action="store_true")
    ap.add_argument("--no-csail", action="store_true")
    ap.add_argument("--no-cli", action="store_true")
    ap.add_argument("--fresh-install", action="store_true")
    ap.add_argument("--out", type=Path, default=None, help="save the CSAIL result here")
    ap.add_argument("--glibc", action="store_true", help="glibc's malloc on huge pages")
    ap.add_argument("--default-pages", action="store_true", help="glibc's malloc, default pages")
    args = ap.parse_args()
    _choose_malloc(args.glibc, args.default_pages)
    print(f"python {sys.version.split()[0]} ({sys.executable})")
    if args.fresh_install:
        fresh_install()
    if not args.no_cold:
        cold_start(args.log)
    if not args.no_csail:
        run_csail(args.log, args.relations, args.workers, args.profile, args.out)
    if not args.no_demo:
        run_demo(args.workers)
    if not args.no_cli:
        cli_runs(args.log, args.relations, args.workers)


if __name__ == "__main__":
    main()
