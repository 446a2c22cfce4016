"""Whole runs: a log file (or the built-in simulated world) through :class:`iceg.slam.Slam`
to an evaluated :class:`iceg.results.SlamResult`. Used by the CLI and by notebooks.
"""

from __future__ import annotations

import contextlib
import gc
import logging
import os
import stat
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import asdict
from pathlib import Path
from typing import Any, Literal, NamedTuple, TypeVar

import numpy as np

from frontends import LaserScan, open_log
from frontends.odometry_shift import shift_odometry
from frontends.registry import adjust_scan, folder_reader
from frontends.relations import Relations, match_stamps, read_relations
from frontends.scan import StampPolicy, StampReport
from iceg.aside import Superseded, compute_aside, while_caller_runs
from iceg.config import IcegConfig
from iceg.consistency import FactorNees, factor_nees, per_node, relation_factor_nees
from iceg.evaluation import position_errors, relation_errors
from iceg.features.prefetch import WORKER_NICENESS, FeaturePrefetcher, auto_workers
from iceg.kernel_warmup import cache_is_new, probed
from iceg.log_checks import Reading, check_returns, reading_adjustments, warn_sparse_stamps
from iceg.match_pool import MatchPool
from iceg.odometry_calibration import systematic_errors
from iceg.odometry_timing import TimeOffsetEstimate, odometry_time_offset, offset_to_read
from iceg.results import SlamResult
from iceg.robot_body import (
    BIN_DEG,
    RobotBodyEstimate,
    leaving_out,
    robot_body_range,
    with_measured_body,
)
from iceg.scan_products import ScanPrecompute
from iceg.scan_store import ScanStore
from iceg.slam import Slam
from iceg.wall_dropouts import WallDropouts, with_measured_dropouts
from iceg_common.errors import ConfigError, EvaluationError, LogFormatError

logger = logging.getLogger(__name__)

T = TypeVar("T")

#: Timestamp tolerance for matching relation stamps to scans (relations carry 5 decimals).
RELATION_TOLERANCE_S = 1e-3
#: ``run_log``'s odometry time offset measured before the run (``--odometry-time-offset auto``).
AUTO_OFFSET = "auto"
#: A run beside its log's checks looks whether they have arrived every this many scans.
CHECKS_POLL_SCANS = 8


def run_scans(
    scans: Iterable[LaserScan],
    config: IcegConfig | None = None,
    progress: bool = False,
    total: int | None = None,
) -> SlamResult:
    """Run SLAM over scans in order and return the finished result.

    With ``config.slam.workers`` > 1 (0: :func:`~iceg.features.prefetch.auto_workers`) the
    features of upcoming scans, and what the run derives from them alone
    (:mod:`iceg.scan_products`), are computed in worker processes
    (:class:`~iceg.features.prefetch.FeaturePrefetcher`), and the loop-closure searches'
    candidate matches run in a helper process (:class:`~iceg.match_pool.MatchPool`) while
    the next keyframe is tracked; the result is the same.

    Raises:
        LogFormatError: there are no scans.
    """
    slam = Slam(config)
    with helper_processes(slam) as prefetch:
        return _process(slam, prefetch, scans, progress, total)


def _process(
    slam: Slam,
    prefetch: FeaturePrefetcher,
    scans: Iterable[LaserScan],
    progress: bool,
    total: int | None,
) -> SlamResult:
    """Every scan through ``slam`` (features from ``prefetch``), then its finished result.

    Raises:
        LogFormatError: there are no scans.
    """
    if progress:
        from tqdm.auto import tqdm  # lazy: tqdm.auto imports asyncio (a cold-start cost)

        scans = tqdm(scans, total=total, unit="scan", desc="iceg")
    n = 0
    for scan, features in prefetch.scans(scans):
        slam.process(scan, features=features)
        n += 1
    if n == 0:
        raise LogFormatError("the input holds no laser scans")
    return slam.finish()


@contextlib.contextmanager
def helper_processes(slam: Slam, workers: int | None = None) -> Iterator[FeaturePrefetcher]:
    """The helper processes of a run of ``slam`` with ``workers`` processes in all (1: none;
    None: ``slam.workers`` of its configuration, 0 there meaning
    :func:`~iceg.features.prefetch.auto_workers`): the feature workers, which also compute
    the scans' pose-independent products (:class:`~iceg.scan_products.ScanPrecompute`), and
    the loop closer's match helper
    (:class:`~iceg.match_pool.MatchPool`). Yields the prefetcher whose ``scans`` feed
    ``slam.process``; the helpers stop when the block ends. Where numba's cache is new
    (:func:`~iceg.kernel_warmup.cache_is_new`, logged as a warning), the first feature worker
    compiles the later stages' kernels while this process compiles the first ones."""
    if workers is None:
        workers = _processes(slam.config)
    precompute = ScanPrecompute(slam.config)
    new_cache = cache_is_new()
    if new_cache:
        logger.warning(
            "numba's cache holds no compiled kernels of this version yet: this run compiles "
            "them as it first calls them (one to three minutes); later runs load them"
        )
    with (
        _frozen_heap(),
        MatchPool(slam.matcher, helper=workers > 1) as pool,
        FeaturePrefetcher(
            slam.config.features, workers, precompute=precompute, warm_up_later=new_cache
        ) as prefetch,
    ):
        slam.loop_closer.match_pool = pool
        try:
            yield prefetch
        finally:
            slam.loop_closer.match_pool = None


@contextlib.contextmanager
def _started(slam: Slam, make_input: Callable[[], T]) -> Iterator[tuple[T, FeaturePrefetcher]]:
    """The run's input (``make_input()``: the scans and what comes with them) and its
    helpers (:func:`helper_processes`). Where this process has yet to load numba's registry
    (its first run), the input is made meanwhile in a forked process
    (:func:`~iceg.aside.compute_aside`); the run's processes are counted before that
    process keeps a core busy (:func:`~iceg.features.prefetch.auto_workers` watches them)."""
    workers = _processes(slam.config)
    with (
        compute_aside(make_input, fork=not probed()) as aside,
        helper_processes(slam, workers) as prefetch,
    ):
        yield aside.result(), prefetch


@contextlib.contextmanager
def _frozen_heap() -> Iterator[None]:
    """The objects alive at the start of a run (modules, numba's typing registry: about
    150 000 on a CARMEN log, against about 15 000 the run adds) kept out of the cyclic
    garbage collector's passes until it ends (``gc.freeze``, then ``gc.unfreeze``), and out
    of the forked helpers' passes, so that a full collection walks the run's objects only
    and a helper's collections do not write into the pages it shares with this process
    (the use the ``gc`` module's documentation gives). Nothing is left uncollected: a
    cycle that was garbage before the run is freed after it. Where the caller has
    frozen objects itself (``gc.get_freeze_count()``), its freeze is left alone."""
    if gc.get_freeze_count():
        yield
        return
    gc.freeze()
    try:
        yield
    finally:
        gc.unfreeze()


def _simulated(seed: int) -> tuple[ScanStore, np.ndarray, np.ndarray]:
    """The office world's run (:func:`frontends.simulate.simulate`): its scans in a store,
    the ``(N, 3)`` true and odometry poses."""
    from frontends.simulate import office_world, simulate

    run = simulate(office_world(), seed=seed)
    return ScanStore(run.scans), run.true_poses, run.odom_poses


def check_relations_match(relations: Relations, stamps_s: np.ndarray) -> None:
    """Fail fast when relations do not belong to the log.

    Raises:
        EvaluationError: no relation has both timestamps within tolerance of a scan.
    """
    _, ok1 = match_stamps(relations.stamps_s[:, 0], stamps_s, RELATION_TOLERANCE_S)
    _, ok2 = match_stamps(relations.stamps_s[:, 1], stamps_s, RELATION_TOLERANCE_S)
    if not np.any(ok1 & ok2):
        raise EvaluationError(
            f"{relations.source}: none of its {len(relations.stamps_s)} relations matches a scan "
            f"timestamp of the log within {RELATION_TOLERANCE_S} s; are they for this log?"
        )


def run_log(
    path: str | Path,
    config: IcegConfig | None = None,
    relations: str | Path | None = None,
    progress: bool = False,
    stamps: StampPolicy = "sort",
    reader_options: Mapping[str, Any] | None = None,
    odometry_time_offset_s: float | Literal["auto"] = 0.0,
) -> SlamResult:
    """Run SLAM over a log file and, if given, score it with a ``.relations`` file.

    The log file is checked before anything runs; its timestamps are ordered by ``stamps``
    (``"sort"``: reorder out-of-order scans, ``"refuse"``: fail at the first one, naming
    ``file:line``); the policy and what the reader found (out-of-order and duplicate stamps,
    odometry breaks) are in ``result.metrics["stamps"]``. ``reader_options`` go to
    :func:`frontends.open_log` (e.g. ``scan_topic`` for ROS bags); a log whose odometry is one
    pose throughout, or turns where its walls do not, is read without it, as ``laser_only``
    reads it, and one whose walls turn against its odometry with its beams mirrored, as
    ``mirror_beams`` reads it (:func:`~iceg.log_checks.reading_adjustments`, recorded so for
    its session). Each scan's odometry is read at its stamp plus ``odometry_time_offset_s``
    (:func:`~frontends.odometry_shift.shift_odometry`);
    ``result.metrics["odometry_time_offset"]`` holds that value and the offset the run's
    matches measure (:func:`~iceg.odometry_timing.odometry_time_offset`), warned when
    significant. With ``"auto"`` (:data:`AUTO_OFFSET`) the offset is measured before the
    run, each scan matched against the one before it
    (:func:`~iceg.odometry_timing.scan_pairs_time_offset`), and where significant the
    odometry is read there (docs/design.md "Readers", the latency); the metrics then also
    hold that measurement (``before_run``). Before the first scan, the robot's own body is
    measured along the odometry and left out (``features.measure_robot_body``:
    :func:`~iceg.robot_body.with_measured_body`, warned); ``result.metrics["robot_body"]``
    holds the range left out and what the scans show of the body along the odometry and
    along the trajectory (:func:`~iceg.robot_body.robot_body_range`), with a warning when
    the latter finds a body the former did not, beyond the range. Then how often the scanner
    loses its return on a wall is measured, and where often, a patch on a wall is read as a
    dropout, not as two ends of wall (``features.measure_wall_dropouts``:
    :func:`~iceg.wall_dropouts.with_measured_dropouts`, warned);
    ``result.metrics["wall_dropouts"]`` holds the measurement (None: not measured).

    A run of two or more processes (``slam.workers``) without ``"auto"`` starts at once and
    makes these checks and measurements in a forked process beside it; where they change
    the reading or the configuration, it starts again with them (:func:`_run_beside_checks`).
    Either way the result is the run made after them, bit for bit.

    Raises:
        LogFormatError: missing, unreadable or empty log, no return in it
            (:func:`~iceg.log_checks.check_returns`), disordered timestamps under
            ``"refuse"``, malformed relations.
        EvaluationError: the relations match no scan of the log.
        ConfigError: a non-finite ``odometry_time_offset_s``, a string other than
            ``"auto"``, or an offset with ``reader_options`` ``laser_only``.
    """
    _check_offset(odometry_time_offset_s, reader_options)
    check_log_file(Path(path))
    reader = open_log(path, stamps=stamps, **(reader_options or {}))
    rel = read_relations(relations) if relations is not None else None
    slam = Slam(config)
    result: SlamResult | None = None
    given_s = 0.0 if isinstance(odometry_time_offset_s, str) else odometry_time_offset_s
    with _started(slam, lambda: _read(path, reader, given_s)) as ((read, report), prefetch):
        _check_read(path, read, rel)
        fresh = odometry_time_offset_s == AUTO_OFFSET or prefetch.workers < 2  # waits for them
        if fresh:
            (measured, reading), result = _reading_checks(path, read, slam.config), None
        else:  # the checks beside the run, which goes on as if they change nothing
            (measured, reading), result = _run_beside_checks(path, slam, prefetch, read, progress)
        scans, measured, applied_s, offset_measured = _as_checked(
            path, (read, reading), slam.config, measured, odometry_time_offset_s
        )
        run_config = measured.config
        if run_config != slam.config:
            _warn_measured(path, slam.config, measured)
        elif fresh:
            result = _process(slam, prefetch, scans, progress, len(scans))
    if result is None:  # the helpers (and a run beside the checks) had what the checks changed
        slam = Slam(run_config)
        with helper_processes(slam) as prefetch:
            result = _process(slam, prefetch, scans, progress, len(scans))
    _note_reading(result, path, (reader_options, reading), applied_s, offset_measured)
    _log_metrics(result, path, (report, stamps), scans, measured, rel)
    return result


def _check_read(path: str | Path, scans: ScanStore, rel: Relations | None) -> None:
    """Fail before the run on a log without a return
    (:func:`~iceg.log_checks.check_returns`) or relations for another log
    (:func:`check_relations_match`); warn where its stamps do not look like seconds
    (:func:`~iceg.log_checks.warn_sparse_stamps`)."""
    check_returns(path, scans)
    stamps = scans.stamps_s  # a copy: read once
    warn_sparse_stamps(path, stamps)
    if rel is not None:
        check_relations_match(rel, stamps)


def _as_checked(
    path: str | Path,
    read: tuple[ScanStore, Reading],
    config: IcegConfig,
    measured: MeasuredScanner,
    offset_s: float | Literal["auto"],
) -> tuple[ScanStore, MeasuredScanner, float, tuple[bool, TimeOffsetEstimate | None]]:
    """The scans of ``read`` = ``(store, the checks' reading)`` read as the checks say, with
    ``offset_s`` applied (``"auto"``: measured, :func:`_at_measured_offset`; a log read
    without its odometry, ``laser_only``, has none to offset); the scanner ``measured`` along
    them, the offset applied (s) and, for the metrics, ``(auto, the measurement)``."""
    store, reading = read
    scans = _as_read(store, reading)
    if reading.options.get("laser_only"):  # as --laser-only reads it: no odometry to offset
        return scans, measured, 0.0, (False, None)
    if not isinstance(offset_s, str):  # a string is "auto" (checked before the run)
        return scans, measured, offset_s, (False, None)
    scans, measured, applied_s, before_run = _at_measured_offset(path, scans, config, measured)
    return scans, measured, applied_s, (True, before_run)


def _note_reading(
    result: SlamResult,
    path: str | Path,
    read: tuple[Mapping[str, Any] | None, Reading],
    applied_s: float,
    measured_before: tuple[bool, TimeOffsetEstimate | None],
) -> None:
    """How a log run read its log (``read`` = ``(reader options, the checks' reading)``):
    in its session (to read the log again the same way: the options with the reading's
    added), in ``result.metrics["odometry_check"]``
    (:meth:`~iceg.odometry_check.OdometryCheck.as_dict`, None without one),
    ``result.metrics["odometry_stalls"]`` (the runs read without their held odometry,
    :meth:`~iceg.odometry_stalls.OdometryStall.as_dict` each) and
    ``result.metrics["odometry_time_offset"]`` (the offset applied, and with ``"auto"`` the
    measurement before the run, ``measured_before`` = ``(auto, measurement)``)."""
    reader_options, reading = read
    if reading.options:
        reader_options = {**(reader_options or {}), **reading.options}
    check = reading.check
    result.metrics["odometry_check"] = None if check is None else check.as_dict()
    result.metrics["odometry_stalls"] = [stall.as_dict() for stall in reading.stalls]
    if result.slam is not None:
        from iceg.session import record_reading  # 23 ms of imports a run without a session skips

        record_reading(result.slam, path, reader_options, applied_s)
    result.metrics["odometry_time_offset"] = _time_offset_metrics(path, applied_s, result)
    auto, before_run = measured_before
    if auto:
        result.metrics["odometry_time_offset"]["before_run"] = _as_dict(before_run)


def _log_metrics(
    result: SlamResult,
    path: str | Path,
    stamps: tuple[StampReport | None, StampPolicy],
    scans: ScanStore,
    measured: MeasuredScanner,
    rel: Relations | None,
) -> None:
    """A log run's metrics on its input: the stamps' report (or policy), the robot's body
    (:func:`_robot_body_metrics`), the odometry's systematic errors
    (:func:`_calibration_metrics`), the wall dropouts and, with ``rel``, the relation error."""
    report, policy = stamps
    result.metrics["stamps"] = report.as_dict() if report is not None else {"policy": policy}
    result.metrics["robot_body"] = _robot_body_metrics(path, scans, result, measured.body)
    result.metrics["odometry_calibration"] = _calibration_metrics(path, result)
    dropouts = measured.dropouts
    result.metrics["wall_dropouts"] = None if dropouts is None else dropouts.as_dict()
    if rel is not None:
        score_against_relations(result, rel)


def score_against_relations(result: SlamResult, rel: Relations) -> None:
    """Score a run with benchmark relations into its ``metrics``: ``relations``, the relation
    error (:func:`iceg.evaluation.relation_errors`, Kümmerle et al. 2009), and
    ``factor_nees``, the NEES of the factors whose two nodes are a relation's two scans per
    factor kind (:func:`iceg.consistency.relation_factor_nees`; None where no relation joins
    two node scans).

    Raises:
        EvaluationError: no relation matches the run's stamps.
    """
    summary, _ = relation_errors(
        result.stamps_s, result.poses, rel.stamps_s, rel.deltas, RELATION_TOLERANCE_S
    )
    result.metrics["relations"] = summary.as_dict()
    nees = relation_nees(result, rel)
    result.metrics["factor_nees"] = None if nees is None else _nees_metrics(nees)


def relation_nees(result: SlamResult, rel: Relations) -> FactorNees | None:
    """The NEES of a run's factors whose two nodes are a relation's two scans
    (:func:`iceg.consistency.relation_factor_nees`), or None where no relation joins two
    node scans (relations between scans far apart)."""
    stamps = per_node(result.node_ids, result.node_scan_index, result.stamps_s)
    try:
        return relation_factor_nees(result.factors, stamps, rel, RELATION_TOLERANCE_S)
    except EvaluationError:
        return None


def _nees_metrics(nees: FactorNees) -> dict[str, dict[str, float]]:
    """``metrics.json`` ``factor_nees``: each factor kind's :class:`~iceg.consistency.NeesSummary`
    as a dict."""
    return {kind: asdict(summary) for kind, summary in nees.summary().items()}


class MeasuredScanner(NamedTuple):
    """A run's configuration with what its scans show of the scanner applied, and those
    measurements (None: not measured).

    Attributes:
        config: The configuration the run uses.
        body: The robot's own body (:func:`~iceg.robot_body.with_measured_body`).
        dropouts: The returns lost on walls (:func:`~iceg.wall_dropouts.with_measured_dropouts`).
    """

    config: IcegConfig
    body: RobotBodyEstimate | None
    dropouts: WallDropouts | None


def measure_scanner(config: IcegConfig, scans: ScanStore) -> MeasuredScanner:
    """``config`` with the robot's body the scans show along their odometry left out, then
    with a patch on a wall read as a dropout where the scanner loses returns on walls often
    and at random (the second measurement reads the beams as the first leaves them);
    ``config`` itself (the same object) where neither changes anything or there is no scan.
    Numpy and one compiled kernel (the features' step 1)."""
    if not len(scans):
        return MeasuredScanner(config, None, None)
    config, body = with_measured_body(config, scans)
    config, dropouts = with_measured_dropouts(config, scans)
    return MeasuredScanner(config, body, dropouts)


def _warn_measured(path: str | Path, config: IcegConfig, measured: MeasuredScanner) -> None:
    """Say what the measurements changed in ``config``, the run's configuration before them."""
    before, after = config.features, measured.config.features
    body = (before.robot_body_range_m, before.robot_body_dark_deg)
    if measured.body is not None and body != (after.robot_body_range_m, after.robot_body_dark_deg):
        logger.warning(
            "%s: %s; they are left out (%s; features.measure_robot_body: false keeps them)",
            path,
            _body_seen(measured.body),
            _body_settings(measured.config),
        )
    dropout_gap_m = after.eow_dropout_max_gap_m
    if measured.dropouts is not None and before.eow_dropout_max_gap_m != dropout_gap_m:
        logger.warning(
            "%s: the scanner loses its return on walls (%.1f patches per 1000 returns over %d "
            "scans): a patch the wall spans is read as a dropout, not as two ends of wall "
            "(features.eow_dropout_max_gap_m: %g; features.measure_wall_dropouts: false keeps "
            "it 0)",
            path,
            measured.dropouts.patches_per_1000,
            measured.dropouts.scans,
            dropout_gap_m,
        )


def _at_measured_offset(
    path: str | Path,
    scans: ScanStore,
    config: IcegConfig,
    measured: MeasuredScanner,
) -> tuple[ScanStore, MeasuredScanner, float, TimeOffsetEstimate | None]:
    """``"auto"``: the scans (read at their stamps) with their odometry read at the offset
    :func:`~iceg.odometry_timing.offset_to_read` measures, and ``config`` with the scanner
    measured along it (``measured`` where the offset is 0: the scans are unchanged); the
    offset applied and the measurement."""
    applied_s, before_run = _offset_to_read(path, scans, measured.config)
    if not applied_s:
        return scans, measured, applied_s, before_run
    shifted = ScanStore(shift_odometry(scans, applied_s))
    return shifted, measure_scanner(config, shifted), applied_s, before_run


def _as_dict(estimate: TimeOffsetEstimate | None) -> dict[str, Any] | None:
    """An offset measurement's JSON-ready fields (None: none)."""
    return None if estimate is None else estimate.as_dict()


def _read(
    path: str | Path, reader: Iterable[LaserScan], offset_s: float
) -> tuple[ScanStore, StampReport | None]:
    """The log at ``path`` (``reader``, not yet iterated) in a store, compact (no LaserScan
    object per scan held during the run), each scan's odometry read at its stamp plus
    ``offset_s``; and the reader's stamp report (out-of-order and duplicate stamps, odometry
    breaks; None for a reader without one). No compiled kernel runs here (it runs in the
    forked process of :func:`_started`, beside the loading of numba's registry).

    Raises:
        LogFormatError: the log holds no scan.
    """
    store = ScanStore(shift_odometry(while_caller_runs(reader), offset_s))
    if not len(store):
        raise LogFormatError(f"{path}: the log holds no laser scans")
    report = getattr(reader, "stamp_report", None)
    return store, report if isinstance(report, StampReport) else None


def _reading_checks(
    path: str | Path, store: ScanStore, config: IcegConfig
) -> tuple[MeasuredScanner, Reading]:
    """How the log's scans must be read (:func:`~iceg.log_checks.reading_adjustments`:
    without an odometry that carries no motion or turns where the walls do not, with beams
    that turn against the odometry mirrored, without it where it holds while they move),
    and ``config`` with what the scans so read show of the scanner (:func:`measure_scanner`).
    """
    reading = reading_adjustments(path, store, config)
    return measure_scanner(config, _as_read(store, reading)), reading


def _as_read(store: ScanStore, reading: Reading) -> ScanStore:
    """The scans of ``store`` read as ``reading`` says (``store`` itself where it says
    nothing)."""
    if not reading.options:
        return store
    return ScanStore(adjust_scan(scan, **reading.options) for scan in store)


def _run_beside_checks(
    path: str | Path,
    slam: Slam,
    prefetch: FeaturePrefetcher,
    store: ScanStore,
    progress: bool,
) -> tuple[tuple[MeasuredScanner, Reading], SlamResult | None]:
    """The log's checks (:func:`_reading_checks`) in a forked process, at the helpers'
    niceness, while ``slam`` runs over ``store`` as if they change nothing: its result where
    they do not, None where they change the reading or the configuration (the run stopped at
    its first look after they arrived, every :data:`CHECKS_POLL_SCANS` scans, and at the
    latest before ``finish``: :meth:`~iceg.aside.Aside.until`). Where they change nothing,
    the run is the one that would have started after them, bit for bit; where they do, the
    caller runs again with what they found, as it would have from the start. The checks'
    warnings are logged here as they arrive."""

    def changes(checks: tuple[MeasuredScanner, Reading]) -> bool:
        measured, reading = checks
        return bool(reading.options) or measured.config != slam.config

    with compute_aside(
        lambda: _reading_checks(path, store, slam.config), niceness=WORKER_NICENESS
    ) as checks:
        scans = checks.until(store, changes, CHECKS_POLL_SCANS)
        try:
            result: SlamResult | None = _process(slam, prefetch, scans, progress, len(store))
        except Superseded:
            logger.info("%s: the checks read the log otherwise; the run starts again", path)
            result = None
        return checks.result(), result


def read_log_scans(
    path: str | Path,
    config: IcegConfig,
    stamps: StampPolicy = "sort",
    reader_options: Mapping[str, Any] | None = None,
    odometry_time_offset_s: float | Literal["auto"] = 0.0,
) -> tuple[list[LaserScan], dict[str, Any], dict[str, Any]]:
    """A log's scans, each one's odometry read at its stamp plus ``odometry_time_offset_s``
    (``"auto"``: :func:`~iceg.odometry_timing.offset_to_read` with ``config``, as
    :func:`run_log` measures it), read as the scans say (:func:`~iceg.log_checks.
    reading_adjustments`: without an odometry that carries no motion or turns where the
    walls do not, with beams that turn against it mirrored), for the runs that take a list of
    scans (a session's continuation, a localization).

    Returns:
        The scans; the offset's record for ``metrics.json``: ``applied_s`` and, with
        ``"auto"``, ``before_run`` (the measurement's fields, None without one); and the
        reader options as the log was read (``laser_only`` or ``mirror_beams`` added where
        the scans said so), for its session to read it again.

    Raises:
        LogFormatError: missing or unreadable log, or one without a single return
            (:func:`~iceg.log_checks.check_returns`).
        ConfigError: a non-finite offset, a string other than ``"auto"``, or an offset
            with ``reader_options`` ``laser_only``.
    """
    _check_offset(odometry_time_offset_s, reader_options)
    check_log_file(Path(path))
    scans = list(open_log(path, stamps=stamps, **(reader_options or {})))
    check_returns(path, scans)
    warn_sparse_stamps(path, [s.stamp_s for s in scans])
    adjusted = reading_adjustments(path, scans, config).options
    options = {**(reader_options or {}), **adjusted}
    scans = [adjust_scan(s, **adjusted) for s in scans] if adjusted else scans
    if adjusted.get("laser_only"):
        return scans, {"applied_s": 0.0}, options
    record: dict[str, Any] = {}
    applied_s = odometry_time_offset_s
    if isinstance(applied_s, str):
        applied_s, before_run = _offset_to_read(path, scans, config)
        record["before_run"] = _as_dict(before_run)
    record["applied_s"] = applied_s
    return list(shift_odometry(scans, applied_s)), record, options


def _check_offset(
    odometry_time_offset_s: float | str, reader_options: Mapping[str, Any] | None
) -> None:
    """Seconds or ``"auto"`` (the seconds are checked where they are applied), and 0 for a
    laser-only reading (``reader_options`` ``laser_only: True``), which has no odometry to
    read at an offset.

    Raises:
        ConfigError: another string, or an offset with a laser-only reading.
    """
    if isinstance(odometry_time_offset_s, str) and odometry_time_offset_s != AUTO_OFFSET:
        raise ConfigError(
            f"odometry_time_offset_s: seconds or {AUTO_OFFSET!r}, not {odometry_time_offset_s!r}"
        )
    if (reader_options or {}).get("laser_only") and odometry_time_offset_s != 0.0:
        raise ConfigError(
            f"odometry_time_offset_s {odometry_time_offset_s!r} reads the log's odometry: "
            "not with a laser-only reading (laser_only; --laser-only)"
        )


def _processes(config: IcegConfig) -> int:
    """Processes a run of ``config`` uses (``slam.workers``, 0: :func:`auto_workers`)."""
    return config.slam.workers or auto_workers()


def _offset_to_read(
    path: str | Path, scans: Sequence[LaserScan], config: IcegConfig
) -> tuple[float, TimeOffsetEstimate | None]:
    """:func:`~iceg.odometry_timing.offset_to_read` of a log's scans with ``config`` (its
    workers), the user told where the odometry is read at a significant offset."""
    applied_s, before_run = offset_to_read(scans, config, _processes(config))
    if before_run is None or not before_run.significant:
        return applied_s, before_run
    logger.warning(
        "%s: consecutive scans turn as the odometry does %+.2f s from their stamps (mean "
        "heading error per step %.2f -> %.2f deg over %d steps): the odometry is read there "
        "(--odometry-time-offset auto)",
        path,
        before_run.offset_s,
        before_run.heading_error_at_zero_deg,
        before_run.heading_error_at_offset_deg,
        before_run.steps,
    )
    return applied_s, before_run


def _time_offset_metrics(path: str | Path, applied_s: float, result: SlamResult) -> dict[str, Any]:
    """The applied odometry time offset and the one the run measures (warned when
    significant: the odometry and the scans disagree on when the robot turned; the offset
    named is from the stamps, the applied one included)."""
    measured = odometry_time_offset(result)
    if measured is not None and measured.significant:
        logger.warning(
            "%s: the scans' rotations match the odometry %+.2f s from their stamps (mean "
            "heading error per step %.2f -> %.2f deg over %d steps); to read it there, "
            "pass --odometry-time-offset %.2f%s",
            path,
            applied_s + measured.offset_s,
            measured.heading_error_at_zero_deg,
            measured.heading_error_at_offset_deg,
            measured.steps,
            applied_s + measured.offset_s,
            "" if applied_s else " (or auto: measured from consecutive scans before the run)",
        )
    return {
        "applied_s": applied_s,
        "measured": None if measured is None else measured.as_dict(),
    }


def _robot_body_metrics(
    path: str | Path, scans: ScanStore, result: SlamResult, on_odometry: RobotBodyEstimate | None
) -> dict[str, Any]:
    """The range left out as the robot's own body, what the scans show of it along the
    odometry (``on_odometry``, measured before the run; None: not measured, or too few turns
    to tell) and along the run's trajectory. Warned when the trajectory shows a body that
    the configuration leaves in and the odometry showed none (its turns are other scans,
    whose farthest body return may differ by a centimetre)."""
    on_trajectory = robot_body_range(scans, result.poses)
    applied = result.config.features
    odometry_found = on_odometry is not None and (
        on_odometry.range_m is not None or bool(on_odometry.dark_deg)
    )
    suggested = leaving_out(result.config, on_trajectory)
    if on_trajectory is not None and suggested is not result.config and not odometry_found:
        logger.warning(
            "%s: %s; to leave them out, set %s",
            path,
            _body_seen(on_trajectory),
            _body_settings(suggested),
        )
    return {
        "range_m": applied.robot_body_range_m,
        "dark_deg": applied.robot_body_dark_deg,
        "on_odometry": None if on_odometry is None else on_odometry.as_dict(),
        "on_trajectory": None if on_trajectory is None else on_trajectory.as_dict(),
    }


#: How a warning names each systematic error of the odometry, and the format of its unit.
_SYSTEMATIC_ERRORS = {
    "distance_scale_error": ("distance scale error", "{:+.1%}", "{:.1%}", "{:.0%} per metre"),
    "turn_scale_error": ("turn scale error", "{:+.1%}", "{:.1%}", "{:.0%} of a turn"),
    "heading_drift_deg_per_m": ("heading drift", "{:+.2f}", "{:.2f} deg/m", "{:.2f} deg/m"),
}


def _calibration_metrics(path: str | Path, result: SlamResult) -> dict[str, Any] | None:
    """The odometry's systematic errors as the run's matches measure them
    (:func:`~iceg.odometry_calibration.systematic_errors`: each one's ``value``, ``std``,
    ``allowed`` and ``beyond_noise_model``), the matches used, the setting (``enabled``:
    true, false or "auto") and whether the run was correcting the odometry at its end
    (``corrected``); warned, naming the setting, where one is beyond the odometry noise
    model and the run did not correct it. None without a Slam (nothing was matched)."""
    if result.slam is None:
        return None
    calibrator = result.slam.odometry_calibrator
    errors = systematic_errors(calibrator, result.config.odometry_noise)
    report = {
        "enabled": result.config.odometry_calibration.enabled,
        "corrected": calibrator.correcting,
        "observations": calibrator.n_observations,
        **{
            name: {**asdict(e), "beyond_noise_model": e.beyond_noise_model}
            for name, e in errors.items()
        },
    }
    said = beyond_noise_model_phrases(report)
    if said and not calibrator.correcting:
        logger.warning(
            "%s: the scans' matches measure the odometry's %s: its factors are biased beyond "
            "their covariance, the same way at every step; to correct it during the run, set "
            "odometry_calibration.enabled: auto (the default) or true",
            path,
            ", ".join(said),
        )
    return report


def beyond_noise_model_phrases(report: dict[str, Any]) -> list[str]:
    """Each systematic error of a run's ``metrics["odometry_calibration"]`` report that is
    beyond the odometry noise model, in words ("heading drift +2.04 ± 0.08 deg/m (its noise
    model allows 0.50 deg/m)"). Raises nothing."""
    return [
        f"{words} {value.format(e['value'])} ± {std.format(e['std'])} (its noise model allows "
        f"{allowed.format(e['allowed'])})"
        for name, (words, value, std, allowed) in _SYSTEMATIC_ERRORS.items()
        if (e := report[name])["beyond_noise_model"]
    ]


def _body_seen(body: RobotBodyEstimate) -> str:
    """What ``body`` (a body was found) says, in words: the bearings of its returns as runs
    of adjacent bins, and its bearings without a return."""
    seen = []
    if body.range_m is not None:
        runs: list[list[float]] = []
        for bearing in body.bearings_deg:
            if runs and bearing - runs[-1][-1] <= BIN_DEG + 1e-9:
                runs[-1].append(bearing)
            else:
                runs.append([bearing])
        where = ", ".join(
            f"{r[0]:.0f}" if len(r) == 1 else f"{r[0]:.0f} to {r[-1]:.0f}" for r in runs
        )
        seen.append(
            f"returns at {len(body.bearings_deg)} bearings ({where} deg) stay within "
            f"{body.range_m:.2f} m of the laser as the robot turns, in "
            f"{100.0 * min(body.agreement):.0f}% or more of {body.pairs} turns"
        )
    if body.dark_deg:
        where = ", ".join(f"{lo:.1f} to {hi:.1f}" for lo, hi in body.dark_deg)
        seen.append(f"the beams at {where} deg hold no return where the turned scans see the world")
    return " and ".join(seen) + ": the robot's own body"


def _body_settings(config: IcegConfig) -> str:
    """The configuration's robot-body settings, as a YAML user writes them."""
    f = config.features
    settings = [f"features.robot_body_range_m: {f.robot_body_range_m:.2f}"]
    if f.robot_body_dark_deg:
        pairs = ", ".join(f"[{lo:.2f}, {hi:.2f}]" for lo, hi in f.robot_body_dark_deg)
        settings.append(f"features.robot_body_dark_deg: [{pairs}]")
    return ", ".join(settings)


def check_log_file(path: Path) -> None:
    """Fail early, with one clear line, when ``path`` cannot be a readable log file.

    A folder is accepted only when a reader claims it (a ROS 2 bag folder, which holds
    ``metadata.yaml``): :func:`frontends.registry.folder_reader`.

    Raises:
        LogFormatError: ``path`` is missing, a folder no reader claims (the message names
            the log files it holds), not a regular file (a FIFO, a device), or not readable.
    """
    if not path.exists():
        raise LogFormatError(f"{path}: no such log file")
    if path.is_dir():
        folder_reader(path)
        return
    if not stat.S_ISREG(path.stat().st_mode):
        raise LogFormatError(f"{path}: not a regular file (a FIFO or a device?); pass a log file")
    if not os.access(path, os.R_OK):
        raise LogFormatError(f"{path}: the log cannot be read (permission denied)")


def run_simulated_demo(
    config: IcegConfig | None = None, progress: bool = False, seed: int = 0
) -> SlamResult:
    """The built-in default: the simulated office world, scored against its ground truth.

    The office run (``frontends.simulate.office_world`` with its default loop route, the
    SICK LMS200 laser model and noisy wheel odometry) starts at the true pose, so errors are
    reported both without alignment and after a rigid SE(2) alignment. ``metrics``
    ``factor_nees`` holds the NEES of its factors against the truth, per factor kind
    (:mod:`iceg.consistency`).
    """
    slam = Slam(config)
    with _started(slam, lambda: _simulated(seed)) as ((scans, true_poses, odom_poses), prefetch):
        result = _process(slam, prefetch, scans, progress, len(scans))
    result.metrics["ground_truth"] = position_errors(result.poses, true_poses).as_dict()
    result.metrics["odometry_vs_truth"] = position_errors(odom_poses, true_poses).as_dict()
    truth = per_node(result.node_ids, result.node_scan_index, true_poses)
    result.metrics["factor_nees"] = _nees_metrics(factor_nees(result.factors, truth))
    result.metrics["source"] = f"simulated office world, seed {seed}"
    return result
