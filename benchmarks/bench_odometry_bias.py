"""Benchmark: biased wheel odometry (issue 11 item 2), online odometry calibration on / off.

Cases (from ``benchmarks/bench_accuracy.py``): ``office_biased`` (simulated office loop, 1.5 %
scale error, 0.4 deg/m heading drift, exact truth), ``aces_synth`` / ``csail_log_synth``
(corrected real logs with synthetic odometry: 1 % scale error, 0.4 deg/m drift, default white
noise; reference = corrected poses), ``csail_raw`` (MIT CSAIL raw odometry, 1172 benchmark
relations) and ``csail_raw_drift`` (its raw odometry plus 0.4 deg/m heading drift). Variants
``*_bias_only`` replace the synthetic odometry by the bias without white noise, to separate
what the bias costs from what the noise and the scan matcher cost. ``aces_strong_drift`` /
``csail_log_strong_drift``: 1 % scale error and 2 deg/m heading drift with the default noise
(a stress case: docs/design.md "Walls of nodes the odometry placed").

Per case and setting (``odometry_calibration.enabled``: ``auto`` = correcting while an error
is beyond the odometry noise model, the configuration's default; ``calib`` = always; ``off`` =
never): ATE (RMSE after SE(2) alignment) against the reference, mean relation error (CSAIL),
the final calibration estimate, whether the run was correcting at its end, and the wall time.

Run: ``PYTHONPATH=. python benchmarks/bench_odometry_bias.py [--only CASE ...] [--setting
off|auto|calib ...] [--seed N] [--json PATH]``.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_accuracy as ba

from frontends.simulate import OdometryModel
from iceg.config import IcegConfig
from iceg.evaluation import position_errors, relation_errors
from iceg.odometry_calibration import OdometryCalibrationConfig
from iceg.slam import Slam

BIAS_ONLY = OdometryModel.biased(scale_error=0.01, heading_drift_deg_per_m=0.4, noise=False)


ACES, CSAIL_LOG = "aces/aces-corrected.log.gz", "mit-csail/csail.log"
CASES: dict[str, Callable[[int], ba.CaseInput]] = {
    name: ba.CASES[name]
    for name in (
        "office_biased",
        "aces_synth",
        "csail_log_synth",
        "csail_raw",
        "csail_raw_drift",
        "aces_strong_drift",
    )
} | {
    "aces_bias_only": ba._corrected(ACES, None, BIAS_ONLY),
    "csail_log_bias_only": ba._corrected(CSAIL_LOG, None, BIAS_ONLY),
    "csail_log_strong_drift": ba._corrected(CSAIL_LOG, None, ba.SYNTH_STRONG_DRIFT),
}


#: ``odometry_calibration.enabled`` of each setting.
SETTINGS: dict[str, bool | Literal["auto"]] = {"off": False, "auto": "auto", "calib": True}


def run(name: str, setting: str, seed: int = 0) -> dict[str, Any]:
    """Run case ``name`` with calibration ``setting`` (a key of :data:`SETTINGS`); return its
    row."""
    try:
        case = CASES[name](seed)
    except ba.CaseSkipped as exc:
        return {"name": name, "setting": setting, "skipped": str(exc)}
    cal = OdometryCalibrationConfig(enabled=SETTINGS[setting])
    slam = Slam(IcegConfig(odometry_calibration=cal))
    t0 = time.perf_counter()
    for scan in case.scans:
        slam.process(scan)
    result = slam.finish()
    c = slam.odometry_calibrator
    row: dict[str, Any] = {
        "name": name,
        "setting": setting,
        "seconds": time.perf_counter() - t0,
        "kappa": c.scale,
        "gamma": c.turn_scale,
        "beta_deg_per_m": math.degrees(c.heading_drift_rad_per_m),
        "rejected": result.match_failures.get("inconsistent with odometry", 0),
        "corrected": c.correcting,
    }
    odom = np.array([s.odom_pose for s in case.scans], dtype=np.float64)
    if case.reference is not None:
        row["ate_m"] = position_errors(result.poses, case.reference).rmse_m
        row["odom_ate_m"] = position_errors(odom, case.reference).rmse_m
    if case.relations is not None:
        rel = case.relations
        est, _ = relation_errors(
            result.stamps_s, result.poses, rel.stamps_s, rel.deltas, ba.RELATION_TOLERANCE_S
        )
        row |= {"rel_m": est.trans_mean_m, "rel_deg": est.rot_mean_deg, "n_rel": est.n_matched}
    return row


def _fmt(row: dict[str, Any]) -> str:
    if "skipped" in row:
        return f"{row['name']:<20} {row['setting']:<6} skipped: {row['skipped']}"
    cells = [f"{row['name']:<20}", f"{row['setting']:<6}"]
    for key, fmt in (
        ("ate_m", "ATE {:.3f} m"),
        ("odom_ate_m", "odoATE {:.2f} m"),
        ("rel_m", "rel {:.4f} m"),
        ("rel_deg", "{:.3f} deg"),
        ("n_rel", "n {:d}"),
        ("kappa", "kappa {:.4f}"),
        ("gamma", "gamma {:.4f}"),
        ("beta_deg_per_m", "beta {:+.3f} deg/m"),
        ("rejected", "rej {:d}"),
        ("corrected", "corrected {}"),
        ("seconds", "{:.1f} s"),
    ):
        if key in row:
            cells.append(fmt.format(row[key]))
    return "  ".join(cells)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--only", action="append", choices=sorted(CASES))
    ap.add_argument("--setting", action="append", choices=tuple(SETTINGS))
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--json", type=Path)
    args = ap.parse_args(argv)
    rows = []
    for name in args.only or list(CASES):
        for setting in args.setting or tuple(SETTINGS):
            rows.append(run(name, setting, args.seed))
            sys.stdout.write(_fmt(rows[-1]) + "\n")
            sys.stdout.flush()
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
