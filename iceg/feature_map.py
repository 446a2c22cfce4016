"""The ICE feature map: landmarks anchored to graph nodes, references for matching, and
time-validity pruning (paper §III-C3, last paragraph; DESIGN.md "Feature map and
time-validity").

Each landmark (an ICE feature) is anchored to the node that first observed it and stored in
that node's frame, so the map follows every re-optimisation of the pose graph. Each node also
keeps its scan's line segments (node frame) for point-to-line refinement. Everything is held
in flat numpy arrays (one row per landmark / segment), not in lists of objects.

Time-validity: a landmark in a reference is **expected** in a new scan when its support points
(the feature point and points a little along its walls; for an Intersection the nearest ends
of its two segments) lie inside the scan's field of view and range, are not occluded (no beam
around their bearing is shorter than their distance minus a tolerance) and its walls are not
seen at grazing incidence. It is **matched** when the matcher paired it. A landmark expected
often but matched rarely, or expected and unmatched for longer than ``validity_s``, is pruned.
"""

from __future__ import annotations

import logging
import math
import weakref
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from frontends.scan import LaserScan
from iceg.matching.geometry import (
    CORNER,
    EOW,
    INTERSECTION,
    PolarProfile,
    rot,
    transform_lines,
)
from iceg.types import MatchResult, ScanFeatures
from iceg_common.errors import MatchingError
from iceg_common.se2 import between, compose, inverse

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: Pruning reasons recorded in :attr:`FeatureMap.pruned`.
PRUNED_RATIO, PRUNED_VALIDITY = 1, 2

NodePoses = Mapping[int, ArrayLike] | tuple[ArrayLike, ArrayLike]

#: How much a feature kind tells (a Corner has a position and two walls, an EOW a position
#: and one wall, an Intersection a virtual position): a landmark takes the kind of a matched
#: observation that ranks higher.
_RANK = np.zeros(3, dtype=np.int64)
_RANK[CORNER], _RANK[EOW], _RANK[INTERSECTION] = 2, 1, 0


class FeatureMapConfig(BaseModel):
    """Association, visibility and time-validity settings of the feature map (paper §III-C3:
    "each feature has a time-validity property ... features placed in visible area but
    observed rarely will be omitted from the map"; DESIGN "Feature map and time-validity").
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    association_gate_m: float = Field(
        default=0.3,
        gt=0.0,
        description="A new feature the matcher did not pair is still associated with a "
        "reference landmark of a compatible kind within this distance (at the matched pose) "
        "instead of becoming a new landmark.",
    )
    expected_max_range_m: float = Field(
        default=7.0,
        gt=0.0,
        description="A landmark is expected only within this distance: farther features are "
        "extracted unreliably (paper eq. 3: precision falls with distance).",
    )
    fov_margin_deg: float = Field(
        default=2.0,
        ge=0.0,
        description="Margin inside the scan's angular limits for a support point to count as "
        "in the field of view (DESIGN: expected = inside the current field of view).",
    )
    occlusion_tolerance_m: float = Field(
        default=0.2,
        gt=0.0,
        description="A support point is occluded when a beam around its bearing is shorter "
        "than its distance minus this (DESIGN: the scan's range at its bearing is not shorter "
        "than its distance).",
    )
    support_offset_m: float = Field(
        default=0.3,
        gt=0.0,
        description="Distance along each wall of a Corner/EOW of its extra support points: a "
        "wall hidden behind another (a box corner with one face visible) is not expected.",
    )
    min_incidence_deg: float = Field(
        default=20.0,
        ge=0.0,
        lt=90.0,
        description="A Corner or EOW is not expected when one of its walls is seen at less "
        "than this angle (grazing: the extractor cannot find it).",
    )
    min_expected: int = Field(
        default=15,
        ge=1,
        description="Ratio pruning applies once a landmark was expected this many times "
        "(paper §III-C3: 'placed in visible area but observed rarely').",
    )
    min_match_ratio: float = Field(
        default=0.15,
        ge=0.0,
        le=1.0,
        description="Pruned when matched / expected falls below this after min_expected.",
    )
    validity_s: float = Field(
        default=10.0,
        gt=0.0,
        description="Pruned when expected but not matched for longer than this since its last "
        "match (seconds; paper §III-C3 'time-validity'), confirmed by min_misses expected "
        "misses over miss_confirm_s.",
    )
    miss_confirm_s: float = Field(
        default=3.0,
        ge=0.0,
        description="Validity pruning also needs the misses to have lasted this long (seconds "
        "since the first expected miss after the last match): a landmark not seen for a long "
        "while is not removed by one glance that misses it.",
    )
    min_misses: int = Field(
        default=3,
        ge=1,
        description="Validity pruning needs at least this many consecutive expected misses "
        "(one missed extraction does not remove a landmark).",
    )
    bookkeeping_recent_nodes: int | None = Field(
        default=200,
        ge=0,
        description="Landmarks a matched scan associates, merges and counts as expected: those "
        "of the reference it was matched against, plus those last matched (or created) by one "
        "of this many most recent nodes; None: every landmark with an anchor pose. Older "
        "landmarks are left alone because the estimate of a place revisited after a long "
        "loop can be off by metres before the loop closes: there they would be missed, merged "
        "or pruned wrongly, and the loop closure needs them.",
    )
    reference_points: bool = Field(
        default=False,
        description="Keep every node's scan points and put those of the chosen nodes into a "
        "reference: the matcher then also uses the off-segment points (PL-ICP rows; more "
        "accurate where walls leave the pose open, about 1 ms slower per match).",
    )
    replace_ratio: float = Field(
        default=0.5,
        gt=0.0,
        le=1.0,
        description="A matched observation replaces a landmark's stored position when its "
        "covariance trace is below this fraction of the stored one (keep the best view).",
    )


@dataclass(frozen=True, eq=False)
class LandmarkView:
    """Landmarks in a common frame (see :meth:`FeatureMap.world_landmarks`).

    Attributes:
        ids: ``(L,)`` int64 landmark ids.
        anchor: ``(L,)`` int64 anchor node ids.
        kind: ``(L,)`` int64 :class:`~iceg.types.FeatureKind`.
        xy: ``(L, 2)`` float64 positions, metres.
        cov: ``(L, 2, 2)`` float64 position covariances, m².
        directions: ``(L, 2, 2)`` float64 unit wall directions (NaN where none).
        opening_rad: ``(L,)`` float64 opening angles (NaN for EOW).
        n_expected: ``(L,)`` int64 times expected.
        n_matched: ``(L,)`` int64 times matched.
        last_matched_s: ``(L,)`` float64 stamp of the last match (creation stamp if never).
    """

    ids: IntArray
    anchor: IntArray
    kind: IntArray
    xy: FloatArray
    cov: FloatArray
    directions: FloatArray
    opening_rad: FloatArray
    n_expected: IntArray
    n_matched: IntArray
    last_matched_s: FloatArray

    def __len__(self) -> int:
        return int(self.ids.shape[0])


@dataclass(frozen=True, eq=False)
class MapUpdate:
    """What one :meth:`FeatureMap.update` did.

    Attributes:
        node_id: The node updated.
        matched_ids: ``(A,)`` int64 landmark ids matched (associated) by this scan.
        added_ids: ``(N,)`` int64 ids of new landmarks.
        expected_ids: ``(E,)`` int64 ids of landmarks expected in this scan.
        pruned_ids: ``(R,)`` int64 ids pruned after this scan.
        merged_ids: ``(D,)`` int64 ids of duplicate landmarks merged into a matched one
            (the same physical feature anchored to another node).
    """

    node_id: int
    matched_ids: IntArray
    added_ids: IntArray
    expected_ids: IntArray
    pruned_ids: IntArray
    merged_ids: IntArray


@dataclass(frozen=True, eq=False)
class PrunedLandmarks:
    """Record of pruned landmarks (anchor frame), for analysis and tests.

    Attributes:
        ids, anchor, kind: ``(R,)`` int64.
        xy: ``(R, 2)`` float64 position in the anchor's frame, metres.
        stamp_s: ``(R,)`` float64 time of pruning.
        created_s: ``(R,)`` float64 time of creation.
        last_matched_s: ``(R,)`` float64 time of the last match.
        reason: ``(R,)`` int64 ``PRUNED_RATIO`` or ``PRUNED_VALIDITY``.
    """

    ids: IntArray
    anchor: IntArray
    kind: IntArray
    xy: FloatArray
    stamp_s: FloatArray
    created_s: FloatArray
    last_matched_s: FloatArray
    reason: IntArray


_LM_FIELDS = {
    # name: (dtype, trailing shape, fill)
    "id": (np.int64, (), -1),
    "anchor": (np.int64, (), -1),
    "kind": (np.int64, (), -1),
    "xy": (np.float64, (2,), np.nan),
    "cov": (np.float64, (2, 2), np.nan),
    "dirs": (np.float64, (2, 2), np.nan),
    "opening": (np.float64, (), np.nan),
    "support": (np.float64, (3, 2), np.nan),
    "wall_p": (np.float64, (2, 2), np.nan),
    "wall_d": (np.float64, (2, 2), np.nan),
    "wall_side": (np.float64, (2,), np.nan),
    "n_expected": (np.int64, (), 0),
    "n_matched": (np.int64, (), 0),
    "misses": (np.int64, (), 0),
    "created_s": (np.float64, (), np.nan),
    "last_matched_s": (np.float64, (), np.nan),
    "first_miss_s": (np.float64, (), np.nan),
    "last_node": (np.int64, (), -1),
}
_SEG_FIELDS = {
    "node": (np.int64, ()),
    "ep": (np.float64, (2, 2)),
    "lines": (np.float64, (2,)),
    "cov": (np.float64, (2, 2)),
    "pr": (np.int64, (2,)),  # point range in the node's own points (-1: none kept)
}


def _node_pose_table(node_poses: NodePoses) -> tuple[IntArray, FloatArray]:
    if isinstance(node_poses, tuple):
        ids = np.asarray(node_poses[0], dtype=np.int64).reshape(-1)
        poses = np.asarray(node_poses[1], dtype=np.float64).reshape(-1, 3)
    else:
        ids = np.fromiter((int(k) for k in node_poses), dtype=np.int64, count=len(node_poses))
        poses = np.array([np.asarray(node_poses[k], dtype=np.float64) for k in node_poses])
        poses = poses.reshape(-1, 3)
    if ids.shape[0] != poses.shape[0]:
        raise MatchingError(
            f"node_poses: {ids.shape[0]} ids but {poses.shape[0]} poses; pass a dict "
            "{node_id: (3,) pose} or a tuple (ids (N,), poses (N, 3))"
        )
    order = np.argsort(ids, kind="stable")
    return ids[order], poses[order]


def _lookup(table_ids: IntArray, query: IntArray) -> tuple[IntArray, BoolArray]:
    """Positions of ``query`` in the sorted ``table_ids`` and whether each was found."""
    if table_ids.shape[0] == 0:
        return np.zeros(query.shape, dtype=np.int64), np.zeros(query.shape, dtype=bool)
    pos = np.clip(np.searchsorted(table_ids, query), 0, table_ids.shape[0] - 1)
    return pos, table_ids[pos] == query


def _geometry(
    features: ScanFeatures, offset_m: float
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Visibility geometry of each feature in its scan's frame (NaN-padded).

    Returns:
        ``support`` ``(K, 3, 2)``: points that must be in view and not occluded: the point
        and ``offset_m`` along each wall for Corners/EOWs; for an Intersection a point
        ``offset_m`` inside each of its two segments from the end nearest to it.
        ``wall_p``, ``wall_d`` ``(K, 2, 2)``: a point on each wall and the wall's direction.
        ``wall_side`` ``(K, 2)``: on which side of each wall the sensor stood (+1 / -1): a
        wall is extracted from the side it was seen from.
    """
    k = features.n_features
    support = np.full((k, 3, 2), np.nan)
    wall_p = np.full((k, 2, 2), np.nan)
    wall_d = np.full((k, 2, 2), np.nan)
    if k == 0:
        return support, wall_p, wall_d, np.full((k, 2), np.nan)
    kind = features.kind
    xy = features.xy
    d = features.directions
    direct = kind != INTERSECTION
    support[direct, 0] = xy[direct]
    support[direct, 1] = xy[direct] + offset_m * d[direct, 0]
    support[direct, 2] = xy[direct] + offset_m * d[direct, 1]  # NaN for EOWs
    wall_p[direct] = xy[direct, None, :]
    wall_d[direct] = d[direct]
    inter = np.flatnonzero(kind == INTERSECTION)
    if inter.shape[0] and features.n_segments:
        for slot in (0, 1):
            sid = features.segment_ids[inter, slot]
            ok = (sid >= 0) & (sid < features.n_segments)
            rows = inter[ok]
            ep = features.seg_endpoints[sid[ok]]  # (n, 2, 2)
            dist = np.linalg.norm(ep - xy[rows, None, :], axis=2)
            near_k = np.argmin(dist, axis=1)
            ar = np.arange(rows.shape[0])
            near = ep[ar, near_k]
            far = ep[ar, 1 - near_k]
            u = far - near
            u /= np.maximum(np.linalg.norm(u, axis=1), 1e-9)[:, None]
            support[rows, slot] = near + offset_m * u
            wall_p[rows, slot] = near
            wall_d[rows, slot] = u
    with np.errstate(invalid="ignore"):
        side = np.sign(wall_d[..., 1] * wall_p[..., 0] - wall_d[..., 0] * wall_p[..., 1])
    return support, wall_p, wall_d, side


class FeatureMap:
    """Landmarks anchored to graph nodes, with time-validity (paper §III-C3).

    Typical use, per keyframe (see ``iceg.slam``)::

        ref = fmap.reference(node_poses, recent_node_ids, node_poses[last])
        res = matcher.match(features, ref, prediction, bounds)
        # ... add the node and factors, update the graph ...
        fmap.update(
            new_id, features, scan.stamp_s, reference=ref, match=res, scan=scan,
            node_poses=updated_node_poses,
        )

    Args:
        config: Feature-map configuration.
    """

    def __init__(self, config: FeatureMapConfig | None = None) -> None:
        self.config = config or FeatureMapConfig()
        self._lm: dict[str, np.ndarray] = {
            k: np.zeros((0, *shape), dtype=dt) for k, (dt, shape, _) in _LM_FIELDS.items()
        }
        self._seg: dict[str, np.ndarray] = {
            k: np.zeros((0, *shape), dtype=dt) for k, (dt, shape) in _SEG_FIELDS.items()
        }
        self._nodes: set[int] = set()
        self._pt_node = np.zeros(0, dtype=np.int64)
        self._pt_xy = np.zeros((0, 2))
        self._next_id = 0
        self.n_merged = 0
        self._range_max_m = 20.0
        self._last_stamp_s = 0.0
        # reference -> (landmark ids (K,), frame pose (3,), node ids (N,), node poses (N, 3))
        self._refs: weakref.WeakKeyDictionary[
            ScanFeatures, tuple[IntArray, FloatArray, IntArray, FloatArray]
        ] = weakref.WeakKeyDictionary()
        self._pruned: dict[str, list[np.ndarray]] = {
            k: [] for k in ("ids", "anchor", "kind", "xy", "stamp_s", "created_s", "last_s", "why")
        }

    # ------------------------------------------------------------------ inspection
    def __len__(self) -> int:
        """Number of landmarks."""
        return int(self._lm["id"].shape[0])

    def __repr__(self) -> str:
        kinds = np.bincount(self._lm["kind"], minlength=3) if len(self) else np.zeros(3, int)
        n_pruned = sum(a.shape[0] for a in self._pruned["ids"])
        return (
            f"FeatureMap(nodes={len(self._nodes)}, landmarks={len(self)} "
            f"[corner={kinds[CORNER]}, eow={kinds[EOW]}, intersection={kinds[INTERSECTION]}], "
            f"segments={self._seg['node'].shape[0]}, pruned={n_pruned}, merged={self.n_merged})"
        )

    @property
    def node_ids(self) -> IntArray:
        """Sorted ids of the nodes added so far."""
        return np.array(sorted(self._nodes), dtype=np.int64)

    @property
    def pruned(self) -> PrunedLandmarks:
        """Every landmark pruned so far (positions in their anchor's frame)."""
        p = self._pruned

        def cat(key: str, shape: tuple[int, ...], dt: type) -> np.ndarray:
            return np.concatenate(p[key]) if p[key] else np.zeros((0, *shape), dtype=dt)

        return PrunedLandmarks(
            ids=cat("ids", (), np.int64),
            anchor=cat("anchor", (), np.int64),
            kind=cat("kind", (), np.int64),
            xy=cat("xy", (2,), np.float64),
            stamp_s=cat("stamp_s", (), np.float64),
            created_s=cat("created_s", (), np.float64),
            last_matched_s=cat("last_s", (), np.float64),
            reason=cat("why", (), np.int64),
        )

    def world_landmarks(self, node_poses: NodePoses) -> LandmarkView:
        """All landmarks whose anchor has a pose, expressed in the frame of ``node_poses``
        (the map/world frame of the graph estimates).

        Args:
            node_poses: ``{node_id: (3,) pose}`` or ``(ids (N,), poses (N, 3))``.
        """
        ids, poses = _node_pose_table(node_poses)
        pos, found = _lookup(ids, self._lm["anchor"])
        sel = np.flatnonzero(found)
        anchor_pose = poses[pos[sel]]
        return self._view(sel, anchor_pose)

    def _view(self, sel: IntArray, frame_from_anchor: FloatArray) -> LandmarkView:
        lm = self._lm
        r = rot(frame_from_anchor[:, 2])
        xy = np.einsum("nab,nb->na", r, lm["xy"][sel]) + frame_from_anchor[:, :2]
        cov = r @ lm["cov"][sel] @ np.swapaxes(r, 1, 2)
        dirs = np.einsum("nab,nkb->nka", r, lm["dirs"][sel])
        return LandmarkView(
            ids=lm["id"][sel].copy(),
            anchor=lm["anchor"][sel].copy(),
            kind=lm["kind"][sel].copy(),
            xy=xy,
            cov=cov,
            directions=dirs,
            opening_rad=lm["opening"][sel].copy(),
            n_expected=lm["n_expected"][sel].copy(),
            n_matched=lm["n_matched"][sel].copy(),
            last_matched_s=lm["last_matched_s"][sel].copy(),
        )

    # ------------------------------------------------------------------ reference
    def reference(
        self,
        node_poses: NodePoses,
        node_ids: Sequence[int] | ArrayLike,
        frame_pose: ArrayLike,
    ) -> ScanFeatures:
        """Build a matching reference from chosen nodes (recent ones for tracking, older
        ones near the current estimate for loop closure; DESIGN "Feature map").

        It holds the landmarks anchored to ``node_ids`` or last matched from one of them,
        and the segments of those nodes, all in the frame of ``frame_pose``.

        Args:
            node_poses: Current pose estimates ``{node_id: (3,) pose}`` or
                ``(ids (N,), poses (N, 3))``, map frame; must include the anchors used.
            node_ids: Nodes whose landmarks and segments to use.
            frame_pose: ``(3,)`` pose (map frame) of the reference frame, usually the pose
                of the newest of ``node_ids``.

        Returns:
            A :class:`~iceg.types.ScanFeatures` in the frame of ``frame_pose``; ``ids`` are
            landmark ids; ``segment_ids`` -1; ``points_xy`` holds the nodes' scan points (with
            ``seg_point_range`` into them) when ``config.reference_points``, else it is empty
            and ``seg_point_range`` -1.
        """
        frame = np.asarray(frame_pose, dtype=np.float64).reshape(3)
        ids, poses = _node_pose_table(node_poses)
        want = np.unique(np.asarray(node_ids, dtype=np.int64).reshape(-1))
        lm, sg = self._lm, self._seg
        apos, afound = _lookup(ids, lm["anchor"])
        chosen = np.isin(lm["anchor"], want) | np.isin(lm["last_node"], want)
        sel = np.flatnonzero(chosen & afound)
        rel = between(frame, poses[apos[sel]]) if sel.shape[0] else np.zeros((0, 3))
        spos, sfound = _lookup(ids, sg["node"])
        ssel = np.flatnonzero(np.isin(sg["node"], want) & sfound)
        srel = between(frame, poses[spos[ssel]]) if ssel.shape[0] else np.zeros((0, 3))
        view = self._view(sel, rel)
        r_s = rot(srel[:, 2])
        ep = np.einsum("nab,nkb->nka", r_s, sg["ep"][ssel]) + srel[:, None, :2]
        lines, lcov = transform_lines(sg["lines"][ssel], sg["cov"][ssel], srel)
        points = np.zeros((0, 2))
        seg_pr = np.full((ssel.shape[0], 2), -1, dtype=np.int64)
        if self.config.reference_points and self._pt_node.shape[0]:
            ppos, pfound = _lookup(ids, self._pt_node)
            psel = np.flatnonzero(np.isin(self._pt_node, want) & pfound)
            prel = between(frame, poses[ppos[psel]])
            points = np.einsum("nab,nb->na", rot(prel[:, 2]), self._pt_xy[psel]) + prel[:, :2]
            # Each node's points are contiguous: shift its segments' ranges to its block.
            nodes_sel, first = np.unique(self._pt_node[psel], return_index=True)
            k = np.searchsorted(nodes_sel, sg["node"][ssel])
            k = np.clip(k, 0, max(nodes_sel.shape[0] - 1, 0))
            has = (nodes_sel.shape[0] > 0) & (sg["pr"][ssel, 0] >= 0)
            if nodes_sel.shape[0]:
                has &= nodes_sel[k] == sg["node"][ssel]
            seg_pr = np.where(has[:, None], sg["pr"][ssel] + first[k][:, None], -1)
        ref = ScanFeatures(
            points_xy=points,
            seg_endpoints=ep,
            seg_lines=lines,
            seg_cov=lcov,
            seg_point_range=seg_pr,
            kind=view.kind,
            xy=view.xy,
            cov=view.cov,
            directions=view.directions,
            opening_rad=view.opening_rad,
            segment_ids=np.full((sel.shape[0], 2), -1, dtype=np.int64),
            ids=view.ids,
            range_max_m=self._range_max_m,
            stamp_s=self._last_stamp_s,
        )
        self._refs[ref] = (view.ids, frame, ids, poses)
        return ref

    # ------------------------------------------------------------------ update
    def update(
        self,
        node_id: int,
        features: ScanFeatures,
        stamp_s: float,
        *,
        reference: ScanFeatures | None = None,
        match: MatchResult | None = None,
        scan: LaserScan | None = None,
        node_poses: NodePoses | None = None,
        node_pose: ArrayLike | None = None,
    ) -> MapUpdate:
        """Add a node's scan to the map: association, new landmarks, time-validity.

        With a successful ``match`` against ``reference`` (built by :meth:`reference`):

        - the matcher's inlier pairs give the landmarks this scan matched; every other
          landmark whose anchor has a pose is brought into the new node's frame and
          associated with an unpaired new feature within ``association_gate_m`` (of any
          kind: a Corner seen partially is an EOW, paper §III-C2, or an Intersection of its
          two walls);
        - a matched landmark keeps the more precise observation, and takes the kind of an
          observation that tells more (Corner > EOW > Intersection);
        - every landmark **expected** in this scan (support points inside its field of view
          and ``expected_max_range_m``, not occluded by its own ranges, walls not at grazing
          incidence) but not matched counts a miss; then pruning runs (paper §III-C3);
        - the remaining new features become landmarks anchored to ``node_id``.

        Without a successful match (first node, failed match) every feature becomes a new
        landmark anchored to ``node_id`` and no bookkeeping is done (the node's pose relative
        to the map is not known well enough to judge visibility).

        Args:
            node_id: The new node's id (each node is added once).
            features: The node's scan features, robot frame (= node frame).
            stamp_s: Scan time, seconds.
            reference: The reference ``match`` was computed against.
            match: The match of ``features`` against ``reference``.
            scan: The laser scan, for visibility (field of view, occlusion by its own
                ranges); ``None`` uses ``features.points_xy`` instead.
            node_poses: Current pose estimates of the nodes (map frame), to place every
                landmark relative to the new node; ``None`` uses the poses given to
                :meth:`reference` and ``frame_pose ∘ match.pose`` for the new node.
            node_pose: ``(3,)`` map-frame pose of the new node, when ``node_poses`` does not
                hold it (default ``frame_pose ∘ match.pose``).

        Returns:
            A :class:`MapUpdate`.

        Raises:
            MatchingError: ``node_id`` was already added, or a successful ``match`` comes
                without the ``reference`` built by this map.
        """
        node_id = int(node_id)
        if node_id in self._nodes:
            raise MatchingError(f"FeatureMap.update: node {node_id} was already added")
        stamp = float(stamp_s)
        empty = np.zeros(0, dtype=np.int64)
        matched_ids = empty
        expected_ids = empty
        merged_ids = empty
        new_mask = np.ones(features.n_features, dtype=bool)
        if match is not None and match.success:
            if reference is None or reference not in self._refs:
                raise MatchingError(
                    "FeatureMap.update: a successful match needs reference=<the ScanFeatures "
                    "returned by this map's reference() that match() was computed against>"
                )
            matched_ids, expected_ids, new_mask, merge_rows = self._bookkeep(
                node_id, features, stamp, reference, match, scan, node_poses, node_pose
            )
            merged_ids = self._lm["id"][merge_rows].copy()
            keep = np.ones(len(self), dtype=bool)
            keep[merge_rows] = False
            for k in self._lm:
                self._lm[k] = self._lm[k][keep]
            self.n_merged += int(merge_rows.shape[0])
        self._store_segments(node_id, features)
        added = self._add_landmarks(node_id, features, new_mask, stamp)
        pruned = self._prune(stamp)
        self._nodes.add(node_id)
        self._range_max_m = float(features.range_max_m)
        self._last_stamp_s = stamp
        return MapUpdate(node_id, matched_ids, added, expected_ids, pruned, merged_ids)

    def _store_segments(self, node_id: int, features: ScanFeatures) -> None:
        m = features.n_segments
        keep = self.config.reference_points
        pr = np.asarray(features.seg_point_range, dtype=np.int64).reshape(m, 2)
        new = {
            "node": np.full(m, node_id, dtype=np.int64),
            "ep": np.asarray(features.seg_endpoints, dtype=np.float64).reshape(m, 2, 2),
            "lines": np.asarray(features.seg_lines, dtype=np.float64).reshape(m, 2),
            "cov": np.asarray(features.seg_cov, dtype=np.float64).reshape(m, 2, 2),
            "pr": pr if keep else np.full((m, 2), -1, dtype=np.int64),
        }
        for k in self._seg:
            self._seg[k] = np.concatenate([self._seg[k], new[k]])
        if keep:
            pts = np.asarray(features.points_xy, dtype=np.float64).reshape(-1, 2)
            self._pt_node = np.concatenate(
                [self._pt_node, np.full(pts.shape[0], node_id, dtype=np.int64)]
            )
            self._pt_xy = np.concatenate([self._pt_xy, pts])

    def _add_landmarks(
        self, node_id: int, features: ScanFeatures, mask: BoolArray, stamp: float
    ) -> IntArray:
        rows = np.flatnonzero(mask)
        n = rows.shape[0]
        ids = np.arange(self._next_id, self._next_id + n, dtype=np.int64)
        self._next_id += n
        support, wall_p, wall_d, wall_side = (
            a[rows] for a in _geometry(features, self.config.support_offset_m)
        )
        new = {
            "id": ids,
            "anchor": np.full(n, node_id, dtype=np.int64),
            "kind": np.asarray(features.kind, dtype=np.int64)[rows],
            "xy": features.xy[rows],
            "cov": features.cov[rows],
            "dirs": features.directions[rows],
            "opening": features.opening_rad[rows],
            "support": support,
            "wall_p": wall_p,
            "wall_d": wall_d,
            "wall_side": wall_side,
            "n_expected": np.zeros(n, dtype=np.int64),
            "n_matched": np.zeros(n, dtype=np.int64),
            "misses": np.zeros(n, dtype=np.int64),
            "created_s": np.full(n, stamp),
            "last_matched_s": np.full(n, stamp),
            "first_miss_s": np.full(n, np.nan),
            "last_node": np.full(n, node_id, dtype=np.int64),
        }
        for k in self._lm:
            self._lm[k] = np.concatenate([self._lm[k], new[k].astype(self._lm[k].dtype)])
        return ids

    def _bookkeep(
        self,
        node_id: int,
        features: ScanFeatures,
        stamp: float,
        reference: ScanFeatures,
        match: MatchResult,
        scan: LaserScan | None,
        node_poses: NodePoses | None,
        node_pose: ArrayLike | None,
    ) -> tuple[IntArray, IntArray, BoolArray, IntArray]:
        """Association and expected/matched counting for one matched scan; also returns the
        rows of duplicate landmarks to merge."""
        cfg = self.config
        lm = self._lm
        ref_ids, frame, snap_ids, snap_poses = self._refs[reference]
        if node_poses is not None:
            tab_ids, tab_poses = _node_pose_table(node_poses)
        else:
            tab_ids, tab_poses = snap_ids, snap_poses
        npos, nfound = _lookup(tab_ids, np.array([node_id]))
        if nfound[0]:
            new_pose = tab_poses[npos[0]]
        elif node_pose is not None:
            new_pose = np.asarray(node_pose, dtype=np.float64).reshape(3)
        else:
            new_pose = compose(frame, match.pose)
        # Every landmark whose anchor has a pose (of the reference, by default), in the new
        # node's frame.
        apos, afound = _lookup(tab_ids, lm["anchor"])
        if cfg.bookkeeping_recent_nodes is not None:
            recent = lm["last_node"] >= node_id - cfg.bookkeeping_recent_nodes
            afound &= recent | np.isin(lm["id"], ref_ids)
        rows = np.flatnonzero(afound)
        anchor_in_new = (
            between(new_pose, tab_poses[apos[rows]]) if rows.shape[0] else np.zeros((0, 3))
        )
        r_an = rot(anchor_in_new[:, 2])
        xy_new = np.einsum("nab,nb->na", r_an, lm["xy"][rows]) + anchor_in_new[:, :2]
        slot = np.full(len(self), -1, dtype=np.int64)
        slot[rows] = np.arange(rows.shape[0])
        # 1. The matcher's pairs (reference index -> landmark id -> row).
        k_new = features.n_features
        pairs = np.asarray(match.inlier_pairs, dtype=np.int64).reshape(-1, 2)
        pairs = pairs[(pairs[:, 0] >= 0) & (pairs[:, 0] < k_new)]
        pairs = pairs[(pairs[:, 1] >= 0) & (pairs[:, 1] < ref_ids.shape[0])]
        lpos, lfound = _lookup(lm["id"], ref_ids[pairs[:, 1]])
        ok = lfound & (slot[lpos] >= 0)
        pair_new = pairs[ok, 0]
        pair_row = lpos[ok]
        # 2. Geometric association of the other new features with the other landmarks.
        free_n = np.setdiff1d(np.arange(k_new), pair_new)
        free_s = np.setdiff1d(np.arange(rows.shape[0]), slot[pair_row])
        if free_n.shape[0] and free_s.shape[0]:
            d = np.linalg.norm(features.xy[free_n][:, None, :] - xy_new[free_s][None], axis=2)
            jbest = np.argmin(d, axis=1)
            good = d[np.arange(free_n.shape[0]), jbest] <= cfg.association_gate_m
            cand_n = free_n[good]
            cand_s = free_s[jbest[good]]
            _, first = np.unique(cand_s, return_index=True)  # one feature per landmark
            pair_new = np.concatenate([pair_new, cand_n[first]])
            pair_row = np.concatenate([pair_row, rows[cand_s[first]]])
        new_mask = np.ones(k_new, dtype=bool)
        new_mask[pair_new] = False
        # Duplicates: other landmarks within the gate of a paired feature are the same
        # physical feature (anchored to another node); they merge into the paired one.
        merge_rows = np.zeros(0, dtype=np.int64)
        if pair_new.shape[0] and rows.shape[0]:
            dd = np.linalg.norm(features.xy[pair_new][:, None, :] - xy_new[None], axis=2)
            near = np.any(dd <= cfg.association_gate_m, axis=0)
            near[slot[pair_row]] = False
            merge_rows = rows[near]
        # Keep the better observation; an EOW seen as a Corner becomes a Corner.
        if pair_row.shape[0]:
            new_in_anchor = inverse(anchor_in_new[slot[pair_row]])
            tr_new = np.trace(features.cov[pair_new], axis1=1, axis2=2)
            tr_old = np.trace(lm["cov"][pair_row], axis1=1, axis2=2)
            upgrade = _RANK[features.kind[pair_new]] > _RANK[lm["kind"][pair_row]]
            same = lm["kind"][pair_row] == features.kind[pair_new]
            rep = np.flatnonzero(upgrade | (same & (tr_new < cfg.replace_ratio * tr_old)))
            if rep.shape[0]:
                rr = pair_row[rep]
                fi = pair_new[rep]
                na = new_in_anchor[rep]
                r = rot(na[:, 2])
                lm["xy"][rr] = np.einsum("nab,nb->na", r, features.xy[fi]) + na[:, :2]
                lm["cov"][rr] = r @ features.cov[fi] @ np.swapaxes(r, 1, 2)
                lm["dirs"][rr] = np.einsum("nab,nkb->nka", r, features.directions[fi])
                lm["opening"][rr] = features.opening_rad[fi]
                lm["kind"][rr] = features.kind[fi]
                sup, wp, wd, _ = (a[fi] for a in _geometry(features, cfg.support_offset_m))
                lm["support"][rr] = np.einsum("nab,nkb->nka", r, sup) + na[:, None, :2]
                lm["wall_p"][rr] = np.einsum("nab,nkb->nka", r, wp) + na[:, None, :2]
                lm["wall_d"][rr] = np.einsum("nab,nkb->nka", r, wd)
                # The side seen from the new node, expressed for the anchor-frame wall.
                o = na[:, None, :2]  # new node's origin in the anchor frame
                wpa = lm["wall_p"][rr]
                wda = lm["wall_d"][rr]
                with np.errstate(invalid="ignore"):
                    lm["wall_side"][rr] = np.sign(
                        wda[..., 0] * (o[..., 1] - wpa[..., 1])
                        - wda[..., 1] * (o[..., 0] - wpa[..., 0])
                    )
        # 3. Expected landmarks (all of them with a known anchor pose).
        expected = self._expected(rows, anchor_in_new, features, scan)
        matched_rows = np.unique(pair_row)
        is_matched = np.zeros(len(self), dtype=bool)
        is_matched[matched_rows] = True
        exp_rows = rows[expected | is_matched[rows]]
        lm["n_expected"][exp_rows] += 1
        lm["n_matched"][matched_rows] += 1
        lm["last_matched_s"][matched_rows] = stamp
        lm["misses"][matched_rows] = 0
        lm["first_miss_s"][matched_rows] = np.nan
        lm["last_node"][matched_rows] = node_id
        miss_rows = rows[expected & ~is_matched[rows]]
        lm["misses"][miss_rows] += 1
        first = miss_rows[np.isnan(lm["first_miss_s"][miss_rows])]
        lm["first_miss_s"][first] = stamp
        return (
            lm["id"][matched_rows].copy(),
            lm["id"][exp_rows].copy(),
            new_mask,
            merge_rows,
        )

    def _expected(
        self,
        rows: IntArray,
        anchor_in_new: FloatArray,
        features: ScanFeatures,
        scan: LaserScan | None,
    ) -> BoolArray:
        """Which landmarks (``rows``, anchors at ``anchor_in_new`` in the new frame) the scan
        should see (DESIGN: inside the field of view and range, not occluded; and its walls
        (one for a Corner or EOW, both for an Intersection) seen from the side they were seen
        from before, not at grazing incidence)."""
        cfg = self.config
        lm = self._lm
        n = rows.shape[0]
        if n == 0:
            return np.zeros(0, dtype=bool)
        r = rot(anchor_in_new[:, 2])
        sup = np.einsum("nab,nkb->nka", r, lm["support"][rows]) + anchor_in_new[:, None, :2]
        wp = np.einsum("nab,nkb->nka", r, lm["wall_p"][rows]) + anchor_in_new[:, None, :2]
        wd = np.einsum("nab,nkb->nka", r, lm["wall_d"][rows])
        has = np.all(np.isfinite(sup), axis=2)  # (n, 3)
        if scan is not None:
            off = np.asarray(scan.laser_offset, dtype=np.float64)
            ro = rot(off[2])
            pts = np.einsum("ba,nkb->nka", ro, sup - off[:2])  # laser frame
            order = np.argsort(scan.angles_rad, kind="stable")
            ang = scan.angles_rad[order]
            rng = scan.ranges_m[order]
            valid = scan.valid_mask()[order]
            with np.errstate(invalid="ignore"):
                beyond = np.isfinite(rng) & (rng >= scan.range_max_m)
            beam_r = np.where(valid, rng, np.where(beyond, np.inf, 0.0))
            spacing = float(np.median(np.diff(ang))) if ang.shape[0] > 1 else math.radians(1)
            prof = PolarProfile(ang, beam_r, spacing, float(scan.range_max_m))
            lo, hi = ang[0], ang[-1]
        else:
            pts = sup
            prof = PolarProfile.from_points(features.points_xy, float(features.range_max_m))
            if prof.bearing.shape[0] == 0:
                return np.zeros(n, dtype=bool)
            lo, hi = prof.bearing[0], prof.bearing[-1]
        bearing = np.arctan2(pts[..., 1], pts[..., 0])
        dist = np.hypot(pts[..., 0], pts[..., 1])
        margin = math.radians(cfg.fov_margin_deg)
        in_fov = (bearing >= lo + margin) & (bearing <= hi - margin)
        in_range = dist <= cfg.expected_max_range_m
        # Both beams around the bearing must reach at least the distance minus tolerance.
        nb = prof.bearing.shape[0]
        k = np.clip(np.searchsorted(prof.bearing, bearing), 1, nb - 1)
        r0 = prof.range[k - 1]
        r1 = prof.range[k]
        gap = (prof.bearing[k] - prof.bearing[k - 1]) > 1.6 * prof.spacing
        with np.errstate(invalid="ignore"):
            clear = (np.fmin(r0, r1) >= dist - cfg.occlusion_tolerance_m) & ~gap
        ok_point = in_fov & in_range & clear
        visible = np.all(ok_point | ~has, axis=1) & np.any(has, axis=1)
        # Each wall: seen from the same side as before, not at grazing incidence.
        with np.errstate(invalid="ignore"):
            side = np.sign(wd[..., 1] * wp[..., 0] - wd[..., 0] * wp[..., 1])
            ray = wp / np.maximum(np.hypot(wp[..., 0], wp[..., 1]), 1e-9)[..., None]
            sin_inc = np.abs(ray[..., 0] * wd[..., 1] - ray[..., 1] * wd[..., 0])
            wall_ok = (side == lm["wall_side"][rows]) & (
                sin_inc >= math.sin(math.radians(cfg.min_incidence_deg))
            )
        has_wall = np.isfinite(lm["wall_side"][rows])
        # An Intersection needs both of its walls; a Corner shows as an EOW when only one
        # of its walls faces the sensor (paper §III-C2), so one suffices.
        all_seen = np.all(wall_ok | ~has_wall, axis=1) & np.any(has_wall, axis=1)
        any_seen = np.any(wall_ok & has_wall, axis=1)
        walls_seen = np.where(lm["kind"][rows] == INTERSECTION, all_seen, any_seen)
        return visible & walls_seen

    def _prune(self, stamp: float) -> IntArray:
        cfg = self.config
        lm = self._lm
        ratio = (lm["n_expected"] >= cfg.min_expected) & (
            lm["n_matched"] < cfg.min_match_ratio * lm["n_expected"]
        )
        with np.errstate(invalid="ignore"):
            stale = (
                (lm["misses"] >= cfg.min_misses)
                & (stamp - lm["last_matched_s"] >= cfg.validity_s)
                & (stamp - lm["first_miss_s"] >= cfg.miss_confirm_s)
            )

        drop = ratio | stale
        if not np.any(drop):
            return np.zeros(0, dtype=np.int64)
        d = np.flatnonzero(drop)
        p = self._pruned
        p["ids"].append(lm["id"][d].copy())
        p["anchor"].append(lm["anchor"][d].copy())
        p["kind"].append(lm["kind"][d].copy())
        p["xy"].append(lm["xy"][d].copy())
        p["stamp_s"].append(np.full(d.shape[0], stamp))
        p["created_s"].append(lm["created_s"][d].copy())
        p["last_s"].append(lm["last_matched_s"][d].copy())
        p["why"].append(np.where(stale[d], PRUNED_VALIDITY, PRUNED_RATIO).astype(np.int64))
        keep = ~drop
        for k in lm:
            lm[k] = lm[k][keep]
        log.debug("pruned %d landmarks at %.2f s", d.shape[0], stamp)
        return p["ids"][-1]


__all__ = [
    "PRUNED_RATIO",
    "PRUNED_VALIDITY",
    "FeatureMap",
    "FeatureMapConfig",
    "LandmarkView",
    "MapUpdate",
    "PrunedLandmarks",
]
