"""Benchmark: stream the MIT CSAIL CARMEN log (1988 FLASER scans of 361 beams) and its relations.

Prints, best and median of 5 runs: scans per second and total time of a full iteration
(``list(open_log(path))``), the fast ``count_scans`` pass, the same log gzip-compressed (a
temporary copy), and ``read_relations`` on ``mit-csail.relations`` when it is beside the log.

Run: ``/work/venv/bin/python benchmarks/bench_read_log.py [path/to/mit-csail.clf]``
"""

from __future__ import annotations

import gzip
import logging
import shutil
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path
from typing import TypeVar

from frontends import open_log
from frontends.relations import read_relations

DEFAULT_LOG = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "mit-csail" / "mit-csail.clf"
)
REPEATS = 5


T = TypeVar("T")


def _time(fn: Callable[[], T]) -> tuple[float, float, T]:
    """Best and median wall time (s) of ``REPEATS`` calls, and the last result."""
    times = []
    for _ in range(REPEATS):
        t0 = time.perf_counter()
        result = fn()
        times.append(time.perf_counter() - t0)
    return min(times), statistics.median(times), result


def _report(label: str, n_scans: int, best: float, median: float) -> None:
    print(
        f"{label:<28} {n_scans:5d} scans  best {best * 1e3:8.1f} ms "
        f"({n_scans / best:8.0f} scans/s)  median {median * 1e3:8.1f} ms "
        f"({n_scans / median:8.0f} scans/s)"
    )


def main(argv: list[str] | None = None) -> None:
    args = sys.argv[1:] if argv is None else argv
    path = Path(args[0]) if args else DEFAULT_LOG
    if not path.is_file():
        print(f"log {path} not found; pass the path of mit-csail.clf as the first argument")
        return
    print(f"log: {path} ({path.stat().st_size / 1e6:.2f} MB), {REPEATS} runs each")

    best, median, scans = _time(lambda: list(open_log(path)))
    n = len(scans)
    _report("iterate (parse all scans)", n, best, median)

    best, median, count = _time(lambda: open_log(path).count_scans())
    _report("count_scans (fast pass)", int(count), best, median)

    with tempfile.TemporaryDirectory() as tmp:
        gz_path = Path(tmp) / (path.name + ".gz")
        with open(path, "rb") as src, gzip.open(gz_path, "wb") as dst:
            shutil.copyfileobj(src, dst)
        best, median, scans_gz = _time(lambda: list(open_log(gz_path)))
        _report("iterate .gz copy", len(scans_gz), best, median)

    relations = path.with_suffix(".relations")
    if relations.is_file():
        rel = read_relations(relations)  # logs its quirks (e.g. a duplicate line) once
        logging.getLogger("frontends.relations").setLevel(logging.ERROR)
        best, median, rel = _time(lambda: read_relations(relations))
        print(
            f"{'read_relations':<28} {len(rel):5d} relations  best {best * 1e3:6.1f} ms  "
            f"median {median * 1e3:6.1f} ms"
        )


if __name__ == "__main__":
    main()
