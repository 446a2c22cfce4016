"""Planar trajectories in the TUM RGB-D format (``stamp x y z qx qy qz qw`` per line).

The format evo and most SLAM benchmarks read. A planar pose ``[x_m, y_m, theta_rad]`` is
written with ``z = qx = qy = 0``, ``qz = sin(theta/2)``, ``qw = cos(theta/2)``, every number
with ``repr`` (the shortest text that reads back to the same float64).
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg_common.atomic import atomic_write
from iceg_common.errors import LogFormatError
from iceg_common.text import read_text_lines

FloatArray = NDArray[np.float64]


def write_tum(path: str | Path, stamps_s: ArrayLike, poses: ArrayLike) -> int:
    """Write a planar trajectory as TUM, atomically.

    Args:
        path: Output file (written to a temporary file beside it, then renamed).
        stamps_s: ``(N,)`` float64 timestamps, seconds.
        poses: ``(N, 3)`` float64 poses ``[x_m, y_m, theta_rad]``.

    Returns:
        The number of poses written.

    Raises:
        ValueError: the shapes disagree.
    """
    t = np.asarray(stamps_s, dtype=np.float64)
    x = np.asarray(poses, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or t.shape != (x.shape[0],):
        raise ValueError(f"write_tum: stamps_s {t.shape} and poses {x.shape} must be (N,), (N, 3)")
    with atomic_write(path) as fh:
        for ti, (xi, yi, th) in zip(t.tolist(), x.tolist(), strict=True):
            q = (0.0, 0.0, math.sin(th / 2.0), math.cos(th / 2.0))
            fh.write(" ".join(repr(float(v)) for v in (ti, xi, yi, 0.0, *q)) + "\n")
    return len(t)


def read_tum(path: str | Path) -> tuple[FloatArray, FloatArray]:
    """Read a TUM trajectory as planar poses.

    Args:
        path: A TUM file; blank lines and ``#`` comments are skipped.

    Returns:
        ``(stamps_s (N,), poses (N, 3))``; ``theta = yaw`` of the quaternion
        (``atan2(2(qw qz + qx qy), 1 - 2(qy² + qz²))``); z, roll and pitch are dropped.

    Raises:
        LogFormatError: missing file, or a line without 8 numbers (``path:line``).
    """
    p = Path(path)
    if not p.is_file():
        raise LogFormatError(f"{p}: no such trajectory file")
    lines = read_text_lines(p, "TUM trajectory", LogFormatError)
    rows = _parse_rows(p, lines)
    a = np.array(rows)
    qx, qy, qz, qw = a[:, 4], a[:, 5], a[:, 6], a[:, 7]
    yaw = np.arctan2(2.0 * (qw * qz + qx * qy), 1.0 - 2.0 * (qy**2 + qz**2))
    return a[:, 0], np.column_stack([a[:, 1], a[:, 2], yaw])


def _parse_rows(p: Path, lines: list[str]) -> list[list[float]]:
    rows: list[list[float]] = []
    for line_no, line in enumerate(lines, start=1):
        text = line.strip()
        if not text or text.startswith("#"):
            continue
        tokens = text.split()
        try:
            values = [float(v) for v in tokens]
        except ValueError:
            values = []
        if len(values) != 8 or not all(math.isfinite(v) for v in values):
            raise LogFormatError(
                f"{p}:{line_no}: a TUM line needs 8 finite numbers "
                f"'stamp x y z qx qy qz qw', got {len(tokens)} tokens"
            )
        rows.append(values)
    if not rows:
        raise LogFormatError(f"{p}: the trajectory file holds no poses")
    return rows
