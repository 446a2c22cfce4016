"""Batches of runs: many logs x a config grid x seeds, one table (``iceg batch SPEC.yaml``).

A spec (YAML) lists logs and configurations::

    name: office-vs-corridor
    logs:
      - sim:office                      # a simulated scenario (random: repeated per seed)
      - name: csail
        path: data/mit-csail.clf        # relative to the spec's folder
        relations: data/mit-csail.relations
        reference: ref.tum              # TUM trajectory, or log_odometry
        max_scans: 500
        reader_options: {stamps: refuse} # keyword options of frontends.open_log
        synthetic_odometry: {scale_error: 0.01, heading_drift_deg_per_m: 0.4}
      - path: data/turtlebot4           # a ROS 2 bag folder
        odometry_time_offset_s: -0.1    # odometry read 0.1 s before each scan's stamp
    config: {slam: {batch_refinement: false}}   # base overrides (or a YAML file name)
    grid:                               # dotted keys and value lists: their product
      matching.method: [ice, plicp]
    variants:                           # and/or named variants (times the grid)
      coarse: {grid.resolution_m: 0.1}
    seeds: [0, 1]
    timeout_s: 600
    outputs: full                       # or metrics (run.json only)

Every run is a pure function of (log, config, seed) (:func:`iceg.batch_run.execute_run`)
writing its own folder ``runs/<run_id>/``; runs go through Ray (:func:`run_batch` with
``executor="ray"``: ``ray.init()`` on this machine, or ``address`` to join a cluster) or a
local process pool. A failing run is a row; a finished run (same inputs) is not run again.
The batch writes ``summary.csv`` (no wall times: the same spec gives the same file whatever
the number of workers), ``timings.csv``, ``summary.md`` and ``variants.png``
(:mod:`iceg.batch_report`).
"""

from __future__ import annotations

import hashlib
import itertools
import json
import logging
import re
from collections.abc import Callable, Iterable
from concurrent.futures import ProcessPoolExecutor, as_completed
from dataclasses import dataclass
from multiprocessing import get_context
from pathlib import Path
from typing import Annotated, Any, Literal

import yaml
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    ValidationError,
    field_validator,
    model_validator,
)

from iceg.batch_report import BatchReport, write_report
from iceg.batch_run import (
    LOG_ODOMETRY,
    SIM_PREFIX,
    RunTask,
    SyntheticOdometrySpec,
    execute_run,
    read_row,
)
from iceg.config import config_from_dict, config_from_yaml
from iceg_common.errors import ConfigError

__all__ = [
    "BatchSpec",
    "LogEntry",
    "expand",
    "load_spec",
    "run_batch",
]

#: Variant name when the spec has no grid and no variants.
DEFAULT_VARIANT = "default"
#: Characters kept in run ids (file names).
_SAFE = re.compile(r"[^A-Za-z0-9._=+-]+")

Executor = Literal["ray", "local"]
OnRow = Callable[[dict[str, Any], bool], None]


class SyntheticOdometryModel(BaseModel):
    """Drifting odometry replacing a log's own (seeded: the log is repeated per seed)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    scale_error: float = 0.01
    heading_drift_deg_per_m: float = 0.4
    noise: bool = True
    restamp_hz: float | None = Field(default=None, gt=0)


class LogEntry(BaseModel):
    """One log of a spec: a file (paths relative to the spec) or ``sim:SCENARIO``."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    path: str
    name: str | None = None
    relations: str | None = None
    reference: str | None = Field(
        default=None, description=f"TUM trajectory file, or {LOG_ODOMETRY!r}"
    )
    max_scans: int | None = Field(default=None, gt=0)
    synthetic_odometry: SyntheticOdometryModel | None = None
    reader_options: dict[str, Any] = Field(
        default_factory=dict,
        description="Keyword options of frontends.open_log for this log (e.g. a bag's "
        "odom_frame, base_frame, laser_frame_offset).",
    )
    laser_only: bool = Field(
        default=False,
        description="Run without the log's odometry (laser only). With reference: "
        "log_odometry the reference is the odometry read first: e.g. motion-capture poses "
        "in a bag's /tf, read with reader_options odom_frame and base_frame.",
    )
    odometry_time_offset_s: Annotated[float, Field(allow_inf_nan=False)] | Literal["auto"] = Field(
        default=0.0,
        description="Read each scan's odometry at its stamp plus this many seconds "
        "(frontends.odometry_shift.shift_odometry; iceg run --odometry-time-offset). "
        "'auto': measured before the run, each scan matched against the one before it, and "
        "read there where significant (the row's odom_time_offset_applied_s).",
    )

    @model_validator(mode="after")
    def _one_odometry(self) -> LogEntry:
        if self.laser_only and self.synthetic_odometry is not None:
            raise ValueError("laser_only and synthetic_odometry exclude each other")
        if self.odometry_time_offset_s and (
            self.laser_only or self.synthetic_odometry is not None or self.reference == LOG_ODOMETRY
        ):
            raise ValueError(
                "odometry_time_offset_s shifts the log's own odometry: not with laser_only, "
                "synthetic_odometry or reference: log_odometry"
            )
        return self

    @property
    def label(self) -> str:
        """The log's name in the table."""
        if self.name:
            return self.name
        if self.path.startswith(SIM_PREFIX):
            return self.path[len(SIM_PREFIX) :]
        return Path(self.path).name.split(".")[0]

    @property
    def is_random(self) -> bool:
        """Whether the input depends on the seed (simulation, synthetic odometry with noise;
        a drift alone draws nothing)."""
        odometry = self.synthetic_odometry
        return self.path.startswith(SIM_PREFIX) or (odometry is not None and odometry.noise)


class BatchSpec(BaseModel):
    """A batch: logs x (variants x grid) x seeds. See the module docstring."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    name: str = "batch"
    logs: list[LogEntry] = Field(min_length=1)
    config: dict[str, Any] | str | None = None
    grid: dict[str, list[Any]] = Field(default_factory=dict)
    variants: dict[str, dict[str, Any]] = Field(default_factory=dict)
    seeds: list[int] = Field(default_factory=lambda: [0], min_length=1)
    timeout_s: float | None = Field(default=None, gt=0)
    outputs: Literal["full", "metrics"] = "full"

    @field_validator("logs", mode="before")
    @classmethod
    def _short_logs(cls, value: Any) -> Any:
        """A plain string is ``{path: string}``."""
        if isinstance(value, list):
            return [{"path": v} if isinstance(v, str) else v for v in value]
        return value


@dataclass(frozen=True)
class Variant:
    """A named configuration: dotted-key overrides of the spec's base config."""

    name: str
    overrides: dict[str, Any]


# ---------------------------------------------------------------------------- spec


def load_spec(path: str | Path) -> BatchSpec:
    """Read and validate a spec file.

    Raises:
        ConfigError: missing, unparsable or invalid spec.
    """
    p = Path(path)
    try:
        data = yaml.safe_load(p.read_text(encoding="utf-8"))
    except OSError as exc:
        raise ConfigError(f"{p}: cannot read the batch spec ({exc})") from exc
    except yaml.YAMLError as exc:
        raise ConfigError(f"{p}: not valid YAML ({exc})") from exc
    return spec_from_dict(data, str(p))


def spec_from_dict(data: Any, source: str = "<dict>") -> BatchSpec:
    """Validate a spec mapping.

    Raises:
        ConfigError: an unknown key or invalid value, naming its path.
    """
    try:
        spec = BatchSpec.model_validate(data)
    except ValidationError as exc:
        first = exc.errors()[0]
        where = ".".join(str(p) for p in first["loc"])
        raise ConfigError(f"{source}: invalid batch spec at '{where}': {first['msg']}") from exc
    labels = [e.label for e in spec.logs]
    dup = sorted({n for n in labels if labels.count(n) > 1})
    if dup:
        raise ConfigError(f"{source}: two logs are named {dup[0]!r}; give them a 'name'")
    return spec


def variants(spec: BatchSpec) -> list[Variant]:
    """The spec's variants: named variants x the grid's product (names joined by ``+``;
    a grid point is named ``key=value`` by the keys' last parts)."""
    named = [Variant(n, dict(o)) for n, o in spec.variants.items()] or [Variant("", {})]
    keys = list(spec.grid)
    points = [
        Variant(
            ",".join(f"{k.split('.')[-1]}={v}" for k, v in zip(keys, values, strict=True)),
            dict(zip(keys, values, strict=True)),
        )
        for values in itertools.product(*(spec.grid[k] for k in keys))
    ]
    out = []
    for a, b in itertools.product(named, points):
        name = "+".join(n for n in (a.name, b.name) if n) or DEFAULT_VARIANT
        out.append(Variant(name, {**a.overrides, **b.overrides}))
    return out


def _base_config(spec: BatchSpec, spec_dir: Path) -> dict[str, Any]:
    if spec.config is None:
        return {}
    if isinstance(spec.config, str):
        path = Path(spec.config)
        config = config_from_yaml(path if path.is_absolute() else spec_dir / path)
        return config.model_dump(mode="json")
    return dict(spec.config)


def apply_overrides(base: dict[str, Any], overrides: dict[str, Any]) -> dict[str, Any]:
    """``base`` (nested) with dotted-key ``overrides`` set (a copy)."""
    out = json.loads(json.dumps(base))
    for dotted, value in overrides.items():
        node = out
        *parents, leaf = dotted.split(".")
        for part in parents:
            node = node.setdefault(part, {})
            if not isinstance(node, dict):
                raise ConfigError(f"config override {dotted!r}: {part!r} is not a section")
        node[leaf] = value
    return out


def _slug(text: str) -> str:
    return _SAFE.sub("_", text).strip("_") or "x"


def _resolve(path: str | None, spec_dir: Path) -> str | None:
    if path is None or path.startswith(SIM_PREFIX) or path == LOG_ODOMETRY:
        return path
    p = Path(path).expanduser()
    return str(p if p.is_absolute() else (spec_dir / p).resolve())


def expand(spec: BatchSpec, spec_dir: Path, out_dir: Path) -> list[RunTask]:
    """Every run of the spec, in table order (log, variant, seed). Each variant's config is
    validated here, before anything runs.

    Raises:
        ConfigError: a variant's configuration is invalid.
    """
    base = _base_config(spec, spec_dir)
    configs = []
    for v in variants(spec):
        cfg = apply_overrides(base, v.overrides)
        config_from_dict(cfg, source=f"batch variant {v.name!r}")
        configs.append((v.name, cfg))
    tasks = []
    for entry in spec.logs:
        seeds: list[int | None] = list(spec.seeds) if entry.is_random else [None]
        for (vname, cfg), seed in itertools.product(configs, seeds):
            tasks.append(_task(spec, entry, vname, cfg, seed, spec_dir, out_dir))
    return tasks


def _task(
    spec: BatchSpec,
    entry: LogEntry,
    vname: str,
    cfg: dict[str, Any],
    seed: int | None,
    spec_dir: Path,
    out_dir: Path,
) -> RunTask:
    run_id = "__".join([_slug(entry.label), _slug(vname), *([] if seed is None else [f"s{seed}"])])
    odo = entry.synthetic_odometry
    fields: dict[str, Any] = {
        "source": _resolve(entry.path, spec_dir),
        "relations": _resolve(entry.relations, spec_dir),
        "reference": _resolve(entry.reference, spec_dir),
        "max_scans": entry.max_scans,
        "odometry": None if odo is None else SyntheticOdometrySpec(**odo.model_dump()),
        "reader_options": dict(entry.reader_options),
        "laser_only": entry.laser_only,
        "odometry_time_offset_s": entry.odometry_time_offset_s,
        "timeout_s": spec.timeout_s,
        "outputs": spec.outputs,
    }
    key_data = {**fields, "config": cfg, "seed": seed, "odometry": odo and odo.model_dump()}
    key = hashlib.sha256(json.dumps(key_data, sort_keys=True).encode()).hexdigest()[:16]
    return RunTask(
        run_id=run_id,
        key=key,
        log_name=entry.label,
        variant=vname,
        seed=seed,
        config=cfg,
        folder=str(out_dir / "runs" / run_id),
        **fields,
    )


# ---------------------------------------------------------------------------- running


def pending(tasks: Iterable[RunTask], retry_failed: bool = False) -> list[RunTask]:
    """The tasks without a finished row of the same key (``retry_failed``: failed and
    timed-out runs count as not finished)."""
    out = []
    for t in tasks:
        row = read_row(Path(t.folder))
        done = row is not None and row.get("key") == t.key
        if done and retry_failed and row is not None and row.get("status") != "ok":
            done = False
        if not done:
            out.append(t)
    return out


def run_batch(
    spec: BatchSpec,
    out_dir: str | Path,
    spec_dir: str | Path = ".",
    executor: Executor = "ray",
    workers: int | None = None,
    address: str | None = None,
    retry_failed: bool = False,
    on_row: OnRow | None = None,
) -> BatchReport:
    """Run a batch and write its summary.

    Args:
        spec: The batch spec.
        out_dir: The batch folder (``runs/``, ``summary.csv``, ...); created if missing.
        spec_dir: Folder that relative paths of the spec are relative to.
        executor: ``"ray"`` (``ray.init()``; the extra ``batch``) or ``"local"`` (a process
            pool).
        workers: Parallel runs (default: the machine's cores; ignored with ``address``).
        address: Join this Ray cluster instead of starting one (``"auto"``, ``ray://...``).
        retry_failed: Run failed and timed-out runs again.
        on_row: Called with each row and whether it was reused from an earlier batch.

    Returns:
        The :class:`~iceg.batch_report.BatchReport` (rows in table order, files written).

    Raises:
        ConfigError: an invalid variant, or Ray requested but not installed.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    tasks = expand(spec, Path(spec_dir).resolve(), out.resolve())
    todo = pending(tasks, retry_failed)
    todo_ids = {t.run_id for t in todo}
    for t in tasks:
        row = read_row(Path(t.folder))
        if t.run_id not in todo_ids and row is not None and on_row is not None:
            on_row(row, True)
    if todo:
        run = _run_ray if executor == "ray" else _run_local
        run(todo, workers, address, on_row)
    rows = [read_row(Path(t.folder)) or _lost_row(t) for t in tasks]
    return write_report(spec.name, rows, out)


def _lost_row(task: RunTask) -> dict[str, Any]:
    """The row of a run whose worker died without writing one."""
    return {
        "run_id": task.run_id,
        "key": task.key,
        "log": task.log_name,
        "variant": task.variant,
        "seed": task.seed,
        "status": "failed",
        "error": "worker died without a result",
        "metrics": {},
        "seconds": float("nan"),
    }


def _run_local(
    tasks: list[RunTask], workers: int | None, address: str | None, on_row: OnRow | None
) -> None:
    """A process pool (spawned processes) of ``workers``."""
    with ProcessPoolExecutor(max_workers=workers, mp_context=get_context("spawn")) as pool:
        futures = {pool.submit(execute_run, t): t for t in tasks}
        for fut in as_completed(futures):
            try:
                row = fut.result()
            except Exception as exc:  # the worker process died
                row = _lost_row(futures[fut]) | {"error": f"worker died: {exc}"}
            if on_row is not None:
                on_row(row, False)


def _project_packages() -> list[Any]:
    """The project's top-level packages (for a Ray cluster's ``py_modules``)."""
    import importlib

    return [importlib.import_module(n) for n in ("iceg", "graph", "frontends", "iceg_common")]


def _run_ray(
    tasks: list[RunTask], workers: int | None, address: str | None, on_row: OnRow | None
) -> None:
    """Ray tasks of one CPU each, on a local Ray (``num_cpus=workers``) or a cluster (the
    project's packages are shipped with the tasks; the logs and the batch folder must be on
    a file system every node sees, each run writes its own folder there)."""
    try:
        import ray
    except ImportError:
        raise ConfigError(
            "Ray is not installed: pip install 'iceg[batch]', or run with --local"
        ) from None
    started = not ray.is_initialized()
    if started:
        kwargs: dict[str, Any] = {
            "include_dashboard": False,
            "log_to_driver": False,
            "logging_level": logging.WARNING,
        }
        if address is None:
            kwargs["num_cpus"] = workers
        else:  # ship the project's packages; the nodes need its dependencies installed
            kwargs["runtime_env"] = {"py_modules": _project_packages()}
        ray.init(address=address, **kwargs)
    try:
        remote = ray.remote(num_cpus=1, max_retries=0)(execute_run)
        refs = {remote.remote(t): t for t in tasks}
        waiting = list(refs)
        while waiting:
            done, waiting = ray.wait(waiting, num_returns=1)
            try:
                row = ray.get(done[0])
            except Exception as exc:  # the worker died (RayTaskError, WorkerCrashedError)
                row = _lost_row(refs[done[0]]) | {"error": f"worker died: {type(exc).__name__}"}
            if on_row is not None:
                on_row(row, False)
    finally:
        if started:
            ray.shutdown()
