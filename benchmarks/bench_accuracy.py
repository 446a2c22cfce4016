"""Benchmark: accuracy on logs and worlds the pipeline was not tuned on (issue 11).

Every case runs the default pipeline (:class:`iceg.slam.Slam` with ``IcegConfig()``) and
reports, in one table:

- ``rel m/deg``: mean Kümmerle et al. 2009 relation error (MIT CSAIL cases);
- ``ATE m``: RMSE of the position error against the truth / reference after a rigid SE(2)
  alignment (``iceg.evaluation.position_errors``), and ``end m``: the unaligned distance of
  the last pose from the truth (the estimate starts at the true first pose);
- ``odo ATE`` / ``odo end``: the same for the odometry alone (what the pipeline starts from);
- ``online max``: the largest unaligned position error of the *online* estimate (the pose
  ``Slam.process`` returns for each scan, before later corrections): the drift a
  loop-closure search around the estimate has to cover;
- ``len ratio``: path length of the estimated keyframe poses over that of the reference at
  the same scans (1.0 = right length; issue 11 failure 1 is a ratio of about 0.988);
- ``sm/kf``: fraction of keyframes (after the first) that got a scan-match factor;
- ``odo dt s``: the time offset between the scans and the odometry that the run's matched
  rotations show (:func:`iceg.odometry_timing.odometry_time_offset`; negative: the scans
  were taken before their stamps), where significant; the JSON rows hold the best fit and
  its p-value either way (``odom_time_offset_best_s``, ``odom_time_offset_p``);
- ``LC acc`` / ``LC false`` / ``LC disp``: loop closures accepted, those whose measured
  relative pose differs from the true one by more than 0.3 m or 3 deg, and those as far off
  whose two scans dispute the reference (matched again from it, they land on the closure:
  a corrected log's own error; :func:`iceg.batch_run.check_loop_closures`), only where a
  reference exists;
- ``body m``: the range left out as the robot's own body (``features.robot_body_range_m``
  after :func:`iceg.pipeline.measure_scanner`, as ``iceg run`` measures it);
- ``drops/k`` / ``drop gap``: the scanner's patches of lost returns on walls per 1000
  returns (:mod:`iceg.wall_dropouts`), and the ``features.eow_dropout_max_gap_m`` the run
  used (0.5 where they switched the dropout rule on);
- ``time s``: SLAM wall time (all scans plus ``finish``).

Cases: the simulated scenarios of ``frontends.simulate.SCENARIOS`` (office, corridor,
office_biased, long_corridor, two_loop, open_loops, outdoor, office_people: the office loop
with ten people walking its corridors; exact truth), MIT CSAIL with its raw odometry, with a
synthetic 0.4 deg/m heading drift added on top of it and without its odometry
(``csail_raw_laser_only``: each scan predicted by constant velocity; relations), and the
corrected ACES / csail.log / csail-corrected logs with synthetic biased odometry (1 % scale
error, 0.4 deg/m heading drift, default white noise; reference = corrected poses;
``frontends.simulate.synthetic_odometry``), ACES with a heading drift beyond the odometry noise
model (``aces_strong_drift``: 1 %, 2 deg/m, noise), and the RC car bag (``rc_car_mocap``: a
360° lidar in a motion-capture arena, laser only, scored against the motion capture; another
car drives beside it), and two real bags with their own odometry and no reference
(``turtlebot4``, ``neato``: the scan-match fraction and the time offset only). Real logs come
from ``../shared/data`` (or ``$ICEG_SHARED_DATA``); a case whose file is absent is reported as
skipped.

Each row is one call of :func:`run_case`, reusable by a batch runner; and the whole benchmark
is one ``iceg batch`` spec (:func:`batch_spec`): ``--batch DIR`` runs it through
``iceg.batch.run_batch`` (Ray, or ``--local``; resumable, one table in ``DIR/summary.md``) and
``--write-spec PATH`` writes it as YAML for ``iceg batch PATH``.

``--seeds 0-9`` runs every case with a random input (simulation, synthetic odometry, added
range noise or dropouts) at each seed and ends with a table per case over the seeds (mean,
median and worst error and matched keyframes, false closures summed): one seed's loop
closure found or missed outweighs most changes, so a change is judged over seeds. With
``--batch``, ``--variant NAME=YAML`` (repeatable) adds configurations beside the default and
``summary.md`` compares them so.

Run: ``python benchmarks/bench_accuracy.py [--only NAME ...] [--quick] [--json PATH]
[--maps DIR] [--seed N | --seeds N|A-B ...] [--config YAML] [--laser NAME] [--degrade NAME]
[--batch DIR [--local] [--workers N] [--variant NAME=YAML ...]] [--write-spec PATH]``.
``--quick`` stops every case after its first 300 scans (a smoke
test: loops are not closed). ``--laser`` drives the simulated scenarios with another scanner
(:data:`LASERS`: the defaults are tuned for none of them; the real-log cases are unchanged).
``--degrade`` does the same for the real logs: their scans degraded as a lesser scanner would
have measured them (:data:`DEGRADATIONS`: fewer scans, a shorter reach, a narrower field of
view, more range noise, dropouts; :func:`frontends.simulate.degrade_scans`), scored against
the same reference or relations at the scans kept; the simulated scenarios are unchanged.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import sys
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontends import LaserScan, open_log
from frontends.relations import Relations, read_relations
from frontends.simulate import (
    SCENARIOS,
    OdometryModel,
    ScannerDegradation,
    degrade_scans,
    simulate_scenario,
    synthetic_odometry,
)
from frontends.simulate.raycast import LaserModel
from graph import FactorKind
from iceg.batch_report import seed_table
from iceg.batch_run import check_loop_closures
from iceg.config import IcegConfig, config_from_yaml
from iceg.evaluation import position_errors, relation_errors
from iceg.features import extract
from iceg.odometry_timing import odometry_time_offset
from iceg.pipeline import measure_scanner
from iceg.results import SlamResult
from iceg.scan_store import ScanStore
from iceg.slam import Slam

FloatArray = NDArray[np.float64]

DATA = Path(
    os.environ.get("ICEG_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)
#: Scans per case with ``--quick``.
QUICK_SCANS = 300
RELATION_TOLERANCE_S = 1e-3
#: Synthetic odometry for the corrected logs, and the drift added to CSAIL's raw odometry.
SYNTH_BIASED = OdometryModel.biased(scale_error=0.01, heading_drift_deg_per_m=0.4)
SYNTH_DRIFT_ONLY = OdometryModel.biased(scale_error=0.0, heading_drift_deg_per_m=0.4, noise=False)
#: Five times the usual heading drift, beyond the odometry noise model (docs/design.md "The
#: odometry's systematic errors, corrected where beyond the model").
SYNTH_STRONG_DRIFT = OdometryModel.biased(scale_error=0.01, heading_drift_deg_per_m=2.0)
#: Scanners for ``--laser`` (datasheet-like geometry, range and noise).
LASERS: dict[str, LaserModel] = {
    "sick_lms200": LaserModel(),  # what the simulated scenarios use: 180°, 1°, 20 m, 1 cm
    "sick_lms200_3cm": LaserModel(range_sigma_m=0.03),  # the same with 3 cm range noise
    "hokuyo_utm30": LaserModel(n_beams=1081, fov_deg=270.0, range_max_m=30.0),
    "hokuyo_urg04": LaserModel(n_beams=683, fov_deg=240.0, range_max_m=5.6, range_sigma_m=0.02),
    "lds_360": LaserModel(n_beams=361, fov_deg=360.0, range_max_m=8.0, range_sigma_m=0.02),
    # the default scanner with 5 % of its beams returning nothing, in runs of 3 (dark patches)
    "sick_lms200_dropouts": LaserModel(dropout_fraction=0.05, dropout_run_beams=3),
    # a 360° lidar among four posts on the robot (its own body in every scan)
    "lds_360_posts": LaserModel(
        n_beams=361,
        fov_deg=360.0,
        range_max_m=8.0,
        range_sigma_m=0.02,
        body_posts_deg=(45.0, 135.0, -135.0, -45.0),
    ),
}

#: Scanner degradations of the real logs for ``--degrade`` (the same building and reference,
#: another scanner; :mod:`frontends.simulate.degraded_scans`).
DEGRADATIONS: dict[str, ScannerDegradation] = {
    "half_rate": ScannerDegradation(every_nth=2),
    "third_rate": ScannerDegradation(every_nth=3),
    # a scanner that reaches 8 m but declares the log's maximum (as many drivers overstate it)
    "reach_8m": ScannerDegradation(reach_m=8.0),
    "reach_8m_declared": ScannerDegradation(reach_m=8.0, declare_reach=True),
    "reach_5.6m_declared": ScannerDegradation(reach_m=5.6, declare_reach=True),
    "fov_120": ScannerDegradation(fov_deg=120.0),
    "noise_2cm": ScannerDegradation(range_sigma_m=0.02),
    "dropouts": ScannerDegradation(dropout_fraction=0.05, dropout_run_beams=3),
}


class CaseSkipped(Exception):
    """A case's input is absent (real logs outside the repository)."""


@dataclass(frozen=True)
class CaseInput:
    """What a case feeds the pipeline and scores against.

    Attributes:
        scans: Laser scans in time order (their ``odom_pose`` is the odometry used).
        reference: ``(N, 3)`` true / reference robot pose per scan, or ``None``.
        relations: Benchmark relations, or ``None``.
        description: One line about the case.
    """

    scans: list[LaserScan]
    reference: FloatArray | None
    relations: Relations | None
    description: str


def _shared(relative: str) -> Path:
    path = DATA / relative
    if not path.exists():
        raise CaseSkipped(f"{path} is absent")
    return path


def _sim_case(scenario: str) -> Callable[..., CaseInput]:
    def build(seed: int, laser: LaserModel | None = None) -> CaseInput:
        run = simulate_scenario(scenario, seed, laser)
        return CaseInput(run.scans, run.true_poses, None, SCENARIOS[scenario].description)

    return build


def _csail_raw(drift: bool, laser_only: bool = False) -> Callable[[int], CaseInput]:
    def build(seed: int) -> CaseInput:
        scans = list(open_log(_shared("mit-csail/mit-csail.clf"), laser_only=laser_only))
        rel = read_relations(_shared("mit-csail/mit-csail.relations"))
        if laser_only:
            return CaseInput(scans, None, rel, "MIT CSAIL without its odometry (laser only)")
        if drift:
            scans = synthetic_odometry(scans, SYNTH_DRIFT_ONLY, seed).scans
            return CaseInput(scans, None, rel, "MIT CSAIL raw odometry + 0.4 deg/m heading drift")
        return CaseInput(scans, None, rel, "MIT CSAIL, raw odometry")

    return build


def _corrected(
    relative: str, restamp_hz: float | None, model: OdometryModel = SYNTH_BIASED
) -> Callable[[int], CaseInput]:
    """A corrected log (``relative`` under the shared data) with synthetic odometry of
    ``model`` (seeded), scored against its corrected poses."""

    def build(seed: int) -> CaseInput:
        scans = list(open_log(_shared(relative)))
        synth = synthetic_odometry(scans, model, seed, restamp_hz)
        desc = (
            f"{Path(relative).name} + synthetic odometry "
            f"({100 * model.translation_scale_bias:.0f} %, "
            f"{math.degrees(model.rotation_bias_rad_per_m):.1f} deg/m, "
            f"{'noise' if model.translation_sigma_per_m > 0 else 'no noise'})"
        )
        return CaseInput(synth.scans, np.array(synth.reference_poses), None, desc)

    return build


#: The RC car bag: laser only, scored against the motion capture's ``map -> ego_pose`` in
#: ``/tf`` (read as the bag's odometry, then dropped); the laser is not linked in tf (the
#: recording's launch file put it 0.12 m behind ``ego_pose``).
RC_CAR_BAG = "rosbag/rc-car-mocap-ros1/overtakes.bag"
RC_CAR_READER: dict[str, Any] = {
    "odom_frame": "map",
    "base_frame": "ego_pose",
    "laser_frame_offset": [-0.12, 0.0, 0.0],
    "outside_odometry": "drop",
}


def _rc_car(seed: int) -> CaseInput:
    scans = list(open_log(_shared(RC_CAR_BAG), **RC_CAR_READER))
    reference = np.array([s.odom_pose for s in scans], dtype=np.float64)
    scans = [s.without_odometry() for s in scans]
    return CaseInput(scans, reference, None, "RC car, 360° lidar, no odometry, mocap truth")


#: Real bags with their own odometry and no reference (their rows: the scan-match fraction
#: and the odometry time offset the run measures), by case name: path and reader options.
BAGS: dict[str, tuple[str, dict[str, Any], str]] = {
    "turtlebot4": ("rosbag/turtlebot4-ros2", {}, "TurtleBot 4, 360° RPLIDAR mounted at 90°"),
    "neato": (
        "rosbag/neato-ros1/neato-obstacle-avoid.bag",
        {"scan_topic": "/scan"},
        "Neato, 360° lidar, 33 % valid beams",
    ),
}


def _bag(name: str) -> Callable[[int], CaseInput]:
    def build(seed: int) -> CaseInput:
        relative, options, description = BAGS[name]
        return CaseInput(list(open_log(_shared(relative), **options)), None, None, description)

    return build


#: Benchmark cases by name.
CASES: dict[str, Callable[..., CaseInput]] = {
    **{name: _sim_case(name) for name in SCENARIOS},
    "csail_raw": _csail_raw(drift=False),
    "csail_raw_drift": _csail_raw(drift=True),
    "csail_raw_laser_only": _csail_raw(drift=False, laser_only=True),
    "aces_synth": _corrected("aces/aces-corrected.log.gz", None),
    "csail_log_synth": _corrected("mit-csail/csail.log", None),
    # csail-corrected prints its stamps as 1.13486e+09 (2 distinct values): re-stamp at 1 Hz.
    "csail_corrected_synth": _corrected("mit-csail/csail-corrected.log.gz", 1.0),
    "aces_strong_drift": _corrected("aces/aces-corrected.log.gz", None, SYNTH_STRONG_DRIFT),
    "rc_car_mocap": _rc_car,
    **{name: _bag(name) for name in BAGS},
}


# ---------------------------------------------------------------------------- metrics


def _path_length(poses: FloatArray) -> float:
    return float(np.hypot(*np.diff(poses[:, :2], axis=0).T).sum())


def _scan_match_fraction(result: SlamResult) -> float:
    """Fraction of the nodes after the first that end a scan-match factor."""
    n_nodes = int(result.node_ids.shape[0])
    matched = {f.j for f in result.factors if f.kind == FactorKind.SCAN_MATCH}
    return len(matched) / (n_nodes - 1) if n_nodes > 1 else math.nan


def _odom_or_nan(scan: LaserScan) -> FloatArray:
    return np.full(3, np.nan) if scan.odom_pose is None else np.asarray(scan.odom_pose)


def _reference_metrics(
    result: SlamResult,
    scans: Sequence[LaserScan],
    odom: FloatArray,
    online: FloatArray,
    ref: FloatArray,
) -> dict[str, Any]:
    nodes = result.node_scan_index
    ref_len = _path_length(ref[nodes])
    closures = check_loop_closures(result, ref, lambda k: extract(scans[k], result.config.features))
    return {
        "online_max_m": float(np.hypot(*(online[:, :2] - ref[:, :2]).T).max()),
        "ate_m": position_errors(result.poses, ref).rmse_m,
        "end_m": float(np.hypot(*(result.poses[-1, :2] - ref[-1, :2]))),
        "odom_ate_m": position_errors(odom, ref).rmse_m if np.isfinite(odom).all() else math.nan,
        "odom_end_m": float(np.hypot(*(odom[-1, :2] - ref[-1, :2]))),
        "length_ratio": _path_length(result.node_poses) / ref_len if ref_len > 0 else math.nan,
        "lc_false": closures.n_false,
        "lc_disputed": closures.n_disputed,
    }


def _relation_metrics(result: SlamResult, odom: FloatArray, rel: Relations) -> dict[str, Any]:
    est, _ = relation_errors(
        result.stamps_s, result.poses, rel.stamps_s, rel.deltas, RELATION_TOLERANCE_S
    )
    raw, _ = relation_errors(result.stamps_s, odom, rel.stamps_s, rel.deltas, RELATION_TOLERANCE_S)
    return {
        "rel_trans_m": est.trans_mean_m,
        "rel_rot_deg": est.rot_mean_deg,
        "rel_matched": est.n_matched,
        "odom_rel_trans_m": raw.trans_mean_m,
        "odom_rel_rot_deg": raw.rot_mean_deg,
    }


# ---------------------------------------------------------------------------- one case


def run_case(
    name: str,
    quick: bool = False,
    seed: int = 0,
    maps_dir: Path | None = None,
    config: IcegConfig | None = None,
    laser: str | None = None,
    degrade: str | None = None,
) -> dict[str, Any]:
    """Run one benchmark case with the default pipeline and return its row.

    Args:
        name: A key of :data:`CASES`.
        quick: Only the first :data:`QUICK_SCANS` scans.
        seed: Seed of the simulation / synthetic odometry noise.
        maps_dir: If given, the run's output files (``map.png``, ``trajectory.tum``, ...)
            are saved in ``maps_dir / name``.
        config: The configuration (``None``: the default, which is what the benchmark
            measures; another one is for experiments).
        laser: A key of :data:`LASERS`: a simulated scenario is driven with that scanner
            (other cases ignore it).
        degrade: A key of :data:`DEGRADATIONS`: a real log's scans are degraded so (with
            ``seed``; its reference and relations score the scans kept; the simulated
            scenarios ignore it).

    Returns:
        A JSON-ready dict: ``name``, ``description``, ``scans``, ``nodes``, ``seconds``,
        ``lc_accepted``, ``sm_per_kf`` and, where a reference exists, ``ate_m`` (RMSE after
        SE(2) alignment), ``end_m``, ``online_max_m``, ``odom_ate_m``, ``odom_end_m``,
        ``length_ratio``, ``lc_false``, ``lc_disputed``; with relations ``rel_trans_m``,
        ``rel_rot_deg``, ``odom_rel_trans_m``, ``odom_rel_rot_deg``; with odometry
        ``odom_time_offset_s`` (the measured offset where significant, else None),
        ``odom_time_offset_best_s`` and ``odom_time_offset_p``. A case whose input is absent returns
        ``{"name", "skipped": reason}``.

    Raises:
        KeyError: unknown case name.
    """
    try:
        if laser is not None and name in SCENARIOS:
            case = CASES[name](seed, LASERS[laser])
        else:
            case = CASES[name](seed)
    except CaseSkipped as exc:
        return {"name": name, "skipped": str(exc)}
    if degrade is not None and name not in SCENARIOS:
        kept, degraded = degrade_scans(case.scans, DEGRADATIONS[degrade], seed)
        reference = None if case.reference is None else case.reference[kept]
        case = replace(case, scans=degraded, reference=reference)
    n = min(len(case.scans), QUICK_SCANS) if quick else len(case.scans)
    scans = case.scans[:n]
    t0 = time.perf_counter()
    measured = measure_scanner(config or IcegConfig(), ScanStore(scans))  # as iceg run does
    run_config = measured.config
    slam = Slam(run_config)
    online = np.array([slam.process(scan) for scan in scans], dtype=np.float64)
    result = slam.finish()
    seconds = time.perf_counter() - t0
    odom = np.array([_odom_or_nan(s) for s in scans], dtype=np.float64)
    row: dict[str, Any] = {
        "name": name,
        "description": case.description,
        "scans": n,
        "nodes": int(result.node_ids.shape[0]),
        "seconds": seconds,
        "lc_accepted": int(result.loop_closures.accepted),
        "sm_per_kf": _scan_match_fraction(result),
        "body_m": run_config.features.robot_body_range_m,
        "dropout_patches_per_1000": (
            None if measured.dropouts is None else measured.dropouts.patches_per_1000
        ),
        "dropout_gap_m": run_config.features.eow_dropout_max_gap_m,
    }
    timing = odometry_time_offset(result)
    if timing is not None:
        row["odom_time_offset_best_s"] = timing.offset_s
        row["odom_time_offset_p"] = timing.p_value
        row["odom_time_offset_s"] = timing.offset_s if timing.significant else None
    if case.reference is not None:
        row |= _reference_metrics(result, scans, odom, online, case.reference[:n])
    if case.relations is not None:
        row |= _relation_metrics(result, odom, case.relations)
    if maps_dir is not None:
        result.save(maps_dir / name)
    return row


# ---------------------------------------------------------------------------- table

_COLUMNS: tuple[tuple[str, str, str], ...] = (
    ("scans", "scans", "{:d}"),
    ("nodes", "nodes", "{:d}"),
    ("rel_trans_m", "rel m", "{:.4f}"),
    ("rel_rot_deg", "rel deg", "{:.3f}"),
    ("odom_rel_trans_m", "odo rel m", "{:.3f}"),
    ("ate_m", "ATE m", "{:.3f}"),
    ("end_m", "end m", "{:.3f}"),
    ("online_max_m", "online max", "{:.3f}"),
    ("odom_ate_m", "odo ATE", "{:.3f}"),
    ("odom_end_m", "odo end", "{:.3f}"),
    ("length_ratio", "len ratio", "{:.4f}"),
    ("sm_per_kf", "sm/kf", "{:.3f}"),
    ("odom_time_offset_s", "odo dt s", "{:+.2f}"),
    ("lc_accepted", "LC acc", "{:d}"),
    ("lc_false", "LC false", "{:d}"),
    ("lc_disputed", "LC disp", "{:d}"),
    ("body_m", "body m", "{:.2f}"),
    ("dropout_patches_per_1000", "drops/k", "{:.1f}"),
    ("dropout_gap_m", "drop gap", "{:.1f}"),
    ("seconds", "time s", "{:.1f}"),
)


def format_table(rows: Sequence[dict[str, Any]]) -> str:
    """The rows as a fixed-width text table ("-": not applicable)."""
    header = ["case", *(c[1] for c in _COLUMNS)]
    lines = [header]
    for row in rows:
        if "skipped" in row:
            lines.append([row["name"], f"skipped: {row['skipped']}"])
            continue
        cells = [row["name"]]
        for key, _, fmt in _COLUMNS:
            v = row.get(key)
            cells.append("-" if v is None else fmt.format(v))
        lines.append(cells)
    widths = [max(len(r[i]) for r in lines if len(r) > i) for i in range(len(header))]
    out = []
    for r in lines:
        if len(r) == 2 and r[1].startswith("skipped"):
            out.append(f"{r[0]:<{widths[0]}}  {r[1]}")
        else:
            out.append(
                "  ".join(
                    c.rjust(w) if i else c.ljust(w)
                    for i, (c, w) in enumerate(zip(r, widths, strict=True))
                )
            )
    return "\n".join(out)


# ---------------------------------------------------------------------------- batch spec

#: Synthetic odometry of the corrected logs and of CSAIL's added drift, as spec entries.
_SPEC_BIASED = {"scale_error": 0.01, "heading_drift_deg_per_m": 0.4, "noise": True}
_SPEC_DRIFT_ONLY = {"scale_error": 0.0, "heading_drift_deg_per_m": 0.4, "noise": False}
_SPEC_STRONG_DRIFT = {"scale_error": 0.01, "heading_drift_deg_per_m": 2.0, "noise": True}


def _spec_log(name: str) -> dict[str, Any]:
    """The batch-spec log entry of case ``name`` (same input as :data:`CASES`)."""
    if name in SCENARIOS:
        return {"name": name, "path": f"sim:{name}"}
    csail = {"path": str(DATA / "mit-csail/mit-csail.clf")}
    rel = {"relations": str(DATA / "mit-csail/mit-csail.relations")}
    corrected = {
        "aces_synth": ("aces/aces-corrected.log.gz", None),
        "csail_log_synth": ("mit-csail/csail.log", None),
        "csail_corrected_synth": ("mit-csail/csail-corrected.log.gz", 1.0),
    }
    if name in BAGS:
        relative, options, _ = BAGS[name]
        return {"name": name, "path": str(DATA / relative), "reader_options": options}
    if name == "rc_car_mocap":
        return {
            "name": name,
            "path": str(DATA / RC_CAR_BAG),
            "reader_options": RC_CAR_READER,
            "reference": "log_odometry",
            "laser_only": True,
        }
    if name == "csail_raw":
        return {"name": name, **csail, **rel}
    if name == "csail_raw_drift":
        return {"name": name, **csail, **rel, "synthetic_odometry": _SPEC_DRIFT_ONLY}
    if name == "csail_raw_laser_only":
        return {"name": name, **csail, **rel, "laser_only": True}
    if name == "aces_strong_drift":
        relative, restamp, odometry = "aces/aces-corrected.log.gz", None, _SPEC_STRONG_DRIFT
    else:
        (relative, restamp), odometry = corrected[name], _SPEC_BIASED
    return {
        "name": name,
        "path": str(DATA / relative),
        "reference": "log_odometry",
        "synthetic_odometry": {**odometry, "restamp_hz": restamp},
    }


def batch_spec(
    names: Sequence[str] | None = None,
    quick: bool = False,
    seeds: Sequence[int] = (0,),
    variants: dict[str, dict[str, Any]] | None = None,
) -> dict[str, Any]:
    """The benchmark as one ``iceg batch`` spec (a dict; :func:`iceg.batch.spec_from_dict`):
    every case of :data:`CASES` (or ``names``) with the default configuration, ``quick``:
    the first :data:`QUICK_SCANS` scans. ``variants``: named configurations (nested, as in a
    config YAML) run beside the default (named ``default``). An absent real log is a failed
    run in the table."""
    logs = [_spec_log(n) for n in (names or list(CASES))]
    if quick:
        logs = [{**entry, "max_scans": QUICK_SCANS} for entry in logs]
    spec: dict[str, Any] = {
        "name": "accuracy",
        "logs": logs,
        "seeds": list(seeds),
        "outputs": "metrics",
    }
    if variants:
        spec["variants"] = {"default": {}} | {n: dotted(c) for n, c in variants.items()}
    return spec


def dotted(nested: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """A nested configuration mapping as the dotted-key overrides of a batch variant
    (``{"a": {"b": 1}}`` -> ``{"a.b": 1}``): each leaf set, the rest of its section kept."""
    out: dict[str, Any] = {}
    for key, value in nested.items():
        if isinstance(value, dict) and value:
            out |= dotted(value, f"{prefix}{key}.")
        else:
            out[f"{prefix}{key}"] = value
    return out


def parse_seeds(tokens: Sequence[str]) -> list[int]:
    """``--seeds`` tokens as seeds: ``N`` or an inclusive range ``A-B``.

    Raises:
        ValueError: a token that is neither.
    """
    seeds: list[int] = []
    for token in tokens:
        first, sep, last = token.partition("-")
        seeds += list(range(int(first), int(last) + 1)) if sep else [int(token)]
    return seeds


def _variant(text: str) -> tuple[str, dict[str, Any]]:
    """``--variant NAME=YAML``: the name and the YAML file's mapping."""
    import yaml

    name, sep, path = text.partition("=")
    if not sep or not name or not path:
        raise argparse.ArgumentTypeError(f"--variant takes NAME=YAML, not {text!r}")
    try:
        data = yaml.safe_load(Path(path).read_text(encoding="utf-8"))
    except (OSError, yaml.YAMLError) as exc:
        raise argparse.ArgumentTypeError(f"--variant {name}: cannot read {path} ({exc})") from exc
    if not isinstance(data, dict):
        raise argparse.ArgumentTypeError(f"--variant {name}: {path} is not a mapping")
    return name, data


def _run_as_batch(args: argparse.Namespace, seeds: list[int]) -> int:
    """``--batch`` / ``--write-spec``: the benchmark through ``iceg.batch``."""
    import yaml

    from iceg.batch import run_batch, spec_from_dict

    data = batch_spec(args.only, quick=args.quick, seeds=seeds, variants=dict(args.variant or []))
    if args.write_spec is not None:
        args.write_spec.write_text(yaml.safe_dump(data, sort_keys=False), encoding="utf-8")
    if args.batch is None:
        return 0
    report = run_batch(
        spec_from_dict(data, "bench_accuracy"),
        args.batch,
        executor="local" if args.local else "ray",
        workers=args.workers,
    )
    sys.stdout.write(report.markdown.read_text(encoding="utf-8"))
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--only", action="append", choices=sorted(CASES), help="case (repeatable)")
    ap.add_argument("--quick", action="store_true", help=f"first {QUICK_SCANS} scans per case")
    ap.add_argument("--json", type=Path, help="also write the rows as JSON here")
    ap.add_argument(
        "--maps", type=Path, help="save each run's files in MAPS/<case> (MAPS/s<seed>/<case>)"
    )
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--config", type=Path, help="a config YAML instead of the default")
    ap.add_argument("--laser", choices=sorted(LASERS), help="scanner of the simulated scenarios")
    ap.add_argument(
        "--degrade", choices=sorted(DEGRADATIONS), help="scanner degradation of the real logs"
    )
    ap.add_argument("--batch", type=Path, help="run the cases as one iceg batch in BATCH")
    ap.add_argument("--local", action="store_true", help="--batch on a process pool, not Ray")
    ap.add_argument("--workers", type=int, help="--batch: parallel runs")
    ap.add_argument("--write-spec", type=Path, help="write the batch spec (YAML) here")
    ap.add_argument("--seeds", nargs="+", help="seeds, N or A-B (instead of --seed)")
    ap.add_argument(
        "--variant",
        action="append",
        type=_variant,
        help="--batch: NAME=YAML, a configuration run beside the default (repeatable)",
    )
    args = ap.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds) if args.seeds else [args.seed]
    except ValueError:
        ap.error(f"--seeds takes N or A-B, not {' '.join(args.seeds)!r}")
    if args.batch is not None or args.write_spec is not None:
        if args.laser is not None or args.degrade is not None:
            ap.error(
                "--laser and --degrade run in this process only (not with --batch / --write-spec)"
            )
        return _run_as_batch(args, seeds)
    if args.variant:
        ap.error("--variant goes with --batch or --write-spec (here: --config)")
    config = config_from_yaml(args.config) if args.config is not None else None
    rows = []
    for seed in seeds:
        for name in args.only or list(CASES):
            if seed != seeds[0] and not is_random(name, args.degrade):
                continue  # the same run again
            row = run_case(
                name,
                quick=args.quick,
                seed=seed,
                maps_dir=(
                    args.maps if args.maps is None or len(seeds) == 1 else args.maps / f"s{seed}"
                ),
                config=config,
                laser=args.laser,
                degrade=args.degrade,
            )
            rows.append(row | {"seed": seed})
            sys.stderr.write(f"done {name} (seed {seed})\n")
        mine = [r for r in rows if r["seed"] == seed]
        sys.stdout.write((f"seed {seed}\n" if len(seeds) > 1 else "") + format_table(mine) + "\n")
    if len(seeds) > 1:
        variant = "default" if args.config is None else args.config.stem
        sys.stdout.write("\nover the seeds (mean / median / worst)\n" + over_seeds(rows, variant))
    if args.json is not None:
        args.json.write_text(json.dumps(rows, indent=2) + "\n")
    return 0


def is_random(name: str, degrade: str | None = None) -> bool:
    """Whether case ``name`` (with the scanner degradation ``degrade``) depends on the seed:
    its batch log does (:attr:`iceg.batch.LogEntry.is_random`: a simulation, synthetic
    odometry with noise), or the degradation adds range noise or dropouts."""
    from iceg.batch import LogEntry

    if LogEntry.model_validate(_spec_log(name)).is_random:
        return True
    d = DEGRADATIONS.get(degrade or "")
    return d is not None and (d.range_sigma_m > 0 or d.dropout_fraction > 0)


def over_seeds(rows: Sequence[dict[str, Any]], variant: str = "default") -> str:
    """The rows of :func:`run_case` over several seeds (of the configuration ``variant``)
    as one table line per case (:func:`iceg.batch_report.seed_table`: mean / median / worst
    error, false closures summed; a skipped case is a failed run)."""
    runs = [
        {
            "log": r["name"],
            "variant": variant,
            "status": "skipped" if "skipped" in r else "ok",
            "metrics": r,
        }
        for r in rows
    ]
    return seed_table(runs)


if __name__ == "__main__":
    raise SystemExit(main())
