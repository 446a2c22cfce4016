"""Edit a saved session's pose graph and re-optimize it (``iceg optimize``, issue 15).

A user finds a wrong loop closure in ``loop_closures.csv`` (large ``chi2``), removes its factor
by index, or adds a closure between two nodes, with a measured pose or matched by ICE between
the two nodes' scans; the graph is rebuilt from the saved estimates and refined by batch
Levenberg–Marquardt. The edited session keeps every array of the original (feature map,
scans, bookkeeping), its factor table renumbered, and can be continued or localized against.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graph import FactorKind
from iceg.features import extract
from iceg.loop_closure import usable_match
from iceg.matching import IceMatcher, MatchBounds
from iceg.session import (
    FACTOR_ARRAYS,
    FACTOR_KINDS,
    ORIGIN_USER,
    ROBUST_KERNELS,
    Session,
    graph_arrays,
    read_scans,
    rebuild_graph,
    write_folder,
)
from iceg_common import se2
from iceg_common.errors import SessionError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Default standard deviations of a closure given with its pose (metres, degrees).
DEFAULT_CLOSURE_SIGMA_M = 0.05
DEFAULT_CLOSURE_SIGMA_DEG = 1.0


@dataclass(frozen=True)
class ClosureEdit:
    """A loop closure to add between two nodes.

    Attributes:
        node_i: The old node (reference frame).
        node_j: The other node.
        measured: ``(3,)`` pose of ``node_j`` in the frame of ``node_i`` ``[x_m, y_m,
            theta_rad]``, or None: matched by ICE between the two nodes' scans.
        sigma_m: Position standard deviation of a given pose, metres.
        sigma_deg: Heading standard deviation of a given pose, degrees.
    """

    node_i: int
    node_j: int
    measured: FloatArray | None = None
    sigma_m: float = DEFAULT_CLOSURE_SIGMA_M
    sigma_deg: float = DEFAULT_CLOSURE_SIGMA_DEG


def parse_closure(text: str, sigma_m: float, sigma_deg: float) -> ClosureEdit:
    """``"I J"`` or ``"I J X_M Y_M THETA_DEG"`` (spaces or commas) as a :class:`ClosureEdit`.

    Raises:
        SessionError: not two integers optionally followed by three numbers.
    """
    parts = text.replace(",", " ").split()
    try:
        if len(parts) == 2:
            return ClosureEdit(int(parts[0]), int(parts[1]), None, sigma_m, sigma_deg)
        if len(parts) == 5:
            x, y, th = (float(v) for v in parts[2:])
            pose = np.array([x, y, np.radians(th)])
            return ClosureEdit(int(parts[0]), int(parts[1]), pose, sigma_m, sigma_deg)
    except ValueError:
        pass
    raise SessionError(
        f"--add-closure {text!r}: give 'NODE_I NODE_J' (matched by ICE) or "
        "'NODE_I NODE_J X_M Y_M THETA_DEG'"
    )


def edit_and_optimize(
    session: Session,
    remove: Sequence[int] = (),
    add: Sequence[ClosureEdit] = (),
    max_iterations: int = 100,
) -> dict[str, np.ndarray]:
    """The session's arrays after removing factors, adding closures and re-optimizing (batch
    Levenberg–Marquardt with the loop closures as Gaussian factors, as a run's final
    refinement: :meth:`graph.PoseGraph.optimize_batch` ``loop_closure_kernels=False``).

    Args:
        session: the session (:func:`iceg.session.read`).
        remove: factor indices (``loop_closures.csv`` column ``factor``; graph.g2o order) to
            remove; the prior cannot be removed.
        add: closures to add (after the removal), as user factors without robust kernel.
        max_iterations: Levenberg–Marquardt iteration cap.

    Returns:
        New ``state.npz`` arrays: the factor table renumbered, ``g_node_final`` the batch
        optimum, ``g_steps`` the new graph's call log (it replays to the same state).

    Raises:
        SessionError: an unknown factor or node, a prior removed, a loop closure removed
            that a revisit's scans hang from (``slam.reuse_nodes``), an ICE match that fails.
        GraphError: a node left without factor, or gtsam failed.
    """
    a = dict(session.arrays)
    a = _remove_factors(a, remove)
    for edit in add:
        a = _append_closure(a, _closure_row(session, a, edit))
    graph = rebuild_graph(a, session.config.graph)
    stats = graph.optimize_batch(max_iterations, loop_closure_kernels=False)  # as a run ends
    logger.info("re-optimized: error %.6g -> %.6g", stats.error_before, stats.error_after)
    corr = {k: float(v) for k, v in enumerate(a["g_correlation"]) if np.isfinite(v)}
    a.update(graph_arrays(graph, corr, a["g_origin"].tolist()))
    return a


def _remove_factors(a: dict[str, np.ndarray], remove: Sequence[int]) -> dict[str, np.ndarray]:
    n = a["g_kind"].shape[0]
    for f in remove:
        if not 0 <= f < n:
            raise SessionError(f"--remove-factor {f}: the graph has factors 0..{n - 1}")
        if FACTOR_KINDS[int(a["g_kind"][f])] is FactorKind.PRIOR:
            raise SessionError(f"--remove-factor {f}: it is the prior that anchors the map")
        _check_no_revisit_hangs_from(a, f)
    keep = np.ones(n, dtype=bool)
    keep[list(remove)] = False
    return {**a, **{k: a[k][keep] for k in FACTOR_ARRAYS}}


def _check_no_revisit_hangs_from(a: dict[str, np.ndarray], f: int) -> None:
    """Refuse to remove a loop closure into a node after which the run's scans hung from old
    nodes (``slam.reuse_nodes``): they were placed in the old nodes' frames because of it, and
    removing the factor leaves them there.

    Raises:
        SessionError: naming the configuration that makes a new run without that closure.
    """
    if FACTOR_KINDS[int(a["g_kind"][f])] is not FactorKind.LOOP_CLOSURE:
        return
    old, node = (int(v) for v in a["g_ij"][f])
    scan_of = a["n_scan"]
    first = int(scan_of[node]) + 1  # the scans after the node's, up to the next node's
    last = int(scan_of[node + 1]) if node + 1 < scan_of.shape[0] else a["s_node"].shape[0]
    # scans placed from older nodes (those of another log's segment hang from newer ones)
    hung = int(np.count_nonzero(a["s_node"][first:last] < node))
    if hung:
        raise SessionError(
            f"--remove-factor {f}: the loop closure {old} -> {node} started a revisit whose "
            f"{hung} scans after node {node} hang from old nodes (slam.reuse_nodes); removing "
            "the factor would leave them there. Run the logs again without it: give the run "
            f"a config with 'loop_closure: {{forbidden_closures: [[{old}, {node}]]}}' (a run "
            f"is deterministic: the same nodes up to node {node})"
        )


def _closure_row(
    session: Session, a: dict[str, np.ndarray], edit: ClosureEdit
) -> dict[str, np.ndarray]:
    ids, poses = a["g_node_ids"], a["g_node_final"]
    for n in (edit.node_i, edit.node_j):
        if n not in set(ids.tolist()) or edit.node_i == edit.node_j:
            raise SessionError(
                f"--add-closure {edit.node_i} {edit.node_j}: needs two different nodes of "
                f"0..{int(ids.max())}"
            )
    if edit.measured is not None:
        sxy, sth = edit.sigma_m, np.radians(edit.sigma_deg)
        return _row(edit, edit.measured, np.diag([sxy**2, sxy**2, sth**2]), np.nan)
    pi, pj = (poses[int(np.searchsorted(ids, n))] for n in (edit.node_i, edit.node_j))
    rows = [int(a["n_scan"][edit.node_i]), int(a["n_scan"][edit.node_j])]
    scan_i, scan_j = read_scans(session, rows)
    cfg = session.config
    fi, fj = extract(scan_i, cfg.features), extract(scan_j, cfg.features)
    res = IceMatcher(cfg.matching).match(fj, fi, se2.between(pi, pj), MatchBounds.global_())
    if not usable_match(res, cfg.loop_closure):
        raise SessionError(
            f"--add-closure {edit.node_i} {edit.node_j}: the ICE match of the two scans failed "
            f"({res.reason or 'correlation'} {res.correlation:.2f}); give the pose X_M Y_M "
            "THETA_DEG"
        )
    return _row(edit, res.pose, res.cov, res.correlation)


def _row(edit: ClosureEdit, z: FloatArray, cov: FloatArray, corr: float) -> dict[str, np.ndarray]:
    return {
        "g_kind": np.array([FACTOR_KINDS.index(FactorKind.LOOP_CLOSURE)]),
        "g_ij": np.array([[edit.node_i, edit.node_j]]),
        "g_measured": np.asarray(z, dtype=np.float64).reshape(1, 3),
        "g_cov": np.asarray(cov, dtype=np.float64).reshape(1, 3, 3),
        "g_robust": np.array([ROBUST_KERNELS.index(None)]),
        "g_robust_k": np.array([np.nan]),
        "g_origin": np.array([ORIGIN_USER]),
        "g_correlation": np.array([corr]),
    }


def _append_closure(a: dict[str, np.ndarray], row: dict[str, np.ndarray]) -> dict[str, np.ndarray]:
    return {**a, **{k: np.concatenate([a[k], row[k].astype(a[k].dtype)]) for k in FACTOR_ARRAYS}}


def write_edited(
    session: Session, arrays: dict[str, np.ndarray], out: str | os.PathLike[str]
) -> Path:
    """Write an edited session (``manifest.json`` ``edited: true``) into ``out``.

    Raises:
        OSError: the folder cannot be written.
    """
    folder = Path(out)
    keep = ("loop_closures", "match_failures", "point_fallbacks", "stage_seconds")
    extra = {k: session.manifest[k] for k in keep if k in session.manifest}
    logs = list(session.manifest.get("logs", []))
    if folder.resolve() != session.path.resolve():
        logs = [_relocate(e, folder) for e in logs]
    write_folder(folder, arrays, session.config, logs, extra, edited=True)
    return folder


def _relocate(entry: dict[str, str], folder: Path) -> dict[str, str]:
    folder.mkdir(parents=True, exist_ok=True)
    return {**entry, "relative": os.path.relpath(entry["path"], folder.resolve())}
