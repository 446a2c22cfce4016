"""Shared test fixtures: the location of ``../shared/data``, a skip helper and a loader of
the benchmark scripts (``benchmarks/`` is no package)."""

from __future__ import annotations

import importlib.util
import math
import os
import sys
from pathlib import Path
from types import ModuleType

import matplotlib
import numpy as np
import pytest

matplotlib.use("Agg")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("ICEG_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_file(relative: str) -> Path:
    """Path of a file (or a ROS 2 bag folder) under ``../shared/data``; skips the test with a
    reason if absent."""
    path = SHARED_DATA / relative
    if not path.exists():
        pytest.skip(f"benchmark data {path} is absent (it lives in ../shared/data beside the repo)")
    return path


def se2_log(pose: object) -> np.ndarray:
    """SE(2) logarithm of ``[x, y, theta]`` by its closed form, independent of the code under
    test: ``[V(theta)^-1 [x, y], theta]`` with ``V = [[s, -c], [c, s]]``, ``s = sin(th) / th``,
    ``c = (1 - cos(th)) / th``."""
    x, y, th = np.asarray(pose, dtype=np.float64).tolist()
    if abs(th) < 1e-12:
        return np.array([x, y, th])
    s, c = math.sin(th) / th, (1.0 - math.cos(th)) / th
    return np.array([*np.linalg.solve([[s, -c], [c, s]], [x, y]), th])


def flaser_line(x_m: float, stamp_s: float) -> str:
    """A 3-beam CARMEN ``FLASER`` line (ranges 1, 2 and 3 m) at odometry and laser pose
    ``(x_m, 0, 0)``, stamped ``stamp_s``."""
    pose = f"{x_m} 0.0 0.0"
    return f"FLASER 3 1.0 2.0 3.0 {pose} {pose} {stamp_s} h {stamp_s}"


def write_odometry_jump_log(path: Path) -> Path:
    """Write a 5-scan CARMEN log to ``path``: scans 0.1 s apart, 0.3 m steps of motion and
    a 50 m jump of the odometry at line 4 (a break: the limit is 2 m + 5 m/s * dt)."""
    xs = [0.0, 0.3, 0.6, 50.6, 50.9]
    path.write_text("".join(flaser_line(x, 10.0 + 0.1 * k) + "\n" for k, x in enumerate(xs)))
    return path


def load_benchmark(name: str) -> ModuleType:
    """The module ``benchmarks/<name>.py``, imported under ``name`` (so a benchmark that
    imports a sibling, e.g. ``bench_scaling`` importing ``bench_accuracy``, finds it once
    that one is loaded too)."""
    spec = importlib.util.spec_from_file_location(name, REPO / "benchmarks" / f"{name}.py")
    assert spec is not None and spec.loader is not None
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def csail_run(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The output folder of ``iceg run`` on MIT CSAIL with its relations (default config),
    computed once per test session for every test that needs the whole run."""
    from typer.testing import CliRunner

    from iceg.cli import app

    log = shared_file("mit-csail/mit-csail.clf")
    rel = shared_file("mit-csail/mit-csail.relations")
    out = tmp_path_factory.mktemp("csail_run") / "out"
    args = ["run", str(log), "--relations", str(rel), "--out", str(out), "--no-progress"]
    result = CliRunner().invoke(app, args)
    assert result.exit_code == 0, result.output
    return out
