"""Shared test fixtures: the location of ``../shared/data`` and a skip helper."""

from __future__ import annotations

import os
from pathlib import Path

import matplotlib
import pytest

matplotlib.use("Agg")

REPO = Path(__file__).resolve().parents[1]
SHARED_DATA = Path(os.environ.get("ICEG_SHARED_DATA", REPO.parent / "shared" / "data"))


def shared_file(relative: str) -> Path:
    """Path of a file under ``../shared/data``; skips the test with a reason if absent."""
    path = SHARED_DATA / relative
    if not path.is_file():
        pytest.skip(f"benchmark data {path} is absent (it lives in ../shared/data beside the repo)")
    return path


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
