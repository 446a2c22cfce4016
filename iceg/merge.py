"""Merge two sessions of one building into one graph and one map (``iceg merge``, issue 15).

Scans of session B (nodes spread over its map, ``query_spacing_m`` apart) are placed in A's map
by global ICE matching (:meth:`iceg.localize.FixedMap.place`: correlation, fit to A's walls,
no ambiguity). Each placement implies the rigid transform ``T = pose_A(anchor) ∘ z ∘
pose_B(node)^-1`` from B's map frame to A's; the largest set of placements whose transforms
agree (within ``agree_m`` / ``agree_deg``) is kept, and must hold ``min_closures`` of them
(consistency, in the spirit of Olson 2009's pairwise check). B's nodes are renumbered after A's
and moved by ``T``; B's prior is dropped (A's anchors the merged map); the agreeing placements
become loop-closure factors (robust kernel of the run's configuration); the graph is refined by
batch Levenberg–Marquardt. The feature maps are concatenated (B's landmarks anchored to B's
renumbered nodes; duplicates of one corner seen in both sessions are not fused). A merged map
in which the robots drive through walls the other session established, both ways, is refused
(:func:`wall_crossings`).
"""

from __future__ import annotations

import dataclasses
import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from graph import FactorKind, PoseGraph
from iceg.features import extract
from iceg.localize import (
    FixedMap,
    LocalizeSettings,
    Placement,
    fixed_map_of_session,
    match_helper,
    segment_fit,
)
from iceg.loop_closure import LoopClosureConfig
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
from iceg.wall_crossings import nodes_of_walls_crossed
from iceg_common import se2
from iceg_common.errors import SessionError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True)
class MergeSettings:
    """Inter-session closure search.

    Attributes:
        query_spacing_m: B's query nodes: one per square of this side (B's map frame).
        max_queries: most B nodes matched against A.
        agree_m / agree_deg / drift_per_m: largest difference between the relative poses of
            two agreeing closures (metres plus a fraction of their distance; degrees).
        min_closures: least number of agreeing closures.
        densify_*: the local closures added after the first alignment (every this many B
            nodes within this radius of A's nodes; least bounds of their matches, grown
            with the node's marginal and B's drift, :func:`densify_bounds`; rounds of
            search and refinement while closures are found).
    """

    query_spacing_m: float = 2.0
    max_queries: int = 60
    agree_m: float = 0.5
    agree_deg: float = 5.0
    drift_per_m: float = 0.05
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
    """

    node_b: int
    placement: Placement
    transform: FloatArray
    robust: bool = True


def find_closures(
    a: Session, b: Session, settings: MergeSettings | None = None
) -> list[InterClosure]:
    """Place spread B nodes' scans in A's map; keep the largest consistent set.

    Raises:
        SessionError: B's scans cannot be re-read, or fewer than ``min_closures`` agree.
    """
    st = settings or MergeSettings()
    with match_helper(fixed_map_of_session(a)) as fixed:
        found = _placements(fixed, b, st)
    best, rival = _consistent(found, st)
    if len(best) < st.min_closures:
        raise SessionError(
            f"{b.path}: only {len(best)} of {len(found)} placements of its scans in {a.path} "
            f"agree (need {st.min_closures}); are the two sessions of the same building?"
        )
    if len(rival) >= len(best):
        raise SessionError(
            f"{b.path}: its placements in {a.path} support two alignments equally "
            f"({len(best)} placements each, {_offset(best, rival)} apart): the building "
            "repeats where the sessions overlap; record more overlap between them"
        )
    return best


def _offset(g: list[InterClosure], h: list[InterClosure]) -> str:
    """How far apart the alignments of two groups are (their first closures'), for messages."""
    d = se2.between(g[0].transform, h[0].transform)
    return f"{np.hypot(d[0], d[1]):.1f} m / {np.degrees(abs(d[2])):.0f} deg"


def _placements(fixed: FixedMap, b: Session, st: MergeSettings) -> list[InterClosure]:
    ids_b, poses_b = b.node_poses
    rows = FixedMap(ids_b, poses_b, b.feature_map(), b.config).candidates(st.query_spacing_m)
    step = max(1, int(np.ceil(rows.shape[0] / st.max_queries)))
    rows = rows[::step]
    scans = read_scans(b, b.arrays["n_scan"][rows].tolist())
    out = []
    # Each placement must be unambiguous (corridors repeat): the consistency vote alone lets
    # a set of equally aliased placements through.
    loc = LocalizeSettings()
    for row, scan in zip(rows.tolist(), scans, strict=True):
        p = fixed.place(extract(scan, fixed.config.features), loc)
        if p is None:
            continue
        t = se2.compose(p.pose, se2.inverse(poses_b[row]))
        out.append(InterClosure(int(ids_b[row]), p, t))
    logger.info("merge: %d of %d B scans placed in A", len(out), rows.shape[0])
    return out


def _consistent(
    found: list[InterClosure], st: MergeSettings
) -> tuple[list[InterClosure], list[InterClosure]]:
    """The largest group of closures that agree pairwise (:func:`same_alignment`) with one of
    them (and with each other), and the largest rival group: one with a member that disagrees
    with a member of the best, so that the two imply different alignments. A building that
    repeats (a mirror-symmetric floor, parallel corridors) gives B's scans placements in A's
    map that are each unambiguous, because A never saw the true place, and a stretch of them
    agrees with itself: only a larger group than every rival tells the true alignment from
    the aliased one."""
    groups = []
    for c in found:
        group = [o for o in found if same_alignment(c, o, st)]
        groups.append([o for o in group if all(same_alignment(o, q, st) for q in group)])
    best = max(groups, key=len, default=[])
    rivals = [g for g in groups if any(not same_alignment(o, q, st) for o in g for q in best)]
    return best, max(rivals, key=len, default=[])


def same_alignment(a: InterClosure, b: InterClosure, st: MergeSettings) -> bool:
    """Whether two closures imply the same alignment of B's map frame in A's (pairwise
    consistency after Olson 2009).

    Their alignments' rotations differ by at most ``agree_deg``; and, turned by the mean of
    the two rotations, the vector between their B nodes in B's map lands on the vector
    between their placements in A's map within ``agree_m`` plus ``drift_per_m`` of its length
    (B's own drift between the two places). Symmetric in ``a`` and ``b``: turned by one
    closure's rotation alone, a rotation difference within ``agree_deg`` counts its lever arm
    (up to 0.09 m per metre at 5 degrees) against one order of the pair only.

    Args:
        a, b: Closures; ``placement.pose`` ``(3,)`` in A's map frame, ``transform`` ``(3,)``
            B's map frame -> A's (metres, radians).
        st: The tolerances.

    Returns:
        True when they agree (also when ``a is b``).
    """
    if a is b:
        return True
    if (a.node_b, *a.placement.pose) > (b.node_b, *b.placement.pose):
        a, b = b, a  # one order for both calls: symmetric to the last bit
    turn = float(se2.wrap_angle(b.transform[2] - a.transform[2]))
    if abs(turn) > np.radians(st.agree_deg):
        return False
    in_a = b.placement.pose[:2] - a.placement.pose[:2]  # A's map frame
    pa_b = se2.compose(se2.inverse(a.transform), a.placement.pose)  # a's B node, B frame
    pb_b = se2.compose(se2.inverse(b.transform), b.placement.pose)
    in_b = pb_b[:2] - pa_b[:2]  # B's map frame
    mean_rotation = se2.rotation_matrix(a.transform[2] + 0.5 * turn)
    miss = float(np.hypot(*(mean_rotation @ in_b - in_a)))
    return miss <= st.agree_m + st.drift_per_m * float(np.hypot(in_b[0], in_b[1]))


# --------------------------------------------------------------------------- arrays


def merge_arrays(
    a: Session,
    b: Session,
    closures: list[InterClosure],
    max_iterations: int = 100,
    settings: MergeSettings | None = None,
) -> dict[str, np.ndarray]:
    """The merged session's ``state.npz`` arrays (see :mod:`iceg.session`).

    Raises:
        GraphError: gtsam failed on the merged graph.
    """
    aa, ba = a.arrays, b.arrays
    n_a = int(aa["g_node_ids"].max()) + 1
    t = closures[0].transform if len(closures) == 1 else _mean_transform(closures)
    out = {**_graph_part(aa, ba, n_a, t), **_scan_part(aa, ba, n_a), **_map_part(aa, ba, n_a)}
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
    graph.optimize_batch(max_iterations, loop_closure_kernels=False)
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
    marginal uncertainty in the merged graph and with B's own drift since its nearest
    linked node (:func:`densify_bounds`): B nodes far from the closures so far can be off by
    more than the base bounds, and a scan-match chain's marginal understates its drift (on
    MIT CSAIL's halves, B's first 90 s were 1.1 m off with a marginal of centimetres).
    Matches of enough correlation whose points fit A's walls are kept."""
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
    path_b = b.arrays["n_path_m"]
    linked_path = path_b[np.isin(ids_b, np.fromiter(linked, dtype=np.int64))]
    for row in rows:
        away = np.abs(linked_path - path_b[row])
        bounds = densify_bounds(
            graph.marginal_covariance(int(ids_b[row]) + n_a),
            float(away.min()) if away.size else 0.0,
            st,
            lc,
        )
        if dist[row] <= st.densify_radius_m + bounds.max_translation_m:
            todo.append((row, bounds))
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
            if p is None or p.match.correlation < loc.correlation_floor(fixed.config):
                continue
            if segment_fit(feats, p, loc.fit_tolerance_m) >= loc.min_fit:
                t = se2.compose(p.pose, se2.inverse(poses[row]))
                out_list.append(InterClosure(int(ids_b[row]), p, t))
                break
    # The run's loop closer also searches without bounds (its global search); here, as
    # there, such closures enter only as a mutually consistent group
    # (pairwise consistency of their implied B-to-A corrections, :func:`_consistent`),
    # larger than any rival group.
    group, rival = _consistent(wide, st)
    if len(group) >= st.min_closures and len(rival) < len(group):
        # no robust kernel: it would ignore the correction
        found += [dataclasses.replace(c, robust=False) for c in group]
    logger.info(
        "merge: %d local inter-session closures of %d tried (%d of %d unbounded ones agree)",
        len(found),
        tried,
        len(group),
        len(wide),
    )
    return found


def densify_bounds(
    marginal_cov: FloatArray, path_m: float, st: MergeSettings, lc: LoopClosureConfig
) -> MatchBounds:
    """Bounds of a densifying match of a B node (:func:`_densify`).

    Translation: the largest of ``st.densify_translation_m``, ``lc.search_n_sigma`` sigmas of
    the node's marginal (largest axis) and B's own drift since its nearest linked node,
    ``st.drift_per_m`` times the odometry path ``path_m`` between them (the allowance of the
    consistency check, :func:`_agree`); at most ``lc.max_search_radius_m``. Rotation: the
    larger of ``st.densify_rotation_deg`` and ``search_n_sigma`` heading sigmas, at most 180°.

    Args:
        marginal_cov: ``(3, 3)`` float64 the node's marginal covariance in the merged graph
            (x, y in metres, heading in radians).
        path_m: B's odometry path length from the node to its nearest linked node, metres.
        st: merge settings.
        lc: the run's loop-closure settings.
    """
    sxy = float(np.sqrt(max(np.linalg.eigvalsh(marginal_cov[:2, :2]).max(), 0.0)))
    sth = float(np.sqrt(max(marginal_cov[2, 2], 0.0)))
    trans = max(st.densify_translation_m, lc.search_n_sigma * sxy, st.drift_per_m * path_m)
    rot = max(st.densify_rotation_deg, np.degrees(lc.search_n_sigma * sth))
    return MatchBounds.local(min(trans, lc.max_search_radius_m), min(rot, 180.0))


@dataclass(frozen=True)
class WallCrossings:
    """How far the merged map lets each robot pass through the other's walls
    (:func:`wall_crossings`).

    Attributes:
        b_through_a: ``(S_B,)`` int64 for each of B's odometry steps, how many of A's nodes
            saw a wall it passes through.
        a_through_b: ``(S_A,)`` int64 the same for A's steps and B's walls.
        established: nodes from which a wall was seen that make it structure (the feature
            map's ``min_expected``: a landmark seen that often is judged, not transient).
    """

    b_through_a: IntArray
    a_through_b: IntArray
    established: int

    @property
    def worst(self) -> tuple[int, int]:
        """Most nodes of A that saw a wall one of B's steps passes through, and the same for
        A's steps and B's walls."""
        return int(self.b_through_a.max(initial=0)), int(self.a_through_b.max(initial=0))

    @property
    def consistent(self) -> bool:
        """The two robots' crossings, combined as the geometric mean of :attr:`worst`, stay
        below ``established``. A door closed during one session and open during the other
        explains crossings one way only (the robot that drove through saw it open, so the
        other's path meets no wall of its): the mean is then zero however often the door was
        seen. A wrong alignment makes each robot cross the other's walls (simulated office
        splits, ``benchmarks/bench_merge.py``: 11-66 nodes the lesser way, 29-79 the
        greater)."""
        through_a, through_b = self.worst
        return through_a * through_b < self.established**2


def wall_crossings(merged: Session, first_b: int) -> WallCrossings:
    """Whether, in the merged map, each robot drives through the other session's walls.

    A merge is a hypothesis about the whole of both sessions, not only about the nodes its
    closures link. A building that repeats itself (a floor that is its own mirror image)
    gives placements of B in A's map that agree with each other at a wrong alignment;
    beyond the part that repeats, B's path then runs through walls A saw from dozens of
    nodes, and A's path through B's. At the true alignment the walls crossed are transient
    (a person; a door closed in one session, crossed one way only) or crossed one way where a
    session's own map is bent: on MIT CSAIL's halves walls seen by at most 2 nodes; on the
    halves of the ACES and CSAIL corrected logs with synthetic biased odometry by at most 5
    and 14 one way and 0-1 the other; on the simulated office's splits, merged at mirror
    images, by 11-66 nodes the lesser way and 29-79 the greater (``benchmarks/bench_merge.py``).
    This is the free-space agreement of the acceptance test for merged maps of Birk and
    Carpin (2006, "Merging occupancy grid maps from multiple robots"), on the cells a robot
    occupied (:func:`iceg.wall_crossings.nodes_of_walls_crossed`).

    Args:
        merged: the merged session (:func:`merge_arrays`; A's configuration).
        first_b: the first of B's node ids (A's nodes keep their ids, B's follow them).
    """
    ids, poses = merged.node_poses
    walls, wall_node = merged.feature_map().world_segments((ids, poses))
    arrays = merged.arrays
    odometry = arrays["g_ij"][arrays["g_kind"] == FACTOR_KINDS.index(FactorKind.ODOMETRY)]
    steps = poses[np.searchsorted(ids, odometry), :2]  # (S, 2, 2) start and end
    of_b, by_b = odometry[:, 0] >= first_b, wall_node >= first_b
    margin = merged.config.matching.validation.see_through_tolerance_m
    return WallCrossings(
        nodes_of_walls_crossed(steps[of_b], walls[~by_b], wall_node[~by_b], margin),
        nodes_of_walls_crossed(steps[~of_b], walls[by_b], wall_node[by_b], margin),
        merged.config.feature_map.min_expected,
    )


def _mean_transform(closures: list[InterClosure]) -> FloatArray:
    ts = np.array([c.transform for c in closures])
    theta = np.arctan2(np.sin(ts[:, 2]).mean(), np.cos(ts[:, 2]).mean())
    return np.array([ts[:, 0].mean(), ts[:, 1].mean(), theta])


def _graph_part(
    aa: dict[str, np.ndarray], ba: dict[str, np.ndarray], n_a: int, t: FloatArray
) -> dict[str, np.ndarray]:
    keep = ba["g_kind"] != FACTOR_KINDS.index(FactorKind.PRIOR)  # A's prior anchors the map
    ij = ba["g_ij"][keep] + n_a
    out = {
        "g_node_ids": np.concatenate([aa["g_node_ids"], ba["g_node_ids"] + n_a]),
        "g_node_initial": np.concatenate([aa["g_node_final"], se2.compose(t, ba["g_node_final"])]),
        "g_node_final": np.concatenate([aa["g_node_final"], se2.compose(t, ba["g_node_final"])]),
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
    """Merge B into A and write the merged session into ``out/session``, with
    ``trajectory.tum`` and the merged map beside it (``map.pgm``/``map.yaml`` for
    map_server and ``map.png``, rendered from both sessions' scans along the merged
    trajectory, :func:`write_merged_map`); A's configuration is kept. The manifest's
    ``wall_crossings`` gives :attr:`WallCrossings.worst` (``b_through_a``, ``a_through_b``).

    Raises:
        SessionError: no consistent inter-session closures; a merged map in which the robots
            drive through walls the other session established, both ways
            (:attr:`WallCrossings.consistent`); unreadable scans.
        OSError: the folder cannot be written.
    """
    from frontends.tum import write_tum
    from iceg.session import SESSION_DIR, write_folder

    closures = find_closures(a, b, settings)
    arrays = merge_arrays(a, b, closures, settings=settings)
    folder = Path(out)
    session_dir = folder / SESSION_DIR
    logs = [*a.manifest.get("logs", []), *b.manifest.get("logs", [])]
    logs = [{**e, "relative": str(Path(e["path"]).resolve())} for e in logs]
    merged = Session(session_dir, {"logs": logs}, a.config, arrays)
    crossings = wall_crossings(merged, int(a.arrays["g_node_ids"].max()) + 1)
    if not crossings.consistent:
        through_a, through_b = crossings.worst
        raise SessionError(
            f"{b.path}: merged into {a.path} at the alignment its placements agree on, the "
            f"robots drive through the other's walls, both ways (B through a wall of A seen from "
            f"{through_a} nodes, A through one of B seen from {through_b}): the alignment is "
            "wrong (the building repeats where the sessions overlap) or a session's own map is "
            "bent; record more overlap between them"
        )
    session_dir.mkdir(parents=True, exist_ok=True)
    extra = {
        "merged_from": [str(a.path.resolve()), str(b.path.resolve())],
        "wall_crossings": dict(zip(("b_through_a", "a_through_b"), crossings.worst, strict=True)),
    }
    write_folder(session_dir, arrays, a.config, logs, extra, edited=True)
    write_tum(folder / "trajectory.tum", *merged.trajectory())
    write_merged_map(merged, folder)
    return folder, closures


def write_merged_map(merged: Session, folder: Path) -> bool:
    """Render the occupancy grid of every scan of ``merged`` along its trajectory and write
    ``map.pgm``, ``map.yaml`` and ``map.png`` (trajectory drawn over it) into ``folder``,
    each atomically. A map that cannot be rendered (too many cells) is a warning, not a
    failure: the merged session is already written.

    Returns:
        Whether the map was written.

    Raises:
        SessionError: the sessions' scans cannot be re-read from their logs.
    """
    from iceg.grid import render_tiled, write_map_server, write_png
    from iceg.session import read_scans
    from iceg_common.errors import GridError

    _, poses = merged.trajectory()
    try:
        grid = render_tiled(
            read_scans(merged),
            poses,
            merged.config.grid,
            range_min_m=merged.config.features.robot_body_range_m,
        )
    except GridError as exc:
        logger.warning("merge: no map written: %s", exc)
        return False
    write_map_server(grid, folder / "map")
    write_png(grid, folder / "map.png", trajectory=poses)
    return True
