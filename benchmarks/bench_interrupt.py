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


def interrupt_after(delay_s: float) -> tuple[float, int, str]:
    """Seconds from SIGINT to exit, the exit code and stderr's last line of one run."""
    with tempfile.TemporaryDirectory() as tmp:
        proc = subprocess.Popen(
            [sys.executable, "-m", "iceg.cli", "run", "--out", str(Path(tmp) / "o")],
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
        latency = time.perf_counter() - t0
    last = (err.replace("\r", "\n").strip().splitlines() or [""])[-1]
    return latency, proc.returncode, last


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--delays", default="0.5,2,4", help="seconds after the progress bar")
    parser.add_argument("--repeats", type=int, default=3)
    args = parser.parse_args()
    print(f"{'delay s':>8s} {'median s':>9s} {'max s':>7s}  exit  last line")
    for delay in (float(d) for d in args.delays.split(",")):
        runs = [interrupt_after(delay) for _ in range(args.repeats)]
        lat = [r[0] for r in runs]
        codes = sorted({r[1] for r in runs})
        print(
            f"{delay:8.1f} {statistics.median(lat):9.3f} {max(lat):7.3f}  {codes}  {runs[-1][2]}",
            flush=True,
        )


if __name__ == "__main__":
    main()
