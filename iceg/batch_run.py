"""One run of a batch (:mod:`iceg.batch`): a pure function of (log, config, seed).

:func:`execute_run` loads the log (a file, or a simulated scenario ``sim:NAME``), optionally
replaces its odometry with synthetic drifting odometry, runs :class:`iceg.slam.Slam`, scores
the result (relations, reference trajectory) and writes the run's own folder:
``run.json`` (the row: status, metrics, error, seconds) and, with ``outputs="full"``, the
usual result files in ``output/``. Any exception, a bad log or the time budget running out
is caught and recorded as the run's status: one run never stops a batch.
"""

from __future__ import annotations

import json
import math
import shutil
import time
import traceback
import warnings
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import NDArray

from frontends import LaserScan, open_log
from frontends.odometry_shift import shift_odometry
from frontends.registry import adjust_scan
from frontends.relations import Relations, match_stamps, read_relations
from frontends.simulate import OdometryModel, simulate_scenario, synthetic_odometry
from frontends.tum import read_tum
from graph import FactorKind, FactorRecord
from iceg.config import IcegConfig, config_from_dict
from iceg.consistency import FactorNees, factor_nees, per_node
from iceg.evaluation import position_errors, relation_errors
from iceg.features import extract
from iceg.log_checks import check_returns, reading_adjustments, warn_sparse_stamps
from iceg.matching.config import MatchBounds
from iceg.matching.peers import make_matcher
from iceg.odometry_calibration import systematic_errors
from iceg.odometry_timing import odometry_time_offset, offset_to_read
from iceg.pipeline import AUTO_OFFSET, check_log_file, measure_scanner, relation_nees
from iceg.results import SlamResult
from iceg.scan_store import ScanStore
from iceg.session import record_reading
from iceg.slam import Slam
from iceg.types import ScanFeatures
from iceg_common import se2
from iceg_common.atomic import atomic_write
from iceg_common.errors import IcegError, LogFormatError

FloatArray = NDArray[np.float64]

#: Prefix of a log entry that names a simulated scenario (``sim:office``).
SIM_PREFIX = "sim:"
#: Reference keyword: the log's own odometry poses (before synthetic odometry replaced them).
LOG_ODOMETRY = "log_odometry"
#: Timestamp tolerance (s) for relations and reference trajectories.
STAMP_TOLERANCE_S = 1e-3
#: A loop closure is false if its measurement is off the reference by more than this.
FALSE_LC_TRANS_M = 0.3
FALSE_LC_ROT_DEG = 3.0
#: Longest error message kept in a row.
MAX_ERROR_CHARS = 300
#: The row file of a run folder.
ROW_FILE = "run.json"

Status = Literal["ok", "failed", "timeout"]


class RunTimeout(IcegError):
    """A run went beyond its time budget."""


@dataclass(frozen=True)
class SyntheticOdometrySpec:
    """Drifting odometry replacing a log's own (``frontends.simulate.synthetic_odometry``)."""

    scale_error: float = 0.01
    heading_drift_deg_per_m: float = 0.4
    noise: bool = True
    restamp_hz: float | None = None


@dataclass(frozen=True)
class RunTask:
    """Everything one run needs (picklable; paths absolute).

    Attributes:
        run_id: Unique, file-name-safe id (``log__variant[__sSEED]``).
        key: Digest of the inputs; a finished run is reused only when its key matches.
        log_name, variant, seed: The row's identity (``seed`` None: nothing random).
        source: ``sim:NAME`` or a log file path.
        config: Nested configuration overrides (validated by :func:`config_from_dict`).
        folder: The run's folder.
        relations: ``.relations`` file, or None.
        reference: TUM reference trajectory, :data:`LOG_ODOMETRY`, or None.
        max_scans: Use only the first scans.
        odometry: Synthetic odometry replacing the log's, or None.
        reader_options: Keyword options of :func:`frontends.open_log`.
        laser_only: Drop the log's odometry (after a :data:`LOG_ODOMETRY` reference is
            taken from it).
        odometry_time_offset_s: Read each scan's odometry at its stamp plus this
            (:func:`~frontends.odometry_shift.shift_odometry`; 0: as logged); ``"auto"``:
            at the offset measured before the run where significant (:func:`load_input`).
        timeout_s: Time budget of the run (checked after every scan), or None.
        outputs: ``"full"`` (result files in ``output/``) or ``"metrics"`` (``run.json`` only).
    """

    run_id: str
    key: str
    log_name: str
    variant: str
    seed: int | None
    source: str
    config: dict[str, Any]
    folder: str
    relations: str | None = None
    reference: str | None = None
    max_scans: int | None = None
    odometry: SyntheticOdometrySpec | None = None
    reader_options: dict[str, Any] = field(default_factory=dict)
    laser_only: bool = False
    odometry_time_offset_s: float | Literal["auto"] = 0.0
    timeout_s: float | None = None
    outputs: Literal["full", "metrics"] = "full"


@dataclass
class _Input:
    scans: list[LaserScan]
    reference: FloatArray | None = None  # (N, 3) per scan, NaN rows where unknown
    relations: Relations | None = None
    offset_s: float = 0.0  # the odometry time offset the scans' odometry is read at
    adjusted: dict[str, Any] = field(default_factory=dict)  # log_checks.reading_adjustments


# ---------------------------------------------------------------------------- input


def load_input(task: RunTask) -> _Input:
    """Scans, reference and relations of a task; a log read as its scans say
    (:func:`~iceg.log_checks.reading_adjustments`, where the run reads the log's own
    odometry: ``adjusted``); with the odometry time offset ``"auto"``, the log's odometry
    read at the offset measured before the run where significant (``offset_s``).

    Raises:
        IcegError: unknown scenario, unreadable log or relations, no scans.
    """
    seed = 0 if task.seed is None else task.seed
    if task.source.startswith(SIM_PREFIX):
        run = simulate_scenario(task.source[len(SIM_PREFIX) :], seed)
        scans: Iterable[LaserScan] = run.scans
        reference = np.asarray(run.true_poses, dtype=np.float64)
    else:
        check_log_file(Path(task.source))  # a file, or a ROS 2 bag folder
        scans, reference = open_log(task.source, **task.reader_options), None
    scans = list(scans)[: task.max_scans]
    if reference is not None:
        reference = reference[: task.max_scans]
    if not scans:
        raise LogFormatError(f"{task.source}: the log holds no laser scans")
    check_returns(task.source, scans)
    warn_sparse_stamps(task.source, [s.stamp_s for s in scans])
    config = config_from_dict(task.config, source=f"batch variant {task.variant!r}")
    reads_odometry = task.odometry is None and not task.laser_only  # the log's own
    adjusted = reading_adjustments(task.source, scans, config).options if reads_odometry else {}
    if adjusted.get("mirror_beams"):
        scans = [s.mirrored() for s in scans]
    offset = task.odometry_time_offset_s
    if adjusted.get("laser_only"):
        offset = 0.0  # no motion to read at an offset
    elif isinstance(offset, str):  # "auto": measured on the scans the run uses, at the stamps
        offset = _measured_offset(config, scans)
    data = _Input(list(shift_odometry(scans, offset)), reference, None, offset, adjusted)
    if task.odometry is not None:
        o = task.odometry
        model = OdometryModel.biased(o.scale_error, o.heading_drift_deg_per_m, noise=o.noise)
        synth = synthetic_odometry(data.scans, model, seed, o.restamp_hz)
        data.scans = list(synth.scans)
        if task.reference == LOG_ODOMETRY:
            data.reference = np.asarray(synth.reference_poses, dtype=np.float64)
    elif task.reference == LOG_ODOMETRY:
        data.reference = np.array([s.odom_pose for s in data.scans], dtype=np.float64)
    if task.laser_only or adjusted.get("laser_only"):
        data.scans = [s.without_odometry() for s in data.scans]
    elif adjusted.get("odometry_stalls_s"):
        stalls = adjusted["odometry_stalls_s"]
        data.scans = [adjust_scan(s, odometry_stalls_s=stalls) for s in data.scans]
    if task.reference not in (None, LOG_ODOMETRY):
        data.reference = _tum_reference(task.reference, data.scans)
    if task.relations is not None:
        data.relations = read_relations(_existing(task.relations))
    return data


def _measured_offset(config: IcegConfig, scans: list[LaserScan]) -> float:
    """The odometry time offset ``"auto"`` reads ``scans`` at (odometry at their stamps):
    :func:`~iceg.odometry_timing.offset_to_read` with the task's configuration and the
    scanner measured (:func:`~iceg.pipeline.measure_scanner`), as
    :func:`iceg.pipeline.run_log` does."""
    return offset_to_read(scans, measure_scanner(config, ScanStore(scans)).config)[0]


def _existing(path: str) -> Path:
    p = Path(path)
    if not p.is_file():
        raise LogFormatError(f"{p}: no such file")
    return p


def _tum_reference(path: str, scans: list[LaserScan]) -> FloatArray:
    """``(N, 3)`` reference pose per scan from a TUM file (NaN where no stamp matches)."""
    stamps, poses = read_tum(_existing(path))
    idx, ok = match_stamps(np.array([s.stamp_s for s in scans]), stamps, STAMP_TOLERANCE_S)
    out = np.full((len(scans), 3), np.nan)
    out[ok] = poses[idx[ok]]
    return out


# ---------------------------------------------------------------------------- running


def run_slam(task: RunTask, scans: list[LaserScan], t0: float) -> tuple[SlamResult, FloatArray]:
    """The SLAM run, with the scanner measured first (the robot's own body along the
    odometry, the returns lost on walls: :func:`~iceg.pipeline.measure_scanner`, as
    :func:`iceg.pipeline.run_log` does);
    the online pose of every scan. Raises :class:`RunTimeout` once the budget is spent
    (checked after every scan)."""
    config = config_from_dict(task.config, source=f"batch variant {task.variant!r}")
    slam = Slam(measure_scanner(config, ScanStore(scans)).config)
    online = []
    for k, scan in enumerate(scans):
        online.append(slam.process(scan))
        if task.timeout_s is not None and time.perf_counter() - t0 > task.timeout_s:
            raise RunTimeout(f"time budget of {task.timeout_s:g} s spent after {k + 1} scans")
    return slam.finish(), np.array(online, dtype=np.float64)


def execute_run(task: RunTask) -> dict[str, Any]:
    """Run one task and write its folder; never raises for a failing run. With the
    odometry time offset ``"auto"`` the row's metrics hold the offset the odometry was read
    at (``odom_time_offset_applied_s``, measured before the run by :func:`load_input`).

    Returns:
        The row (also in ``folder/run.json``): ``run_id``, ``key``, ``log``, ``variant``,
        ``seed``, ``status`` (``ok``, ``failed``, ``timeout``), ``error`` (one line),
        ``metrics`` (see :func:`run_metrics`) and ``seconds`` (wall time).
    """
    t0 = time.perf_counter()
    folder = Path(task.folder)
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True, exist_ok=True)
    status: Status = "ok"
    error = ""
    metrics: dict[str, Any] = {}
    try:
        data = load_input(task)
        result, online = run_slam(task, data.scans, t0)
        if result.slam is not None and not task.source.startswith(SIM_PREFIX):
            # how its session reads the log again (scans changed after reading: stored)
            changed = task.odometry is not None or task.laser_only or bool(data.adjusted)
            record_reading(result.slam, task.source, task.reader_options, data.offset_s, changed)
        metrics = run_metrics(result, data, online)
        if task.odometry_time_offset_s == AUTO_OFFSET:
            metrics["odom_time_offset_applied_s"] = data.offset_s
        if task.outputs == "full":
            result.save(folder / "output")
    except RunTimeout as exc:
        status, error = "timeout", str(exc)
    except Exception as exc:  # a failing run is a row, never the end of the batch
        status, error = "failed", _one_line(exc)
    row = {
        "run_id": task.run_id,
        "key": task.key,
        "log": task.log_name,
        "variant": task.variant,
        "seed": task.seed,
        "status": status,
        "error": error,
        "metrics": metrics,
        "seconds": time.perf_counter() - t0,
        "task": asdict(task),
    }
    with atomic_write(folder / ROW_FILE) as fh:
        json.dump(row, fh, indent=2, default=_json_default)
        fh.write("\n")
    return row


def _one_line(exc: BaseException) -> str:
    text = " ".join(str(exc).split()) or traceback.format_exception_only(type(exc), exc)[-1]
    msg = f"{type(exc).__name__}: {text}"
    return msg if len(msg) <= MAX_ERROR_CHARS else msg[: MAX_ERROR_CHARS - 3] + "..."


def _json_default(obj: Any) -> Any:
    if isinstance(obj, np.generic):
        return obj.item()
    raise TypeError(f"not JSON serialisable: {type(obj).__name__}")


def read_row(folder: Path) -> dict[str, Any] | None:
    """The row of a finished run folder, or None (absent or unreadable)."""
    try:
        row = json.loads((folder / ROW_FILE).read_text(encoding="utf-8"))
    except (OSError, ValueError):
        return None
    return row if isinstance(row, dict) else None


# ---------------------------------------------------------------------------- metrics


def run_metrics(result: SlamResult, data: _Input, online: FloatArray) -> dict[str, Any]:
    """Figures of a run: ``scans``, ``nodes``, ``sm_per_kf`` (keyframes with a scan-match
    factor), ``match_failures`` (failed local matches), ``lc_accepted``; with relations
    ``rel_trans_m``, ``rel_rot_deg``, ``rel_matched`` (Kümmerle et al. 2009); with a
    reference ``ate_m`` (RMSE after SE(2) alignment), ``end_m``, ``online_max_m``,
    ``odom_ate_m``, ``lc_false`` and ``lc_disputed`` (:func:`check_loop_closures`); with
    odometry the time offset its matches show
    (:func:`~iceg.odometry_timing.odometry_time_offset`): ``odom_time_offset_s`` where
    significant (else NaN), the best fit ``odom_time_offset_best_s`` and its
    ``odom_time_offset_p``; ``robot_body_range_m``, the range left out as the robot's own
    body; ``sm_nees`` and ``odo_nees`` (:func:`_nees_medians`); the odometry's systematic
    errors (:func:`_odometry_errors`); how the log's own checks had it read
    (:func:`~iceg.log_checks.reading_adjustments`): ``beams_mirrored`` (1: mirrored, else 0)
    and ``scans_without_odometry`` (all of them where its odometry is not the robot's, those
    where it held while they moved, else 0)."""
    n_nodes = int(result.node_ids.shape[0])
    matched = {f.j for f in result.factors if f.kind == FactorKind.SCAN_MATCH}
    out: dict[str, Any] = {
        "scans": result.n_scans,
        "nodes": n_nodes,
        "sm_per_kf": len(matched) / (n_nodes - 1) if n_nodes > 1 else math.nan,
        "match_failures": int(sum(result.match_failures.values())),
        "lc_accepted": int(result.loop_closures.accepted),
        "robot_body_range_m": result.config.features.robot_body_range_m,
    }
    timing = odometry_time_offset(result)
    if timing is not None:
        out |= {
            "odom_time_offset_s": timing.offset_s if timing.significant else math.nan,
            "odom_time_offset_best_s": timing.offset_s,
            "odom_time_offset_p": timing.p_value,
        }
    if data.relations is not None:
        rel = data.relations
        est, _ = relation_errors(
            result.stamps_s, result.poses, rel.stamps_s, rel.deltas, STAMP_TOLERANCE_S
        )
        out |= {
            "rel_trans_m": est.trans_mean_m,
            "rel_rot_deg": est.rot_mean_deg,
            "rel_matched": est.n_matched,
        }
    if data.reference is not None:
        with warnings.catch_warnings():  # a straight trajectory aligns poorly: not an error
            warnings.simplefilter("ignore", UserWarning)
            out |= _reference_metrics(result, data, online)
    out |= _nees_medians(result, data)
    out |= _odometry_errors(result)
    adjusted, stalls = data.adjusted, data.adjusted.get("odometry_stalls_s", ())
    out["beams_mirrored"] = int(bool(adjusted.get("mirror_beams")))
    out["scans_without_odometry"] = (
        len(data.scans)
        if adjusted.get("laser_only")
        else sum(any(a <= scan.stamp_s <= b for a, b in stalls) for scan in data.scans)
    )
    return out


def _odometry_errors(result: SlamResult) -> dict[str, float]:
    """``odom_scale_error``, ``odom_turn_scale_error`` (fractions) and
    ``odom_heading_drift_deg_per_m``: the odometry's systematic errors as the run's matches
    measure them (:func:`~iceg.odometry_calibration.systematic_errors`), and
    ``odom_corrected`` (1 where the run was correcting them at its end, else 0); none without
    a matched keyframe step with odometry."""
    if result.slam is None or not result.slam.odometry_calibrator.n_observations:
        return {}
    calibrator = result.slam.odometry_calibrator
    errors = systematic_errors(calibrator, result.config.odometry_noise)
    return {
        "odom_scale_error": errors["distance_scale_error"].value,
        "odom_turn_scale_error": errors["turn_scale_error"].value,
        "odom_heading_drift_deg_per_m": errors["heading_drift_deg_per_m"].value,
        "odom_corrected": int(calibrator.correcting),
    }


def _nees_medians(result: SlamResult, data: _Input) -> dict[str, float]:
    """``sm_nees`` and ``odo_nees``: the median NEES of the scan-match and odometry factors
    (:mod:`iceg.consistency`; 2.37 for honest covariances) against the reference, else the
    relations (where one joins two node scans); none without either."""
    nees: FactorNees | None = None
    if data.reference is not None:
        truth = per_node(result.node_ids, result.node_scan_index, data.reference)
        nees = factor_nees(result.factors, truth)
    elif data.relations is not None:
        nees = relation_nees(result, data.relations)
    if nees is None:
        return {}
    out = {}
    for kind, key in ((FactorKind.SCAN_MATCH, "sm_nees"), (FactorKind.ODOMETRY, "odo_nees")):
        values = nees.nees[nees.kind == kind.value]
        if values.size:
            out[key] = float(np.median(values))
    return out


def _reference_metrics(result: SlamResult, data: _Input, online: FloatArray) -> dict[str, Any]:
    ref = data.reference
    assert ref is not None
    ok = np.all(np.isfinite(ref), axis=1)
    odom = np.array([s.odom_pose for s in data.scans], dtype=np.float64)
    out: dict[str, Any] = {
        "ate_m": position_errors(result.poses[ok], ref[ok]).rmse_m,
        "end_m": float(np.hypot(*(result.poses[ok][-1, :2] - ref[ok][-1, :2]))),
        "online_max_m": float(np.hypot(*(online[ok, :2] - ref[ok, :2]).T).max()),
    }
    closures = check_loop_closures(
        result, ref, lambda k: extract(data.scans[k], result.config.features)
    )
    out |= {"lc_false": closures.n_false, "lc_disputed": closures.n_disputed}
    if np.all(np.isfinite(odom)):
        out["odom_ate_m"] = position_errors(odom[ok], ref[ok]).rmse_m
    return out


@dataclass(frozen=True)
class ClosureCheck:
    """Accepted loop closures judged against a reference trajectory
    (:func:`check_loop_closures`).

    Attributes:
        n_false: Closures off the reference relative pose of their two scans by more than
            :data:`FALSE_LC_TRANS_M` or :data:`FALSE_LC_ROT_DEG` that the scans do not
            dispute.
        n_disputed: Closures as far off whose two scans dispute the reference: matched
            again from the reference's relative pose, they land on the closure. A reference
            made by another SLAM run (a "corrected" log) is wrong there, not the closure.
    """

    n_false: int
    n_disputed: int


def check_loop_closures(
    result: SlamResult,
    reference: FloatArray,
    scan_features: Callable[[int], ScanFeatures] | None = None,
) -> ClosureCheck:
    """Judge the accepted loop closures against the reference relative pose of their two
    scans. A closure off it by more than :data:`FALSE_LC_TRANS_M` or
    :data:`FALSE_LC_ROT_DEG` is false, unless the scans dispute the reference: the run's
    matcher, predicting the later scan at the reference's relative pose within the run's
    local-match bounds (``slam.match_max_translation_m``, ``slam.match_max_rotation_deg``),
    lands within those thresholds of the closure. A wrong closure is not disputed so: from
    the true relative pose the scans match there, and a look-alike metres away is outside
    the bounds. A corrected log's own error can be (csail-corrected's scan 399 lies about
    10° off where its scan aligns with its neighbours'; docs/design.md, "Closures against a
    corrected log").

    Args:
        result: A finished run (its loop-closure factors, the scan of each node and, with
            ``scan_features``, its ``config``).
        reference: ``(S, 3)`` float64 reference pose ``[x_m, y_m, theta_rad]`` of each of
            the run's scans, map frame; a closure with a non-finite end is not counted.
        scan_features: The features of a scan by its index, extracted as the run extracted
            them; ``None`` disputes nothing.

    Returns:
        A :class:`ClosureCheck`.

    Raises:
        ConfigError: the run's matching method's library is not installed.
    """
    scan_of = dict(zip(result.node_ids.tolist(), result.node_scan_index.tolist(), strict=True))
    n_false = n_disputed = 0
    for f in result.factors:
        if f.kind != FactorKind.LOOP_CLOSURE or f.j is None:
            continue
        si, sj = scan_of[f.i], scan_of[f.j]
        a, b = reference[si], reference[sj]
        if not (np.all(np.isfinite(a)) and np.all(np.isfinite(b))):
            continue
        truth = se2.between(a, b)
        if _within_false_limits(truth, f.measured):
            continue
        if scan_features is not None and _scans_dispute(result, scan_features, si, sj, truth, f):
            n_disputed += 1
        else:
            n_false += 1
    return ClosureCheck(n_false, n_disputed)


def _within_false_limits(pose: FloatArray, other: FloatArray) -> bool:
    """Whether two relative poses differ by at most :data:`FALSE_LC_TRANS_M` and
    :data:`FALSE_LC_ROT_DEG`."""
    err = se2.between(pose, other)
    return bool(
        math.hypot(err[0], err[1]) <= FALSE_LC_TRANS_M
        and abs(math.degrees(err[2])) <= FALSE_LC_ROT_DEG
    )


def _scans_dispute(
    result: SlamResult,
    scan_features: Callable[[int], ScanFeatures],
    si: int,
    sj: int,
    truth: FloatArray,
    closure: FactorRecord,
) -> bool:
    """Whether scan ``sj`` matched against scan ``si`` from the reference's relative pose
    ``truth`` lands on the ``closure``'s measurement (:func:`check_loop_closures`)."""
    slam = result.config.slam
    bounds = MatchBounds.local(slam.match_max_translation_m, slam.match_max_rotation_deg)
    match = make_matcher(result.config.matching).match(
        scan_features(sj), scan_features(si), truth, bounds
    )
    return bool(match.success and _within_false_limits(match.pose, closure.measured))
