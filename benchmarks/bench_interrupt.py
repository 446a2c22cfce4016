"""Benchmark: how soon ``iceg run`` stops after Ctrl-C (issue 12: "stop promptly").

Starts ``iceg run`` on the built-in demo in a fresh process, waits until its progress bar
shows, sleeps a given delay (so the signal lands in different stages: early scans, loop
closure, the final solve), sends SIGINT and prints the seconds until the process has exited,
its exit code and the last line of its stderr (after the progress bar). The tests check the
exit code, the message and that nothing is written (``tests/iceg/test_cli.py``); the latency
is a timing, so it is measured here.

Run: ``python benchmarks/bench_interrupt.py [--delays 0.5,2,4] [--repeats 3]``
"""

from __future__ import annotations

import argparse
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def interrupt_after(delay_s: float, out: Path) -> tuple[float, int, str]:
    """Run ``iceg run --out out`` on the demo, send SIGINT ``delay_s`` after its progress bar
    shows; return the seconds from the signal to the exit, the exit code and the stderr."""
    proc = subprocess.Popen(
        [sys.executable, "-m", "iceg.cli", "run", "--out", str(out)],
        cwd=REPO,
        stderr=subprocess.PIPE,
        text=True,
    )
    assert proc.stderr is not None
    seen = ""
    while "%|" not in seen:  # the progress bar: the run is under way
        char = proc.stderr.read(1)
        if not char:
            raise RuntimeError(f"the run ended before it started: {seen[-300:]}")
        seen += char
    time.sleep(delay_s)
    proc.send_signal(signal.SIGINT)
    t0 = time.perf_counter()
    _, err = proc.communicate(timeout=120)
    return time.perf_counter() - t0, proc.returncode, seen + err


def _last_line(stderr: str) -> str:
    return (stderr.replace("\r", "\n").strip().splitlines() or [""])[-1]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--delays", default="0.5,2,4", help="seconds after the progress bar")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"{'delay s':>8s} {'median s':>9s} {'max s':>7s}  exit  last line")
    for delay in (float(d) for d in args.delays.split(",")):
        runs = []
        for _ in range(args.repeats):
            with tempfile.TemporaryDirectory() as tmp:
                runs.append(interrupt_after(delay, Path(tmp) / "o"))
        lat = [r[0] for r in runs]
        codes = sorted({r[1] for r in runs})
        last = _last_line(runs[-1][2])
        print(f"{delay:8.1f} {statistics.median(lat):9.3f} {max(lat):7.3f}  {codes}  {last}")


if __name__ == "__main__":
    main()
