"""Tests of the accuracy benchmark's metrics (benchmarks/bench_accuracy.py): false loop
closures against a known truth, the scan-match fraction, and one quick row end to end."""

from __future__ import annotations

import importlib.util
import math
import sys
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import pytest

from graph import FactorKind, FactorRecord
from iceg_common.se2 import between, compose

BENCH = Path(__file__).resolve().parents[1] / "benchmarks" / "bench_accuracy.py"


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    spec = importlib.util.spec_from_file_location("bench_accuracy", BENCH)
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules["bench_accuracy"] = module
    spec.loader.exec_module(module)
    return module


def _factor(index: int, kind: FactorKind, i: int, j: int, measured: np.ndarray) -> FactorRecord:
    return FactorRecord(index, kind, i, j, measured, np.eye(3), None, None)


def test_false_loop_closures_and_scan_match_fraction(bench: ModuleType) -> None:
    # Truth: a reference trajectory; node k is scan 2k. A closure equal to the true relative
    # pose, or off by 0.2 m / 2 deg, is right; off by 0.4 m or by 4 deg it is false
    # (thresholds 0.3 m, 3 deg).
    rng = np.random.default_rng(0)
    ref = np.column_stack([rng.uniform(-5, 5, (12, 2)), rng.uniform(-3, 3, 12)])
    nodes = np.arange(6)
    true_05 = between(ref[0], ref[10])
    off = [
        np.zeros(3),
        np.array([0.2, 0.0, 0.0]),
        np.array([0.0, 0.0, math.radians(2.0)]),
        np.array([0.0, 0.4, 0.0]),
        np.array([0.0, 0.0, math.radians(4.0)]),
    ]
    factors = [
        _factor(k, FactorKind.LOOP_CLOSURE, 0, 5, compose(true_05, e)) for k, e in enumerate(off)
    ]
    factors += [_factor(10 + k, FactorKind.SCAN_MATCH, k - 1, k, np.zeros(3)) for k in (1, 2, 4)]
    factors += [_factor(20, FactorKind.SCAN_MATCH, 1, 2, np.zeros(3))]
    result = SimpleNamespace(node_ids=nodes, node_scan_index=2 * nodes, factors=factors)
    assert bench._false_loop_closures(result, ref) == 2
    assert bench._scan_match_fraction(result) == pytest.approx(3 / 5)


def test_quick_row_against_truth(bench: ModuleType) -> None:
    # Truth: the simulated corridor (40 m, 2 m wide). The first 300 scans cover the whole
    # 20 m route; the estimate must have the route's length and start at the true pose.
    row = bench.run_case("corridor", quick=True)
    assert row["scans"] == 201 and row["nodes"] >= 2
    assert 0.0 <= row["sm_per_kf"] <= 1.0
    assert row["length_ratio"] == pytest.approx(1.0, abs=0.05)
    assert row["ate_m"] < row["odom_ate_m"] + 0.5
    assert row["lc_false"] == 0
    assert 0.0 <= row["online_max_m"] < 1.0
    assert "rel_trans_m" not in row
    assert "corridor" in bench.format_table([row, {"name": "x", "skipped": "absent"}])
