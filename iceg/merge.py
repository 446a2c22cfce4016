"""Merge two sessions of one building into one graph and one map (``iceg merge``, issue 15).

B's log is localized in A's frozen map (:func:`iceg.localize.localize_scans`: global ICE
placement, tracking, the run's gated loop closures to A's nodes), which puts B's scans in A's
frame along one consistent track however far B drifted on its own; every ``query_every``-th B
node is then matched against A's map at its localized pose, and kept with enough correlation,
fit to A's walls and an innovation within the run's chi-square gate (:func:`find_closures`):
inter-session closures wherever the sessions overlap. B's nodes are renumbered after A's and
start at their localized poses; B's prior is dropped (A's anchors the merged map); the
closures become loop-closure factors (robust kernel of the run's configuration); the graph is
refined by batch Levenberg–Marquardt, then densified by local closures at the merged
estimates in rounds (:func:`_densify`). The feature maps are concatenated (B's landmarks
anchored to B's renumbered nodes; duplicates of one corner seen in both sessions are not
fused).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from frontends import LaserScan
from graph import FactorKind, PoseGraph
from iceg.features import extract
from iceg.localize import (
    FixedMap,
    LocalizationResult,
    LocalizeSettings,
    Placement,
    Status,
    agrees_with,
    fixed_map_of_session,
    localize_scans,
    segment_fit,
)
from iceg.matching import MatchBounds
from iceg.session import (
    FACTOR_KINDS,
    ORIGIN_RUN,
    ROBUST_KERNELS,
    Session,
    graph_arrays,
    read_scans,
    rebuild_graph,
)
from iceg_common import se2
from iceg_common.errors import SessionError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class MergeSettings:
    """Inter-session closure search.

    Attributes:
        query_every: every this many of B's nodes (all over B, where localized) is matched
            against A's map at its localized pose.
        min_closures: least number of inter-session closures (fewer: not the same
            building), and of an agreeing group of unbounded densify closures.
        agree_m / agree_deg: unbounded densify closures: largest difference between the
            relative poses of two whose B nodes are close along B's path.
        drift_per_m / drift_deg_per_m: that allowance grows by this much per metre of B's
            path between the two B nodes (B's own drift).
        support_window_m: each closure of such a group needs ``min_closures - 1`` others
            within this much of B's path that agree with it.
        densify_*: the local closures added after the first alignment (every this many B
            nodes within this radius of A's nodes; least bounds of their matches, grown
            with the node's marginal; rounds of search and refinement while closures are
            found).
    """

    query_every: int = 3
    agree_m: float = 0.5
    agree_deg: float = 5.0
    drift_per_m: float = 0.05
    drift_deg_per_m: float = 0.1
    support_window_m: float = 20.0
    min_closures: int = 2
    densify_every: int = 3
    densify_radius_m: float = 3.0
    densify_translation_m: float = 1.0
    densify_rotation_deg: float = 15.0
    densify_rounds: int = 3


@dataclass(frozen=True, eq=False)
class InterClosure:
    """A B node placed in A's map.

    Attributes:
        node_b: B's node (B's numbering).
        placement: the match (``anchor`` an A node; ``match.pose`` B's node in its frame).
        transform: ``(3,)`` B map frame -> A map frame that it implies.
        robust: enters with the run's robust kernel (False: accepted as a consistent group
            correcting B's estimate by more than its bounds, as the run's global closures).
        path_m: B's odometry path length at ``node_b`` (m).
    """

    node_b: int
    placement: Placement
    transform: FloatArray
    robust: bool = True
    path_m: float = 0.0


def find_closures(
    a: Session, b: Session, settings: MergeSettings | None = None
) -> tuple[list[InterClosure], FloatArray]:
    """Inter-session loop closures wherever the sessions overlap.

    B's log is localized in A's frozen map (:func:`iceg.localize.localize_scans`: global ICE
    placement without an initial pose, confirmed by tracking; then the run's own SLAM with
    A's nodes held, its local and global loop closures to A's nodes gated as in a run, and
    new segments where a kidnapping is confirmed). That puts every B scan the map can
    explain into A's frame along one consistent track, however far B drifted on its own.
    Every ``query_every``-th B node with a pose is then matched against A's map at its
    localized pose (:func:`_track_closures`).

    Returns:
        ``(closures, initial)``: the closures and ``(N_b, 3)`` A-frame poses of B's nodes
        where they were localized (NaN rows elsewhere).

    Raises:
        SessionError: B's scans cannot be re-read, or fewer than ``min_closures`` closures.
    """
    st = settings or MergeSettings()
    fixed = fixed_map_of_session(a)
    scans = read_scans(b)
    loc = localize_scans(fixed, scans)
    rows = b.arrays["n_scan"]
    initial = np.where((loc.status[rows] > Status.LOST)[:, None], loc.poses[rows], np.nan)
    found = _track_closures(fixed, b, scans, loc, st)
    if len(found) < st.min_closures:
        raise SessionError(
            f"{b.path}: only {len(found)} of its scans could be placed in {a.path} "
            f"(need {st.min_closures}); are the two sessions of the same building?"
        )
    return found, initial


def _track_closures(
    fixed: FixedMap,
    b: Session,
    scans: list[LaserScan],
    loc: LocalizationResult,
    st: MergeSettings,
) -> list[InterClosure]:
    """B nodes (every ``query_every``-th with a localized pose) matched against A's map at
    that pose, within bounds of ``search_n_sigma`` of its covariance (at least the tracking
    bounds, at most the run's ``max_search_radius_m``); kept with enough correlation, fit
    to A's walls (:func:`~iceg.localize.segment_fit`), and an innovation within the run's
    chi-square gate (``loop_closure.consistency_chi2``) under the localization's
    covariance: the track is the consistency check, as a run's estimate is for its loop
    closures."""
    lc = fixed.config.loop_closure
    ls = LocalizeSettings()
    ids_b, poses_b = b.node_poses
    path_b = b.arrays["n_path_m"]
    out = []
    for row in range(0, ids_b.size, st.query_every):
        r = int(b.arrays["n_scan"][row])
        if loc.status[r] <= Status.LOST:
            continue
        pose, cov = loc.poses[r], loc.covs[r]
        sxy = float(np.sqrt(np.linalg.eigvalsh(cov[:2, :2]).max()))
        trans = min(max(ls.track_translation_m, ls.search_n_sigma * sxy), lc.max_search_radius_m)
        rot = max(ls.track_rotation_deg, np.degrees(ls.search_n_sigma * np.sqrt(cov[2, 2])))
        feats = extract(scans[r], fixed.config.features)
        p = fixed.match_at(
            feats, pose, MatchBounds.local(trans, min(rot, 180.0)), lc.reference_nodes
        )
        if (
            p is None
            or p.match.correlation < ls.min_correlation
            or segment_fit(feats, p, ls.fit_tolerance_m) < ls.min_fit
            or not agrees_with(pose, cov, p, lc.consistency_chi2)
        ):
            continue
        t = se2.compose(p.pose, se2.inverse(poses_b[row]))
        out.append(InterClosure(int(ids_b[row]), p, t, path_m=float(path_b[row])))
    logger.info("merge: %d inter-session closures along B's localized track", len(out))
    return out


def _consistent(found: list[InterClosure], st: MergeSettings) -> list[InterClosure]:
    """The largest set of closures that agree pairwise (:func:`_agreement`; after Olson
    2009 and PCM, Mangelson et al. 2018: the largest group agreeing with one seed, then with
    each other), whose members each have ``min_closures - 1`` agreeing others within
    ``support_window_m`` of B's path: far apart along B, B's drift lets almost any two
    agree, so each place must vouch for itself."""
    if not found:
        return []
    agree = _agreement(found, st)
    path = np.array([c.path_m for c in found])
    near = np.abs(path[:, None] - path[None, :]) <= st.support_window_m
    best = np.zeros(len(found), dtype=bool)
    for seed in range(len(found)):
        group = agree[seed].copy()
        group &= agree[:, group].all(axis=1)
        while True:  # drop members without support, until none is dropped
            support = (agree & near & group[None, :]).sum(axis=1) - 1
            keep = group & (support >= st.min_closures - 1)
            if keep.sum() == group.sum():
                break
            group = keep
        if group.sum() > best.sum():
            best = group
    return [c for c, k in zip(found, best.tolist(), strict=True) if k]


def _agreement(found: list[InterClosure], st: MergeSettings) -> NDArray[np.bool_]:
    """``(n, n)`` whether two closures agree: the relative pose of their B nodes in B's map
    matches that of their placements in A's map within ``agree_m`` / ``agree_deg`` plus the
    drift allowance for the B path between them (its rotation part moving the far node by
    the distance between them)."""
    n = len(found)
    in_a = np.array([c.placement.pose for c in found])
    in_b = np.array([se2.compose(se2.inverse(c.transform), c.placement.pose) for c in found])
    path = np.array([c.path_m for c in found])
    out = np.eye(n, dtype=bool)
    for i in range(n):
        rel_a = se2.between(np.broadcast_to(in_a[i], (n, 3)), in_a)
        rel_b = se2.between(np.broadcast_to(in_b[i], (n, 3)), in_b)
        d = se2.between(rel_b, rel_a)
        span = np.abs(path - path[i])
        rot = np.radians(st.agree_deg + st.drift_deg_per_m * span)
        dist = np.hypot(rel_b[:, 0], rel_b[:, 1])
        lever = np.radians(st.drift_deg_per_m * span)  # B's heading drift swings the far node
        trans = st.agree_m + st.drift_per_m * span + np.minimum(lever, np.pi) * dist
        out[i] |= (np.hypot(d[:, 0], d[:, 1]) <= trans) & (np.abs(d[:, 2]) <= rot)
    return out


# --------------------------------------------------------------------------- arrays


def merge_arrays(
    a: Session,
    b: Session,
    closures: list[InterClosure],
    max_iterations: int = 100,
    settings: MergeSettings | None = None,
    initial: FloatArray | None = None,
) -> dict[str, np.ndarray]:
    """The merged session's ``state.npz`` arrays (see :mod:`iceg.session`).

    ``initial``: ``(N_b, 3)`` A-frame initial values of B's nodes (NaN rows: B's estimate
    moved by the closures' mean B-to-A transform, as all of them when not given).

    Raises:
        GraphError: gtsam failed on the merged graph.
    """
    aa, ba = a.arrays, b.arrays
    n_a = int(aa["g_node_ids"].max()) + 1
    t = closures[0].transform if len(closures) == 1 else _mean_transform(closures)
    b_init = se2.compose(t, ba["g_node_final"])
    if initial is not None:
        b_init = np.where(np.isnan(initial[:, :1]), b_init, initial)
    parts = (_graph_part(aa, ba, n_a, b_init), _scan_part(aa, ba, n_a), _map_part(aa, ba, n_a))
    out = {k: v for part in parts for k, v in part.items()}
    kernel = a.config.loop_closure.robust_kernel
    st = settings or MergeSettings()
    out = _add_closures(out, closures, n_a, kernel)
    out, graph = _optimized(out, a, max_iterations)
    linked = {c.node_b for c in closures}
    for _ in range(st.densify_rounds):
        dense = _densify(a, b, out, graph, n_a, st, linked)
        if not dense:
            break
        linked |= {c.node_b for c in dense}
        out, graph = _optimized(_add_closures(out, dense, n_a, kernel), a, max_iterations)
    return out


def _optimized(
    out: dict[str, np.ndarray], a: Session, max_iterations: int
) -> tuple[dict[str, np.ndarray], PoseGraph]:
    """The arrays with the graph rebuilt at their estimates and batch-refined (and the
    graph, for its marginals)."""
    graph = rebuild_graph(out, a.config.graph)
    graph.optimize_batch(max_iterations)
    corr = {k: float(v) for k, v in enumerate(out["g_correlation"]) if np.isfinite(v)}
    return {**out, **graph_arrays(graph, corr, out["g_origin"].tolist())}, graph


def _densify(
    a: Session,
    b: Session,
    out: dict[str, np.ndarray],
    graph: PoseGraph,
    n_a: int,
    st: MergeSettings,
    linked: set[int],
) -> list[InterClosure]:
    """More inter-session closures once B is in A's frame: every ``densify_every``-th B node
    not yet linked, near A's nodes, is matched locally against A's map at its merged
    estimate (as the loop-closure search of a run would). The search grows with the node's
    marginal uncertainty in the merged graph (``search_n_sigma`` sigmas of the run's loop
    closure, capped at its ``max_search_radius_m``): B nodes far from the closures so far
    can be off by more than the base bounds. Matches of enough correlation whose points fit
    A's walls are kept."""
    fixed = fixed_map_of_session(a)
    lc = a.config.loop_closure
    ids_b = b.arrays["g_node_ids"]
    poses = out["g_node_final"][np.searchsorted(out["g_node_ids"], ids_b + n_a)]
    dist = np.array([np.hypot(*(fixed.poses[:, :2] - p[:2]).T).min() for p in poses])
    rows = [
        r
        for r in np.flatnonzero(dist <= st.densify_radius_m + lc.max_search_radius_m)[
            :: st.densify_every
        ].tolist()
        if int(ids_b[r]) not in linked
    ]
    todo = []
    for row in rows:
        cov = graph.marginal_covariance(int(ids_b[row]) + n_a)
        sxy = float(np.sqrt(np.linalg.eigvalsh(cov[:2, :2]).max()))
        sth = float(np.sqrt(cov[2, 2]))
        trans = min(max(st.densify_translation_m, lc.search_n_sigma * sxy), lc.max_search_radius_m)
        rot = min(max(st.densify_rotation_deg, np.degrees(lc.search_n_sigma * sth)), 180.0)
        if dist[row] <= st.densify_radius_m + trans:
            todo.append((row, MatchBounds.local(trans, rot)))
    scans = read_scans(b, [int(b.arrays["n_scan"][row]) for row, _ in todo])
    loc = LocalizeSettings()
    found: list[InterClosure] = []
    tried = len(todo)
    # matched without bounds around the estimate: accepted by consistency only
    wide: list[InterClosure] = []
    for (row, bounds), scan in zip(todo, scans, strict=True):
        feats = extract(scan, fixed.config.features)
        for bnd, out_list in ((bounds, found), (MatchBounds.global_(), wide)):
            p = fixed.match_at(feats, poses[row], bnd, loc.reference_nodes)
            if p is None or p.match.correlation < loc.min_correlation:
                continue
            if segment_fit(feats, p, loc.fit_tolerance_m) >= loc.min_fit:
                t = se2.compose(p.pose, se2.inverse(poses[row]))
                path = float(b.arrays["n_path_m"][row])
                out_list.append(InterClosure(int(ids_b[row]), p, t, path_m=path))
                break
    # The run's loop closer searches without bounds where the local radius is capped; here,
    # as in its global search, such closures enter only as a mutually consistent group
    # (pairwise consistency of their implied B-to-A corrections, :func:`_consistent`).
    group = _consistent(wide, st) if len(wide) >= st.min_closures else []
    if len(group) >= st.min_closures:  # no robust kernel: it would ignore the correction
        found += [dataclasses.replace(c, robust=False) for c in group]
    logger.info(
        "merge: %d local inter-session closures of %d tried (%d of %d unbounded ones agree)",
        len(found),
        tried,
        len(group),
        len(wide),
    )
    return found


def _mean_transform(closures: list[InterClosure]) -> FloatArray:
    ts = np.array([c.transform for c in closures])
    theta = np.arctan2(np.sin(ts[:, 2]).mean(), np.cos(ts[:, 2]).mean())
    return np.array([ts[:, 0].mean(), ts[:, 1].mean(), theta])


def _graph_part(
    aa: dict[str, np.ndarray], ba: dict[str, np.ndarray], n_a: int, b_init: FloatArray
) -> dict[str, np.ndarray]:
    keep = ba["g_kind"] != FACTOR_KINDS.index(FactorKind.PRIOR)  # A's prior anchors the map
    ij = ba["g_ij"][keep] + n_a
    out = {
        "g_node_ids": np.concatenate([aa["g_node_ids"], ba["g_node_ids"] + n_a]),
        "g_node_initial": np.concatenate([aa["g_node_final"], b_init]),
        "g_node_final": np.concatenate([aa["g_node_final"], b_init]),
        "g_ij": np.concatenate([aa["g_ij"], ij]),
    }
    for k in ("g_kind", "g_measured", "g_cov", "g_robust", "g_robust_k", "g_origin"):
        out[k] = np.concatenate([aa[k], ba[k][keep]])
    out["g_correlation"] = np.concatenate([aa["g_correlation"], ba["g_correlation"][keep]])
    return out


def _scan_part(
    aa: dict[str, np.ndarray], ba: dict[str, np.ndarray], n_a: int
) -> dict[str, np.ndarray]:
    n_scans_a = aa["s_stamp"].shape[0]
    n_logs_a = int(aa["s_log"].max()) + 1 if aa["s_log"].size else 0
    inline_a = aa["inline_meta"].shape[0]
    b_log = np.where(ba["s_log"] >= 0, ba["s_log"] + n_logs_a, -1)
    b_key = np.array(
        [
            str(int(k) + inline_a) if li < 0 else k
            for li, k in zip(ba["s_log"], ba["s_key"], strict=True)
        ],
        dtype=np.str_,
    )
    path_off = float(aa["n_path_m"].max()) + 1000.0 if aa["n_path_m"].size else 0.0
    cat = np.concatenate
    return {
        "s_stamp": cat([aa["s_stamp"], ba["s_stamp"]]),
        "s_node": cat([aa["s_node"], ba["s_node"] + n_a]),
        "s_delta": cat([aa["s_delta"], ba["s_delta"]]),
        "s_log": cat([aa["s_log"], b_log]),
        "s_key": cat([aa["s_key"], b_key]),
        "s_hash": cat([aa["s_hash"], ba["s_hash"]]),
        "n_scan": cat([aa["n_scan"], ba["n_scan"] + n_scans_a]),
        "n_odom": cat([aa["n_odom"], ba["n_odom"]]),
        "n_odom_measured": cat([aa["n_odom_measured"], ba["n_odom_measured"]]),
        "n_path_m": cat([aa["n_path_m"], ba["n_path_m"] + path_off]),
        "lc_ij": cat([aa["lc_ij"], ba["lc_ij"] + n_a]),
        "lc_measured": cat([aa["lc_measured"], ba["lc_measured"]]),
        "lc_cov": cat([aa["lc_cov"], ba["lc_cov"]]),
        "lc_correlation": cat([aa["lc_correlation"], ba["lc_correlation"]]),
        "lc_implied": cat([aa["lc_implied"], ba["lc_implied"]]),
        "lc_places_rows": cat([aa["lc_places_rows"], ba["lc_places_rows"]]),
        "lc_places_ids": cat([aa["lc_places_ids"], ba["lc_places_ids"] + n_a]),
        "cal_state": aa["cal_state"],
        "inline_meta": cat([aa["inline_meta"], ba["inline_meta"]]),
        "inline_offsets": cat(
            [aa["inline_offsets"], ba["inline_offsets"][1:] + aa["inline_offsets"][-1]]
        ),
        "inline_ranges": cat([aa["inline_ranges"], ba["inline_ranges"]]),
        "inline_angles": cat([aa["inline_angles"], ba["inline_angles"]]),
    }


#: Feature-map arrays holding node ids (shifted for B) and landmark ids.
_NODE_KEYS = ("fm_lm_anchor", "fm_lm_last_node", "fm_seg_node", "fm_pts_node", "fm_pruned_anchor")
_ID_KEYS = ("fm_lm_id", "fm_pruned_ids")


def _map_part(
    aa: dict[str, np.ndarray], ba: dict[str, np.ndarray], n_a: int
) -> dict[str, np.ndarray]:
    next_a = int(aa["fm_scalars"][0])
    out = {}
    for k in (k for k in aa if k.startswith("fm_") and k not in ("fm_scalars", "fm_nodes")):
        shift = n_a if k in _NODE_KEYS else next_a if k in _ID_KEYS else 0
        out[k] = np.concatenate([aa[k], ba[k] + shift if shift else ba[k]])
    out["fm_nodes"] = np.concatenate([aa["fm_nodes"], ba["fm_nodes"] + n_a])
    sa, sb = aa["fm_scalars"], ba["fm_scalars"]
    out["fm_scalars"] = np.array(
        [sa[0] + sb[0], sa[1] + sb[1], max(sa[2], sb[2]), max(sa[3], sb[3])]
    )
    return out


def _add_closures(
    out: dict[str, np.ndarray], closures: list[InterClosure], n_a: int, kernel: str
) -> dict[str, np.ndarray]:
    k = len(closures)
    rows = {
        "g_kind": np.full(k, FACTOR_KINDS.index(FactorKind.LOOP_CLOSURE)),
        "g_ij": np.array([[c.placement.anchor, c.node_b + n_a] for c in closures]),
        "g_measured": np.array([c.placement.match.pose for c in closures]),
        "g_cov": np.array([c.placement.match.cov for c in closures]),
        "g_robust": np.array(
            [ROBUST_KERNELS.index(kernel if c.robust else None) for c in closures], dtype=int
        ),
        "g_robust_k": np.full(k, np.nan),
        "g_origin": np.full(k, ORIGIN_RUN),
        "g_correlation": np.array([c.placement.match.correlation for c in closures]),
    }
    return {
        **out,
        **{key: np.concatenate([out[key], v.astype(out[key].dtype)]) for key, v in rows.items()},
    }


def merge_sessions(
    a: Session, b: Session, out: str | Path, settings: MergeSettings | None = None
) -> tuple[Path, list[InterClosure]]:
    """Merge B into A and write the merged session into ``out/session`` (with
    ``trajectory.tum`` beside it); A's configuration is kept.

    Raises:
        SessionError: no consistent inter-session closures, or unreadable scans.
        OSError: the folder cannot be written.
    """
    from frontends.tum import write_tum
    from iceg.session import SESSION_DIR, write_folder

    closures, initial = find_closures(a, b, settings)
    arrays = merge_arrays(a, b, closures, settings=settings, initial=initial)
    folder = Path(out)
    logs = [*a.manifest.get("logs", []), *b.manifest.get("logs", [])]
    session_dir = folder / SESSION_DIR
    session_dir.mkdir(parents=True, exist_ok=True)
    logs = [{**e, "relative": str(Path(e["path"]).resolve())} for e in logs]
    extra = {"merged_from": [str(a.path.resolve()), str(b.path.resolve())]}
    write_folder(session_dir, arrays, a.config, logs, extra, edited=True)
    merged = Session(session_dir, {"logs": logs}, a.config, arrays)
    write_tum(folder / "trajectory.tum", *merged.trajectory())
    return folder, closures
