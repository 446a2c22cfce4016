"""A real log's scans as a lesser scanner would have measured them (generality probes).

A real log carries what no simulated world does: its building's walls and clutter, its
people, its robot's motion and odometry. But it was recorded with one scanner, and the
pipeline's defaults were tuned on logs of that kind (SICK LMS, 180°, 1 cm). A
:class:`ScannerDegradation` turns each scan into what a weaker scanner in the same place
would have returned, so the same building and the same reference score another scanner:

- ``every_nth``: one scan in ``every_nth`` kept (a slower scanner, or a robot that moves
  farther between scans);
- ``reach_m``: returns at or beyond it become no-returns (a shorter-range scanner). The scan
  keeps the range maximum it declares unless ``declare_reach``: many drivers declare more
  than the scanner reaches on dark or grazing walls;
- ``fov_deg``: only the beams within ``±fov_deg / 2`` of the laser's axis are kept;
- ``range_sigma_m``: zero-mean Gaussian noise added to every return (on top of the log's
  own noise, so the total standard deviation is ``sqrt(own² + range_sigma_m²)``);
- ``dropout_fraction`` in runs of ``dropout_run_beams``: returns lost to dark or glossy
  patches, drawn as the simulator draws them (:func:`~frontends.simulate.raycast.dropped_beams`).

A dropped or capped beam becomes ``+inf``, a no-return under :class:`~frontends.scan.LaserScan`'s
``r < range_max_m``. Odometry, stamps and the laser mounting are kept, so a log's benchmark
relations or reference poses still score the run (at the scans kept).
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from frontends.scan import LaserScan
from frontends.simulate.raycast import dropped_beams

IntArray = NDArray[np.int64]


class ScannerDegradation(BaseModel):
    """How each scan of a real log is degraded (the module docstring gives each field's
    physics); the defaults change nothing."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    every_nth: int = Field(default=1, ge=1, description="Keep scans 0, n, 2n, ...")
    reach_m: float | None = Field(
        default=None, gt=0.0, description="Returns at or beyond this range become no-returns."
    )
    declare_reach: bool = Field(
        default=False, description="Also declare reach_m as the scans' range_max_m."
    )
    fov_deg: float | None = Field(
        default=None,
        gt=0.0,
        le=360.0,
        description="Keep only the beams within +-fov_deg/2 of the laser's axis.",
    )
    range_sigma_m: float = Field(
        default=0.0, ge=0.0, description="Standard deviation of the added range noise, metres."
    )
    dropout_fraction: float = Field(
        default=0.0, ge=0.0, lt=1.0, description="Fraction of the beams that lose their return."
    )
    dropout_run_beams: int = Field(default=1, ge=1, description="Beams per run of dropouts.")


def degrade_scans(
    scans: Sequence[LaserScan], degradation: ScannerDegradation, seed: int = 0
) -> tuple[IntArray, list[LaserScan]]:
    """The scans as the degraded scanner would have measured them.

    Per kept scan, in this order: beams outside the field of view removed, noise added to
    the returns (clipped at 0 m), dropouts drawn, returns at or beyond ``reach_m`` made
    no-returns. The noise and dropouts come from one generator seeded with ``seed``, drawn
    scan by scan, so the same inputs give the same scans.

    Args:
        scans: The log's scans, in time order.
        degradation: What to degrade.
        seed: Seed of the noise and the dropouts (``numpy.random.default_rng``).

    Returns:
        ``kept``: ``(K,)`` int64 indices into ``scans`` of the scans kept, and the ``K``
        degraded scans (their stamps, odometry, laser offset and source unchanged).
    """
    d = degradation
    rng = np.random.default_rng(seed)
    kept = np.arange(0, len(scans), d.every_nth, dtype=np.int64)
    out = []
    for k in kept.tolist():
        scan = scans[k]
        ranges, angles, returns = scan.ranges_m, scan.angles_rad, scan.valid_mask()
        if d.fov_deg is not None:
            inside = np.abs(angles) <= math.radians(d.fov_deg) / 2.0 + 1e-9
            ranges, angles, returns = ranges[inside], angles[inside], returns[inside]
        ranges = np.array(ranges, dtype=np.float64)
        if d.range_sigma_m > 0.0:
            noise = rng.normal(0.0, d.range_sigma_m, size=ranges.shape)
            ranges[returns] = np.maximum(ranges[returns] + noise[returns], 0.0)
        if d.dropout_fraction > 0.0:
            lost = dropped_beams(ranges.shape[0], d.dropout_fraction, d.dropout_run_beams, rng)
            ranges[lost & returns] = np.inf
        range_max_m = scan.range_max_m
        if d.reach_m is not None:
            ranges[returns & (ranges >= d.reach_m)] = np.inf
            if d.declare_reach:
                range_max_m = min(range_max_m, d.reach_m)
        out.append(
            dataclasses.replace(
                scan, ranges_m=ranges, angles_rad=np.array(angles), range_max_m=range_max_m
            )
        )
    return kept, out
