"""The later stages' compiled kernels, compiled beside the first ones on a new install
(issue 13, "a new user's first run").

numba compiles a kernel at its first call and keeps it in its cache on disk
(docs/design.md, "Compiled kernels"). A fresh install's first run therefore compiles some 45
kernels, one after another, in the main process as the run first calls each: 52 s for the
built-in demo on the 2-core benchmark machine, against 3 s for the second run, while the second
core waits. Before it starts the feature worker (:mod:`iceg.features.prefetch`), the run asks
:func:`cache_is_new`; where it is, the first worker compiles the kernels the main process
needs last, while the main process compiles those of the features, the hypotheses, the
correlation and the refinement: :func:`compile_without_features` (the grid, the
contradiction test's point query, the node index) before the worker's warm-up extraction, then
:func:`compile_later_stages` (a match's covariance and free-space checks, the feature map)
with the features. The main process then loads them from the cache. Nothing here changes a
result: the calls' outputs are dropped, and a kernel is the same compiled code whichever
process compiled it.
"""

from __future__ import annotations

import contextlib
import functools
import gc
import logging
from collections.abc import Iterator

import numpy as np

from frontends.scan import LaserScan
from iceg.config import IcegConfig
from iceg.feature_map import FeatureMap, compile_table_moves
from iceg.grid import render_tiled_chunks
from iceg.landmark_frames import move_point_blocks, poses_in_frame
from iceg.matching.matcher import IceMatcher
from iceg.matching.refine import blocks_explained_counts, points_within
from iceg.node_index import NodeGrid, nearest_within
from iceg.scan_store import ScanStore
from iceg.types import MatchResult, ScanFeatures
from iceg_common.numba_loading import njit

log = logging.getLogger(__name__)

#: The second node's pose in the first's frame, ``[x_m, y_m, theta_rad]``: a small step.
_STEP = np.array([0.05, 0.02, 0.01])


@njit(cache=True)
def _probe(x: float) -> float:
    """A kernel of this module's own, for :func:`cache_is_new`."""
    return x + 1.0


@contextlib.contextmanager
def _collector_paused() -> Iterator[None]:
    """The cyclic garbage collector off for the block, then as it was: numba's registry,
    installed at the first kernel call, adds some 60 000 objects that live as long as the
    process, and the full collection they set off walks the whole heap (60-70 ms at the
    start of a MIT CSAIL run, for about ten objects freed; the run then freezes the heap,
    :func:`iceg.pipeline.helper_processes`)."""
    enabled = gc.isenabled()
    gc.disable()
    try:
        yield
    finally:
        if enabled:
            gc.enable()


@functools.cache
def cache_is_new() -> bool:
    """Whether numba's cache lacked this module's probe kernel when this process first
    asked, so that it compiled it instead of loading it: a new install, a new numba cache
    folder, or a new version of this module. The answer is kept for the process (and its
    forks). Where no kernel has run in the process yet, the first call installs numba's
    typing registry (about 0.3 s), which the run's first kernel would pay otherwise."""
    with _collector_paused():
        _probe(0.0)
    stats = getattr(_probe, "stats", None)  # None where numba's JIT is off
    return stats is not None and sum(stats.cache_misses.values()) > 0


def probed() -> bool:
    """Whether this process has called :func:`cache_is_new` (every run does as it starts its
    helpers): numba's typing registry is then loaded, and so are the kernels of any run it
    made."""
    return cache_is_new.cache_info().currsize > 0


def compile_without_features(scan: LaserScan, config: IcegConfig) -> None:
    """Call the later stages' kernels that need no features on ``scan`` and drop the
    results: the grid of two copies of it, the contradiction test's point query (the
    general one, and the one on points in blocks) and its recent points moved node by node
    (the point match's), the loop-closure search's node index and its ordering
    of the nodes near a point.

    Args:
        scan: A laser scan.
        config: The run's configuration (the same kernels, with the same argument types).

    Raises:
        IcegError: a stage rejects the scan (the caller drops the warm-up; the run compiles
            what is missing when it first needs it).
    """
    poses = _poses()
    store = ScanStore([scan, scan])
    render_tiled_chunks(poses, store.beam_chunk, config.grid)
    points = scan.points_xy()
    gate_m = config.slam.contradiction_gate_m or 0.1
    points_within(points, poses, points, gate_m)
    blocks = (
        poses_in_frame(poses[1], poses, np.arange(2)),
        np.full(2, points.shape[0], dtype=np.int64),
        np.concatenate([points, points]),
    )
    blocks_explained_counts(points, poses[0].copy(), poses[1].copy(), *blocks, gate_m)
    move_point_blocks(*blocks)
    nodes = NodeGrid(1.0)
    nodes.add(np.arange(2), poses[:, :2])
    nodes.query(poses[1, :2], 1.0)
    ids, dist = nodes.nearest_first(poses[1, :2], 1.0, 2)
    nearest_within(ids, dist, ids.shape[0], 1.0)


def compile_later_stages(scan: LaserScan, features: ScanFeatures, config: IcegConfig) -> None:
    """Call the later stages' kernels that need features on ``scan`` and its ``features``,
    in the order the main process first needs them, and drop the results: a match's
    covariance and free-space checks, two nodes of the feature map.

    Args:
        scan: A laser scan.
        features: Its features (``extract(scan, config.features)``).
        config: The run's configuration (the same kernels, with the same argument types).

    Raises:
        IcegError: a stage rejects the scan (the caller drops the warm-up; the run compiles
            what is missing when it first needs it).
    """
    IceMatcher(config.matching).compile_checks(features)
    _feature_map(scan, features, config, _poses())
    log.debug("later stages' kernels compiled in the feature worker")


def _poses() -> np.ndarray:
    """``(2, 3)`` float64 two nodes' poses a small step apart, the first at the origin."""
    return np.stack([np.zeros(3), _STEP])


def _feature_map(
    scan: LaserScan, features: ScanFeatures, config: IcegConfig, poses: np.ndarray
) -> None:
    """Two nodes of the same scan a small step apart: the first adds its features, the
    second matches each of them (association, visibility, time-validity, pruning)."""
    fm = FeatureMap(config.feature_map)
    ids = np.arange(2)
    fm.update(0, features, scan.stamp_s, scan=scan)
    ref = fm.reference((ids, poses), [0], poses[0])
    tolerance_m = config.matching.validation.see_through_tolerance_m
    ref = ref.without_walls_seen_through(features.points_xy, tolerance_m)
    n = min(features.n_features, ref.features.n_features)
    pairs = np.repeat(np.arange(n, dtype=np.int64)[:, None], 2, axis=1)
    match = MatchResult(True, _STEP.copy(), np.eye(3) * 1e-4, 1.0, pairs)
    stamp_s = scan.stamp_s + 0.1
    fm.update(1, features, stamp_s, reference=ref, match=match, scan=scan, node_poses=(ids, poses))
    fm.reference((ids, poses), fm.reference_pose_nodes(ids), poses[1])
    compile_table_moves()  # merges and pruning move the landmark table's rows
    fm.update_pose_nodes(2, ref)
