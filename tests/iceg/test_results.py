"""Saving a run never loses it and never mixes two runs (issue 12); the tiled grid renders
large sites in bounded memory."""

from __future__ import annotations

import dataclasses
import json
import math
import signal
import subprocess
import sys
import textwrap
from pathlib import Path

import numpy as np
import pytest

from frontends import LaserScan
from frontends.simulate import office_world, simulate
from frontends.simulate.raycast import ray_ranges
from frontends.simulate.worlds import rectangle
from iceg.config import config_from_dict
from iceg.grid import (
    TILE_SIZE,
    GridConfig,
    render,
    render_tiled,
    write_map_server,
)
from iceg.pipeline import run_scans
from iceg.results import (
    CORE_FILES,
    MAP_FILES,
    OUTPUT_FILES,
    SESSION_DIR,
    STAGING_MARKER,
    SlamResult,
)
from iceg_common.errors import GraphError, OutputError

REPO = Path(__file__).resolve().parents[2]
N_SCANS = 40


def _result(seed: int = 1, config: dict | None = None) -> SlamResult:  # type: ignore[type-arg]
    run = simulate(office_world(), seed=seed)
    cfg = config_from_dict(config or {})
    return run_scans(run.scans[:N_SCANS], cfg)


@pytest.fixture(scope="module")
def result_a() -> SlamResult:
    return _result(seed=1)


@pytest.fixture(scope="module")
def result_b() -> SlamResult:
    return _result(seed=2)


def _files(folder: Path) -> dict[str, bytes]:
    """The result files (the session folder is checked by tests/iceg/test_session.py)."""
    assert (folder / SESSION_DIR / "manifest.json").is_file()
    return {p.name: p.read_bytes() for p in sorted(folder.iterdir()) if p.name != SESSION_DIR}


def _leftovers(out: Path) -> list[str]:
    return sorted(p.name for p in out.parent.iterdir() if p.name != out.name)


def test_save_replaces_the_whole_set_and_leaves_no_staging(
    result_a: SlamResult, result_b: SlamResult, tmp_path: Path
) -> None:
    out = tmp_path / "run"
    result_a.save(out)
    first = _files(out)
    assert sorted(first) == sorted(OUTPUT_FILES) == sorted(CORE_FILES + MAP_FILES)
    result_b.save(out)
    second = _files(out)
    assert sorted(second) == sorted(OUTPUT_FILES)
    # every file is the second run's: the trajectories differ (different noise seeds)
    assert second["trajectory.tum"] != first["trajectory.tum"]
    assert json.loads(second["metrics.json"])["map"]["rendered"] is True
    assert _leftovers(out) == []


@pytest.mark.parametrize("with_session", [True, False])
def test_graph_and_config_files_are_the_graph_and_config_written_afresh(
    result_a: SlamResult, tmp_path: Path, with_session: bool
) -> None:
    # With its session, the result links the session's graph and configuration files
    # instead of writing them again; without one it writes them itself: the same bytes.
    result = result_a if with_session else dataclasses.replace(result_a, slam=None)
    out = tmp_path / "run"
    result.save(out)
    result.graph.write_g2o(tmp_path / "fresh.g2o")
    assert (out / "graph.g2o").read_bytes() == (tmp_path / "fresh.g2o").read_bytes()
    assert (out / "config.yaml").read_text() == result.config.to_yaml()
    assert (out / SESSION_DIR).is_dir() is with_session


def test_a_map_rendered_beside_the_first_step_is_the_map_rendered_before_it(
    tmp_path: Path,
) -> None:
    # save() renders a map not rendered yet in another thread while it writes the core
    # files; the same run with its map rendered first (render_map) saves the same files,
    # and the map's figures and grid time are the result's either way.
    beside, before = _result(seed=3), _result(seed=3)
    assert not beside._map_tried
    before.render_map()
    beside.save(tmp_path / "beside")
    before.save(tmp_path / "before")
    got, want = _files(tmp_path / "beside"), _files(tmp_path / "before")
    metrics = json.loads(got.pop("metrics.json"))
    assert metrics["map"] == json.loads(want.pop("metrics.json"))["map"]
    assert metrics["map"]["rendered"] is True
    assert got == want and sorted(got) == sorted(set(OUTPUT_FILES) - {"metrics.json"})
    assert beside.stage_seconds["grid"] > 0.0
    assert beside.render_map() is beside._map is not None  # kept: not rendered again


def test_unrenderable_map_keeps_trajectory_graph_metrics(tmp_path: Path) -> None:
    # A grid limit far below the run's footprint: the map cannot be rendered.
    result = _result(config={"grid": {"max_cells": 1000}})
    out = tmp_path / "run"
    result.save(out)
    assert sorted(_files(out)) == sorted(CORE_FILES)
    metrics = json.loads((out / "metrics.json").read_text())
    assert metrics["map"]["rendered"] is False
    assert "max_cells=1000" in metrics["map"]["reason"]
    assert len((out / "trajectory.tum").read_text().splitlines()) == N_SCANS


def test_absurd_extent_is_a_warning_not_a_lost_run(
    result_a: SlamResult, tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # A broken log: one pose 1e9 m away. The bounds would span ~1e20 tiles.
    poses = result_a.poses.copy()
    poses[-1, 0] += 1e9
    broken = dataclasses.replace(result_a, poses=poses, metrics={})
    out = tmp_path / "run"
    broken.save(out)
    assert sorted(_files(out)) == sorted(CORE_FILES)
    assert "no map written" in caplog.text
    assert "tiles" in json.loads((out / "metrics.json").read_text())["map"]["reason"]


def test_out_that_is_a_file_or_holds_other_files_is_refused(
    result_a: SlamResult, tmp_path: Path
) -> None:
    file = tmp_path / "file"
    file.write_text("keep me")
    with pytest.raises(OutputError, match="not a folder"):
        result_a.save(file)
    assert file.read_text() == "keep me"
    folder = tmp_path / "home"
    folder.mkdir()
    (folder / "thesis.tex").write_text("keep me")
    with pytest.raises(OutputError, match="not iceg results"):
        result_a.save(folder)
    assert sorted(p.name for p in folder.iterdir()) == ["thesis.tex"]
    with pytest.raises(OutputError, match="not a folder"):
        result_a.save(file / "sub")


_CHILD = """
import os, signal, sys
sys.path.insert(0, {repo!r})
import iceg.results as results
from frontends.simulate import office_world, simulate
from iceg.pipeline import run_scans

run = simulate(office_world(), seed=3)
result = run_scans(run.scans[:{n}])
target = getattr(results, {victim!r})

def killed_midway(*args, **kwargs):
    target(*args, **kwargs)
    os.kill(os.getpid(), signal.SIGKILL)

setattr(results, {victim!r}, killed_midway)
result.save({out!r})
"""


def _kill_during(victim: str, out: Path) -> subprocess.CompletedProcess[str]:
    code = _CHILD.format(repo=str(REPO), n=N_SCANS, victim=victim, out=str(out))
    return subprocess.run(
        [sys.executable, "-c", textwrap.dedent(code)], capture_output=True, text=True, timeout=600
    )


@pytest.mark.parametrize(("victim", "kept"), [("write_tum", "previous"), ("write_png", "core")])
def test_kill_during_save_keeps_a_complete_set_and_next_save_cleans_up(
    result_a: SlamResult, result_b: SlamResult, tmp_path: Path, victim: str, kept: str
) -> None:
    out = tmp_path / "run"
    result_a.save(out)
    previous = _files(out)
    proc = _kill_during(victim, out)
    assert proc.returncode == -signal.SIGKILL, proc.stderr
    stale = _leftovers(out)
    # the killed save's staging folder: visible (no leading dot), named after its target
    assert len(stale) == 1 and stale[0].startswith(f"run{STAGING_MARKER}"), stale
    now = _files(out)
    if kept == "previous":  # killed while writing step 1: the previous set, untouched
        assert now == previous
    else:  # killed while writing the map: the new core set, none of the old map files
        assert sorted(now) == sorted(CORE_FILES)
        assert now["trajectory.tum"] != previous["trajectory.tum"]
        assert json.loads(now["metrics.json"])["map"]["rendered"] is False
    result_b.save(out)
    assert _leftovers(out) == []
    assert sorted(_files(out)) == sorted(OUTPUT_FILES)


def test_finish_is_idempotent_and_process_after_finish_is_refused() -> None:
    from iceg.slam import Slam

    run = simulate(office_world(), seed=1)
    slam = Slam()
    for scan in run.scans[:10]:
        slam.process(scan)
    first = slam.finish()
    assert slam.finish() is first
    with pytest.raises(GraphError, match="after finish"):
        slam.process(run.scans[10])


# ---------------------------------------------------------------------------------------------
# Tiled grid
# ---------------------------------------------------------------------------------------------


def _ring_site(
    size_m: float, corridor_m: float, step_m: float
) -> tuple[list[LaserScan], np.ndarray]:
    """A square ring corridor ``size_m`` on a side, driven along its centre line: exact
    ranges (no noise) from :func:`ray_ranges`, 181 beams over 180 deg, 30 m max range."""
    walls = np.array(
        rectangle(0.0, 0.0, size_m, size_m)
        + rectangle(corridor_m, corridor_m, size_m - corridor_m, size_m - corridor_m)
    )
    c = corridor_m / 2
    corners = np.array([[c, c], [size_m - c, c], [size_m - c, size_m - c], [c, size_m - c]])
    angles = np.linspace(-math.pi / 2, math.pi / 2, 181)
    scans: list[LaserScan] = []
    poses: list[list[float]] = []
    for k in range(4):
        a, b = corners[k], corners[(k + 1) % 4]
        heading = math.atan2(*(b - a)[::-1])
        n = int(np.linalg.norm(b - a) / step_m)
        for f in np.arange(n) / n:
            xy = a + f * (b - a)
            ranges = ray_ranges(xy, heading + angles, walls)
            scans.append(LaserScan(len(scans) * 0.1, ranges, angles, 0.0, 30.0, None))
            poses.append([xy[0], xy[1], heading])
    return scans, np.array(poses)


def test_400m_site_renders_at_5cm_in_memory_proportional_to_the_rays() -> None:
    size, corridor, res = 400.0, 10.0, 0.05
    scans, poses = _ring_site(size, corridor, step_m=2.0)
    grid = render_tiled(scans, poses, GridConfig(resolution_m=res))
    h, w = grid.shape
    assert h * w > 64_000_000  # the dense grid: 8040 x 8040 cells
    # Storage: only tiles the rays cross. The ring band (10 m) touches at most a band of
    # 10 m + 2 tiles across: bound the stored cells by that area.
    tile_m = TILE_SIZE * res
    band_cells = 4 * (size + 2) * (corridor + 2 * tile_m) / res**2
    assert grid.allocated_cells <= band_cells
    assert grid.allocated_cells < 0.2 * h * w
    touched = int(np.count_nonzero((grid.hits + grid.misses) > 0))
    assert touched <= grid.allocated_cells <= 2.0 * touched

    # Truth: walls where the world has them, free corridor, unknown courtyard.
    def log_odds_near(x: float, y: float, cells: int) -> np.ndarray:
        row, col = np.floor((np.array([y, x]) - grid.origin_xy[::-1]) / res).astype(int)
        return grid.rows(row - cells, row + cells + 1)[:, col - cells : col + cells + 1]

    for x, y in [(200.0, 0.0), (size, 200.0), (200.0, corridor), (corridor, 123.4)]:
        assert log_odds_near(x, y, 1).max() > 0.0, (x, y)  # a wall: occupied
    assert log_odds_near(200.0, 0.3 * corridor, 0)[0, 0] < 0.0  # corridor: free
    assert np.all(log_odds_near(200.0, 200.0, 20) == 0.0)  # courtyard: never seen
    assert grid.tile_index[int(200 / tile_m), int(200 / tile_m)] == -1  # ... and not stored


def test_tiled_export_equals_the_dense_export(tmp_path: Path) -> None:
    run = simulate(office_world(), seed=1)
    cfg = GridConfig(resolution_m=0.05)
    tiled = render_tiled(run.scans, run.true_poses, cfg)
    dense = render(run.scans, run.true_poses, cfg)
    np.testing.assert_array_equal(tiled.to_dense().log_odds, dense.log_odds)
    write_map_server(tiled, tmp_path / "tiled")
    write_map_server(dense, tmp_path / "dense")
    assert (tmp_path / "tiled.pgm").read_bytes() == (tmp_path / "dense.pgm").read_bytes()
