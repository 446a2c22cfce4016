"""The ``iceg`` command line end to end: outputs, determinism, bad input."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import yaml
from PIL import Image
from typer.testing import CliRunner

from iceg.cli import app
from iceg.results import OUTPUT_FILES
from tests.conftest import shared_file

runner = CliRunner()


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("demo") / "run"
    result = runner.invoke(app, ["run", "--out", str(out), "--no-progress"])
    assert result.exit_code == 0, result.output
    return out


def test_demo_writes_every_output(demo_dir: Path) -> None:
    assert sorted(p.name for p in demo_dir.iterdir()) == sorted(OUTPUT_FILES)
    metrics = json.loads((demo_dir / "metrics.json").read_text())
    n = metrics["scans"]
    assert len((demo_dir / "trajectory.tum").read_text().splitlines()) == n
    meta = yaml.safe_load((demo_dir / "map.yaml").read_text())
    assert meta["image"] == "map.pgm"
    assert Image.open(demo_dir / "map.pgm").mode == "L"
    config = yaml.safe_load((demo_dir / "config.yaml").read_text())
    assert set(config) >= {"features", "matching", "graph", "slam", "grid"}


def test_demo_error_against_ground_truth(demo_dir: Path) -> None:
    # Truth: the simulator's exact poses. Issue 7: mean position error below 10 cm.
    metrics = json.loads((demo_dir / "metrics.json").read_text())
    gt = metrics["ground_truth"]
    odom = metrics["odometry_vs_truth"]
    assert gt["mean_m"] < 0.10, f"SLAM {gt['mean_m']:.3f} m vs odometry {odom['mean_m']:.3f} m"
    assert gt["mean_m"] < odom["mean_m"]


def test_same_input_gives_identical_trajectory(demo_dir: Path, tmp_path: Path) -> None:
    out = tmp_path / "again"
    result = runner.invoke(app, ["run", "--out", str(out), "--no-progress"])
    assert result.exit_code == 0, result.output
    assert (out / "trajectory.tum").read_bytes() == (demo_dir / "trajectory.tum").read_bytes()


def _assert_one_line_error(args: list[str], out: Path, needle: str) -> None:
    result = runner.invoke(app, [*args, "--out", str(out), "--no-progress"])
    assert result.exit_code == 1, result.output
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], result.stderr
    assert not out.exists() or not any(out.iterdir())


def test_missing_log_file(tmp_path: Path) -> None:
    _assert_one_line_error(["run", str(tmp_path / "nope.clf")], tmp_path / "o", "no such log file")


def test_log_without_scans(tmp_path: Path) -> None:
    log = tmp_path / "empty.clf"
    log.write_text("PARAM robot_front_laser_max 81.9 1.0 host 1.0\n")
    _assert_one_line_error(["run", str(log)], tmp_path / "o", "no laser scans")


def test_relations_matching_no_scan(tmp_path: Path) -> None:
    from frontends.carmen import write_carmen
    from frontends.simulate import office_world, simulate

    run = simulate(office_world(), seed=1)
    log = tmp_path / "short.clf"
    write_carmen(log, run.scans[:20])
    rel = tmp_path / "other.relations"
    rel.write_text("5.0 6.0 0.1 0.0 0.0 0.0 0.0 0.0\n")
    _assert_one_line_error(
        ["run", str(log), "--relations", str(rel)], tmp_path / "o", "none of its 1 relations"
    )


def test_invalid_config_value(tmp_path: Path) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_text("slam:\n  keyframe_distance_m: -1\n")
    _assert_one_line_error(
        ["run", "--config", str(cfg)], tmp_path / "o", "slam.keyframe_distance_m"
    )


def test_dump_config_round_trips(tmp_path: Path) -> None:
    result = runner.invoke(app, ["dump-config"])
    assert result.exit_code == 0
    cfg = tmp_path / "c.yaml"
    cfg.write_text(result.stdout)
    again = runner.invoke(app, ["dump-config", "--config", str(cfg)])
    assert again.stdout == result.stdout


@pytest.mark.slow
def test_mit_csail_benchmark(tmp_path: Path) -> None:
    # Truth: the Kümmerle et al. 2009 relations of MIT CSAIL. Issue 7 acceptance: all 1172
    # matched, mean error at most 0.10 m and 1.0 deg (raw odometry: 1.68 m, 5.07 deg).
    log = shared_file("mit-csail/mit-csail.clf")
    rel = shared_file("mit-csail/mit-csail.relations")
    out = tmp_path / "csail"
    result = runner.invoke(
        app, ["run", str(log), "--relations", str(rel), "--out", str(out), "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    r = json.loads((out / "metrics.json").read_text())["relations"]
    assert r["n_matched"] == 1172
    assert r["trans_mean_m"] <= 0.10, r
    assert r["rot_mean_deg"] <= 1.0, r
    # eval on the written trajectory reproduces the figure
    ev = runner.invoke(app, ["eval", str(out / "trajectory.tum"), str(rel)])
    assert ev.exit_code == 0
    assert f"{r['trans_mean_m']:.6g}" in ev.stdout
