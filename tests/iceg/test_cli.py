"""The ``iceg`` command line end to end: outputs, determinism, bad input."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml
from PIL import Image
from typer.testing import CliRunner

from iceg.cli import app
from iceg.results import OUTPUT_FILES
from tests.conftest import flaser_line, shared_file

runner = CliRunner()


@pytest.fixture(scope="module")
def demo_dir(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("demo") / "run"
    result = runner.invoke(app, ["run", "--out", str(out), "--no-progress"])
    assert result.exit_code == 0, result.output
    return out


def test_demo_writes_every_output(demo_dir: Path) -> None:
    assert sorted(p.name for p in demo_dir.iterdir()) == sorted([*OUTPUT_FILES, "session"])
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
    # The factors' NEES against the same truth: one entry per between-factor kind, counting
    # every factor of that kind (the simulator knows every node's pose).
    nees = metrics["factor_nees"]
    counts = {k: v for k, v in metrics["factors"].items() if k != "prior"}
    assert {k: v["count"] for k, v in nees.items()} == counts
    assert all(v["bound"] == pytest.approx(7.8147, abs=1e-3) for v in nees.values())


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


def test_a_log_of_laser_records_the_reader_skips_is_refused_by_name(tmp_path: Path) -> None:
    log = tmp_path / "rear.log"
    log.write_text(
        "ODOM 0.0 0.0 0.0 0 0 0 10.0 h 10.0\n"
        "RAWLASER2 0 -0.5 1.0 0.25 20.0 0.01 0 5 1 2 3 4 5 0 10.25 h 10.3\n"
    )
    _assert_one_line_error(["run", str(log)], tmp_path / "o", "laser records (1 RAWLASER2)")


@pytest.mark.skipif(sys.platform != "linux", reason="the helper processes are Linux only")
def test_a_malformed_log_is_one_line_with_the_helpers_running(tmp_path: Path) -> None:
    # The helpers are stopped at once when the run fails; they inherit the command's SIGTERM
    # handler, which raises: they used to print its traceback. A fresh process, as a user
    # types it (the helpers' stderr is the terminal's, not a test runner's capture).
    log = tmp_path / "bad.clf"
    log.write_text(flaser_line(0.0, 10.0) + "\nFLASER 3 1.0 oops 3.0 0 0 0 0 0 0 11.0 h 11.0\n")
    config = tmp_path / "two.yaml"
    config.write_text("slam:\n  workers: 2\n")
    out = tmp_path / "o"
    args = ["run", str(log), "--config", str(config), "--out", str(out), "--no-progress"]
    done = subprocess.run(
        [sys.executable, "-m", "iceg.cli", *args], capture_output=True, text=True, timeout=120
    )
    assert done.returncode == 1, done.stderr
    lines = done.stderr.strip().splitlines()
    assert len(lines) == 1 and f"{log}:2:" in lines[0], done.stderr
    assert not out.exists()


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
def test_mit_csail_benchmark(csail_run: Path) -> None:
    # Truth: the Kümmerle et al. 2009 relations of MIT CSAIL. Issue 7 acceptance: all 1172
    # matched, mean error at most 0.10 m and 1.0 deg (raw odometry: 1.68 m, 5.07 deg).
    rel = shared_file("mit-csail/mit-csail.relations")
    out = csail_run
    r = json.loads((out / "metrics.json").read_text())["relations"]
    assert r["n_matched"] == 1172
    assert r["trans_mean_m"] <= 0.10, r
    assert r["rot_mean_deg"] <= 1.0, r
    # A SICK on the front of the robot sees nothing of the robot: no body bin in 200 turns,
    # along the odometry before the run or along its trajectory, and nothing is left out.
    body = json.loads((out / "metrics.json").read_text())["robot_body"]
    assert body["range_m"] == 0.0, body
    for seen in (body["on_odometry"], body["on_trajectory"]):
        assert seen["range_m"] is None and seen["pairs"] == 200, body
    # eval on the written trajectory reproduces the figure
    ev = runner.invoke(app, ["eval", str(out / "trajectory.tum"), str(rel)])
    assert ev.exit_code == 0
    assert f"{r['trans_mean_m']:.6g}" in ev.stdout
    # nees on the saved run: the sequential factors the relations span, as the library
    # scores them from the session
    from frontends.relations import read_relations
    from iceg import session
    from iceg.consistency import relation_factor_nees

    ne = runner.invoke(app, ["nees", str(out), str(rel)])
    assert ne.exit_code == 0, ne.output
    saved = session.read(out)
    want = relation_factor_nees(
        session.factor_records(saved.arrays), saved.node_stamps(), read_relations(rel)
    ).summary()
    rows = {line.split()[0]: line.split()[1:] for line in ne.stdout.splitlines()[1:]}
    assert set(rows) == set(want) == {"odometry", "scan_match"}
    for kind, s in want.items():
        assert rows[kind][:3] == [str(s.count), f"{s.mean:.3g}", f"{s.median:.3g}"]
    # the run scored the same factors itself (metrics.json)
    scored = json.loads((out / "metrics.json").read_text())["factor_nees"]
    assert {k: v["count"] for k, v in scored.items()} == {k: s.count for k, s in want.items()}


# ---------------------------------------------------------------------------------------------
# Issue 12: one line and exit 1, no partial result, never a lost run
# ---------------------------------------------------------------------------------------------


def _short_log(tmp_path: Path, n: int = 20, name: str = "short.clf") -> Path:
    from frontends.carmen import write_carmen
    from frontends.simulate import office_world, simulate

    run = simulate(office_world(), seed=1)
    log = tmp_path / name
    write_carmen(log, run.scans[:n])
    return log


def test_out_is_an_existing_file(tmp_path: Path) -> None:
    target = tmp_path / "taken"
    target.write_text("keep")
    result = runner.invoke(app, ["run", "--out", str(target), "--no-progress"])
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and "not a folder" in lines[0], result.stderr
    assert target.read_text() == "keep"


def test_out_under_a_file_is_refused_before_the_run(tmp_path: Path) -> None:
    target = tmp_path / "taken"
    target.write_text("keep")
    _assert_one_line_error(["run", str(_short_log(tmp_path))], target / "sub", "not a folder")


def test_out_in_a_read_only_folder_is_refused_before_the_run(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    import os

    parent = tmp_path / "ro"
    parent.mkdir()
    parent.chmod(0o555)
    if os.access(parent, os.W_OK):  # root ignores permissions: emulate the read-only mount
        real = os.access
        monkeypatch.setattr(
            os, "access", lambda p, mode: False if Path(p) == parent else real(p, mode)
        )
    try:
        _assert_one_line_error(["run", "nope.clf"], parent / "a" / "b", "is not writable")
    finally:
        parent.chmod(0o755)


@pytest.mark.parametrize(
    ("text", "needle"),
    [
        (b"grid:\n  resolution_m: .inf\n", "grid.resolution_m"),
        (b"grid:\n  l_occ: .nan\n", "grid.l_occ"),
        (b"grid: [unclosed\n", "not valid YAML"),
        (b"grid:\n  resolution_m: 0.05 \xff\xfe\n", "not a UTF-8 text file"),
    ],
)
def test_bad_config_is_one_line(tmp_path: Path, text: bytes, needle: str) -> None:
    cfg = tmp_path / "bad.yaml"
    cfg.write_bytes(text)
    _assert_one_line_error(["run", "--config", str(cfg)], tmp_path / "o", needle)


def test_eval_input_not_utf8(tmp_path: Path) -> None:
    tum = tmp_path / "t.tum"
    tum.write_bytes(b"\x80\x81 binary\n")
    rel = tmp_path / "r.relations"
    rel.write_text("1.0 2.0 0.1 0 0 0 0 0\n")
    _fails_in_one_line(["eval", str(tum), str(rel)], "not a text TUM trajectory")


def _fails_in_one_line(args: list[str], needle: str) -> None:
    result = runner.invoke(app, args)
    assert result.exit_code == 1
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 1 and needle in lines[0], result.stderr


def test_log_that_is_a_folder_or_fifo(tmp_path: Path) -> None:
    import os

    folder = tmp_path / "dir.clf"
    folder.mkdir()
    _assert_one_line_error(["run", str(folder)], tmp_path / "o", "a folder no reader recognises")
    # a folder that holds a log (as a downloaded ROS 1 bag's does): the message names it
    (folder / "run1.bag").write_bytes(b"#ROSBAG V2.0\n")
    _assert_one_line_error(
        ["run", str(folder)], tmp_path / "o", "it holds run1.bag: pass the log file itself"
    )
    fifo = tmp_path / "fifo.clf"
    os.mkfifo(fifo)
    _assert_one_line_error(["run", str(fifo)], tmp_path / "o", "not a regular file")


def test_empty_relations(tmp_path: Path) -> None:
    rel = tmp_path / "empty.relations"
    rel.write_text("# nothing\n\n")
    _assert_one_line_error(
        ["run", str(_short_log(tmp_path)), "--relations", str(rel)],
        tmp_path / "o",
        "holds no relations",
    )


def _shuffled_log(tmp_path: Path) -> Path:
    log = _short_log(tmp_path, n=30)
    lines = log.read_text().splitlines(keepends=True)
    scan_rows = [i for i, line in enumerate(lines) if line.startswith("FLASER")]
    a, b = scan_rows[10], scan_rows[11]
    lines[a], lines[b] = lines[b], lines[a]
    log.write_text("".join(lines))
    return log


def test_stamps_refuse_names_file_and_line(tmp_path: Path) -> None:
    log = _shuffled_log(tmp_path)
    _assert_one_line_error(["run", str(log), "--stamps", "refuse"], tmp_path / "o", f"{log}:")


def test_stamps_sort_runs_and_records_the_policy(tmp_path: Path) -> None:
    log = _shuffled_log(tmp_path)
    rel = tmp_path / "r.relations"
    from frontends import open_log

    stamps = [s.stamp_s for s in open_log(log)]
    rel.write_text(f"{stamps[2]:.6f} {stamps[25]:.6f} 0.1 0 0 0 0 0\n")
    out = tmp_path / "o"
    result = runner.invoke(
        app, ["run", str(log), "--relations", str(rel), "--out", str(out), "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    # the command's time holds the run's stages (printed to two decimals)
    time_row = next(line for line in result.stdout.splitlines() if line.split()[0] == "time")
    in_all = float(time_row.split()[1])
    assert in_all >= round(metrics["total_seconds"], 2) > 0, time_row
    assert f"the run's stages {metrics['total_seconds']:.2f} s" in time_row
    assert metrics["stamps"]["policy"] == "sort"
    assert metrics["stamps"]["out_of_order"] == 1
    assert metrics["relations"]["n_matched"] == 1
    assert metrics["factor_nees"] is None  # no factor joins scans 2 and 25: nothing to score
    written = [float(line.split()[0]) for line in (out / "trajectory.tum").read_text().splitlines()]
    assert written == sorted(written) == stamps


def test_default_out_folders_are_unique(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from iceg import cli

    monkeypatch.chdir(tmp_path)
    first, second, third = (cli._default_out_dir() for _ in range(3))
    assert len({first, second, third}) == 3
    assert second.name == f"{first.name}-2" and third.name == f"{first.name}-3"
    assert all(p.is_dir() for p in (first, second, third))


def test_sigint_stops_and_writes_nothing(tmp_path: Path) -> None:
    """How soon it stops is a timing: ``benchmarks/bench_interrupt.py`` measures it."""
    import importlib.util

    path = Path(__file__).resolve().parents[2] / "benchmarks" / "bench_interrupt.py"
    spec = importlib.util.spec_from_file_location("bench_interrupt", path)
    assert spec is not None and spec.loader is not None
    bench = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(bench)
    out = tmp_path / "o"
    _, code, err = bench.interrupt_after(0.5, out)
    assert code == 130
    assert err.rstrip().endswith("\niceg: interrupted, nothing written"), err[-300:]
    assert not out.exists()
    assert list(tmp_path.iterdir()) == []


def _jump_log(tmp_path: Path) -> Path:
    import dataclasses

    from frontends.carmen import write_carmen
    from frontends.simulate import office_world, simulate

    run = simulate(office_world(), seed=1)
    scans = list(run.scans[:20])
    jump = np.array([1e6, 0.0, 0.0])
    scans[10:] = [
        dataclasses.replace(s, odom_pose=s.odom_pose + jump)  # type: ignore[operator]
        for s in scans[10:]
    ]
    log = tmp_path / "jump.clf"
    write_carmen(log, scans)
    return log


def test_unrenderable_map_keeps_the_run(tmp_path: Path) -> None:
    from iceg.results import CORE_FILES

    cfg = tmp_path / "fine.yaml"
    cfg.write_text("grid:\n  resolution_m: 0.001\n")
    out = tmp_path / "o"
    args = ["run", str(_short_log(tmp_path)), "--config", str(cfg)]
    result = runner.invoke(app, [*args, "--out", str(out), "--no-progress"])
    assert result.exit_code == 0, result.output
    assert sorted(p.name for p in out.iterdir()) == sorted([*CORE_FILES, "session"])
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["map"]["rendered"] is False, metrics["map"]
    assert len((out / "trajectory.tum").read_text().splitlines()) == 20


def test_odometry_jump_is_a_break_and_stays_out_of_the_trajectory(tmp_path: Path) -> None:
    """A 1000 km odometry jump at scan 10: flagged when read (file:line), no odometry factor
    across it, so the trajectory stays on the truth and the map renders."""
    from frontends.simulate import office_world, simulate
    from frontends.tum import read_tum

    out = tmp_path / "o"
    result = runner.invoke(
        app, ["run", str(_jump_log(tmp_path)), "--out", str(out), "--no-progress"]
    )
    assert result.exit_code == 0, result.output
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["map"]["rendered"] is True, metrics["map"]
    assert metrics["stamps"]["odometry_breaks"] == 1
    assert metrics["stamps"]["first_odometry_breaks"][0].startswith(f"{tmp_path}/jump.clf:")
    truth = simulate(office_world(), seed=1).true_poses[:20]
    _, poses = read_tum(out / "trajectory.tum")
    assert np.max(np.hypot(*(poses[:, :2] - truth[:, :2]).T)) < 0.1


@pytest.mark.parametrize(("offset", "applied_s"), [("-0.05", -0.05), ("auto", 0.0)])
def test_odometry_time_offset_is_applied_and_recorded(
    tmp_path: Path, offset: str, applied_s: float
) -> None:
    # 'auto' on the Gazebo TurtleBot 3 bag, which shows no offset, reads it at the stamps.
    bag = shared_file("rosbag/turtlebot3-gazebo-ros2")
    out = tmp_path / "o"
    args = ["run", str(bag), "--odometry-time-offset", offset, "--out", str(out)]
    result = runner.invoke(app, [*args, "--no-progress"])
    assert result.exit_code == 0, result.output
    recorded = json.loads((out / "metrics.json").read_text())["odometry_time_offset"]
    assert recorded["applied_s"] == applied_s
    assert recorded["measured"]["steps"] > 0
    if offset == "auto":
        assert not recorded["before_run"]["significant"]
    assert f"odometry time offset  {applied_s:+.2f} s" in result.output


def test_skip_malformed_reads_past_a_broken_line(tmp_path: Path) -> None:
    from frontends.carmen import write_carmen
    from frontends.simulate import office_world, simulate
    from iceg import session as sess

    log = tmp_path / "broken.clf"
    write_carmen(log, simulate(office_world(), seed=1).scans[:60])
    lines = log.read_text().splitlines(keepends=True)
    k = next(i for i, line in enumerate(lines) if line.startswith("FLASER")) + 30
    lines[k] = lines[k][:80] + "\n"  # line k + 1 cut short, with its newline: malformed
    log.write_text("".join(lines))
    result = runner.invoke(app, ["run", str(log), "--out", str(tmp_path / "a"), "--no-progress"])
    assert result.exit_code == 1
    assert f"broken.clf:{k + 1}: FLASER declares 181 beams" in result.output
    assert "--skip-malformed" in result.output
    out = tmp_path / "b"
    args = ["run", str(log), "--skip-malformed", "--out", str(out), "--no-progress"]
    result = runner.invoke(app, args)
    assert result.exit_code == 0, result.output
    assert "scans          59" in result.output
    session = sess.read(out / "session")  # read again the same way
    assert session.manifest["logs"][0]["reader_options"] == {"strict": False}
    assert len(sess.read_scans(session)) == 59


def test_a_stuck_odometry_is_read_as_laser_only(tmp_path: Path) -> None:
    """A log whose odometry reads one pose throughout (a stuck encoder, a log without
    odometry written with one pose): trusted, it would hold every scan at the start. The
    run reads it without its odometry, with a warning, as ``--laser-only`` does: the same
    trajectory bit for bit, which follows the true path (10.9 m) to within the matches'
    centimetres, and both sessions read the log again the same way (its scans' hashes)."""
    import dataclasses

    from frontends.carmen import write_carmen
    from frontends.simulate import office_world, simulate
    from frontends.tum import read_tum
    from iceg import session as sess
    from iceg_common import se2

    run = simulate(office_world(), seed=1)
    stuck = run.scans[0].odom_pose
    scans = [dataclasses.replace(s, odom_pose=stuck) for s in run.scans[:150]]
    log = tmp_path / "stuck.clf"
    write_carmen(log, scans)
    truth = np.array([se2.between(run.true_poses[0], p) for p in run.true_poses[:150]])
    poses = {}
    for name, extra in (("odometry", []), ("laser_only", ["--laser-only"])):
        out = tmp_path / name
        result = runner.invoke(app, ["run", str(log), *extra, "--out", str(out), "--no-progress"])
        assert result.exit_code == 0, result.output
        _, poses[name] = read_tum(out / "trajectory.tum")
        session = sess.read(out / "session")
        assert session.manifest["logs"][0]["reader_options"] == {"laser_only": True}
        again = sess.read_scans(session)
        assert len(again) == 150 and all(s.odom_pose is None for s in again)
    np.testing.assert_array_equal(poses["odometry"], poses["laser_only"])
    moved = np.array([se2.between(poses["odometry"][0], p) for p in poses["odometry"]])
    assert np.max(np.hypot(*(moved[:, :2] - truth[:, :2]).T)) < 0.03


def test_beams_that_turn_against_the_odometry_are_read_mirrored(tmp_path: Path) -> None:
    """A log written with its beams mirrored (a laser mounted upside down, or a converter
    that wrote them clockwise): every match would fight the odometry. The run reads them
    mirrored back, with a warning: its trajectory is the one of the log as it should have
    been written (within the 180-degree fan's rounding of the bearings), following the true
    path to within the matches' centimetres, and its session reads the log again so."""
    from frontends.carmen import write_carmen
    from frontends.simulate import office_world, simulate
    from frontends.tum import read_tum
    from iceg import session as sess
    from iceg_common import se2

    run = simulate(office_world(), seed=1)
    scans = run.scans[:150]
    poses = {}
    for name, written in (("as_is", scans), ("mirrored", [s.mirrored() for s in scans])):
        log = tmp_path / f"{name}.clf"
        write_carmen(log, written)
        out = tmp_path / name
        result = runner.invoke(app, ["run", str(log), "--out", str(out), "--no-progress"])
        assert result.exit_code == 0, result.output
        _, poses[name] = read_tum(out / "trajectory.tum")
        check = json.loads((out / "metrics.json").read_text())["odometry_check"]
        assert check["beams_mirrored"] == (name == "mirrored") and check["turns"] >= 7
        session = sess.read(out / "session")
        options = session.manifest["logs"][0].get("reader_options", {})
        assert options == ({"mirror_beams": True} if name == "mirrored" else {})
        again = sess.read_scans(session)
        np.testing.assert_allclose(again[7].ranges_m, scans[7].ranges_m, atol=0.005)
    np.testing.assert_allclose(poses["mirrored"], poses["as_is"], atol=1e-6)
    truth = np.array([se2.between(run.true_poses[0], p) for p in run.true_poses[:150]])
    moved = np.array([se2.between(poses["mirrored"][0], p) for p in poses["mirrored"]])
    assert np.max(np.hypot(*(moved[:, :2] - truth[:, :2]).T)) < 0.03


@pytest.mark.parametrize(
    ("args", "needle"),
    [
        (["--odometry-time-offset", "0.1"], "applies to a log run"),  # the demo
        (["--laser-only"], "--laser-only applies to a log run"),  # the demo
        (["--skip-malformed"], "--skip-malformed applies to a log run"),  # the demo
        (["LOG", "--laser-only", "--odometry-time-offset", "0.1"], "laser-only reading"),
        (["LOG", "--laser-only", "--odometry-time-offset", "auto"], "laser-only reading"),
        (["LOG", "--odometry-time-offset", "nan"], "finite"),
        (["LOG", "--odometry-time-offset", "later"], "or 'auto'"),
        (["--odometry-time-offset", "auto"], "applies to a log run"),  # the demo
    ],
)
def test_bad_odometry_time_offset(tmp_path: Path, args: list[str], needle: str) -> None:
    bag = shared_file("rosbag/turtlebot3-gazebo-ros2")
    args = [str(bag) if a == "LOG" else a for a in args]
    _assert_one_line_error(["run", *args], tmp_path / "o", needle)


def test_nees_of_a_folder_without_a_session(tmp_path: Path) -> None:
    rel = tmp_path / "r.relations"
    rel.write_text("1.0 2.0 0.1 0 0 0 0 0\n")
    _fails_in_one_line(["nees", str(tmp_path), str(rel)], "not a readable iceg session")


def test_help_lists_every_command_with_its_summary() -> None:
    # Each command's summary is its docstring's first line, a sentence of its own: the
    # command list shows it whole (reflowed, never cut), and nothing more of the docstring.
    result = runner.invoke(app, ["--help"], terminal_width=80)
    assert result.exit_code == 0, result.output
    box = result.output.split("Commands")[1]
    listed = " ".join(box.translate(str.maketrans("│╮╯╰─", "     ")).split())
    expected = []
    for command in app.registered_commands:
        assert command.callback is not None
        summary = (command.callback.__doc__ or "").splitlines()[0].strip()
        assert summary.endswith("."), (command.name, summary)
        expected.append(f"{command.name or command.callback.__name__} {summary}")
    assert listed == " ".join(" ".join(expected).split()), result.output
