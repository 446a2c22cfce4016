"""The result of a SLAM run: an object to inspect in a notebook and to save to a folder.

Saving never loses a run and never leaves a mix of two runs (README "Outputs"): the result
set is written into a visible staging folder ``<out>.iceg-saving-<pid>`` beside ``out`` and
swapped in with one rename, in two steps: first trajectory, graph, metrics and config (as soon
as the optimization has ended), then the same set plus the map files, rendered from the
optimized poses. A map that cannot be rendered is a warning in ``metrics.json``, never a lost
run. Staging folders left by a killed save are removed by the next save into the same place.
"""

from __future__ import annotations

import concurrent.futures
import contextlib
import ctypes
import errno
import json
import logging
import os
import shutil
import time
from collections import Counter
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from frontends.tum import write_tum
from iceg.grid import (
    OccupancyGrid,
    TiledGrid,
    render_tiled,
    render_tiled_chunks,
    write_map_server,
    write_png,
)
from iceg.scan_store import ScanStore
from iceg_common.atomic import atomic_write
from iceg_common.errors import GridError, OutputError

if TYPE_CHECKING:
    from frontends import LaserScan
    from graph import FactorRecord, PoseGraph
    from iceg.config import IcegConfig
    from iceg.feature_map import FeatureMap
    from iceg.slam import LoopClosureStats, Slam

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Files of the first save step (written as soon as the optimization has ended).
CORE_FILES = ("trajectory.tum", "graph.g2o", "metrics.json", "config.yaml")

#: Map files added by the second step (absent when the map cannot be rendered).
MAP_FILES = ("map.pgm", "map.yaml", "map.png")

#: Files :meth:`SlamResult.save` writes.
OUTPUT_FILES = (
    "trajectory.tum",
    "graph.g2o",
    "map.pgm",
    "map.yaml",
    "map.png",
    "metrics.json",
    "config.yaml",
)

#: The session folder every save writes beside the files (:mod:`iceg.session`).
SESSION_DIR = "session"

#: Marker in the name of a staging folder beside the output folder.
STAGING_MARKER = ".iceg-saving-"


@dataclass
class SlamResult:
    """Everything a run produced.

    Attributes:
        stamps_s: ``(N,)`` timestamp of every input scan, seconds.
        poses: ``(N, 3)`` optimized robot pose of every input scan ``[x_m, y_m, theta_rad]``
            in the map frame (non-node scans: their node's estimate ∘ odometry delta, bent
            to meet the next node's: :func:`iceg.scan_poses.scan_poses`).
        node_ids: ``(M,)`` graph node ids; ``node_poses`` ``(M, 3)`` their estimates.
        node_scan_index: ``(M,)`` index of each node's scan in the input.
        factors: every factor of the graph (``graph.FactorRecord``: index, kind, nodes
            ``i``/``j``, measurement, covariance, robust kernel), the prior first.
        correlations: ICE correlation (eq. 1) of each scan-match and loop-closure factor,
            by factor index.
        loop_closures: loop-closure statistics.
        match_failures: count of failed local matches per reason (no scan-match factor).
        point_fallbacks: count of failed local ICE matches per reason whose scan got a
            point-match factor instead (``slam.point_fallback``).
        reused_keyframes: keyframes of revisits that hung from an old node instead of
            becoming nodes (``slam.reuse_nodes``).
        stage_seconds: wall time per pipeline stage, seconds.
        feature_map: the final feature map (landmarks anchored to nodes).
        graph: the pose graph (marginals, g2o export).
        config: the effective configuration.
        scans: the input scans (a compact :class:`~iceg.scan_store.ScanStore` from
            :class:`~iceg.slam.Slam`), for rendering the map along ``poses``.
        metrics: evaluation figures added by the caller (relations, ground truth), and
            ``map`` once the map was rendered (or could not be).
        slam: the :class:`~iceg.slam.Slam` that produced the result; :meth:`save` writes
            its session folder (:mod:`iceg.session`) from it.
    """

    stamps_s: FloatArray
    poses: FloatArray
    node_ids: NDArray[np.int64]
    node_poses: FloatArray
    node_scan_index: NDArray[np.int64]
    factors: tuple[FactorRecord, ...]
    correlations: dict[int, float]
    loop_closures: LoopClosureStats
    match_failures: dict[str, int]
    stage_seconds: dict[str, float]
    feature_map: FeatureMap
    graph: PoseGraph
    config: IcegConfig
    scans: Sequence[LaserScan] = ()
    point_fallbacks: dict[str, int] = field(default_factory=dict)
    reused_keyframes: int = 0
    metrics: dict[str, Any] = field(default_factory=dict)
    slam: Slam | None = field(default=None, repr=False)
    _map: TiledGrid | None = field(default=None, init=False, repr=False)
    _map_tried: bool = field(default=False, init=False, repr=False)

    @property
    def n_scans(self) -> int:
        """Number of input scans."""
        return int(self.stamps_s.shape[0])

    def factor_counts(self) -> dict[str, int]:
        """Number of factors per kind."""
        return dict(Counter(f.kind.value for f in self.factors))

    def summary(self) -> dict[str, Any]:
        """Counts, timing and evaluation figures as a JSON-ready dict."""
        total = sum(self.stage_seconds.values())
        return {
            "scans": self.n_scans,
            "nodes": int(self.node_ids.shape[0]),
            "reused_keyframes": self.reused_keyframes,
            "factors": self.factor_counts(),
            "loop_closures": self.loop_closures.as_dict(),
            "match_failures": self.match_failures,
            "point_fallbacks": self.point_fallbacks,
            "stage_seconds": {k: round(v, 6) for k, v in self.stage_seconds.items()},
            "total_seconds": round(total, 6),
            "scans_per_second": self.n_scans / total if total > 0 else float("nan"),
            **self.metrics,
        }

    def __repr__(self) -> str:
        counts = self.factor_counts()
        lc = self.loop_closures
        parts = [
            f"scans={self.n_scans}",
            f"nodes={self.node_ids.shape[0]}",
            "factors={" + ", ".join(f"{k}: {v}" for k, v in sorted(counts.items())) + "}",
            f"loop_closures={lc.accepted}/{lc.attempts}",
            f"time={sum(self.stage_seconds.values()):.2f} s",
        ]
        rel = self.metrics.get("relations")
        if rel:
            parts.append(
                f"relation_error={rel['trans_mean_m']:.3f} m / {rel['rot_mean_deg']:.2f} deg"
            )
        gt = self.metrics.get("ground_truth")
        if gt:
            parts.append(f"position_error={gt['mean_m']:.3f} m")
        return "SlamResult(" + ", ".join(parts) + ")"

    def render_map(self) -> TiledGrid | None:
        """Render (once) the occupancy grid of ``scans`` along ``poses`` (sparse, tiled).

        A map that cannot be rendered (an absurd extent, too many cells) is logged as a
        warning and recorded in ``metrics["map"]``; the result stays usable.

        Returns:
            The :class:`~iceg.grid.TiledGrid`, or None (no scans, or not renderable).
        """
        if self._map_tried:
            return self._map
        return self._adopt_map(*self._rendered())

    def _rendered(self) -> tuple[TiledGrid | GridError | None, float]:
        """The map as :meth:`render_map` renders it, and the seconds it took: the grid, the
        :class:`~iceg_common.errors.GridError` that refused it, or None without scans. Reads
        the scans, poses and configuration and changes nothing, so it may run in another
        thread beside other reads of the result (:meth:`save`)."""
        if not self.scans:
            return None, 0.0
        t0 = time.perf_counter()
        body = self.config.features.robot_body_range_m
        try:
            if isinstance(self.scans, ScanStore):
                # Chunk by chunk: the grid pass adds a constant, not a copy of every beam.
                grid = render_tiled_chunks(
                    self.poses, self.scans.beam_chunk, self.config.grid, range_min_m=body
                )
            else:
                grid = render_tiled(self.scans, self.poses, self.config.grid, range_min_m=body)
        except GridError as exc:
            return exc, time.perf_counter() - t0
        return grid, time.perf_counter() - t0

    def _adopt_map(
        self, rendered: TiledGrid | GridError | None, seconds: float
    ) -> TiledGrid | None:
        """Keep what :meth:`_rendered` returned as the map, with its figures in ``metrics``
        and its time in ``stage_seconds``; the map, or None."""
        self._map_tried = True
        if rendered is None:
            self.metrics["map"] = {"rendered": False, "reason": "no scans"}
            return None
        if isinstance(rendered, GridError):
            logger.warning("no map written: %s", rendered)
            self.metrics["map"] = {"rendered": False, "reason": str(rendered)}
            return None
        self._map = g = rendered
        self.stage_seconds["grid"] = seconds
        self.metrics["map"] = {
            "rendered": True,
            "shape": list(g.shape),
            "resolution_m": g.resolution_m,
            "allocated_cells": g.allocated_cells,
        }
        return g

    @property
    def grid(self) -> OccupancyGrid | None:
        """The map as a dense :class:`~iceg.grid.OccupancyGrid` (rendered on first use);
        None when there is no map.

        Raises:
            GridError: the dense grid would exceed ``config.grid.max_cells`` (use
                :meth:`render_map` for the sparse grid).
        """
        tiled = self.render_map()
        return None if tiled is None else tiled.to_dense(self.config.grid.max_cells)

    def save(self, out_dir: str | Path, on_saved: Callable[[str], None] | None = None) -> Path:
        """Write the result files (:data:`OUTPUT_FILES`) into ``out_dir``, replacing the whole
        previous set there, never part of it.

        Step 1 swaps in :data:`CORE_FILES`; step 2 swaps in the same set plus
        :data:`MAP_FILES` (and ``metrics.json`` with the map's figures). Each step is written
        in a staging folder ``<out_dir>.iceg-saving-<pid>`` beside ``out_dir`` and exchanged
        with ``out_dir`` by one rename, so ``out_dir`` always holds a complete set. A map not
        rendered yet (:meth:`render_map`) is rendered in another thread while step 1 writes:
        the grid's compiled passes release the interpreter, so the writing (formatting,
        hashing, compressing) and the rendering share the cores; the files are the same.

        Args:
            out_dir: The output folder (created with its parents if missing).
            on_saved: Called with ``"core"`` after step 1 and ``"map"`` after step 2.

        Returns:
            ``out_dir`` as a Path.

        Raises:
            OutputError: ``out_dir`` is a file or a folder that is not a result folder, or it
                cannot be written.
        """
        out = Path(out_dir)
        check_output_dir(out)
        clean_stale_staging(out)
        self.metrics.setdefault(
            "map", {"rendered": False, "reason": "pending: written by the second save step"}
        )
        with concurrent.futures.ThreadPoolExecutor(1, "iceg-map") as beside:
            rendering = None if self._map_tried else beside.submit(self._rendered)
            self._save_steps(out, on_saved, rendering)
        return out

    def _save_steps(
        self,
        out: Path,
        on_saved: Callable[[str], None] | None,
        rendering: concurrent.futures.Future[tuple[TiledGrid | GridError | None, float]] | None,
    ) -> None:
        """:meth:`save`'s two steps, the map from ``rendering`` where it is being rendered."""
        try:
            with _staging(out) as staging:
                self._write_core(staging)
                _swap_in(staging, out)
            if on_saved is not None:
                on_saved("core")
            grid = self.render_map() if rendering is None else self._adopt_map(*rendering.result())
            with _staging(out) as staging:
                _link_files(out, staging, CORE_FILES)
                if (out / SESSION_DIR).is_dir():
                    from iceg.session import link_session

                    link_session(out / SESSION_DIR, staging / SESSION_DIR)
                if grid is not None:
                    write_map_server(grid, staging / "map")
                    write_png(grid, staging / "map.png", trajectory=self.poses)
                self._write_metrics(staging)
                _swap_in(staging, out)
            if on_saved is not None:
                on_saved("map")
        except OSError as exc:
            raise OutputError(f"{out}: cannot write the results ({exc})") from exc

    def _write_core(self, folder: Path) -> None:
        write_tum(folder / "trajectory.tum", self.stamps_s, self.poses)
        self._write_metrics(folder)
        if self.slam is not None:
            from iceg.session import CONFIG, GRAPH
            from iceg.session import save as save_session

            save_session(self.slam, folder / SESSION_DIR)
            if self.slam.graph is self.graph and self.slam.config is self.config:
                # The session wrote the same graph (estimates and factors) and configuration
                # under the same names: linked, not formatted and written twice.
                _link_files(folder / SESSION_DIR, folder, (GRAPH, CONFIG))
                return
        self.graph.write_g2o(folder / "graph.g2o")
        with atomic_write(folder / "config.yaml") as fh:
            fh.write(self.config.to_yaml())

    def _write_metrics(self, folder: Path) -> None:
        target = folder / "metrics.json"
        with contextlib.suppress(FileNotFoundError):
            target.unlink()  # a hard link to the previous step's file: do not write through it
        with atomic_write(target) as fh:
            json.dump(self.summary(), fh, indent=2, sort_keys=False)
            fh.write("\n")


# ---------------------------------------------------------------------------------------------
# Output folders
# ---------------------------------------------------------------------------------------------


def check_output_dir(out: Path) -> None:
    """Fail early (before a run) when results cannot be written to ``out``.

    ``out`` may be missing (it is created, with its parents) or a folder that is empty or
    holds a previous result set (it is replaced as a whole).

    Raises:
        OutputError: ``out`` (or a parent) is a file, ``out`` is a folder holding other
            files, or the nearest existing parent is not writable.
    """
    if out.exists() and not out.is_dir():
        raise OutputError(f"{out}: exists and is not a folder; choose another --out")
    if out.is_dir():
        known = (*OUTPUT_FILES, SESSION_DIR)
        foreign = sorted(p.name for p in out.iterdir() if p.name not in known)
        if foreign:
            raise OutputError(
                f"{out}: the folder holds files that are not iceg results ({foreign[0]}"
                f"{' ...' if len(foreign) > 1 else ''}); choose an empty or new --out"
            )
    parent = out.parent
    while not parent.exists():
        parent = parent.parent
    if not parent.is_dir():
        raise OutputError(f"{out}: {parent} is not a folder; choose another --out")
    if not os.access(parent, os.W_OK | os.X_OK):
        raise OutputError(f"{out}: {parent} is not writable; choose another --out")


def clean_stale_staging(out: Path) -> list[Path]:
    """Remove staging folders ``<out>.iceg-saving-<pid>`` left by killed saves into ``out``
    (those of a process still running are kept).

    Returns:
        The folders removed.
    """
    removed: list[Path] = []
    if not out.parent.is_dir():
        return removed
    for p in out.parent.glob(f"{out.name}{STAGING_MARKER}*"):
        pid = p.name.rsplit("-", 1)[-1]
        if pid.isdigit() and int(pid) != os.getpid() and _alive(int(pid)):
            continue
        shutil.rmtree(p, ignore_errors=True)
        removed.append(p)
        logger.info("removed %s, left by an interrupted save", p)
    return removed


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


@contextlib.contextmanager
def _staging(out: Path) -> Iterator[Path]:
    """A fresh staging folder beside ``out``; removed on exit (it holds the old set after a
    swap, or a partial set after an error)."""
    out.parent.mkdir(parents=True, exist_ok=True)
    staging = out.parent / f"{out.name}{STAGING_MARKER}{os.getpid()}"
    shutil.rmtree(staging, ignore_errors=True)
    staging.mkdir()
    try:
        yield staging
    finally:
        shutil.rmtree(staging, ignore_errors=True)


def _link_files(src: Path, dst: Path, names: tuple[str, ...]) -> None:
    """Hard-link (or copy) ``names`` from ``src`` into ``dst``."""
    for name in names:
        try:
            os.link(src / name, dst / name)
        except OSError:
            shutil.copy2(src / name, dst / name)


_RENAME_EXCHANGE = 2
_AT_FDCWD = -100


def _swap_in(staging: Path, out: Path) -> None:
    """Make ``staging`` the folder ``out`` with one rename; the previous ``out`` (if any) ends
    up at ``staging`` (removed by the caller). Uses ``renameat2(RENAME_EXCHANGE)`` (Linux);
    where it is unavailable, ``out`` is moved aside and ``staging`` renamed in its place."""
    if not out.exists():
        os.rename(staging, out)
        return
    if _exchange(staging, out):
        return
    aside = staging.with_name(staging.name + "-old")
    os.rename(out, aside)
    os.rename(staging, out)
    os.rename(aside, staging)


def _exchange(a: Path, b: Path) -> bool:
    """Atomically exchange two paths; False when the platform or filesystem cannot."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        renameat2 = libc.renameat2
    except (OSError, AttributeError):
        return False
    rc = renameat2(_AT_FDCWD, os.fsencode(a), _AT_FDCWD, os.fsencode(b), _RENAME_EXCHANGE)
    if rc == 0:
        return True
    err = ctypes.get_errno()
    if err in (errno.EINVAL, errno.ENOSYS, errno.ENOTSUP):
        return False
    raise OSError(err, os.strerror(err), str(b))
