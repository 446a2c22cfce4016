"""Saved SLAM sessions: a folder that gives back a :class:`~iceg.slam.Slam` exactly where a run
ended, for continuing, localizing, merging and editing (issue 15).

Layout of a session folder (``<run output>/session/``, format ``iceg-session`` version 1)::

    manifest.json      format, version, counts, the logs the scans come from (absolute and
                       relative paths), loop and match statistics, ``online_factors`` (the
                       factors before the final refinement); written last
    state.npz          every array below (numpy ``.npz``, read with allow_pickle=False)
    graph.g2o          the pose graph at the saved (batch-refined) estimates, factor kinds,
                       robust kernels and priors as ``# ICEG_*`` lines (graph.g2o)
    loop_closures.csv  one row per loop closure, accepted or held back (see CLOSURE_COLUMNS)
    config.yaml        the run's configuration

``state.npz`` arrays (frames: the map frame unless said; metres, radians, seconds):

- graph ``g_*``: ``g_node_ids (N,)`` int64 ascending (the order nodes were added),
  ``g_node_initial (N, 3)`` initial values, ``g_node_final (N, 3)`` estimates when saved;
  factors in insertion order ``g_kind (F,)`` (index into :data:`FACTOR_KINDS`), ``g_ij (F, 2)``
  (``j = -1`` for a prior), ``g_measured (F, 3)``, ``g_cov (F, 3, 3)`` (tangent space of the
  measurement, gtsam convention), ``g_robust (F,)`` (index into :data:`ROBUST_KERNELS`),
  ``g_robust_k (F,)`` (NaN: none), ``g_origin (F,)`` (0: the run, 1: added by the user),
  ``g_correlation (F,)`` (ICE correlation, NaN: none); ``g_steps (S, 3)`` the solver call log
  (:attr:`graph.PoseGraph.steps`) that rebuilds iSAM2 bit for bit.
- scans ``s_*``: one row per processed scan in order: ``s_stamp``, ``s_node`` (its node),
  ``s_delta (R, 3)`` (odometry from the node's scan), ``s_log`` (index into the manifest's
  ``logs``; -1: stored inline in ``inline_*``), ``s_key`` (the record's place in its log,
  e.g. the CARMEN line), ``s_hash`` (sha256 prefix of the scan's content).
- nodes ``n_*``: ``n_scan (N,)`` scan row of each node, ``n_odom (N, 3)`` odometry pose,
  ``n_odom_measured (N,)``, ``n_path_m (N,)`` odometry path length.
- held-back loop closures ``lc_*``: ``lc_ij (P, 2)``, ``lc_measured (P, 3)``,
  ``lc_cov (P, 3, 3)``, ``lc_correlation (P,)``, ``lc_implied (P, 3)``; the place index of
  the global loop-closure search ``lc_places_rows (n, D)`` (descriptors) and
  ``lc_places_ids (n,)``; the odometry calibration ``cal_state (14,)``
  (:meth:`iceg.odometry_calibration.OdometryCalibrator.export_state`).
- disputed keyframe steps ``d_*`` (:attr:`iceg.slam.SlamState.disputed`): ``d_node (D,)``,
  ``d_pose (D, 3)``, ``d_cov (D, 3, 3)``, ``d_correlation (D,)``.
- the feature map ``fm_*`` (:meth:`iceg.feature_map.FeatureMap.export_state`).
- inline scans (runs from memory, e.g. the simulator): ``inline_meta (K, 10)``
  ``[stamp, range_min, range_max, odom x y theta (NaN: none), offset x y theta, odom_break]``,
  ``inline_offsets (K + 1,)`` into ``inline_ranges`` / ``inline_angles``.

Continuation is exact: :func:`load` replays the factor log with the same update() calls (the
final batch refinement of the saved run is left out, as an uninterrupted run has none at that
point), restores the bookkeeping, the feature map and the held-back closures, and re-reads each
scan from its log by reference, checking its hash.
"""

from __future__ import annotations

import hashlib
import json
import logging
import os
from collections import defaultdict
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends import LaserScan, open_log
from frontends.odometry_shift import shift_odometry
from graph import FactorKind, FactorRecord, GraphConfig, PoseGraph
from graph.g2o import write_g2o_file
from graph.pose_graph import (
    STEP_BATCH,
    STEP_BATCH_CORRECTION,
    STEP_BATCH_GAUSSIAN_LOOPS,
    STEP_DELTA,
    STEP_UPDATE,
)
from iceg.config import IcegConfig, config_from_yaml
from iceg.feature_map import FeatureMap
from iceg.loop_closure import LoopClosure, LoopClosureStats
from iceg.scan_poses import odometry_steps, scan_poses
from iceg.scan_store import ScanStore
from iceg.slam import Anchor, ScanRecords, Slam, SlamState
from iceg.types import MatchResult
from iceg_common import se2
from iceg_common.atomic import atomic_write
from iceg_common.errors import IcegError, SessionError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

SESSION_DIR = "session"
FORMAT = "iceg-session"
FORMAT_VERSION = 1
MANIFEST, STATE, GRAPH, CLOSURES, CONFIG = (
    "manifest.json",
    "state.npz",
    "graph.g2o",
    "loop_closures.csv",
    "config.yaml",
)
SESSION_FILES = (STATE, GRAPH, CLOSURES, CONFIG, MANIFEST)

FACTOR_KINDS: tuple[FactorKind, ...] = tuple(FactorKind)
ROBUST_KERNELS: tuple[str | None, ...] = (None, "huber", "cauchy")
ORIGIN_RUN, ORIGIN_USER = 0, 1

#: Columns of ``loop_closures.csv``.
CLOSURE_COLUMNS = (
    "factor",  # factor index in the graph (-1: held back, not in the graph)
    "node_i",  # the old node
    "node_j",  # the new node
    "stamp_i_s",
    "stamp_j_s",
    "x_m",  # measured pose of node_j in the frame of node_i
    "y_m",
    "theta_rad",
    "cov_xx",  # covariance, tangent space of the measurement (upper triangle)
    "cov_xy",
    "cov_xt",
    "cov_yy",
    "cov_yt",
    "cov_tt",
    "correlation",  # ICE correlation (eq. 1), NaN for a closure given with its pose
    "chi2",  # Mahalanobis distance² of the residual at the saved estimate (3 dof)
    "status",  # accepted | held_back
    "why",
)


# --------------------------------------------------------------------------- graph table


def graph_arrays(
    graph: PoseGraph,
    correlations: Mapping[int, float] | None = None,
    origin: Sequence[int] | None = None,
) -> dict[str, np.ndarray]:
    """The ``g_*`` arrays of a graph (see the module docstring)."""
    ids, final = graph.estimates()
    recs = graph.factors
    corr = correlations or {}
    return {
        "g_node_ids": ids,
        "g_node_initial": np.array([graph.initial_pose(int(n)) for n in ids]).reshape(-1, 3),
        "g_node_final": final,
        "g_kind": np.array([FACTOR_KINDS.index(r.kind) for r in recs], dtype=np.int64),
        "g_ij": np.array([[r.i, -1 if r.j is None else r.j] for r in recs], dtype=np.int64),
        "g_measured": np.array([r.measured for r in recs]).reshape(-1, 3),
        "g_cov": np.array([r.cov for r in recs]).reshape(-1, 3, 3),
        "g_robust": np.array([ROBUST_KERNELS.index(r.robust) for r in recs], dtype=np.int64),
        "g_robust_k": np.array([np.nan if r.robust_k is None else r.robust_k for r in recs]),
        "g_origin": np.asarray(
            origin if origin is not None else [ORIGIN_RUN] * len(recs), dtype=np.int64
        ),
        "g_correlation": np.array([corr.get(r.index, np.nan) for r in recs], dtype=np.float64),
        "g_steps": np.array(graph.steps, dtype=np.int64).reshape(-1, 3),
    }


def factor_records(a: Mapping[str, np.ndarray]) -> list[FactorRecord]:
    """The factors of ``g_*`` arrays as :class:`graph.FactorRecord` (index = row)."""
    out = []
    for k in range(a["g_kind"].shape[0]):
        j = int(a["g_ij"][k, 1])
        rk = float(a["g_robust_k"][k])
        out.append(
            FactorRecord(
                k,
                FACTOR_KINDS[int(a["g_kind"][k])],
                int(a["g_ij"][k, 0]),
                None if j < 0 else j,
                a["g_measured"][k],
                a["g_cov"][k],
                ROBUST_KERNELS[int(a["g_robust"][k])],
                None if np.isnan(rk) else rk,
            )
        )
    return out


def _add_factor(graph: PoseGraph, r: FactorRecord) -> None:
    if r.j is None:
        graph.add_prior(r.i, r.measured, r.cov)
    else:
        graph.add_between(
            r.i,
            r.j,
            r.measured,
            r.cov,
            kind=r.kind,
            robust=r.robust,  # type: ignore[arg-type]
            robust_k=r.robust_k,
        )


def replay_graph(
    a: Mapping[str, np.ndarray],
    config: GraphConfig,
    *,
    skip_final_batch: bool = True,
    online_factors: int | None = None,
) -> PoseGraph:
    """Rebuild a graph by replaying its solver call log (``g_steps``): the same nodes, factors
    and calls in the same order, hence the same iSAM2 state bit for bit. Nodes and factors
    saved after the last call (the keyframes between deferred updates of a long run,
    ``SlamConfig.isam2_defer_from_nodes``) are buffered again for the next
    :meth:`~graph.PoseGraph.update`.

    Args:
        a: ``g_*`` arrays (:func:`graph_arrays`).
        config: the graph settings of the saved run.
        skip_final_batch: leave out a batch refinement that ended the log (the run's
            ``finish()``), so that the graph continues as the uninterrupted run would.
        online_factors: with a final batch left out, the number of factors before it
            (:attr:`iceg.slam.Slam.online_factors`): those after the last call up to it are
            buffered again; ``None`` (older sessions): none are.

    Raises:
        SessionError: the log refers to more nodes or factors than saved.
        GraphError: gtsam failed on the replayed calls.
    """
    steps = [tuple(int(v) for v in s) for s in a["g_steps"]]
    trimmed = False
    if skip_final_batch:
        last = max((k for k, s in enumerate(steps) if s[0] != STEP_DELTA), default=-1)
        if last >= 0 and steps[last][0] in (STEP_BATCH, STEP_BATCH_GAUSSIAN_LOOPS):
            steps, trimmed = steps[:last], True
    ids, init, recs = a["g_node_ids"], a["g_node_initial"], factor_records(a)
    # A batch step does not log its node count: every node it saw was linked by one of its
    # factors, so its nodes are the prefix (in order of addition) up to the last they name.
    position = {int(n): k for k, n in enumerate(ids.tolist())}
    named = [max(position.get(r.i, 0), 0 if r.j is None else position.get(r.j, 0)) for r in recs]
    last_named = np.maximum.accumulate(named or [0])
    graph = PoseGraph(config, auto_prior=False)
    nn = nf = 0
    for code, n_a, n_b in steps:
        if code == STEP_DELTA:
            graph.read_delta()
            continue
        # (a step beyond the saved factors is refused just below)
        batch_nodes = int(last_named[min(n_b, len(recs)) - 1]) + 1 if n_b else nn
        upto_nodes = n_a if code == STEP_UPDATE else batch_nodes
        if upto_nodes > len(ids) or n_b > len(recs):
            raise SessionError(f"solver log step {(code, n_a, n_b)} beyond the saved graph")
        for k in range(nn, upto_nodes):
            graph.add_node(int(ids[k]), init[k])
        for r in recs[nf:n_b]:
            _add_factor(graph, r)
        nn, nf = max(nn, upto_nodes), n_b
        if code == STEP_UPDATE:
            graph.update()
        else:
            graph.optimize_batch(
                n_a,
                loop_closure_kernels=code != STEP_BATCH_GAUSSIAN_LOOPS,
                correction=code == STEP_BATCH_CORRECTION,
            )
    # Nodes and factors after the last call were buffered for the next update (a run saved
    # between the deferred iSAM2 updates of a long log): buffer them again, without the
    # factors of a final refinement left out.
    end = len(recs)
    if trimmed:
        end = nf if online_factors is None else online_factors
    for k in range(nn, len(ids)):
        graph.add_node(int(ids[k]), init[k])
    for r in recs[nf:end]:
        _add_factor(graph, r)
    return graph


def rebuild_graph(a: Mapping[str, np.ndarray], config: GraphConfig) -> PoseGraph:
    """A new graph of the factors of ``g_*`` arrays, every node starting at its saved
    estimate, through one iSAM2 update (its own call log then replays it exactly).

    Raises:
        GraphError: a node is left without factor, or gtsam failed.
    """
    graph = PoseGraph(config, auto_prior=False)
    for n, pose in zip(a["g_node_ids"].tolist(), a["g_node_final"], strict=True):
        graph.add_node(n, pose)
    for r in factor_records(a):
        _add_factor(graph, r)
    graph.update()
    return graph


# --------------------------------------------------------------------------- scans


def scan_hash(scan: LaserScan) -> str:
    """Content hash of a scan (16 hex digits of sha256 over stamp, ranges, bearings,
    odometry and laser offset): the check that a re-read scan is the saved one."""
    return _content_hash(
        scan.stamp_s, scan.ranges_m, scan.angles_rad, scan.laser_offset, scan.odom_pose
    )


def _content_hash(
    stamp_s: float,
    ranges_m: ArrayLike,
    angles_rad: ArrayLike,
    laser_offset: ArrayLike,
    odom_pose: ArrayLike | None,
) -> str:
    """:func:`scan_hash` of a scan's values."""
    h = hashlib.sha256()
    h.update(np.float64(stamp_s).tobytes())
    for arr in (ranges_m, angles_rad, laser_offset):
        h.update(np.ascontiguousarray(arr, dtype=np.float64).tobytes())
    if odom_pose is not None:
        h.update(np.ascontiguousarray(odom_pose, dtype=np.float64).tobytes())
    return h.hexdigest()[:16]


#: Scans whose beams :func:`_store_hashes` decodes at a time.
_HASH_CHUNK_SCANS = 1024


def _store_hashes(scans: ScanStore) -> list[str]:
    """:func:`scan_hash` of every scan of a store, from its arrays (a chunk of scans' beams
    decoded at a time), without building the scans."""
    _, odom, _ = scans.odometry
    has_odom = [bool(v) for v in np.isfinite(odom[:, 0])]  # finite odometry, or a NaN row
    stamps = scans.stamps_s.tolist()
    hashes: list[str] = []
    for lo in range(0, len(scans), _HASH_CHUNK_SCANS):
        chunk = scans.beam_chunk(lo, min(lo + _HASH_CHUNK_SCANS, len(scans)))
        ends = np.cumsum(chunk.beam_counts).tolist()
        for k, (a, b) in enumerate(zip([0, *ends[:-1]], ends, strict=True)):
            n = lo + k
            hashes.append(
                _content_hash(
                    stamps[n],
                    chunk.ranges_m[a:b],
                    chunk.angles_rad[a:b],
                    chunk.laser_offsets[k],
                    odom[n] if has_odom[n] else None,
                )
            )
    return hashes


def _split_source(source: str, resolved: dict[str, str | None]) -> tuple[str, str] | None:
    """``(absolute path, key)`` of a ``path:key`` source whose path is a readable log, else
    None; ``resolved`` memoizes each path's absolute form (None: not a log)."""
    path, sep, key = source.rpartition(":")
    if path not in resolved:
        exists = bool(sep and path and os.path.exists(path))
        resolved[path] = str(Path(path).resolve()) if exists else None
    absolute = resolved[path]  # no ":" leaves path "", never a log
    return None if absolute is None else (absolute, key)


def scan_arrays(
    scans: Sequence[LaserScan],
    session_dir: Path,
    readings: Mapping[str, Mapping[str, Any]] | None = None,
) -> tuple[dict[str, np.ndarray], list[dict[str, Any]]]:
    """Scan references (``s_log``, ``s_key``, ``s_hash``) and inline scans, and the logs table
    of the manifest (``{"path": absolute, "relative": from the session folder}``, with the
    entries of ``readings[absolute path]``: how the log was read, :data:`READING_KEYS`).
    Scans from memory, and those of a log whose reading is marked :data:`STORED_INLINE`,
    are stored inline."""
    logs: dict[str, int] = {}
    log_idx: list[int] = []
    keys: list[str] = []
    inline: list[LaserScan] = []
    resolved: dict[str, str | None] = {}  # a source's log, resolved once per path
    if isinstance(scans, ScanStore):  # from its arrays: no scan built but the inline ones
        hashes, sources = _store_hashes(scans), scans.sources()
    else:
        hashes, sources = [scan_hash(s) for s in scans], [s.source for s in scans]
    for k, source in enumerate(sources):
        split = _split_source(source, resolved)
        if split is None or (readings or {}).get(split[0], {}).get(STORED_INLINE):
            log_idx.append(-1)
            keys.append(str(len(inline)))
            inline.append(scans[k])
            continue
        path, key = split
        log_idx.append(logs.setdefault(path, len(logs)))
        keys.append(key)
    out = {
        "s_log": np.array(log_idx, dtype=np.int64),
        "s_key": np.array(keys, dtype=np.str_),
        "s_hash": np.array(hashes, dtype=np.str_),
        **_inline_arrays(inline),
    }
    table = [
        {
            "path": p,
            "relative": os.path.relpath(p, session_dir.resolve()),
            **_reading(p, readings or {}),
        }
        for p in logs
    ]
    return out, table


#: How a log was read, in its entry of the manifest's logs table: the keyword options of
#: :func:`frontends.open_log` (a bag's topics, frames, laser offset) and the odometry time
#: offset (:func:`frontends.odometry_shift.shift_odometry`). Without them the log is read
#: as it is: a session's scans must be read again as they were, or their hashes differ.
READING_KEYS = ("reader_options", "odometry_time_offset_s")

#: A log's reading key: its scans were changed after reading (synthetic odometry replacing
#: the log's, the odometry dropped: ``iceg batch``), so no reading gives them back; the
#: session stores them inline.
STORED_INLINE = "stored_inline"


def record_reading(
    slam: Slam,
    path: str | os.PathLike[str],
    reader_options: Mapping[str, Any] | None,
    odometry_time_offset_s: float,
    changed: bool = False,
) -> None:
    """Note in ``slam.log_readings`` how the log at ``path`` was read (:data:`READING_KEYS`),
    for its session (:func:`save`) to read the scans again the same way; ``changed``: the
    scans were changed after reading, and the session stores them (:data:`STORED_INLINE`)."""
    slam.log_readings[str(Path(path).resolve())] = {
        "reader_options": dict(reader_options or {}),
        "odometry_time_offset_s": odometry_time_offset_s,
        STORED_INLINE: changed,
    }


def _reading(path: str, readings: Mapping[str, Mapping[str, Any]]) -> dict[str, Any]:
    """The :data:`READING_KEYS` entries of log ``path`` (absolute) that differ from a plain
    read, JSON-ready."""
    got = readings.get(path, {})
    out: dict[str, Any] = {}
    if got.get("reader_options"):
        out["reader_options"] = {
            k: list(v) if isinstance(v, tuple) else v for k, v in got["reader_options"].items()
        }
    if got.get("odometry_time_offset_s"):
        out["odometry_time_offset_s"] = float(got["odometry_time_offset_s"])
    return out


def _inline_arrays(scans: Sequence[LaserScan]) -> dict[str, np.ndarray]:
    meta = np.zeros((len(scans), 10))
    for k, s in enumerate(scans):
        odom = s.odom_pose if s.odom_pose is not None else np.full(3, np.nan)
        meta[k] = [s.stamp_s, s.range_min_m, s.range_max_m, *odom, *s.laser_offset, s.odom_break]
    lengths = [s.ranges_m.shape[0] for s in scans]
    cat = (lambda xs: np.concatenate(xs)) if scans else (lambda xs: np.zeros(0))
    return {
        "inline_meta": meta,
        "inline_offsets": np.concatenate([[0], np.cumsum(lengths)]).astype(np.int64),
        "inline_ranges": cat([s.ranges_m for s in scans]),
        "inline_angles": cat([s.angles_rad for s in scans]),
    }


def _inline_scans(a: Mapping[str, np.ndarray]) -> list[LaserScan]:
    meta, off = a["inline_meta"], a["inline_offsets"]
    out = []
    for k in range(meta.shape[0]):
        m = meta[k]
        out.append(
            LaserScan(
                stamp_s=float(m[0]),
                ranges_m=a["inline_ranges"][off[k] : off[k + 1]].copy(),
                angles_rad=a["inline_angles"][off[k] : off[k + 1]].copy(),
                range_min_m=float(m[1]),
                range_max_m=float(m[2]),
                odom_pose=None if np.isnan(m[3]) else m[3:6].copy(),
                laser_offset=m[6:9].copy(),
                source=f"<session inline scan {k}>",
                odom_break=bool(m[9]),
            )
        )
    return out


def read_scans(session: Session, rows: Sequence[int] | None = None) -> list[LaserScan]:
    """Scans of a session (every one, in processing order, or the scan ``rows``), re-read
    from their logs by reference (or from the inline arrays).

    Raises:
        SessionError: a log is missing, a scan is not in it, or its content hash differs.
    """
    a = session.arrays
    inline = _inline_scans(a)
    by_log: dict[int, dict[str, LaserScan]] = {}
    out = []
    wanted = range(a["s_log"].shape[0]) if rows is None else rows
    for k in wanted:
        li, key, digest = int(a["s_log"][k]), str(a["s_key"][k]), str(a["s_hash"][k])
        if li < 0:
            scan = inline[int(key)]
        else:
            if li not in by_log:
                by_log[li] = _read_log(session, li)
            scan = by_log[li].get(key)  # type: ignore[assignment]
            if scan is None:
                raise SessionError(f"{session.log_path(li)}: has no scan record {key} (scan {k})")
        if scan_hash(scan) != digest:
            raise SessionError(
                f"{scan.source}: the scan differs from the one saved in {session.path} "
                "(content hash); was the log changed?"
            )
        out.append(scan)
    return out


def _read_log(session: Session, li: int) -> dict[str, LaserScan]:
    """The scans of log ``li`` by record key, read as the run read them (:data:`READING_KEYS`)."""
    path = session.log_path(li)
    entry = session.manifest["logs"][li]
    try:
        reader = open_log(path, **entry.get("reader_options", {}))
        scans = list(shift_odometry(reader, entry.get("odometry_time_offset_s", 0.0)))
    except IcegError as exc:
        raise SessionError(f"{session.path}: cannot re-read its log {path}: {exc}") from exc
    return {s.source.rpartition(":")[2]: s for s in scans}


# --------------------------------------------------------------------------- Slam state


def _slam_arrays(slam: Slam) -> dict[str, np.ndarray]:
    s = slam.export_state()
    stamps, nodes, deltas = s.records.arrays()
    pend = slam.loop_closer.pending
    return {
        "s_stamp": stamps,
        "s_node": nodes,
        "s_delta": deltas,
        "n_scan": np.array(s.node_scan_index, dtype=np.int64),
        "n_odom": np.array(s.node_odom).reshape(-1, 3),
        "n_odom_measured": np.array(s.node_odom_measured, dtype=bool),
        "n_path_m": np.array(s.node_path_m, dtype=np.float64),
        "lc_ij": np.array([[c.node_from, c.node_to] for c in pend], dtype=np.int64).reshape(-1, 2),
        "lc_measured": np.array([c.measured for c in pend]).reshape(-1, 3),
        "lc_cov": np.array([c.cov for c in pend]).reshape(-1, 3, 3),
        "lc_correlation": np.array([c.correlation for c in pend], dtype=np.float64),
        "lc_implied": np.array([c.implied for c in pend]).reshape(-1, 3),
        **{f"lc_places_{k}": v for k, v in slam.loop_closer.places.export_state().items()},
        "cal_state": slam.odometry_calibrator.export_state(),
        # slam.reuse_nodes: the old node a revisit hangs from, the newest node placed in an
        # old node's frame (the next keyframe tries that place), the keyframes hung so far
        "reuse_anchor": _anchor_array(s.anchor),
        "reuse_from": _anchor_array(s.reuse_from),
        "reuse_count": np.array([s.reused_keyframes], dtype=np.int64),
        # the disputed keyframe steps a later closure may confirm (SlamState.disputed)
        "d_node": np.array(list(s.disputed), dtype=np.int64),
        "d_pose": np.array([r.pose for r in s.disputed.values()]).reshape(-1, 3),
        "d_cov": np.array([r.cov for r in s.disputed.values()]).reshape(-1, 3, 3),
        "d_correlation": np.array([r.correlation for r in s.disputed.values()], dtype=np.float64),
    }


def _factor_prefix(a: Mapping[str, np.ndarray], n: int) -> dict[str, np.ndarray]:
    """The arrays with only the first ``n`` factors: those of the online run when the replay
    left out the final refinement (whose factors, :meth:`iceg.slam.Slam.finish`, come after)."""
    return {k: v[:n] if k in FACTOR_ARRAYS else v for k, v in a.items()}


def _slam_state(session: Session, a: Mapping[str, np.ndarray], scans: list[LaserScan]) -> SlamState:
    corr = a["g_correlation"]
    return SlamState(
        scans=ScanStore(scans),
        records=ScanRecords(a["s_stamp"], a["s_node"], a["s_delta"]),
        node_scan_index=[int(v) for v in a["n_scan"]],
        node_odom=[p.copy() for p in a["n_odom"]],
        node_odom_measured=[bool(v) for v in a["n_odom_measured"]],
        node_matched=node_matched(a),
        node_path_m=[float(v) for v in a["n_path_m"]],
        correlations={int(k): float(corr[k]) for k in np.flatnonzero(np.isfinite(corr))},
        match_failures=defaultdict(int, session.manifest.get("match_failures", {})),
        point_fallbacks=defaultdict(int, session.manifest.get("point_fallbacks", {})),
        segment_start=segment_start(a),
        log_start=log_start(a),
        anchor=_anchor_of(a, "reuse_anchor"),
        reuse_from=_anchor_of(a, "reuse_from"),
        reused_keyframes=int(a["reuse_count"][0]) if "reuse_count" in a else 0,
        disputed=_disputed(a),
    )


def _disputed(a: Mapping[str, np.ndarray]) -> dict[int, MatchResult]:
    """The disputed keyframe steps (:attr:`iceg.slam.SlamState.disputed`); none in a session
    saved before they were kept."""
    if "d_node" not in a:
        return {}
    return {
        int(k): MatchResult(True, p.copy(), c.copy(), float(r))
        for k, p, c, r in zip(a["d_node"], a["d_pose"], a["d_cov"], a["d_correlation"], strict=True)
    }


def _anchor_array(anchor: Anchor | None) -> np.ndarray:
    return anchor.as_array() if anchor is not None else np.zeros(0)


def _anchor_of(a: Mapping[str, np.ndarray], key: str) -> Anchor | None:
    """The anchor saved under ``key``; None when empty or absent (a session saved before
    ``slam.reuse_nodes``)."""
    v = a.get(key)
    return Anchor.from_array(v) if v is not None and v.size else None


def node_matched(a: Mapping[str, np.ndarray]) -> list[bool]:
    """Per node, whether it was placed by a match (:attr:`iceg.slam.SlamState.node_matched`):
    a scan-match factor into it (from the node before it, or from the old node a revisit
    hung from: ``slam.reuse_nodes``), or no odometry factor into it (the first
    node of a log, placed by :meth:`iceg.slam.Slam.start_segment` or fixed at the start).

    Args:
        a: A session's arrays (``g_node_ids``, ``g_kind``, ``g_ij``).

    Returns:
        One bool per entry of ``g_node_ids``, in its order.
    """
    kind, ij = a["g_kind"], a["g_ij"]
    scan_match = ij[kind == FACTOR_KINDS.index(FactorKind.SCAN_MATCH), 1]
    odometry = ij[kind == FACTOR_KINDS.index(FactorKind.ODOMETRY), 1]
    ids = a["g_node_ids"]
    return (np.isin(ids, scan_match) | ~np.isin(ids, odometry)).tolist()


def segment_start(a: Mapping[str, np.ndarray]) -> int:
    """First node of the session's last log, or of its path after a revisit left the old
    nodes (``slam.reuse_nodes``): the last node without an odometry factor from the node
    before it (:meth:`iceg.slam.Slam.start_segment`; 0 for a single run)."""
    return _last_without_odometry(a, from_previous=True)


def log_start(a: Mapping[str, np.ndarray]) -> int:
    """First node of the session's last log: the last node without an odometry factor to it
    (:meth:`iceg.slam.Slam.start_segment` links it by its placement only; 0 for a single
    run)."""
    return _last_without_odometry(a, from_previous=False)


def _last_without_odometry(a: Mapping[str, np.ndarray], from_previous: bool) -> int:
    """The last node (id > 0) no odometry factor leads to; with ``from_previous`` only
    factors from the node before it count (not from an old node, ``slam.reuse_nodes``)."""
    odo = a["g_kind"] == FACTOR_KINDS.index(FactorKind.ODOMETRY)
    if from_previous:
        odo &= a["g_ij"][:, 1] == a["g_ij"][:, 0] + 1
    linked = set(a["g_ij"][odo, 1].tolist())
    starts = [int(n) for n in a["g_node_ids"].tolist() if n > 0 and n not in linked]
    return max(starts, default=0)


def _pending(a: Mapping[str, np.ndarray]) -> list[LoopClosure]:
    return [
        LoopClosure(int(ij[0]), int(ij[1]), m.copy(), c.copy(), float(r), implied=p.copy())
        for ij, m, c, r, p in zip(
            a["lc_ij"],
            a["lc_measured"],
            a["lc_cov"],
            a["lc_correlation"],
            a["lc_implied"],
            strict=True,
        )
    ]


# --------------------------------------------------------------------------- session


@dataclass
class Session:
    """A session folder read into memory (nothing replayed yet).

    Attributes:
        path: the session folder.
        manifest: ``manifest.json`` as a dict.
        config: the run's configuration.
        arrays: every array of ``state.npz`` (see the module docstring).
    """

    path: Path
    manifest: dict[str, Any]
    config: IcegConfig
    arrays: dict[str, np.ndarray]

    @property
    def edited(self) -> bool:
        """Whether the graph was edited and re-optimized (``iceg optimize``): its solver log
        ends with a batch refinement that belongs to the state (kept on load)."""
        return bool(self.manifest.get("edited", False))

    @property
    def node_poses(self) -> tuple[IntArray, FloatArray]:
        """Saved node estimates: ``ids (N,)``, ``poses (N, 3)`` map frame."""
        return self.arrays["g_node_ids"], self.arrays["g_node_final"]

    def log_path(self, li: int) -> Path:
        """Path of log ``li``: relative to the session folder if it exists there, else the
        absolute path saved."""
        entry = self.manifest["logs"][li]
        rel = (self.path / entry["relative"]).resolve()
        return rel if rel.exists() else Path(entry["path"])

    def trajectory(self, node_poses: FloatArray | None = None) -> tuple[FloatArray, FloatArray]:
        """Pose of every scan, ``(stamps_s (R,), poses (R, 3))``, from node poses (the saved
        estimates by default; rows = ``g_node_ids`` order) and each scan's odometry delta,
        as :meth:`iceg.slam.Slam.trajectory` gives them (:func:`iceg.scan_poses.scan_poses`)."""
        a = self.arrays
        poses = a["g_node_final"] if node_poses is None else node_poses
        ids = a["g_node_ids"]
        step_from, steps = odometry_steps(
            a["g_kind"] == FACTOR_KINDS.index(FactorKind.ODOMETRY),
            a["g_ij"],
            a["g_measured"],
            a["g_cov"],
            self.config.slam.no_odometry_covariance(),
        )
        stamps = a["s_stamp"].copy()
        return stamps, scan_poses(
            stamps,
            a["s_node"],
            a["s_delta"],
            ids,
            poses,
            a["n_scan"],
            step_from,
            steps,
            self.config.odometry_noise,
        )

    def feature_map(self) -> FeatureMap:
        """The saved feature map."""
        prefix = "fm_"
        state = {k[len(prefix) :]: v for k, v in self.arrays.items() if k.startswith(prefix)}
        return FeatureMap.from_state(state, self.config.feature_map)

    def node_stamps(self) -> FloatArray:
        """``(N,)`` stamp of each node's scan, seconds."""
        return self.arrays["s_stamp"][self.arrays["n_scan"]]


def _session_folder(path: str | os.PathLike[str]) -> Path:
    """The session folder of a session or of a run folder holding ``session/``."""
    folder = Path(path)
    if not (folder / MANIFEST).is_file() and (folder / SESSION_DIR / MANIFEST).is_file():
        return folder / SESSION_DIR
    return folder


def read_config(path: str | os.PathLike[str]) -> IcegConfig:
    """A session's configuration alone (its ``config.yaml``; :func:`read` reads it all).

    Raises:
        SessionError: no readable configuration there.
    """
    try:
        return config_from_yaml(_session_folder(path) / CONFIG)
    except (OSError, IcegError) as exc:
        raise SessionError(f"{path}: not a readable iceg session ({exc})") from exc


def read(path: str | os.PathLike[str]) -> Session:
    """Read a session folder (or a run folder holding ``session/``).

    Raises:
        SessionError: not a session, an unknown format version, or a missing/corrupt file.
    """
    folder = _session_folder(path)
    try:
        manifest = json.loads((folder / MANIFEST).read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        raise SessionError(f"{folder}: not a readable iceg session ({exc})") from exc
    if manifest.get("format") != FORMAT:
        raise SessionError(f"{folder}: {MANIFEST} is not an {FORMAT} manifest")
    if manifest.get("version") != FORMAT_VERSION:
        raise SessionError(
            f"{folder}: session format version {manifest.get('version')!r}; this ICEG reads "
            f"version {FORMAT_VERSION}"
        )
    try:
        config = config_from_yaml(folder / CONFIG)
        with np.load(folder / STATE, allow_pickle=False) as npz:
            arrays = {k: npz[k] for k in npz.files}
    except (OSError, ValueError, IcegError) as exc:
        raise SessionError(f"{folder}: cannot read the session state ({exc})") from exc
    return Session(folder, manifest, config, arrays)


#: The factor table's arrays (one row per factor, in factor order).
FACTOR_ARRAYS = (
    "g_kind",
    "g_ij",
    "g_measured",
    "g_cov",
    "g_robust",
    "g_robust_k",
    "g_origin",
    "g_correlation",
)

#: Arrays :func:`load` needs besides the feature map's.
_REQUIRED = (
    "g_node_ids",
    "g_node_initial",
    *(name for name in FACTOR_ARRAYS if name != "g_origin"),  # load does not read g_origin
    "g_steps",
    "s_stamp",
    "s_node",
    "s_delta",
    "s_log",
    "s_key",
    "s_hash",
    "n_scan",
    "n_odom",
    "n_odom_measured",
    "n_path_m",
    "lc_ij",
    "lc_measured",
    "lc_cov",
    "lc_correlation",
    "lc_implied",
    "lc_places_rows",
    "lc_places_ids",
    "cal_state",
    "inline_meta",
    "inline_offsets",
    "inline_ranges",
    "inline_angles",
)


def load(path: str | os.PathLike[str], *, scans: Sequence[LaserScan] | None = None) -> Slam:
    """A :class:`~iceg.slam.Slam` that continues exactly where the saved run ended.

    Processing more scans and calling ``finish()`` gives the same result, bit for bit, as
    one uninterrupted run over all the scans (a session edited by ``iceg optimize``
    continues from its re-optimized graph).

    Args:
        path: the session folder (or the run folder holding it).
        scans: the session's scans in processing order, if already in memory (checked by
            hash); by default re-read from their logs.

    Raises:
        SessionError: unreadable session, missing log, or a scan whose hash differs.
        GraphError: gtsam failed while replaying the graph.
    """
    session = read(path)
    missing = sorted(set(_REQUIRED) - set(session.arrays))
    if missing:
        raise SessionError(
            f"{session.path}: state.npz lacks {missing[0]}{' ...' if len(missing) > 1 else ''}"
            " (written by an older ICEG?); run the log again"
        )
    if scans is None:
        loaded = read_scans(session)
    else:
        loaded = list(scans)
        digests = session.arrays["s_hash"].tolist()
        if len(loaded) != len(digests) or any(
            scan_hash(s) != d for s, d in zip(loaded, digests, strict=True)
        ):
            raise SessionError(f"{session.path}: the scans given are not the session's scans")
    a = session.arrays
    graph = replay_graph(
        a,
        session.config.graph,
        skip_final_batch=not session.edited,
        online_factors=session.manifest.get("online_factors"),
    )
    stats = LoopClosureStats(**session.manifest.get("loop_closures", {}))
    slam = Slam.from_state(
        session.config,
        graph,
        session.feature_map(),
        _slam_state(session, _factor_prefix(a, len(graph.factors)), loaded),
        stats,
    )
    slam.loop_closer.pending = _pending(a)
    slam.loop_closer.places.restore_state({"rows": a["lc_places_rows"], "ids": a["lc_places_ids"]})
    slam.odometry_calibrator.restore_state(a["cal_state"])
    slam.log_readings = {
        e["path"]: {k: e[k] for k in READING_KEYS if k in e} for e in session.manifest["logs"]
    }
    return slam


def save(slam: Slam, folder: str | os.PathLike[str]) -> Path:
    """Write ``slam``'s session (before or after ``finish()``) into ``folder`` (created).

    Each file is written atomically; ``manifest.json`` last, so a folder without it is not
    a session.

    Raises:
        OSError: the folder cannot be written (the caller maps it to an ``OutputError``).
    """
    out = Path(folder)
    out.mkdir(parents=True, exist_ok=True)
    s = slam.export_state()
    refs, logs = scan_arrays(s.scans, out, slam.log_readings)
    arrays = {
        **graph_arrays(slam.graph, s.correlations),
        **_slam_arrays(slam),
        **refs,
        **{f"fm_{k}": v for k, v in slam.feature_map.export_state().items()},
    }
    extra = {
        "loop_closures": slam.loop_stats.as_dict(),
        "match_failures": dict(s.match_failures),
        "point_fallbacks": dict(s.point_fallbacks),
        "stage_seconds": {k: round(v, 6) for k, v in slam.timer.seconds.items()},
        "online_factors": slam.online_factors,
    }
    write_folder(out, arrays, slam.config, logs, extra)
    return out


def write_folder(
    out: Path,
    arrays: Mapping[str, np.ndarray],
    config: IcegConfig,
    logs: list[dict[str, Any]],
    extra: Mapping[str, Any],
    edited: bool = False,
) -> None:
    """Write the session files from their arrays (see :func:`save`)."""
    from iceg import __version__

    out.mkdir(parents=True, exist_ok=True)
    with atomic_write(out / STATE, "wb") as fb:
        np.savez(fb, **dict(arrays))  # type: ignore[arg-type]
    write_g2o_file(
        out / GRAPH, arrays["g_node_ids"], arrays["g_node_final"], factor_records(arrays)
    )
    with atomic_write(out / CONFIG) as fh:
        fh.write(config.to_yaml())
    write_closures_csv(out / CLOSURES, arrays)
    manifest = {
        "format": FORMAT,
        "version": FORMAT_VERSION,
        "iceg_version": __version__,
        "edited": edited,
        "nodes": int(arrays["g_node_ids"].shape[0]),
        "factors": int(arrays["g_kind"].shape[0]),
        "scans": int(arrays["s_stamp"].shape[0]),
        "landmarks": int(arrays["fm_lm_id"].shape[0]),
        "logs": logs,
        "files": list(SESSION_FILES),
        **extra,
    }
    with atomic_write(out / MANIFEST) as fh:
        json.dump(manifest, fh, indent=2)
        fh.write("\n")


# --------------------------------------------------------------------------- loop closures


def closure_chi2(
    measured: FloatArray, cov: FloatArray, pose_i: FloatArray, pose_j: FloatArray
) -> float:
    """Squared Mahalanobis distance of a closure's residual ``measured^-1 ∘ pose_i^-1 ∘
    pose_j`` (``(3,)`` x, y, theta) under its covariance ``(3, 3)``; chi-square, 3 dof."""
    e = se2.between(measured, se2.between(pose_i, pose_j))
    return float(e @ np.linalg.solve(cov, e))


def closure_rows(a: Mapping[str, np.ndarray]) -> list[list[Any]]:
    """Rows of ``loop_closures.csv`` (:data:`CLOSURE_COLUMNS`): accepted closures (graph
    factors of kind loop closure), then the held-back ones."""
    ids, poses = a["g_node_ids"], a["g_node_final"]
    stamps = a["s_stamp"][a["n_scan"]] if a["n_scan"].size else np.zeros(0)

    def row(
        f: int, ij: IntArray, z: FloatArray, c: FloatArray, r: float, status: str, why: str
    ) -> list[Any]:
        pi, pj = (int(np.searchsorted(ids, n)) for n in ij)
        up = c[np.triu_indices(3)]
        chi2 = closure_chi2(z, c, poses[pi], poses[pj])
        return [f, int(ij[0]), int(ij[1]), stamps[pi], stamps[pj], *z, *up, r, chi2, status, why]

    rows = []
    lc = FACTOR_KINDS.index(FactorKind.LOOP_CLOSURE)
    for f in np.flatnonzero(a["g_kind"] == lc).tolist():
        rows.append(
            row(
                f,
                a["g_ij"][f],
                a["g_measured"][f],
                a["g_cov"][f],
                a["g_correlation"][f],
                "accepted",
                _why_accepted(a, f),
            )
        )
    for k in range(a["lc_ij"].shape[0]):
        rows.append(
            row(
                -1,
                a["lc_ij"][k],
                a["lc_measured"][k],
                a["lc_cov"][k],
                a["lc_correlation"][k],
                "held_back",
                "failed the chi-square gate; no agreeing closure yet",
            )
        )
    return rows


def _why_accepted(a: Mapping[str, np.ndarray], f: int) -> str:
    if int(a["g_origin"][f]) == ORIGIN_USER:
        return "added by the user"
    kernel = ROBUST_KERNELS[int(a["g_robust"][f])]
    if kernel is None:  # a group, or a global closure beyond its own covariance
        return "without kernel: a group by pairwise agreement or a global large correction"
    return f"passed the chi-square gate ({kernel} kernel)"


def write_closures_csv(path: Path, a: Mapping[str, np.ndarray]) -> None:
    """Write ``loop_closures.csv`` atomically (floats exact, ``repr``)."""
    with atomic_write(path) as fh:
        fh.write(",".join(CLOSURE_COLUMNS) + "\n")
        for r in closure_rows(a):
            fh.write(",".join(_cell(v) for v in r) + "\n")


def _cell(v: Any) -> str:
    if isinstance(v, str):
        return '"' + v.replace('"', "'") + '"' if "," in v else v
    if isinstance(v, (float, np.floating)):
        return repr(float(v))
    return str(v)


def read_closures_csv(path: str | os.PathLike[str]) -> list[dict[str, str]]:
    """``loop_closures.csv`` rows as dicts of strings (column name -> cell)."""
    import csv

    with open(path, encoding="utf-8", newline="") as fh:
        return list(csv.DictReader(fh))


def link_session(src: Path, dst: Path) -> None:
    """Hard-link (or copy) a session folder's files from ``src`` into a new ``dst``."""
    import shutil

    dst.mkdir()
    for name in os.listdir(src):
        try:
            os.link(src / name, dst / name)
        except OSError:
            shutil.copy2(src / name, dst / name)


def iter_logs(session: Session) -> Iterable[Path]:
    """Paths of the logs a session's scans come from."""
    return (session.log_path(k) for k in range(len(session.manifest["logs"])))


__all__ = [
    "CLOSURE_COLUMNS",
    "SESSION_DIR",
    "Session",
    "load",
    "read",
    "read_closures_csv",
    "replay_graph",
    "save",
]
