"""Synthetic wheel odometry for real logs: any log whose poses are already corrected becomes
a SLAM test with a reference trajectory.

A corrected log (GMapping output such as ``aces-corrected.log.gz``, or ``csail.log``) stores
near-ground-truth robot poses in the odometry fields of its laser records. This module keeps
the scans and replaces the odometry with a drifting, biased odometry made from those poses
by :class:`~frontends.simulate.odometry.OdometryModel` (the Probabilistic Robotics §5.4
"alpha" model plus systematic drift). Per step ``k`` the reference increment
``u_k = x_k^-1 ∘ x_{k+1} = (dx, dy, dtheta)`` (robot frame, ``d = |(dx, dy)|``) becomes

- ``(dx, dy) * (1 + scale_error)`` (per-step scale error),
- ``dtheta + heading_drift_rad_per_m * d`` (heading drift per metre driven),
- plus white Gaussian noise of the model's per-increment standard deviations,

and the odometry pose is the composition of the changed increments from ``x_0``. The
original poses are the reference, written as a TUM trajectory beside the new log.

The same function applied to a raw log adds the drift on top of its real odometry
(e.g. MIT CSAIL's raw odometry plus a synthetic heading drift; the benchmark relations
still score it).

Command line::

    python -m frontends.simulate.synthetic_odometry IN_LOG OUT_LOG [--scale-error 0.01]
        [--heading-drift-deg-per-m 0.4] [--no-noise] [--seed 0] [--restamp-hz 5]
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from frontends.carmen import write_carmen
from frontends.registry import open_log
from frontends.scan import LaserScan
from frontends.simulate.odometry import OdometryModel
from frontends.tum import write_tum
from iceg_common.errors import ConfigError, LogFormatError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class SyntheticOdometry:
    """Scans with synthetic odometry and their reference trajectory.

    Attributes:
        scans: The input scans with ``odom_pose`` replaced (and ``stamp_s`` if re-stamped).
        reference_poses: ``(N, 3)`` float64 the input ``odom_pose`` of every scan
            ``[x_m, y_m, theta_rad]`` (the corrected poses: the reference trajectory).
        odom_poses: ``(N, 3)`` float64 the synthetic odometry, same frame (starts at
            ``reference_poses[0]``).
        stamps_s: ``(N,)`` float64 scan timestamps, seconds.
        model: The odometry model used.
        seed: The seed of the noise.
    """

    scans: list[LaserScan]
    reference_poses: FloatArray
    odom_poses: FloatArray
    stamps_s: FloatArray
    model: OdometryModel
    seed: int

    def end_drift_m(self) -> float:
        """Distance in metres between the last odometry pose and the last reference pose."""
        return float(np.hypot(*(self.odom_poses[-1, :2] - self.reference_poses[-1, :2])))


def _stamps(scans: Sequence[LaserScan], restamp_hz: float | None) -> FloatArray:
    """Original stamps, or ``t_0 + k / restamp_hz`` (for logs whose printed stamps lost
    their precision, e.g. ``csail-corrected.log.gz``)."""
    t = np.array([s.stamp_s for s in scans], dtype=np.float64)
    if restamp_hz is None:
        return t
    if restamp_hz <= 0:
        raise ConfigError(f"restamp_hz must be > 0, got {restamp_hz}")
    return np.asarray(t[0] + np.arange(t.size) / restamp_hz, dtype=np.float64)


def synthetic_odometry(
    scans: Sequence[LaserScan],
    model: OdometryModel,
    seed: int = 0,
    restamp_hz: float | None = None,
) -> SyntheticOdometry:
    """Replace the scans' odometry with ``model``'s drifting odometry of their poses.

    Args:
        scans: Laser scans in time order, each with an ``odom_pose`` (the reference).
        model: Odometry model (e.g. ``OdometryModel.biased(0.01, 0.4)``); its ``start`` must
            be ``"true"`` so the odometry and the reference share a frame.
        seed: Seed of the white noise (``numpy.random.SeedSequence(seed)``).
        restamp_hz: Re-stamp scan ``k`` at ``stamp_0 + k / restamp_hz`` seconds; ``None``
            keeps the stamps.

    Returns:
        A :class:`SyntheticOdometry`.

    Raises:
        LogFormatError: no scans, or a scan without odometry.
        ConfigError: ``model.start != "true"`` or ``restamp_hz <= 0``.
    """
    if not scans:
        raise LogFormatError("synthetic_odometry: no scans")
    if model.start != "true":
        raise ConfigError("synthetic_odometry: the model must start at the reference ('true')")
    missing = [s.source for s in scans if s.odom_pose is None]
    if missing:
        raise LogFormatError(f"{missing[0]}: scan has no odometry pose to use as reference")
    ref = np.array([s.odom_pose for s in scans], dtype=np.float64)
    odom = model.simulate(ref, np.random.default_rng(np.random.SeedSequence(seed)))
    stamps = _stamps(scans, restamp_hz)
    out = [
        dataclasses.replace(s, odom_pose=odom[k], stamp_s=float(stamps[k]))
        for k, s in enumerate(scans)
    ]
    for a in (ref, odom, stamps):
        a.setflags(write=False)
    return SyntheticOdometry(out, ref, odom, stamps, model, seed)


def reference_path(log_path: str | Path) -> Path:
    """Where :func:`write_synthetic_log` puts the reference TUM file for ``log_path``:
    beside it, suffixes ``.gz``, ``.log``, ``.clf`` removed, ``.reference.tum`` added."""
    p = Path(log_path)
    name = p.name
    for suffix in (".gz", ".log", ".clf"):
        name = name.removesuffix(suffix)
    return p.with_name(name + ".reference.tum")


def write_synthetic_log(
    in_log: str | Path,
    out_log: str | Path,
    model: OdometryModel,
    seed: int = 0,
    restamp_hz: float | None = None,
    laser_record: Literal["FLASER", "ROBOTLASER1"] = "ROBOTLASER1",
) -> SyntheticOdometry:
    """Read a corrected log, replace its odometry (:func:`synthetic_odometry`), and write a
    CARMEN log (``frontends.carmen.write_carmen``) and the reference poses as TUM beside it
    (:func:`reference_path`).

    ``ROBOTLASER1`` (the default) stores each scan's bearings and maximum range, so any
    evenly spaced scan round-trips; ``FLASER`` needs the FLASER bearing grid.

    Returns:
        The :class:`SyntheticOdometry` written.

    Raises:
        LogFormatError: unreadable input, no scans, a scan without odometry, or an output
            that cannot be written.
        ConfigError: see :func:`synthetic_odometry`.
    """
    synth = synthetic_odometry(list(open_log(in_log)), model, seed, restamp_hz)
    write_carmen(out_log, synth.scans, laser_record=laser_record)
    write_tum(reference_path(out_log), synth.stamps_s, synth.reference_poses)
    return synth


def _parser() -> argparse.ArgumentParser:
    ap = argparse.ArgumentParser(
        prog="python -m frontends.simulate.synthetic_odometry",
        description="Replace a corrected log's odometry by drifting synthetic odometry.",
    )
    ap.add_argument("in_log", type=Path)
    ap.add_argument("out_log", type=Path)
    ap.add_argument("--scale-error", type=float, default=0.01, help="e.g. 0.01 = 1 %%")
    ap.add_argument("--heading-drift-deg-per-m", type=float, default=0.4)
    ap.add_argument("--no-noise", action="store_true", help="bias only, no white noise")
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--restamp-hz", type=float, default=None)
    return ap


def main(argv: Sequence[str] | None = None) -> int:
    """Command-line entry point; returns the exit status."""
    args = _parser().parse_args(argv)
    model = OdometryModel.biased(
        args.scale_error, args.heading_drift_deg_per_m, noise=not args.no_noise
    )
    synth = write_synthetic_log(args.in_log, args.out_log, model, args.seed, args.restamp_hz)
    msg = (
        f"{args.out_log}: {len(synth.scans)} scans, odometry end drift "
        f"{synth.end_drift_m():.3f} m; reference {reference_path(args.out_log)}\n"
    )
    import sys

    sys.stdout.write(msg)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
