"""Benchmark: where the main process of a MIT CSAIL run spends its CPU, by library.

Samples the main process only (``perf record -F 499 -i``: the helper processes are not
followed) over ``run_log`` on the log with the pipeline benchmark's configuration
(``bench_pipeline._config``), then prints the share of the samples in each shared object
(the Python interpreter, numba's compiled kernels, numpy's C code, libc, gtsam, ...),
separately for the start (the first ``--start-s`` seconds: imports, numba's typing registry,
the kernels' loading) and the rest of the run. The interpreter's and numpy's share of the
rest is the glue between the kernels (docs/design.md, "Where the main process's time goes,
by library"). Needs Linux ``perf`` with permission to sample (``perf_event_paranoid``); it
says so and exits 0 where it has neither.

Run: ``python benchmarks/bench_libraries.py [--workers N] [--start-s S] [path/to/mit-csail.clf]``
"""

from __future__ import annotations

import argparse
import shutil
import subprocess
import sys
import tempfile
from collections import Counter
from pathlib import Path

from bench_pipeline import DATA, ROOT

#: The run, in a child Python: the pipeline benchmark's configuration, nothing printed.
_RUN = """
import sys
sys.path.insert(0, {bench!r})
from pathlib import Path
import bench_pipeline
from iceg.pipeline import run_log
run_log(Path({log!r}), bench_pipeline._config({workers}))
"""


def _library(dso: str) -> str:
    """A readable name of a shared object (``[JIT] tid``/``perf-<pid>.map``: numba's kernels)."""
    name = dso.strip("()").rsplit("/", 1)[-1]
    if name.startswith("perf-") or name.startswith("[JIT]"):
        return "numba kernels (JIT)"
    return name


def _samples(data: Path) -> list[tuple[float, str]]:
    """``(time_s, library)`` of every sample in a perf data file."""
    out = subprocess.run(
        ["perf", "script", "-i", str(data), "-F", "time,ip,dso"],
        capture_output=True,
        text=True,
        check=True,
    ).stdout
    samples = []
    for line in out.splitlines():
        parts = line.split()
        if len(parts) >= 3:
            samples.append((float(parts[0].rstrip(":")), _library(parts[2])))
    return samples


def _print_shares(label: str, libraries: list[str], rate_hz: int) -> None:
    """Print each library's share of ``libraries`` (one entry a sample), largest first."""
    counts = Counter(libraries)
    total = sum(counts.values())
    print(f"{label}: {total} samples (about {total / rate_hz:.2f} s of CPU)")
    if not total:
        return
    for name, n in counts.most_common():
        if n / total >= 0.005:
            print(f"  {100 * n / total:5.1f} %  {name}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("log", nargs="?", type=Path, default=DATA / "mit-csail.clf")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--start-s", type=float, default=2.6)
    ap.add_argument("--rate-hz", type=int, default=499)
    args = ap.parse_args()
    if shutil.which("perf") is None:
        print("perf is not installed: nothing measured")
        return
    if not args.log.is_file():
        print(f"{args.log}: no such log: nothing measured")
        return
    code = _RUN.format(bench=str(ROOT / "benchmarks"), log=str(args.log), workers=args.workers)
    with tempfile.TemporaryDirectory() as tmp:
        data = Path(tmp) / "perf.data"
        record = ["perf", "record", "-F", str(args.rate_hz), "-i", "-o", str(data)]
        rec = subprocess.run(
            [*record, sys.executable, "-c", code],
            capture_output=True,
            text=True,
        )
        if rec.returncode != 0 or not data.is_file():
            print(f"perf record failed (permissions?): {rec.stderr.strip()[-300:]}")
            return
        samples = _samples(data)
    if not samples:
        print("perf recorded no samples")
        return
    t0 = samples[0][0]
    start = [lib for t, lib in samples if t - t0 < args.start_s]
    rest = [lib for t, lib in samples if t - t0 >= args.start_s]
    print(f"{args.log.name}, workers {args.workers}, main process, {args.rate_hz} Hz")
    _print_shares(f"start (first {args.start_s} s)", start, args.rate_hz)
    _print_shares("rest of the run", rest, args.rate_hz)


if __name__ == "__main__":
    main()
