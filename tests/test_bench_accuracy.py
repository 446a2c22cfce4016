"""Tests of the accuracy benchmark's metrics (benchmarks/bench_accuracy.py): false loop
closures against a known truth, the scan-match fraction, and one quick row end to end."""

from __future__ import annotations

import math
from pathlib import Path
from types import ModuleType, SimpleNamespace

import numpy as np
import pytest

from graph import FactorKind, FactorRecord
from iceg_common.se2 import between, compose
from tests.conftest import load_benchmark


@pytest.fixture(scope="module")
def bench() -> ModuleType:
    return load_benchmark("bench_accuracy")


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
    check = bench.check_loop_closures(result, ref)
    assert (check.n_false, check.n_disputed) == (2, 0)
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


def test_the_benchmark_is_one_batch_spec(bench: ModuleType, tmp_path: Path) -> None:
    """Every case is a log of the spec, with the same input: scenarios by name, CSAIL with
    its relations, the corrected logs with synthetic odometry scored against their poses."""
    from iceg.batch import expand, spec_from_dict

    data = bench.batch_spec(quick=True, seeds=[3])
    spec = spec_from_dict(data)
    tasks = {t.log_name: t for t in expand(spec, tmp_path, tmp_path)}
    assert set(tasks) == set(bench.CASES)
    assert tasks["office"].source == "sim:office" and tasks["office"].seed == 3
    assert tasks["csail_raw"].relations is not None and tasks["csail_raw"].seed is None
    drift = tasks["csail_raw_drift"].odometry
    assert drift is not None and drift.scale_error == 0.0 and not drift.noise
    assert tasks["csail_raw_drift"].seed is None  # a drift without noise: one run
    laser_only = tasks["csail_raw_laser_only"]
    assert laser_only.laser_only and laser_only.relations is not None and laser_only.seed is None
    synth = tasks["csail_corrected_synth"]
    assert synth.reference == "log_odometry" and synth.odometry is not None
    assert synth.odometry.restamp_hz == 1.0 and synth.odometry.scale_error == 0.01
    rc_car = tasks["rc_car_mocap"]
    assert rc_car.laser_only and rc_car.reference == "log_odometry" and rc_car.seed is None
    assert rc_car.reader_options == bench.RC_CAR_READER
    neato = tasks["neato"]
    assert neato.reader_options == {"scan_topic": "/scan"} and neato.reference is None
    assert tasks["turtlebot4"].source.endswith("turtlebot4-ros2")
    assert all(t.max_scans == bench.QUICK_SCANS for t in tasks.values())
    assert all(t.config == {} for t in tasks.values())  # the default configuration


def test_seeds_and_variants_make_the_batch_that_compares_them(
    bench: ModuleType, tmp_path: Path
) -> None:
    """``--seeds 0-2 5`` and ``--variant``: each random case at every seed, each case with the
    default and the variant's configuration (its YAML's leaves set, the rest default)."""
    from iceg.batch import expand, spec_from_dict

    assert bench.parse_seeds(["0-2", "5"]) == [0, 1, 2, 5]
    with pytest.raises(ValueError):
        bench.parse_seeds(["two"])
    variant = {"matching": {"correlation": {"fimp_range_m": 20.0}}, "slam": {"local_map_nodes": 6}}
    assert bench.dotted(variant) == {
        "matching.correlation.fimp_range_m": 20.0,
        "slam.local_map_nodes": 6,
    }
    data = bench.batch_spec(
        ["corridor", "csail_raw"], seeds=[0, 1, 2, 5], variants={"f20": variant}
    )
    tasks = expand(spec_from_dict(data), tmp_path, tmp_path)
    runs = [(t.log_name, t.variant, t.seed) for t in tasks]
    assert runs == [
        *[("corridor", v, s) for v in ("default", "f20") for s in (0, 1, 2, 5)],
        ("csail_raw", "default", None),  # a log without a random input runs once
        ("csail_raw", "f20", None),
    ]
    f20 = next(t for t in tasks if t.variant == "f20")
    assert f20.config == variant
    assert all(t.config == {} for t in tasks if t.variant == "default")


def test_in_process_seeds_repeat_only_the_random_cases_and_end_with_their_spread(
    bench: ModuleType,
) -> None:
    """A seed changes a simulation, synthetic odometry and added noise or dropouts, not a real
    log as recorded or a degradation without a draw; the rows of several seeds end in one line
    per case: mean / median / worst and the false closures summed, a skipped case a failure."""
    assert bench.is_random("office") and bench.is_random("aces_synth")
    assert not bench.is_random("csail_raw") and not bench.is_random("turtlebot4")
    assert not bench.is_random("csail_raw_drift")  # a drift without noise draws nothing
    assert bench.is_random("csail_raw", "noise_2cm") and bench.is_random("neato", "dropouts")
    assert not bench.is_random("csail_raw", "reach_8m") and not bench.is_random(
        "csail_raw", "half_rate"
    )
    rows = [
        {"name": "aces_synth", "seed": 0, "ate_m": 0.2, "lc_false": 1},
        {"name": "aces_synth", "seed": 1, "ate_m": 0.6, "lc_false": 0},
        {"name": "aces_synth", "seed": 2, "ate_m": 0.1, "lc_false": 2},
        {"name": "neato", "seed": 0, "skipped": "absent"},
    ]
    table = bench.over_seeds(rows, "f20")
    assert "| aces_synth | f20 | 3 | 0 | 0.3 / 0.2 / 0.6 | 3 |" in table
    assert "| neato | f20 | 1 | 1 |  |  |" in table


def test_a_batch_row_matches_run_case(bench: ModuleType, tmp_path: Path) -> None:
    """The batch run of a case gives the figures of :func:`run_case` (same input, same
    pipeline)."""
    from iceg.batch import expand, spec_from_dict
    from iceg.batch_run import execute_run

    data = bench.batch_spec(["corridor"], seeds=[0])
    data["logs"][0]["max_scans"] = 80
    (task,) = expand(spec_from_dict(data), tmp_path, tmp_path)
    row = execute_run(task)
    assert row["status"] == "ok", row["error"]
    bench.QUICK_SCANS, quick = 80, bench.QUICK_SCANS
    try:
        ref = bench.run_case("corridor", quick=True, seed=0)
    finally:
        bench.QUICK_SCANS = quick
    for key in ("scans", "nodes", "lc_accepted", "ate_m", "end_m", "online_max_m", "odom_ate_m"):
        assert row["metrics"][key] == pytest.approx(ref[key], rel=1e-9), key
