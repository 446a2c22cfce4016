"""Tests of the A/B benchmark's bookkeeping (benchmarks/bench_compare.py): the alternated
order of the versions and the paired ratios, against hand-computed values."""

from __future__ import annotations

from types import ModuleType

import pytest

from tests.conftest import load_benchmark


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_benchmark("bench_compare")


def test_every_other_pair_runs_b_first(bench: ModuleType) -> None:
    assert bench.run_order(1) == ["A", "B"]
    assert bench.run_order(3) == ["A", "B", "B", "A", "A", "B"]
    # each version runs first in half of an even number of pairs
    order = bench.run_order(4)
    firsts = order[0::2]
    assert firsts.count("A") == firsts.count("B") == 2


def test_paired_summary_takes_the_ratio_of_each_pair(bench: ModuleType) -> None:
    # pairs (10, 9), (12, 12), (8, 10): ratios 0.9, 1.0, 1.25
    s = bench.paired_summary([10.0, 12.0, 8.0], [9.0, 12.0, 10.0])
    assert s.ratios == pytest.approx([0.9, 1.0, 1.25])
    assert s.median == pytest.approx(1.0)
    assert (s.low, s.high) == (pytest.approx(0.9), pytest.approx(1.25))
    assert s.b_less == 1  # only the first pair: a tie is not "less"
    # an even count: the median is the mean of the middle two ratios (0.9 and 1.1)
    even = bench.paired_summary([10.0, 10.0, 10.0, 10.0], [8.0, 9.0, 11.0, 12.0])
    assert even.median == pytest.approx(1.0)
    assert even.b_less == 2


def test_paired_summary_refuses_unpaired_samples(bench: ModuleType) -> None:
    with pytest.raises(ValueError, match="same nonzero count"):
        bench.paired_summary([1.0, 2.0], [1.0])
    with pytest.raises(ValueError, match="same nonzero count"):
        bench.paired_summary([], [])
