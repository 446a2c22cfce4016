"""The ``iceg`` command line: a thin shell over the library.

Errors of the ``IcegError`` family are caught here, and only here: one line on stderr and
exit code 1.
"""

from __future__ import annotations

import atexit
import contextlib
import functools
import gc
import logging
import math
import os
import shutil
import signal
import sys
import threading
import time
from collections.abc import Callable
from datetime import datetime
from enum import Enum
from pathlib import Path
from typing import TYPE_CHECKING, Annotated, Any, Literal, TypeVar

import typer

from iceg import __version__
from iceg.malloc import chosen_malloc
from iceg_common.errors import IcegError, OutputError

if TYPE_CHECKING:
    from iceg.results import SlamResult

app = typer.Typer(
    name="iceg",
    help="2D laser SLAM with ICE feature matching and a GTSAM iSAM2 pose graph.",
    add_completion=False,
    no_args_is_help=False,
    pretty_exceptions_enable=False,
    # a docstring's single line breaks are reflowed, not kept, in --help
    rich_markup_mode="markdown",
)

F = TypeVar("F", bound=Callable[..., Any])


class StampChoice(str, Enum):
    """``--stamps`` policy (see ``frontends.scan.order_by_stamp``)."""

    sort = "sort"
    refuse = "refuse"


def _one_line_errors(func: F) -> F:
    """Turn an ``IcegError`` into one line on stderr and exit code 1."""

    @functools.wraps(func)
    def wrapper(*args: Any, **kwargs: Any) -> Any:
        try:
            return func(*args, **kwargs)
        except IcegError as exc:
            typer.echo(f"iceg: error: {' '.join(str(exc).split())}", err=True)
            raise typer.Exit(code=1) from None

    return wrapper  # type: ignore[return-value]


def _version(value: bool) -> None:
    if value:
        typer.echo(f"iceg {__version__}")
        raise typer.Exit()


@app.callback()
@_one_line_errors
def main(
    version: Annotated[
        bool, typer.Option("--version", callback=_version, is_eager=True, help="Show version.")
    ] = False,
    verbose: Annotated[bool, typer.Option("--verbose", "-v", help="Log progress details.")] = False,
) -> None:
    """ICEG: ICE matching + iSAM2 2D laser SLAM."""
    chosen_malloc(os.environ)  # a wrong ICEG_MALLOC (iceg.malloc) is reported here
    # A run leaves a large heap (graph, map, scans, numba's types); the interpreter's
    # teardown would traverse it in its cycle collections (0.3 s after MIT CSAIL) only to
    # free memory the exit returns anyway. Frozen at exit, they skip it (files are closed and
    # helper processes stopped by then). Registered once, however often the app is invoked.
    atexit.unregister(gc.freeze)
    atexit.register(gc.freeze)
    logging.basicConfig(
        level=logging.INFO if verbose else logging.WARNING,
        format="%(levelname)s %(name)s: %(message)s",
    )


def _default_out_dir() -> Path:
    """``results/<date_time>``, claimed by creating it; a suffix ``-2``, ``-3``, ... when a run
    of the same second has it already (never overwrite a run silently)."""
    base = Path("results") / datetime.now().strftime("%Y-%m-%d_%H-%M-%S")
    try:
        base.parent.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{base.parent}: cannot create the results folder ({exc})") from exc
    for k in range(1, 10_000):
        out = base if k == 1 else base.with_name(f"{base.name}-{k}")
        try:
            out.mkdir()
        except FileExistsError:
            continue
        except OSError as exc:
            raise OutputError(f"{out}: cannot create the output folder ({exc})") from exc
        return out
    raise OutputError(f"{base}: 10000 output folders of this second exist already")


def _link_latest(out: Path) -> None:
    latest = out.parent / "latest"
    try:
        if latest.is_symlink() or latest.exists():
            latest.unlink()
        latest.symlink_to(out.name)
    except OSError:
        pass


def _print_table(rows: list[tuple[str, str]]) -> None:
    width = max(len(k) for k, _ in rows)
    for key, value in rows:
        typer.echo(f"  {key:<{width}}  {value}")


def _hung(reused: int) -> str:
    return f" (and {reused} keyframes hung from old nodes)" if reused else ""


def _summary_rows(result: SlamResult, out: Path, wall_s: float) -> list[tuple[str, str]]:
    """The rows the run command prints; ``wall_s``: the command's time so far (seconds)."""
    s = result.summary()
    rows = [
        ("scans", str(s["scans"])),
        ("nodes", str(s["nodes"]) + _hung(s["reused_keyframes"])),
        ("factors", ", ".join(f"{k} {v}" for k, v in sorted(s["factors"].items()))),
        (
            "loop closures",
            f"{s['loop_closures']['accepted']} accepted of {s['loop_closures']['attempts']} tried",
        ),
        (
            "time",
            f"{wall_s:.2f} s in all, input and saving included; the run's stages "
            f"{s['total_seconds']:.2f} s ({s['scans_per_second']:.0f} scans/s)",
        ),
    ]
    if "relations" in s:
        r = s["relations"]
        rows.append(
            (
                "relation error",
                f"{r['trans_mean_m']:.4f} ± {r['trans_std_m']:.4f} m, "
                f"{r['rot_mean_deg']:.3f} ± {r['rot_std_deg']:.3f} deg "
                f"({r['n_matched']}/{r['n_relations']} relations)",
            )
        )
    if "ground_truth" in s:
        g = s["ground_truth"]
        rows.append(
            (
                "error vs truth",
                f"mean {g['mean_m']:.4f} m, rmse {g['rmse_m']:.4f} m, max {g['max_m']:.4f} m, "
                f"heading {g['rot_mean_deg']:.3f} deg",
            )
        )
    if s.get("factor_nees"):
        nees = s["factor_nees"].items()
        # relations are another system's poses, centimetres off (docs/design.md, "Covariance
        # consistency"): their own error counts in the NEES too
        honest = "3 if honest and the relations exact" if "relations" in s else "3 if honest"
        rows.append(
            (
                "factor NEES vs " + ("relations" if "relations" in s else "truth"),
                ", ".join(f"{k} {v['mean']:.2f}" for k, v in nees) + f" (mean; {honest})",
            )
        )
    rows += _time_offset_rows(result.metrics.get("odometry_time_offset"))
    calibration = result.metrics.get("odometry_calibration")
    if calibration is not None and calibration["corrected"]:
        from iceg.pipeline import beyond_noise_model_phrases

        said = ", ".join(beyond_noise_model_phrases(calibration))
        rows.append(("odometry corrected", said or "always (odometry_calibration.enabled: true)"))
    rows.append(("output", str(out)))
    return rows


def _time_offset_rows(offset: dict[str, Any] | None) -> list[tuple[str, str]]:
    """The summary's row of the odometry time offset read, where one was given (none at 0)."""
    if offset is None or not (offset["applied_s"] or "before_run" in offset):
        return []
    how = ""
    if "before_run" in offset:  # --odometry-time-offset auto
        how = " (auto: measured before the run)" if offset["applied_s"] else " (auto: none)"
    return [("odometry time offset", f"{offset['applied_s']:+.2f} s{how}")]


# ROS bag options of ``iceg run`` (typer reads the help from the annotation).
ScanTopicOption = Annotated[
    str | None, typer.Option(help="ROS bag: the LaserScan topic (if several).")
]
OdomTopicOption = Annotated[
    str | None, typer.Option(help="ROS bag: the nav_msgs/Odometry topic (if several).")
]
OdomFrameOption = Annotated[
    str | None, typer.Option(help="ROS bag: odometry from /tf, this frame to the base.")
]
BaseFrameOption = Annotated[
    str | None, typer.Option(help="ROS bag: the robot base frame (tf to the laser).")
]
LaserOffsetOption = Annotated[
    str | None,
    typer.Option(help="ROS bag: laser pose in the base frame 'X_M,Y_M,YAW_DEG' (not tf)."),
]
OdometryTimeOffsetOption = Annotated[
    str,
    typer.Option(
        help="Read each scan's odometry at its stamp plus this many seconds (negative: the "
        "scans were measured before their stamps). A run measures it: metrics.json, "
        "odometry_time_offset. 'auto': measure it before the run, each scan matched against "
        "the one before it, and read the odometry there where significant.",
    ),
]
LaserOnlyOption = Annotated[
    bool,
    typer.Option(
        "--laser-only",
        help="Leave the log's odometry out: each scan is predicted by constant velocity "
        "and placed by its matches alone (for wheel odometry that is wrong or missing).",
    ),
]
SkipMalformedOption = Annotated[
    bool,
    typer.Option(
        "--skip-malformed",
        help="CARMEN log: skip malformed lines (counted in one warning with the first "
        "file:line) instead of stopping at the first one.",
    ),
]
ContinueOption = Annotated[
    Path | None,
    typer.Option(
        "--continue",
        help="Extend this saved session (its config is used): the log's first scan is "
        "placed in its map by global ICE matching.",
    ),
]
InitialPoseOption = Annotated[
    tuple[float, float, float] | None,
    typer.Option(help="With --continue: first scan's pose in the map, X_M Y_M THETA_DEG."),
]
RelationsArgument = Annotated[Path, typer.Argument(help="Kümmerle et al. 2009 .relations file.")]
ToleranceOption = Annotated[float, typer.Option(help="Timestamp matching tolerance, s.")]


@app.command()
@_one_line_errors
def run(
    log: Annotated[
        Path | None,
        typer.Argument(
            help="Laser log: CARMEN .clf/.log[.gz], or a ROS bag (.bag, .db3, .mcap, bag folder). "
            "Omit to run the built-in demo."
        ),
    ] = None,
    relations: Annotated[
        Path | None, typer.Option(help="Kümmerle et al. 2009 .relations file to score against.")
    ] = None,
    config: Annotated[Path | None, typer.Option(help="YAML config (partial is fine).")] = None,
    out: Annotated[
        Path | None, typer.Option(help="Output folder (default: results/<date_time>).")
    ] = None,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
    stamps: Annotated[
        StampChoice,
        typer.Option(
            help="Out-of-order or duplicate log timestamps: sort the scans (warning with "
            "file:line) or refuse the log. Recorded in metrics.json."
        ),
    ] = StampChoice.sort,
    scan_topic: ScanTopicOption = None,
    odom_topic: OdomTopicOption = None,
    odom_frame: OdomFrameOption = None,
    base_frame: BaseFrameOption = None,
    laser_frame_offset: LaserOffsetOption = None,
    odometry_time_offset: OdometryTimeOffsetOption = "0",
    laser_only: LaserOnlyOption = False,
    lenient: SkipMalformedOption = False,
    continue_: ContinueOption = None,
    initial_pose: InitialPoseOption = None,
) -> None:
    """Optimize a laser log end to end: trajectory, pose graph, map and metrics.

    With no LOG, runs the built-in simulated office world and scores against its truth.
    LOG may be a CARMEN log or a ROS 1 / ROS 2 bag (.bag, .db3, .mcap or a bag folder).
    """
    started = time.perf_counter()
    from iceg.results import check_output_dir

    cfg = _load_config(config)
    if out is not None:
        check_output_dir(out)
    offset = _time_offset(odometry_time_offset)
    _check_log_run_option("--odometry-time-offset", offset != 0.0, log is not None)
    _check_log_run_option("--laser-only", laser_only, log is not None)
    _check_log_run_option("--skip-malformed", lenient, log is not None)
    reader_options = _reader_options(
        scan_topic, odom_topic, odom_frame, base_frame, laser_frame_offset, laser_only, lenient
    )
    out_dir = out if out is not None else _default_out_dir()
    saved: list[str] = []
    cont = None if continue_ is None else (continue_, initial_pose)
    try:
        result = _interruptible(
            lambda: _run_and_save(
                log,
                relations,
                cfg,
                progress,
                stamps.value,
                reader_options,
                out_dir,
                saved.append,
                cont,
                offset,
            ),
            lambda: _on_interrupt(out_dir, saved, remove_empty=out is None),
        )
    except BaseException:
        if out is None and not saved:
            _remove_if_empty(out_dir)
        raise
    if out is None:
        _link_latest(out_dir)
    typer.echo(f"iceg run: {log if log is not None else 'built-in simulated office world'}")
    _print_table(_summary_rows(result, out_dir, time.perf_counter() - started))


def _time_offset(value: str) -> float | Literal["auto"]:
    """``--odometry-time-offset``: seconds, or ``auto``.

    Raises:
        ConfigError: neither a number nor ``auto``.
    """
    from iceg.pipeline import AUTO_OFFSET
    from iceg_common.errors import ConfigError

    if value.strip().lower() == AUTO_OFFSET:
        return "auto"
    try:
        return float(value)
    except ValueError:
        raise ConfigError(
            f"--odometry-time-offset takes seconds (e.g. -0.1) or 'auto', not {value!r}"
        ) from None


def _check_log_run_option(option: str, given: bool, log_run: bool) -> None:
    """``option`` (``--odometry-time-offset``, ``--laser-only``, ``--skip-malformed``)
    changes how a log is read: not for the demo.

    Raises:
        ConfigError: it is given for the demo.
    """
    from iceg_common.errors import ConfigError

    if given and not log_run:
        raise ConfigError(f"{option} applies to a log run, not to the demo")


def _run_and_save(
    log: Path | None,
    relations: Path | None,
    cfg: Any,
    progress: bool,
    stamps: Any,
    reader_options: dict[str, Any],
    out_dir: Path,
    on_saved: Callable[[str], None],
    cont: tuple[Path, tuple[float, float, float] | None] | None = None,
    odometry_time_offset_s: float | Literal["auto"] = 0.0,
) -> SlamResult:
    from iceg.pipeline import run_log, run_simulated_demo

    if cont is not None:
        result = _continue(
            log, cont, relations, progress, stamps, reader_options, odometry_time_offset_s
        )
    elif log is None:
        result = run_simulated_demo(cfg, progress=progress)
    else:
        result = run_log(
            log,
            cfg,
            relations=relations,
            progress=progress,
            stamps=stamps,
            reader_options=reader_options,
            odometry_time_offset_s=odometry_time_offset_s,
        )
    result.save(out_dir, on_saved=on_saved)
    return result


def _on_interrupt(out_dir: Path, saved: list[str], remove_empty: bool) -> str:
    """Clean up after an interrupted run; the one line saying what was kept."""
    from iceg.results import STAGING_MARKER

    staging = out_dir.parent / f"{out_dir.name}{STAGING_MARKER}{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    if not saved:
        if remove_empty:
            _remove_if_empty(out_dir)
        return "interrupted, nothing written"
    if "map" in saved:
        return f"interrupted; the results in {out_dir} are complete"
    return f"interrupted; kept trajectory, graph, metrics and config in {out_dir} (no map)"


def _remove_if_empty(folder: Path) -> None:
    with contextlib.suppress(OSError):
        folder.rmdir()


R = TypeVar("R")


def _interruptible(work: Callable[[], R], on_interrupt: Callable[[], str]) -> R:
    """Run ``work`` in a worker thread so that Ctrl-C (SIGINT) or SIGTERM stops the command
    at once, even inside a long compiled call: one line on stderr, exit 130 (143 for SIGTERM).
    A save in progress is abandoned (the output folder holds a complete set, or the previous
    one; the staging folder is removed here or by the next save)."""
    box: dict[str, Any] = {}

    def target() -> None:
        try:
            box["result"] = work()
        except BaseException as exc:  # re-raised in the main thread
            box["error"] = exc

    def on_term(signum: int, frame: Any) -> None:
        raise _Terminated

    worker = threading.Thread(target=target, name="iceg-run", daemon=True)
    previous = signal.signal(signal.SIGTERM, on_term)
    try:
        worker.start()
        while worker.is_alive():
            worker.join(0.1)
    except (KeyboardInterrupt, _Terminated) as exc:
        code = 143 if isinstance(exc, _Terminated) else 130
        message = on_interrupt()
        if _progress_bar_open():
            sys.stderr.write("\n")  # the bar's line ends where the run stopped
        typer.echo(f"iceg: {message}", err=True)
        sys.stderr.flush()
        os._exit(code)
    finally:
        signal.signal(signal.SIGTERM, previous)
    if "error" in box:
        raise box["error"]
    return box["result"]


def _progress_bar_open() -> bool:
    """Whether a tqdm progress bar is still drawn on stderr (the run was stopped in it)."""
    std = sys.modules.get("tqdm.std")
    return std is not None and bool(getattr(std.tqdm, "_instances", ()))


class _Terminated(Exception):
    """SIGTERM, raised in the main thread."""


@app.command("eval")
@_one_line_errors
def eval_(
    trajectory: Annotated[Path, typer.Argument(help="Trajectory in TUM format.")],
    relations: RelationsArgument,
    tolerance_s: ToleranceOption = 1e-3,
) -> None:
    """Score a TUM trajectory with benchmark relations.

    Prints the mean and standard deviation of the translational and rotational errors."""
    from frontends.relations import read_relations
    from frontends.tum import read_tum
    from iceg.evaluation import relation_errors

    stamps, poses = read_tum(trajectory)
    rel = read_relations(relations)
    summary, _ = relation_errors(stamps, poses, rel.stamps_s, rel.deltas, tolerance_s)
    _print_table(
        [(k, f"{v:.6g}" if isinstance(v, float) else str(v)) for k, v in summary.as_dict().items()]
    )


@app.command("nees")
@_one_line_errors
def nees_(
    run: Annotated[Path, typer.Argument(help="A run's output folder (or its session folder).")],
    relations: RelationsArgument,
    tolerance_s: ToleranceOption = 1e-3,
) -> None:
    """Whether a saved run's covariances are honest: its factors' NEES against relations.

    Per factor kind: mean 3 and 5 % beyond the 95 % bound if they are honest and the
    relations exact (relations from another system's corrected poses carry centimetres of
    their own error, which counts in the NEES too)."""
    from frontends.relations import read_relations
    from iceg import session
    from iceg.consistency import relation_factor_nees

    saved = session.read(run)
    nees = relation_factor_nees(
        session.factor_records(saved.arrays),
        saved.node_stamps(),
        read_relations(relations),
        tolerance_s,
    )
    summaries = nees.summary()
    bound = next(iter(summaries.values())).bound
    head = f"  {'factors':<12} {'count':>6} {'mean':>9} {'median':>9} {'p90':>9}"
    typer.echo(f"{head}  > {bound:.2f}")
    for kind, s in summaries.items():
        typer.echo(
            f"  {kind:<12} {s.count:>6} {s.mean:>9.3g} {s.median:>9.3g} {s.p90:>9.3g}  "
            f"{s.beyond_bound:.1%}"
        )


@app.command("dump-config")
@_one_line_errors
def dump_config(
    config: Annotated[
        Path | None, typer.Option(help="Show this file merged with defaults.")
    ] = None,
) -> None:
    """Print the effective configuration as YAML."""
    typer.echo(_load_config(config).to_yaml(), nl=False)


@app.command()
@_one_line_errors
def info(
    log: Annotated[Path, typer.Argument(help="CARMEN log or ROS bag (.bag/.db3/.mcap/folder).")],
    scan_topic: Annotated[str | None, typer.Option(help="ROS bag: the LaserScan topic.")] = None,
    odom_topic: Annotated[str | None, typer.Option(help="ROS bag: the Odometry topic.")] = None,
    odom_frame: Annotated[str | None, typer.Option(help="ROS bag: odom frame in /tf.")] = None,
    base_frame: Annotated[str | None, typer.Option(help="ROS bag: the base frame.")] = None,
    laser_frame_offset: Annotated[
        str | None, typer.Option(help="ROS bag: laser pose 'X_M,Y_M,YAW_DEG'.")
    ] = None,
    lenient: SkipMalformedOption = False,
) -> None:
    """Print what a log holds, and what in it a run would have to correct.

    Topics or record types, counts, duration, beams, range limits, returns, odometry source,
    the interval between its scans, whether its walls turn and move with its odometry, and
    where its odometry holds while the scans move."""
    from frontends.registry import describe_log, open_log
    from iceg.config import IcegConfig
    from iceg.log_checks import describe_odometry_checks, describe_stamps
    from iceg.scan_store import ScanStore
    from iceg_common.errors import LogFormatError

    options = _reader_options(
        scan_topic, odom_topic, odom_frame, base_frame, laser_frame_offset, False, lenient
    )
    scans = ScanStore()
    rows = describe_log(open_log(log, **options), on_scan=scans.append)
    if not len(scans):  # a bag answered from its index: its scans are read for the checks
        with contextlib.suppress(LogFormatError):  # the plan needs an option: its row says so
            scans = ScanStore(open_log(log, **options))
    rows += describe_stamps(scans.stamps_s) + describe_odometry_checks(scans, IcegConfig())
    typer.echo(f"iceg info: {log}")
    _print_table(rows)


def _reader_options(
    scan_topic: str | None,
    odom_topic: str | None,
    odom_frame: str | None,
    base_frame: str | None,
    laser_frame_offset: str | None,
    laser_only: bool = False,
    lenient: bool = False,
) -> dict[str, Any]:
    """The reader options that were given: a ROS bag's topics, frames and laser offset
    (degrees -> radians for the yaw), ``laser_only`` (:func:`frontends.open_log`) and a
    CARMEN log's ``strict: False`` (``--skip-malformed``) when given."""
    from iceg_common.errors import ConfigError

    options: dict[str, Any] = {
        k: v
        for k, v in (
            ("scan_topic", scan_topic),
            ("odom_topic", odom_topic),
            ("odom_frame", odom_frame),
            ("base_frame", base_frame),
        )
        if v is not None
    }
    if laser_frame_offset is not None:
        try:
            x, y, yaw_deg = (float(v) for v in laser_frame_offset.split(","))
        except ValueError:
            raise ConfigError(
                f"--laser-frame-offset {laser_frame_offset!r}: give 'X_M,Y_M,YAW_DEG', "
                "e.g. -0.12,0,0"
            ) from None
        options["laser_frame_offset"] = (x, y, math.radians(yaw_deg))
    if laser_only:
        options["laser_only"] = True
    if lenient:
        options["strict"] = False
    return options


def _load_config(path: Path | None) -> Any:
    from iceg.config import IcegConfig, config_from_yaml

    return IcegConfig() if path is None else config_from_yaml(path)


@app.command("batch")
@_one_line_errors
def batch(
    spec: Annotated[Path, typer.Argument(help="Batch spec (YAML): logs, config grid, seeds.")],
    out: Annotated[
        Path | None, typer.Option(help="Batch folder (default: results/batch-<spec name>).")
    ] = None,
    local: Annotated[
        bool, typer.Option("--local", help="Run on a local process pool instead of Ray.")
    ] = False,
    workers: Annotated[
        int | None, typer.Option(help="Parallel runs (default: this machine's cores).")
    ] = None,
    address: Annotated[
        str | None, typer.Option(help="Join this Ray cluster ('auto', 'ray://host:10001').")
    ] = None,
    retry_failed: Annotated[
        bool, typer.Option(help="Run failed and timed-out runs again.")
    ] = False,
) -> None:
    """Run many logs x configs x seeds (Ray, or --local) into one table.

    Writes summary.csv, timings.csv, summary.md and variants.png. Finished runs are kept
    (resumable)."""
    from iceg.batch import load_spec, run_batch

    s = load_spec(spec)
    out_dir = out if out is not None else Path("results") / f"batch-{s.name}"

    def on_row(row: dict[str, Any], reused: bool) -> None:
        what = "kept" if reused else f"{row['seconds']:.1f} s"
        err = f": {row['error']}" if row["error"] else ""
        typer.echo(f"  {row['status']:<7} {row['run_id']} ({what}){err}")

    typer.echo(f"iceg batch: {spec} -> {out_dir}")
    report = run_batch(
        s,
        out_dir,
        spec_dir=spec.parent,
        executor="local" if local else "ray",
        workers=workers,
        address=address,
        retry_failed=retry_failed,
        on_row=on_row,
    )
    typer.echo(
        f"{len(report.rows)} runs, {report.n_failed} failed; table: {report.markdown}, "
        f"{report.summary_csv}"
    )


# --------------------------------------------------------------------------- map life cycle
# (issue 15: sessions; see iceg.session, iceg.edit, iceg.localize, iceg.merge)


@app.command()
@_one_line_errors
def optimize(
    session_dir: Annotated[
        Path, typer.Argument(metavar="SESSION", help="Session folder (or the run folder).")
    ],
    remove_factor: Annotated[
        list[int] | None,
        typer.Option(help="Remove this factor (index in loop_closures.csv / graph.g2o)."),
    ] = None,
    add_closure: Annotated[
        list[str] | None,
        typer.Option(
            help="Add a loop closure 'NODE_I NODE_J' (matched by ICE between the two scans) or "
            "'NODE_I NODE_J X_M Y_M THETA_DEG' (pose of NODE_J in NODE_I's frame)."
        ),
    ] = None,
    closure_sigma_m: Annotated[float, typer.Option(help="Sigma of a given closure, m.")] = 0.05,
    closure_sigma_deg: Annotated[
        float, typer.Option(help="Heading sigma of a given closure, deg.")
    ] = 1.0,
    relations: Annotated[
        Path | None, typer.Option(help="Score the re-optimized trajectory with a .relations file.")
    ] = None,
    out: Annotated[
        Path | None, typer.Option(help="Write the edited session here (default: in place).")
    ] = None,
) -> None:
    """Re-optimize a saved session's pose graph after edits (remove / add loop closures)."""
    from iceg import session as sess
    from iceg.edit import edit_and_optimize, parse_closure, write_edited

    s = sess.read(session_dir)
    edits = [parse_closure(t, closure_sigma_m, closure_sigma_deg) for t in add_closure or []]
    arrays = edit_and_optimize(s, remove_factor or [], edits)
    try:
        folder = write_edited(s, arrays, out if out is not None else s.path)
    except OSError as exc:
        raise OutputError(f"{out or s.path}: cannot write the session ({exc})") from exc
    edited = sess.read(folder)
    rows = [
        ("nodes", str(arrays["g_node_ids"].shape[0])),
        ("factors", str(arrays["g_kind"].shape[0])),
        ("loop closures", str(len(sess.closure_rows(arrays)))),
    ]
    rows += _relation_rows(edited, relations)
    rows.append(("session", str(folder)))
    typer.echo(f"iceg optimize: {session_dir}")
    _print_table(rows)


@app.command()
@_one_line_errors
def localize(
    log: Annotated[Path, typer.Argument(help="Laser log to localize (CARMEN or ROS bag).")],
    map_: Annotated[
        Path, typer.Option("--map", help="Saved session (or run folder) holding the map.")
    ],
    out: Annotated[
        Path | None, typer.Option(help="Output folder (default: results/<date_time>).")
    ] = None,
    initial_pose: Annotated[
        tuple[float, float, float] | None,
        typer.Option(help="First scan's pose in the map, X_M Y_M THETA_DEG (may be wrong)."),
    ] = None,
    relations: Annotated[
        Path | None, typer.Option(help="Score the localized trajectory with a .relations file.")
    ] = None,
    stamps: Annotated[StampChoice, typer.Option(help="Disordered log stamps.")] = (
        StampChoice.sort
    ),
    scan_topic: ScanTopicOption = None,
    odom_topic: OdomTopicOption = None,
    odom_frame: OdomFrameOption = None,
    base_frame: BaseFrameOption = None,
    laser_frame_offset: LaserOffsetOption = None,
    odometry_time_offset: OdometryTimeOffsetOption = "0",
    laser_only: LaserOnlyOption = False,
    lenient: SkipMalformedOption = False,
) -> None:
    """Localize a log in a saved map (nothing is added to it).

    Writes the trajectory with per-pose covariance (localization.csv), trajectory.tum and a
    map.png overlay."""
    import numpy as np

    from iceg import session as sess
    from iceg.localize import fixed_map_of_session, localize_scans, save_localization
    from iceg.pipeline import read_log_scans

    options = _reader_options(
        scan_topic, odom_topic, odom_frame, base_frame, laser_frame_offset, laser_only, lenient
    )
    offset_s = _time_offset(odometry_time_offset)
    s = sess.read(map_)
    scans, offset, _ = read_log_scans(log, s.config, stamps.value, options, offset_s)
    pose = None
    if initial_pose is not None:
        pose = np.array([initial_pose[0], initial_pose[1], math.radians(initial_pose[2])])
    result = localize_scans(fixed_map_of_session(s), scans, initial_pose=pose)
    out_dir = out if out is not None else _default_out_dir()
    try:
        save_localization(result, s, out_dir, metrics={"odometry_time_offset": offset})
    except OSError as exc:
        raise OutputError(f"{out_dir}: cannot write the results ({exc})") from exc
    rows = [(k, str(v)) for k, v in result.summary.items()]
    rows.append(("relocalizations", str(result.relocalizations)))
    rows += _time_offset_rows(offset)
    if relations is not None:
        ok = ~np.isnan(result.poses[:, 0])
        rows += _relation_rows_of(result.stamps_s[ok], result.poses[ok], relations)
    rows.append(("output", str(out_dir)))
    typer.echo(f"iceg localize: {log} in {s.path}")
    _print_table(rows)


@app.command()
@_one_line_errors
def merge(
    session_a: Annotated[Path, typer.Argument(metavar="A", help="First session (kept fixed).")],
    session_b: Annotated[Path, typer.Argument(metavar="B", help="Session merged into A.")],
    out: Annotated[Path, typer.Option(help="Output folder (session/, trajectory.tum, map files).")],
    relations: Annotated[
        Path | None, typer.Option(help="Score the merged trajectory with a .relations file.")
    ] = None,
) -> None:
    """Merge two sessions of one building into one graph and one map.

    The sessions are linked by inter-session loop closures found by global ICE matching and
    checked for consistency."""
    from iceg import session as sess
    from iceg.merge import merge_sessions

    a, b = sess.read(session_a), sess.read(session_b)
    if out.exists() and any(out.iterdir()):
        raise OutputError(f"{out}: exists and is not empty; choose a new --out")
    try:
        folder, closures = merge_sessions(a, b, out)
    except OSError as exc:
        raise OutputError(f"{out}: cannot write the merged session ({exc})") from exc
    merged = sess.read(folder)
    rows = [
        ("nodes", f"{merged.manifest['nodes']} ({a.manifest['nodes']} + {b.manifest['nodes']})"),
        ("inter-session closures", str(len(closures))),
        (
            "walls driven through",
            "seen by at most {b_through_a} of A's nodes (B's path), {a_through_b} of B's "
            "(A's path)".format(**merged.manifest["wall_crossings"]),
        ),
        *_relation_rows(merged, relations),
        ("output", str(folder)),
    ]
    typer.echo(f"iceg merge: {session_a} + {session_b}")
    _print_table(rows)


def _continue(
    log: Path | None,
    cont: tuple[Path, tuple[float, float, float] | None],
    relations: Path | None,
    progress: bool,
    stamps: Any,
    reader_options: dict[str, Any],
    odometry_time_offset_s: float | Literal["auto"],
) -> SlamResult:
    """``iceg run LOG --continue SESSION [--initial-pose X Y THETA_DEG]``."""
    from iceg.continuation import continue_log

    if log is None:
        from iceg_common.errors import ConfigError

        raise ConfigError("--continue needs a LOG to extend the session with")
    session_dir, initial_pose = cont
    pose = None
    if initial_pose is not None:
        pose = (initial_pose[0], initial_pose[1], math.radians(initial_pose[2]))
    return continue_log(
        log,
        session_dir,
        relations,
        pose,
        progress,
        stamps,
        reader_options,
        odometry_time_offset_s,
    )


def _relation_rows(s: Any, relations: Path | None) -> list[tuple[str, str]]:
    """The relation-error row of a session's trajectory (none without relations)."""
    if relations is None:
        return []
    stamps, poses = s.trajectory()
    return _relation_rows_of(stamps, poses, relations)


def _relation_rows_of(stamps: Any, poses: Any, relations: Path) -> list[tuple[str, str]]:
    """The relation-error row of a trajectory."""
    from frontends.relations import read_relations
    from iceg.evaluation import relation_errors
    from iceg.pipeline import RELATION_TOLERANCE_S

    rel = read_relations(relations)
    r, _ = relation_errors(stamps, poses, rel.stamps_s, rel.deltas, RELATION_TOLERANCE_S)
    d = r.as_dict()
    return [
        (
            "relation error",
            f"{d['trans_mean_m']:.4f} ± {d['trans_std_m']:.4f} m, {d['rot_mean_deg']:.3f} ± "
            f"{d['rot_std_deg']:.3f} deg ({d['n_matched']}/{d['n_relations']} relations)",
        )
    ]


if __name__ == "__main__":  # pragma: no cover
    sys.exit(app())
