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
