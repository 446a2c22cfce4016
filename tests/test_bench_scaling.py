"""Tests of the scaling benchmark's log (benchmarks/bench_scaling.py): the back-and-forth
plan against hand-computed indices and stamps, and the flatness summary (time and memory) on
made-up blocks."""

from __future__ import annotations

from types import ModuleType

import numpy as np
import pytest

from tests.conftest import load_benchmark


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_benchmark("bench_scaling")


def test_back_and_forth_plan_turns_around_without_repeating_the_turnaround_scan(
    bench: ModuleType,
) -> None:
    # A log of 3 scans at 0, 1, 3 s (median step 1.5 s): forward, backward, forward.
    index, stamps = bench.back_and_forth_plan(np.array([0.0, 1.0, 3.0]), 7)
    assert index.tolist() == [0, 1, 2, 1, 0, 1, 2]
    # backward pass from 3 + 1.5: scan 1 is 2 s before the end, scan 0 3 s; then forward
    # from 7.5 + 1.5 with scan 1 at 1 s and scan 2 at 3 s into the log
    assert stamps.tolist() == [0.0, 1.0, 3.0, 6.5, 7.5, 10.0, 12.0]


def test_summary_prints_the_median_over_runs_and_the_within_run_ratio(
    bench: ModuleType, capsys: pytest.CaptureFixture[str]
) -> None:
    def fig(n: int, blocks: list[float], rss_peak_mb: float = 300.0) -> dict:
        return {
            "n": n,
            "blocks_s": blocks,
            "cpu_blocks_s": blocks,
            "process_s": sum(blocks),
            "rss_peak_mb": rss_peak_mb,
            "rss_start_mb": 100.0,
            "rss_blocks_mb": [280.0] * len(blocks),
            # each block: matching 5 s, iSAM2 the rest
            "stage_blocks_s": [{"matching": 5.0, "isam2": b - 5.0} for b in blocks],
        }

    # 2k: one steady block each run (8 and 10 s: median 9); 25k: 24 steady blocks, the
    # first ten at 9 s, the last ten at 11.6 s (mean 10.083)
    late = [9.0] * 14 + [11.6] * 10
    # memory: 2k adds 300 - 280 MB over the 1000 scans after the first block (20 MB per 1000),
    # 25k adds 808 - 280 MB over 24000 scans (22 MB per 1000)
    runs = [fig(2000, [20.0, 8.0]), fig(25000, [20.0, *late], 808.0), fig(2000, [20.0, 10.0])]
    bench.print_summary(runs)
    out = capsys.readouterr().out
    assert "2000: 8.00, 10.00" in out
    assert "largest / smallest median 1.12" in out  # (9 * 14 + 11.6 * 10) / 24 / 9 = 1.120
    assert "MB   2000: 20.00, 20.00; 25000: 22.00; largest / smallest median 1.10" in out
    assert "last 10 blocks / first 10 after the first: wall 1.29, CPU 1.29" in out  # 11.6 / 9
    # per stage over the same blocks: iSAM2 4 s -> 6.6 s, matching 5 s in both
    rows = {line.split()[0]: line.split()[1:] for line in out.splitlines() if line[:4] == "    "}
    assert rows["isam2"] == ["4.00", "6.60", "+2.60"]
    assert rows["matching"] == ["5.00", "5.00", "+0.00"]
