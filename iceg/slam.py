"""The SLAM pipeline: ICE matching factors and wheel odometry in a GTSAM iSAM2 pose graph.

Per scan (docs/design.md "Data flow of one scan"): ICE features; prediction from odometry (corrected
by the online calibration of :mod:`iceg.odometry_calibration`, which every accepted local
match updates, while it corrects: by default where the odometry's errors are beyond its noise
model); keyframe decision; ICE match against the feature map of the
recent nodes; odometry and scan-match factors (covariance from the match); iSAM2 update;
feature-map update with time-validity pruning; and, every few nodes, a loop-closure search
among older nodes near the current estimate and, by appearance, among all older places
(global loop closure). A revisit that retraces old nodes hangs from them instead of adding
nodes (reduced pose graph, ``slam.reuse_nodes``). After the run an optional batch
Levenberg–Marquardt refinement.

The pipeline never reads files: it takes :class:`frontends.LaserScan` records.
"""

from __future__ import annotations

import functools
import logging
import math
import time
from array import array
from collections import defaultdict
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends import LaserScan
from graph import FactorKind, PoseGraph, odometry_covariance
from iceg.config import IcegConfig
from iceg.feature_map import FeatureMap, MapCheckpoint, MapReference
from iceg.features import extract, extract_points
from iceg.landmark_frames import move_point_blocks, poses_in_frame
from iceg.loop_closure import (
    AcceptedClosures,
    LoopCloser,
    LoopClosureStats,
    OpenSearch,
    innovation_chi2,
)
from iceg.matching import MatchBounds
from iceg.matching.geometry import PolarProfile
from iceg.matching.matcher import (
    REASON_DEGENERATE,
    REASON_FEW_INLIERS,
    REASON_LOW_CORRELATION,
    REASON_NO_CANDIDATES,
    scan_derived,
)
from iceg.matching.peers import make_matcher
from iceg.matching.plicp import PlIcpMatcher
from iceg.matching.refine import blocks_explained_counts, points_within
from iceg.odometry_calibration import OdometryCalibrator
from iceg.results import SlamResult
from iceg.scan_poses import odometry_steps, scan_poses
from iceg.scan_store import ScanStore
from iceg.types import MatchResult, ScanFeatures
from iceg_common import se2
from iceg_common.errors import GraphError, ScanError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
#: Points in blocks, each block in its own frame (:func:`~iceg.landmark_frames.move_point_blocks`):
#: ``(n, 3)`` float64 the pose of each block's frame in the target frame, ``(n,)`` int64 the
#: points in each block and ``(R, 2)`` float64 the points, one block after the other, metres.
PointBlocks = tuple[FloatArray, IntArray, FloatArray]

#: A weak match direction agrees with the prediction when their difference is within this
#: many standard deviations of the joint noise (a 3-sigma consistency test).
AGREE_SIGMAS = 3.0

#: Probability of the chi-square test of a point match against the prediction.
CONSISTENCY_PROBABILITY = 0.999


#: ``scipy.stats.chi2.ppf(CONSISTENCY_PROBABILITY, 3)``, bit for bit
#: (``test_chi2_quantile_is_scipy_stats``), written out: a run imports no ``scipy.special``.
_CHI2_3DOF = 16.26623619623813


def chi2_3dof() -> float:
    """The chi-square quantile of :data:`CONSISTENCY_PROBABILITY` for 3 degrees of freedom,
    the value ``scipy.stats.chi2.ppf`` computes (``2 gammaincinv(k / 2, p)``). It is a
    literal rather than scipy's call: importing ``scipy.special`` cost a run 86 ms."""
    return _CHI2_3DOF


#: Failure category of a successful ICE match that :func:`points_prefer_prediction` rejects.
REASON_CONTRADICTED = "contradicted by the points"

#: Failure categories after which the point match is tried (``slam.point_fallback``): ICE
#: had too little evidence (too few features, pairs or correlation, a degenerate scene) or the
#: points contradict it. Not after a conflict ICE found (outside the bounds, inconsistent with
#: free space, ambiguous): a point match seeded by the same prediction has no better answer.
_POINT_FALLBACK_REASONS = frozenset(
    {
        REASON_NO_CANDIDATES,
        REASON_FEW_INLIERS,
        REASON_LOW_CORRELATION,
        REASON_DEGENERATE,
        REASON_CONTRADICTED,
    }
)

#: Failure category of a match whose reason is empty.
_UNKNOWN_REASON = "unknown"

#: At most this many keyframes placed without a match keep their features for the offline
#: second match (:meth:`Slam._rematch_unmatched_keyframes`); the others are extracted again.
#: MIT CSAIL has 11 such keyframes of 1814.
KEPT_UNMATCHED_FEATURES = 256

__all__ = [
    "Anchor",
    "LoopClosureStats",
    "PointBlocks",
    "ScanRecords",
    "Slam",
    "SlamState",
    "StageTimer",
    "blocks_prefer_prediction",
    "chi2_3dof",
    "consistent_with_prediction",
    "points_prefer_prediction",
    "remap_weak_directions",
    "sign_test_rejects",
]


class StageTimer:
    """Wall time per pipeline stage (seconds): totals in ``seconds`` and every call's time
    in ``samples`` (one float64 per call, in call order, 8 bytes each: per-keyframe medians
    for ``benchmarks/bench_pipeline.py``)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)
        self.samples: dict[str, array[float]] = defaultdict(lambda: array("d"))

    def add(self, stage: str, t0: float) -> float:
        """Add ``now - t0`` to ``stage`` (total and one sample); return now."""
        now = time.perf_counter()
        dt = now - t0
        self.seconds[stage] += dt
        self.samples[stage].append(dt)
        return now


class ScanRecords:
    """Where each processed scan's pose comes from, one row per scan in columns (no Python
    object per scan): its stamp, the node it hangs from and the odometry delta from that
    node's scan to it (a node's own row has the zero delta); the trajectory is
    ``estimate(node) ∘ delta`` (docs/design.md "Data flow of one scan").

    Args:
        stamps_s: ``(N,)`` float64 stamps (s).
        node_ids: ``(N,)`` int64 node ids.
        deltas: ``(N, 3)`` float64 ``[dx_m, dy_m, dtheta_rad]`` in the node's frame.
    """

    def __init__(
        self,
        stamps_s: ArrayLike = (),
        node_ids: ArrayLike = (),
        deltas: ArrayLike = (),
    ) -> None:
        stamps = np.asarray(stamps_s, dtype=np.float64).reshape(-1)
        n = stamps.shape[0]
        cap = max(n, 256)
        self._stamp = np.zeros(cap)
        self._node = np.zeros(cap, dtype=np.int64)
        self._delta = np.zeros((cap, 3))
        self._stamp[:n] = stamps
        self._node[:n] = np.asarray(node_ids, dtype=np.int64).reshape(n)
        self._delta[:n] = np.asarray(deltas, dtype=np.float64).reshape(n, 3)
        self._n = n

    def __len__(self) -> int:
        return self._n

    def append(self, stamp_s: float, node_id: int, delta: ArrayLike | None = None) -> None:
        """One more scan; ``delta`` ``None``: the node's own scan (zero delta)."""
        if self._n == self._stamp.shape[0]:
            self._stamp = np.concatenate([self._stamp, np.zeros_like(self._stamp)])
            self._node = np.concatenate([self._node, np.zeros_like(self._node)])
            self._delta = np.concatenate([self._delta, np.zeros_like(self._delta)])
        k = self._n
        self._stamp[k] = stamp_s
        self._node[k] = node_id
        self._delta[k] = 0.0 if delta is None else delta
        self._n += 1

    def arrays(self) -> tuple[FloatArray, IntArray, FloatArray]:
        """Copies of the columns: stamps ``(N,)`` s, node ids ``(N,)``, deltas ``(N, 3)``."""
        n = self._n
        return self._stamp[:n].copy(), self._node[:n].copy(), self._delta[:n].copy()


@dataclass(frozen=True, eq=False)
class _Motion:
    """Motion of a scan relative to the last node, and whether the scan becomes a node."""

    odom: FloatArray  # (3,) odometry pose of the scan (predicted when the log has none)
    delta: FloatArray  # (3,) last node -> scan, odometry (calibrated)
    cov: FloatArray  # (3, 3) covariance of delta, tangent space
    is_keyframe: bool
    measured: bool = True  # odom is the scan's own odometry (not a prediction)
    odometry_break: bool = False  # odom starts a new odometry frame (no delta across)
    raw: tuple[FloatArray, FloatArray] | None = None  # raw odometry delta and its noise cov


@dataclass(frozen=True, eq=False)
class _LocalMatch:
    """A keyframe's match against the local map of the recent nodes."""

    reference: MapReference
    result: MatchResult
    last_pose: FloatArray  # (3,) estimate of the last node when the reference was built
    ice_failure: str = ""  # why the ICE match failed (reason category; "": it succeeded)


@dataclass(eq=False)
class _OpenSearch:
    """A node's loop-closure search whose matches run in the helper process while the next
    keyframe is tracked (:meth:`Slam._finish_search`)."""

    begun: OpenSearch
    map_update: tuple[int, ScanFeatures, LaserScan, _LocalMatch]  # the node's _update_map
    checkpoint: MapCheckpoint | None = None  # the feature map before that update ran


@dataclass(frozen=True, eq=False)
class Anchor:
    """The old node a revisit hangs from (``slam.reuse_nodes``; docs/design.md, "Reused
    nodes"): the scans after the anchoring scan take ``estimate(node) ∘ offset ∘ odometry``.

    Attributes:
        node: The old node.
        offset: ``(3,)`` float64 pose of the anchoring scan in the node's frame
            ``[x_m, y_m, theta_rad]`` (its match against the old place).
        offset_cov: ``(3, 3)`` float64 covariance of ``offset`` (the match's), tangent space
            at the scan (m², rad²).
        odom: ``(3,)`` float64 odometry pose of the anchoring scan.
        stamp_s: Its stamp (s).
        path_m: The odometry path length at it (m).
    """

    node: int
    offset: FloatArray
    offset_cov: FloatArray
    odom: FloatArray
    stamp_s: float
    path_m: float

    def as_array(self) -> FloatArray:
        """``(18,)`` float64: node, offset, odom, stamp, path, offset_cov row-major."""
        head = [float(self.node), *self.offset, *self.odom, self.stamp_s, self.path_m]
        return np.array([*head, *self.offset_cov.reshape(9)], dtype=np.float64)

    @classmethod
    def from_array(cls, a: ArrayLike) -> Anchor:
        """The inverse of :meth:`as_array`."""
        v = np.asarray(a, dtype=np.float64).reshape(18)
        return cls(
            int(v[0]), v[1:4].copy(), v[9:18].reshape(3, 3).copy(), v[4:7].copy(), v[7], v[8]
        )


@dataclass(frozen=True, eq=False)
class _Reuse:
    """A keyframe's match against an old place (``slam.reuse_nodes``)."""

    reference: MapReference
    result: MatchResult
    frame_pose: FloatArray  # (3,) estimate of the node the match is relative to
    pose: FloatArray  # (3,) the scan's pose in that frame (the prediction where it failed)
    cov: FloatArray  # (3, 3) its covariance given the match and the prediction
    node: int | None = None  # the old node within one keyframe spacing of the match
    offset: FloatArray | None = None  # (3,) the scan's pose in that node's frame


@dataclass
class SlamState:
    """Mutable per-run bookkeeping of :class:`Slam` (scans, nodes, match statistics).

    ``scans`` is a compact :class:`~iceg.scan_store.ScanStore`; a sequence of scans given
    instead (e.g. by :mod:`iceg.session`) is stored into one.
    """

    scans: ScanStore = field(default_factory=ScanStore)
    records: ScanRecords = field(default_factory=ScanRecords)
    node_scan_index: list[int] = field(default_factory=list)
    node_odom: list[FloatArray] = field(default_factory=list)
    node_odom_measured: list[bool] = field(default_factory=list)  # False: predicted odom
    # True: the node was placed by a match (a local scan match, the first node, a placement)
    node_matched: list[bool] = field(default_factory=list)
    node_path_m: list[float] = field(default_factory=list)  # odometry path length at node
    correlations: dict[int, float] = field(default_factory=dict)  # factor index -> eq. 1
    match_failures: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    # ICE failures (by reason category) whose scan got the point match's factor instead
    point_fallbacks: dict[str, int] = field(default_factory=lambda: defaultdict(int))
    # first node of the current log (Slam.start_segment) or of the path after a revisit
    # (slam.reuse_nodes): the local map's oldest node
    segment_start: int = 0
    # first node of the current log (Slam.start_segment; 0 for a single run): the nodes
    # before it are another log's, never the path just driven
    log_start: int = 0
    # slam.reuse_nodes: the old node the scans hang from while a revisit follows old nodes,
    # and the newest node placed in an old node's frame (by a loop closure just accepted, or
    # on leaving the old nodes), from which the next keyframe tries that old place
    anchor: Anchor | None = None
    reuse_from: Anchor | None = None
    reused_keyframes: int = 0  # keyframes that hung from an old node instead of a new one
    # keyframe steps k-1 -> k whose tracking match failed for lack of evidence, by node k:
    # the match's unverified hypothesis, for a later loop closure to confirm (only those
    # after the newest accepted closure; docs/design.md "A disputed step confirmed by a
    # loop closure")
    disputed: dict[int, MatchResult] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.scans, ScanStore):
            self.scans = ScanStore(self.scans)


class Slam:
    """Incremental ICE-matching SLAM, usable scan by scan.

    Example:
        >>> slam = Slam(IcegConfig())
        >>> for scan in scans:
        ...     pose = slam.process(scan)
        >>> result = slam.finish()

    Args:
        config: The full configuration (:class:`iceg.config.IcegConfig`).
    """

    def __init__(self, config: IcegConfig | None = None) -> None:
        self.config = config or IcegConfig()
        self._graph = PoseGraph(self.config.graph)
        self._open: _OpenSearch | None = None  # a search decided at the next keyframe
        self.matcher = make_matcher(self.config.matching)
        self.point_matcher = PlIcpMatcher(self.config.matching)
        self._node_points: dict[int, FloatArray] = {}  # recent nodes' scan points (cache)
        self._last_features: tuple[int, ScanFeatures] | None = None  # newest node, features
        # keyframes placed without a match: their features, for the offline second match
        self._unmatched_features: dict[int, ScanFeatures] = {}
        self._feature_map = FeatureMap(self.config.feature_map)
        self.loop_closer = LoopCloser(
            self.config.loop_closure, self.matcher, self._feature_map, self.config.odometry_noise
        )
        self.odometry_calibrator = OdometryCalibrator(
            self.config.odometry_calibration, self.config.odometry_noise
        )
        self.timer = StageTimer()
        self._s = SlamState()
        self._result: SlamResult | None = None
        self._online_factors: int | None = None  # factors before the final refinement
        # How each log (absolute path) was read, for a saved session to read its scans again
        # (iceg.session): ``reader_options`` of frontends.open_log, ``odometry_time_offset_s``.
        self.log_readings: dict[str, dict[str, Any]] = {}

    @property
    def graph(self) -> PoseGraph:
        """The pose graph, every loop-closure search begun so far decided
        (:meth:`_finish_search`)."""
        self._finish_search()
        return self._graph

    @graph.setter
    def graph(self, graph: PoseGraph) -> None:
        self._graph = graph

    @property
    def feature_map(self) -> FeatureMap:
        """The feature map, every loop-closure search begun so far decided
        (:meth:`_finish_search`): a node's map update that ran before its search accepted a
        closure is redone first."""
        self._finish_search()
        return self._feature_map

    @property
    def loop_stats(self) -> LoopClosureStats:
        """Loop-closure statistics of the run so far."""
        self._finish_search()
        return self.loop_closer.stats

    @property
    def online_factors(self) -> int:
        """Number of factors the scans added, i.e. all but those of :meth:`finish`'s final
        refinement (a session continues from these)."""
        return self.graph.n_factors if self._online_factors is None else self._online_factors

    # ------------------------------------------------------------------ state (sessions)

    def export_state(self) -> SlamState:
        """The per-run bookkeeping (shared, not a copy), for :mod:`iceg.session` (every
        loop-closure search begun so far decided)."""
        self._finish_search()
        return self._s

    @classmethod
    def from_state(
        cls,
        config: IcegConfig,
        graph: PoseGraph,
        feature_map: FeatureMap,
        state: SlamState,
        loop_stats: LoopClosureStats | None = None,
    ) -> Slam:
        """A Slam that continues from saved parts (:func:`iceg.session.load` builds them):
        the graph rebuilt by replay, the feature map, the bookkeeping and loop statistics.
        Held-back closures go to ``slam.loop_closer.pending`` afterwards."""
        slam = cls(config)
        slam._graph = graph
        slam._feature_map = feature_map
        slam.loop_closer = LoopCloser(
            config.loop_closure, slam.matcher, feature_map, config.odometry_noise
        )
        if loop_stats is not None:
            slam.loop_closer.stats = loop_stats
        slam._s = state
        return slam

    def start_segment(
        self,
        scan: LaserScan,
        anchor: int,
        match: MatchResult,
        before: Sequence[LaserScan] = (),
    ) -> FloatArray:
        """Begin another log in this map (``iceg run --continue``): ``scan`` becomes a node
        placed by ``match`` (its pose in the frame of node ``anchor``, from a match against a
        reference built by this map's ``feature_map.reference`` in ``anchor``'s frame), linked
        to ``anchor`` by a loop-closure factor and to nothing by odometry (the new log is a
        new odometry frame); its features join the map. ``before``: the new log's scans
        before ``scan`` (none could be placed), in order, with odometry unbroken up to
        ``scan`` (or none of them with odometry): they hang off the node as scans between
        nodes do, each placed by tracking backwards from it (:meth:`_track_backwards`).
        Later scans go to :meth:`process`.
        Returns the node's pose estimate ``(3,)``, map frame.

        Raises:
            ScanError: the scan is earlier than the last one processed.
            GraphError: ``anchor`` is unknown, the match failed, or gtsam failed.
        """
        if self._result is not None or not match.success or not self._s.node_odom:
            raise GraphError("Slam.start_segment needs a running Slam and a successful match")
        self._finish_search()
        t0 = time.perf_counter()
        for early in before:
            self._check_order(early)
            self._s.scans.append(early)
        self._check_order(scan)
        feats = extract(scan, self.config.features)
        for early, delta in zip(before, self._track_backwards(scan, feats, before), strict=True):
            self._s.records.append(early.stamp_s, len(self._s.node_odom), delta)
        anchor_pose = self._graph.estimate(anchor)
        self._s.scans.append(scan)
        new_id = self._add_node(
            scan,
            self._odometry_of(scan),
            initial=se2.compose(anchor_pose, match.pose),
            odom_measured=scan.odom_pose is not None,
        )
        self._add_factor(
            FactorKind.LOOP_CLOSURE, anchor, new_id, match.pose, match.cov, match.correlation
        )
        # The local map of the new log holds its own nodes only: the old log's last nodes
        # are another trajectory, linked to this one only through the map (which may not yet
        # agree with itself where that log left a loop open).
        self._s.segment_start = self._s.log_start = new_id
        self._s.anchor = self._s.reuse_from = None
        self._graph.update()
        # All its features become its own landmarks, as the first node of a run: the next
        # scans are matched against the landmarks of the recent nodes (this one), not against
        # the old place's that the placement matched.
        self._remember_points(new_id, feats)
        self.loop_closer.observe(new_id, feats)  # a place the global search can find
        self._feature_map.update(new_id, feats, scan.stamp_s, scan=scan)
        self.timer.add("segment_start", t0)
        return self._graph.estimate(new_id)

    def _track_backwards(
        self, scan: LaserScan, feats: ScanFeatures, before: Sequence[LaserScan]
    ) -> list[FloatArray]:
        """Poses ``(3,)`` of the scans ``before`` a segment's first node (``scan``, features
        ``feats``) in the node's frame, in their order: tracked backwards in time as the run
        tracks forwards. Each is matched against the scan after it, predicted by the odometry
        between them (the local match's bounds), and takes the matched motion where the match
        succeeds, the odometry where it fails. Carrying them all by odometry from the node
        would put a fast turn's lagging odometry into their poses (MIT CSAIL's second half
        starts in one: up to 17 degrees)."""
        cfg = self.config.slam
        bounds = MatchBounds.local(cfg.match_max_translation_m, cfg.match_max_rotation_deg)
        poses: list[FloatArray] = [np.zeros(3)] * len(before)
        later, later_feats, later_pose = scan, feats, np.zeros(3)  # in the node's frame
        for i in range(len(before) - 1, -1, -1):
            early = before[i]
            early_feats = extract(early, self.config.features)
            odometry = se2.between(self._odometry_of(later), self._odometry_of(early))
            result = self.matcher.match(early_feats, later_feats, odometry, bounds)
            later_pose = se2.compose(later_pose, result.pose if result.success else odometry)
            poses[i] = later_pose
            later, later_feats = early, early_feats
        return poses

    # ------------------------------------------------------------------ per scan

    def process(
        self, scan: LaserScan, features: Callable[[], ScanFeatures] | None = None
    ) -> FloatArray:
        """Process one scan; return its current pose estimate ``(3,)`` in the map frame.

        The map frame is the odometry frame of the first scan (the first node is fixed at
        the first odometry pose, or at the origin when the log has no odometry). Steps
        (docs/design.md "Data flow of one scan"): motion from odometry and keyframe decision; for a
        keyframe ICE features, local match, node and factors, iSAM2 update, loop-closure
        search and feature-map update. With ``slam.reuse_nodes``, a keyframe of a revisit
        hangs from an old node instead (docs/design.md "Reused nodes").

        ``features``, when given, returns exactly ``extract(scan, config.features)`` (e.g.
        computed ahead by :class:`iceg.features.prefetch.FeaturePrefetcher`); it is called
        only when the scan needs features (a keyframe).

        With a match helper (``loop_closer.match_pool``, set by :mod:`iceg.pipeline` for two
        processes), a keyframe's loop-closure search is decided at the next keyframe, before
        its node (or when :attr:`graph`, :attr:`feature_map`, :meth:`trajectory`,
        :meth:`export_state` or :meth:`finish` is read): until then the poses returned leave
        its closures out. The run is the same bit for bit (:meth:`_finish_search`).

        Raises:
            ScanError: the scan's stamp is earlier than the previous scan's.
        """
        if self._result is not None:
            raise GraphError("Slam.process() after finish(): start a new Slam for a new run")
        self._check_order(scan)
        t0 = time.perf_counter()
        odom = self._odometry_of(scan)
        self._s.scans.append(scan)
        if not self._s.node_odom:
            return self._start(scan, odom, t0, features)
        if self._s.anchor is not None:
            self._finish_search()
            return self._process_anchored(scan, odom, self._s.anchor, t0, features)
        last = len(self._s.node_odom) - 1
        motion = self._motion(scan, odom, last)
        if not motion.is_keyframe:
            self._s.records.append(scan.stamp_s, last, motion.delta)
            return se2.compose(self._graph.estimate(last), motion.delta)
        return self._process_keyframe(scan, motion, last, t0, features)

    # ------------------------------------------------------------------ steps

    def _process_keyframe(
        self,
        scan: LaserScan,
        motion: _Motion,
        last: int,
        t0: float,
        features: Callable[[], ScanFeatures] | None = None,
    ) -> FloatArray:
        """A keyframe: features, local match, node and factors, iSAM2, loop closure, map.
        Right after a loop closure (``slam.reuse_nodes``), first a match against the old
        place: where it puts the scan at an old node, the scan hangs from that node."""
        feats = self._features(scan, features)
        t0 = self.timer.add("features", t0)
        if self._s.reuse_from is not None:
            self._finish_search()  # a closure it accepts names the old place to try
        old, self._s.reuse_from = self._s.reuse_from, None
        if old is not None and motion.measured and not motion.odometry_break:
            # predicted from the last node's pose in the old node's frame (the closure's
            # measurement), not from the estimates the closure has yet to pull together
            predicted = self._anchored_motion(scan, motion.odom, old)
            reuse = self._match_old_place(feats, old.node, predicted.delta, predicted.cov)
            t0 = self.timer.add("old_place", t0)
            if reuse.node is not None:
                return self._hang_from(scan, predicted, reuse, old)
            logger.debug(
                "keyframe at %.3f s stays a node at old node %d: %s",
                scan.stamp_s,
                old.node,
                reuse.result.reason or "no old node within a keyframe spacing",
            )
        local = self._match_local(feats, motion, last, self._s.segment_start)
        if not local.result.success:
            local = self._match_from_node_before(feats, motion, last, local)
        t0 = self.timer.add("matching", t0)
        if self._finish_search():
            # The last node's search, its matches run by the helper meanwhile, accepted a
            # closure: the keyframe starts again from the corrected estimates and map.
            motion = self._motion(scan, self._odometry_of(scan), last)
            return self._process_keyframe(scan, motion, last, time.perf_counter(), lambda: feats)
        t0 = time.perf_counter()  # the search's decision is timed as its own stage
        if local.ice_failure:
            counts = self._s.point_fallbacks if local.result.success else self._s.match_failures
            counts[local.ice_failure] += 1
        self._calibrate_odometry(local, motion)
        new_id = self._add_keyframe(scan, motion, local, last)
        self._after_node(new_id, feats, scan, local, t0)
        return self._graph.estimate(new_id)

    def _after_node(
        self, node_id: int, feats: ScanFeatures, scan: LaserScan, local: _LocalMatch, t0: float
    ) -> None:
        """A new keyframe node's iSAM2 update (or buffered solve), loop-closure search and
        feature-map update."""
        self._remember_points(node_id, feats)
        self.loop_closer.observe(node_id, feats)
        t0 = self.timer.add("graph_build", t0)
        if self._isam2_due():
            self._graph.update()
        else:
            self._graph.solve_pending()
        t0 = self.timer.add("isam2", t0)
        if self.loop_closer.due(node_id):
            self._begin_search(node_id, feats, scan, local)
            t0 = self.timer.add("loop_closure", t0)
        if self._open is not None:
            self._open.checkpoint = self._feature_map.checkpoint()
        self._update_map(node_id, feats, scan, local)
        self.timer.add("feature_map", t0)

    # ------------------------------------------------------------------ reused nodes

    def _process_anchored(
        self,
        scan: LaserScan,
        odom: FloatArray,
        anchor: Anchor,
        t0: float,
        features: Callable[[], ScanFeatures] | None,
    ) -> FloatArray:
        """A scan while a revisit hangs from the old node ``anchor.node``: between keyframes
        it takes the odometry from the anchoring scan; a keyframe is matched against the old
        place and hangs from the old node nearest it, or becomes a node where the path
        leaves the old nodes (:meth:`_leave_old_place`)."""
        motion = self._anchored_motion(scan, odom, anchor)
        if not motion.is_keyframe:
            self._s.records.append(scan.stamp_s, anchor.node, motion.delta)
            return se2.compose(self._graph.estimate(anchor.node), motion.delta)
        feats = self._features(scan, features)
        t0 = self.timer.add("features", t0)
        reuse = self._match_old_place(feats, anchor.node, motion.delta, motion.cov)
        t0 = self.timer.add("old_place", t0)
        if reuse.node is not None and motion.measured and not motion.odometry_break:
            return self._hang_from(scan, motion, reuse, anchor)
        return self._leave_old_place(scan, motion, anchor, feats, reuse, t0)

    def _anchored_motion(self, scan: LaserScan, odom: FloatArray, anchor: Anchor) -> _Motion:
        """The scan's pose in the anchor node's frame (``anchor.offset`` then the odometry
        from the anchoring scan) with its covariance, and the keyframe decision (the
        odometry since the anchoring scan, as :meth:`_motion` from a node). Without usable
        odometry the scan is a keyframe predicted at the anchoring scan's pose."""
        cfg = self.config.slam
        if scan.odom_pose is None or scan.odom_break:
            cov = cfg.no_odometry_covariance()
            measured = scan.odom_pose is not None
            return _Motion(odom, anchor.offset, anchor.offset_cov + cov, True, measured, measured)
        raw = se2.between(anchor.odom, odom)
        raw_cov = odometry_covariance(raw, self.config.odometry_noise)
        delta, cov = raw, raw_cov
        if self.odometry_calibrator.correcting:
            delta, cov = self.odometry_calibrator.correct(raw, raw_cov)
        is_keyframe = bool(
            np.hypot(delta[0], delta[1]) >= cfg.keyframe_distance_m
            or abs(delta[2]) >= np.radians(cfg.keyframe_rotation_deg)
            or scan.stamp_s - anchor.stamp_s >= cfg.keyframe_max_interval_s
        )
        # offset ∘ exp(a) ∘ delta ∘ exp(b) = offset ∘ delta ∘ exp(Ad(delta⁻¹) a + b)
        ad = se2.adjoint(se2.inverse(delta))
        full_cov = ad @ anchor.offset_cov @ ad.T + cov
        return _Motion(
            odom, se2.compose(anchor.offset, delta), full_cov, is_keyframe, raw=(raw, raw_cov)
        )

    def _match_old_place(
        self, feats: ScanFeatures, node: int, prediction: FloatArray, prediction_cov: FloatArray
    ) -> _Reuse:
        """Match the keyframe against the landmarks of the old nodes around ``node`` (the
        ``local_map_nodes`` nearest by id: its pass through the place), predicted at
        ``prediction`` (its pose in ``node``'s frame, covariance ``prediction_cov``) within
        the local match's bounds. Along directions the place leaves weak (a corridor) the
        pose is the prediction's (:func:`remap_weak_directions`, as for a local match), and
        its covariance fuses the two (information sum), so that a chain of keyframes
        hanging from old nodes of a corridor keeps the odometry's length. The old node within
        one keyframe spacing of the pose, the nearest, is the one it hangs from."""
        cfg = self.config.slam
        half = cfg.local_map_nodes // 2
        window = np.arange(
            max(0, node - half), min(self._graph.n_nodes, node + half + 1), dtype=np.int64
        )
        ids, poses = self._graph.estimates_of(self._feature_map.reference_pose_nodes(window))
        frame = poses[np.searchsorted(ids, node)]
        reference = self._feature_map.reference((ids, poses), window, frame)
        bounds = MatchBounds.local(cfg.match_max_translation_m, cfg.match_max_rotation_deg)
        result = self.matcher.match(feats, reference.features, prediction, bounds)
        if not result.success:
            return _Reuse(reference, result, frame, prediction, prediction_cov)
        pose = remap_weak_directions(result.pose, result.cov, prediction, prediction_cov)
        try:
            cov = np.linalg.inv(np.linalg.inv(result.cov) + np.linalg.inv(prediction_cov))
        except np.linalg.LinAlgError:
            cov = result.cov
        # the pose in the frame of each old node of the window
        d = se2.between(se2.between(frame, poses[np.searchsorted(ids, window)]), pose)
        dist = np.hypot(d[:, 0], d[:, 1])
        near = (dist <= cfg.keyframe_distance_m) & (
            np.abs(d[:, 2]) <= np.radians(cfg.keyframe_rotation_deg)
        )
        if not near.any() or not self._identifies_node(result.cov):
            return _Reuse(reference, result, frame, pose, cov)
        k = int(np.flatnonzero(near)[np.argmin(dist[near])])
        return _Reuse(reference, result, frame, pose, cov, int(window[k]), d[k])

    def _identifies_node(self, cov: FloatArray) -> bool:
        """Whether a match with covariance ``cov`` tells which old node the scan is at: two
        standard deviations within one keyframe spacing along every direction (in a
        corridor the match does not say how far along it the scan is)."""
        cfg = self.config.slam
        sigma_xy = float(np.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0)))
        sigma_theta = float(np.sqrt(max(cov[2, 2], 0.0)))
        return bool(
            2.0 * sigma_xy <= cfg.keyframe_distance_m
            and 2.0 * sigma_theta <= np.radians(cfg.keyframe_rotation_deg)
        )

    def _anchor_of(self, node: int, old: int, offset: FloatArray, cov: FloatArray) -> Anchor:
        """Node ``node``'s scan placed at ``offset`` (covariance ``cov``) in the frame of
        the old node ``old``."""
        s = self._s
        stamp = s.scans.stamp_s(s.node_scan_index[node])
        return Anchor(old, offset, cov, s.node_odom[node], stamp, s.node_path_m[node])

    def _hang_from(
        self, scan: LaserScan, motion: _Motion, reuse: _Reuse, origin: Anchor
    ) -> FloatArray:
        """The keyframe hangs from the old node ``reuse.node`` (no node, factor or
        landmark); ``motion`` is its :meth:`_anchored_motion` from ``origin``."""
        assert reuse.node is not None and reuse.offset is not None
        s = self._s
        s.anchor = Anchor(
            reuse.node,
            reuse.offset,
            reuse.cov,  # the same in the old node's frame: tangent space at the scan
            np.asarray(motion.odom, dtype=np.float64).copy(),
            scan.stamp_s,
            _path_m(origin, motion),
        )
        s.reused_keyframes += 1
        s.records.append(scan.stamp_s, reuse.node, reuse.offset)
        return se2.compose(reuse.frame_pose, reuse.pose)

    def _leave_old_place(
        self,
        scan: LaserScan,
        motion: _Motion,
        anchor: Anchor,
        feats: ScanFeatures,
        reuse: _Reuse,
        t0: float,
    ) -> FloatArray:
        """The path leaves the old nodes: the keyframe becomes a node linked to the anchor
        node as a keyframe to the node before it: by the odometry since the anchoring scan
        (after the anchor's offset) and by its match against the old place where that
        succeeded. Its local map starts at it (as after :meth:`start_segment`); its features
        meet the old place's landmarks."""
        s = self._s
        s.anchor = None
        result = reuse.result
        logger.debug(
            "keyframe at %.3f s leaves old node %d: %s",
            scan.stamp_s,
            anchor.node,
            "no old node within a keyframe spacing" if result.success else result.reason,
        )
        new_id = self._add_node(
            scan,
            motion.odom,
            initial=se2.compose(reuse.frame_pose, reuse.pose),
            odom_measured=motion.measured,
            step_m=_path_m(anchor, motion) - s.node_path_m[-1],
            matched=result.success,
        )
        # as a keyframe's factors from the node before it (_add_keyframe)
        self._add_factor(FactorKind.ODOMETRY, anchor.node, new_id, motion.delta, motion.cov)
        if result.success:
            self._add_scan_match(anchor.node, new_id, result, motion.delta, motion.cov)
        s.segment_start = new_id
        local = _LocalMatch(reuse.reference, result, reuse.frame_pose)
        self._after_node(new_id, feats, scan, local, t0)
        if s.reuse_from is None:  # a brief departure (a person passing): the next keyframe
            # tries the old place again
            s.reuse_from = self._anchor_of(new_id, anchor.node, reuse.pose, reuse.cov)
        return self._graph.estimate(new_id)

    def _isam2_due(self) -> bool:
        """Whether this keyframe updates iSAM2: always below ``isam2_defer_from_nodes`` nodes,
        beyond once ``k * loop_closure.every_n_nodes`` keyframes wait, ``k`` the multiple of
        ``isam2_defer_from_nodes`` the graph has reached. An update costs O(N) in gtsam 4.3,
        so this bounds its cost per keyframe (docs/design.md, "Long logs")."""
        defer_from = self.config.slam.isam2_defer_from_nodes
        n = self._graph.n_nodes
        if defer_from is None or n < defer_from:
            return True
        every_n = self.config.loop_closure.every_n_nodes
        return self._graph.n_pending[0] >= (n // defer_from) * every_n

    def _check_order(self, scan: LaserScan) -> None:
        if self._s.scans and scan.stamp_s < self._s.scans.stamp_s(-1):
            raise ScanError(
                f"scan at {scan.stamp_s:.6f} s is earlier than the previous scan at "
                f"{self._s.scans.stamp_s(-1):.6f} s: Slam.process needs scans in time order"
            )

    def _features(
        self, scan: LaserScan, features: Callable[[], ScanFeatures] | None
    ) -> ScanFeatures:
        return features() if features is not None else extract(scan, self.config.features)

    def _start(
        self,
        scan: LaserScan,
        odom: FloatArray,
        t0: float,
        features: Callable[[], ScanFeatures] | None = None,
    ) -> FloatArray:
        """The first scan: node 0, fixed at its odometry pose, and its landmarks."""
        feats = self._features(scan, features)
        t0 = self.timer.add("features", t0)
        self._add_node(scan, odom, initial=odom, odom_measured=scan.odom_pose is not None)
        self._remember_points(0, feats)
        self.loop_closer.observe(0, feats)
        self._graph.update()
        self._feature_map.update(0, feats, scan.stamp_s, scan=scan)
        self.timer.add("feature_map", t0)
        return odom.copy()

    def _motion(self, scan: LaserScan, odom: FloatArray, last: int) -> _Motion:
        """Odometry delta from the last node and the keyframe decision."""
        cfg = self.config.slam
        s = self._s
        if scan.odom_pose is None or scan.odom_break or not s.node_odom_measured[last]:
            # No usable odometry delta (no odometry, a jump or a new odometry frame flagged by
            # the reader, or the last node had none): the scan is a node, predicted by constant
            # velocity, and a weak motion prior keeps the graph connected where matching fails.
            delta = self._constant_velocity_delta(last)
            cov = cfg.no_odometry_covariance()
            if scan.odom_pose is None:
                return _Motion(se2.compose(s.node_odom[last], delta), delta, cov, True, False)
            return _Motion(odom, delta, cov, True, odometry_break=True)  # new odometry frame
        raw = se2.between(s.node_odom[last], odom)
        raw_cov = odometry_covariance(raw, self.config.odometry_noise)
        delta, cov = raw, raw_cov
        if self.odometry_calibrator.correcting:
            delta, cov = self.odometry_calibrator.correct(raw, raw_cov)
        dt = scan.stamp_s - s.scans.stamp_s(s.node_scan_index[last])
        is_keyframe = bool(
            np.hypot(delta[0], delta[1]) >= cfg.keyframe_distance_m
            or abs(delta[2]) >= np.radians(cfg.keyframe_rotation_deg)
            or dt >= cfg.keyframe_max_interval_s
        )
        return _Motion(odom, delta, cov, is_keyframe, raw=(raw, raw_cov))

    def _match_local(
        self, feats: ScanFeatures, motion: _Motion, last: int, log_start: int
    ) -> _LocalMatch:
        """ICE match against the landmarks of the ``local_map_nodes`` nodes up to ``last``
        (none before ``log_start``, the first node of their log). A match the scan's own
        points contradict (:func:`points_prefer_prediction` against the recent nodes' points,
        ``slam.contradiction_gate_m``) counts as failed; where it fails with too little
        evidence or was contradicted (``_POINT_FALLBACK_REASONS``), the point match
        (:meth:`_point_match`) when ``slam.point_fallback``."""
        cfg = self.config.slam
        first = max(log_start, last - cfg.local_map_nodes + 1)
        recent = np.arange(first, last + 1, dtype=np.int64)
        ids, poses = self._graph.estimates_of(self._feature_map.reference_pose_nodes(recent))
        last_pose = poses[np.searchsorted(ids, last)]
        reference = self._feature_map.reference((ids, poses), recent, last_pose)
        if cfg.drop_walls_seen_through and self._s.node_matched[last]:
            # The last node's scan is the newest view of the place; its pose comes from a
            # match against these walls, so a wall it sees through is gone.
            reference = reference.without_walls_seen_through(
                self._points_of(last),
                self.config.matching.validation.see_through_tolerance_m,
                self._matching_profile(last),
            )
        bounds = MatchBounds.local(cfg.match_max_translation_m, cfg.match_max_rotation_deg)
        result = self.matcher.match(feats, reference.features, motion.delta, bounds)
        # the recent nodes' points, gathered once for the points test and the point match
        blocks = functools.cache(lambda: self._recent_blocks(recent, ids, poses))
        if result.success and cfg.contradiction_gate_m is not None:
            contradiction = blocks_prefer_prediction(
                feats.points_xy, blocks(), result.pose, motion.delta, cfg.contradiction_gate_m
            )
            if contradiction:
                result = MatchResult.failed(motion.delta, contradiction)
        if not result.success:
            # Counted by the reason's category (the text before the first colon).
            category = (result.reason or _UNKNOWN_REASON).split(":")[0]
            fallback = (
                self._point_match(feats, motion, bounds, lambda: move_point_blocks(*blocks()))
                if category in _POINT_FALLBACK_REASONS
                else None
            )
            if fallback is not None and fallback.success:
                return _LocalMatch(reference, fallback, last_pose, category)
            return _LocalMatch(reference, result, last_pose, category)
        return _LocalMatch(reference, result, last_pose)

    def _match_from_node_before(
        self, feats: ScanFeatures, motion: _Motion, last: int, failed: _LocalMatch
    ) -> _LocalMatch:
        """The local match again, predicted through the node before the last: that node's
        estimate composed with the odometry from it to the scan, in the last node's frame.
        Where the last node's match moved it far from its odometry (a reading that jumped
        ahead and then stalled, a heading that lags in a turn), the odometry from the last
        node carries the same error into the next prediction, while from the node before it
        cancels. Tried only when the local match ``failed`` and that prediction lies beyond
        the first search's bounds (``match_max_translation_m``, ``match_max_rotation_deg``)
        of the odometry's; the first result is kept unless this one succeeds. It needs
        measured odometry from the node before to the scan without a break (a break always
        makes its scan a node); the step between the two nodes is the raw odometry (with
        ``odometry_calibration`` on, only a search's starting point)."""
        s, cfg = self._s, self.config.slam
        before = last - 1
        if (
            before < s.segment_start
            or not motion.measured
            or motion.odometry_break
            or not s.node_odom_measured[before]
            or not s.node_odom_measured[last]
            or s.scans[s.node_scan_index[last]].odom_break
        ):
            return failed
        _, poses = self._graph.estimates_of([before, last])
        odometry = se2.compose(se2.between(s.node_odom[before], s.node_odom[last]), motion.delta)
        predicted = se2.between(poses[1], se2.compose(poses[0], odometry))
        gap = se2.between(motion.delta, predicted)
        if np.hypot(gap[0], gap[1]) <= cfg.match_max_translation_m and abs(gap[2]) <= np.radians(
            cfg.match_max_rotation_deg
        ):
            return failed  # the first search covered it
        second = self._match_local(feats, replace(motion, delta=predicted), last, s.segment_start)
        return second if second.result.success else failed

    def _point_match(
        self,
        feats: ScanFeatures,
        motion: _Motion,
        bounds: MatchBounds,
        recent_xy: Callable[[], FloatArray],
    ) -> MatchResult | None:
        """Point-to-line ICP (:class:`~iceg.matching.plicp.PlIcpMatcher`, Censi 2008) of the
        scan's points against the recent nodes' scan points (``recent_xy()``: those of
        :meth:`_recent_blocks` moved into the last node's frame), seeded by the odometry
        prediction ``delta`` (frame of the last node): a factor for a scan whose ICE match had
        too little evidence or was contradicted by its points (outdoors: trees, posts), with
        the point match's own covariance. ``None`` when disabled, when the matcher is not ICE,
        or when a successful point match fails the chi-square test against the odometry
        (:func:`consistent_with_prediction`)."""
        if not self.config.slam.point_fallback or self.config.matching.method != "ice":
            return None
        ref = ScanFeatures.empty(recent_xy())
        result = self.point_matcher.match(feats, ref, motion.delta, bounds)
        if result.success and not consistent_with_prediction(result, motion.delta, motion.cov):
            return None
        return result

    def _recent_blocks(
        self, recent: NDArray[np.int64], ids: NDArray[np.int64], poses: FloatArray
    ) -> PointBlocks:
        """The scan points of the ``recent`` nodes (ascending) in blocks (:data:`PointBlocks`),
        each node placed in the frame of the last of them by the estimates ``poses`` ``(N, 3)``
        of the sorted node ``ids`` ``(N,)`` that hold them (the reference's table, read in this
        state of the graph)."""
        rows = np.searchsorted(ids, recent)
        relative = poses_in_frame(poses[rows[-1]], poses, rows)
        points = [self._points_of(i) for i in recent.tolist()]
        counts = np.array([p.shape[0] for p in points], dtype=np.int64)
        return relative, counts, np.concatenate(points)

    def _remember_points(self, node_id: int, feats: ScanFeatures) -> None:
        """Keep the new node's scan points for :meth:`_point_match`, and its features where
        no match placed it (:data:`KEPT_UNMATCHED_FEATURES`, for the offline second match:
        the same features as an extraction, which the calling process may not have loaded
        the kernels of); forget the points of nodes that left the local map."""
        self._node_points[node_id] = feats.points_xy
        self._last_features = (node_id, feats)
        unmatched = self._unmatched_features
        if not self._s.node_matched[node_id] and len(unmatched) < KEPT_UNMATCHED_FEATURES:
            unmatched[node_id] = feats
        for old in [
            i for i in self._node_points if i <= node_id - self.config.slam.local_map_nodes
        ]:
            del self._node_points[old]

    def _matching_profile(self, node_id: int) -> PolarProfile | None:
        """The polar profile of ``node_id``'s scan points that its ICE match computed
        (:func:`~iceg.matching.matcher.scan_derived`), when it is the newest node and the
        matcher is ICE; else None."""
        if self._last_features is None or self.config.matching.method != "ice":
            return None
        node, feats = self._last_features
        return scan_derived(feats).profile if node == node_id else None

    def _points_of(self, node_id: int) -> FloatArray:
        """``(P, 2)`` float64 scan points of a node, its frame (features' ``points_xy``;
        re-extracted for a node of a loaded session)."""
        points = self._node_points.get(node_id)
        if points is None:
            scan = self._s.scans[self._s.node_scan_index[node_id]]
            points = extract_points(scan, self.config.features)
        return points

    def _calibrate_odometry(self, local: _LocalMatch, motion: _Motion) -> None:
        """Feed a successful local match to the odometry calibration (same step's raw
        odometry increment; :class:`OdometryCalibrator`)."""
        if local.result.success and motion.raw is not None:
            self.odometry_calibrator.observe(*motion.raw, local.result.pose, local.result.cov)

    def _add_keyframe(self, scan: LaserScan, motion: _Motion, local: _LocalMatch, last: int) -> int:
        """The keyframe's node (initialised by the match, else odometry) and its factors; the
        scan-match measurement is remapped to the odometry along directions where it is
        weaker than odometry and agrees with it (:func:`remap_weak_directions`)."""
        result = local.result
        step = result.pose if result.success else motion.delta
        new_id = self._add_node(
            scan,
            motion.odom,
            initial=se2.compose(local.last_pose, step),
            odom_measured=motion.measured,
            step_m=self._step_m(motion, last),
            matched=result.success,
        )
        self._add_factor(FactorKind.ODOMETRY, last, new_id, motion.delta, motion.cov)
        if result.success:
            self._add_scan_match(last, new_id, result, motion.delta, motion.cov)
        elif (
            result.unverified is not None
            and motion.measured
            and not motion.odometry_break
            and last == new_id - 1
        ):
            self._s.disputed[new_id] = result.unverified
        return new_id

    def _add_scan_match(
        self,
        last: int,
        node: int,
        result: MatchResult,
        odometry: FloatArray,
        odometry_cov: FloatArray,
    ) -> None:
        """The scan-match factor ``last -> node``, remapped to the odometry along directions
        where it is weaker than odometry and agrees with it."""
        self._add_factor(
            FactorKind.SCAN_MATCH,
            last,
            node,
            remap_weak_directions(result.pose, result.cov, odometry, odometry_cov),
            result.cov,
            result.correlation,
            robust=self.config.slam.scan_match_kernel,
        )

    def _begin_search(
        self, node_id: int, feats: ScanFeatures, scan: LaserScan, local: _LocalMatch
    ) -> None:
        """Begin the node's loop-closure search. With the match helper
        (``loop_closer.match_pool``) it stays open: the node's map update and the next
        keyframe's local match run while the helper runs its matches, and
        :meth:`_finish_search` decides it before the graph changes again. Otherwise (or
        with no match to run) it is decided now."""
        begun = self.loop_closer.start_search(
            node_id, feats, self._graph, self._s.node_path_m, self._s.log_start
        )
        if begun is None:
            return
        self._open = _OpenSearch(begun, (node_id, feats, scan, local))
        if self.loop_closer.match_pool is None or not begun.sent.jobs:
            self._finish_search()

    def _finish_search(self) -> bool:
        """Decide the open loop-closure search, if any (:meth:`_begin_search`); return
        whether it accepted closures. Accepted closures enter as factors, then iSAM2
        updates. Where the node's map update ran meanwhile, it is undone before
        (:meth:`FeatureMap.restore`) and runs again after: the map update needs the
        closure's correction, and every step is the one a search decided at its node takes,
        bit for bit (docs/design.md, "Loop-closure searches decided at the next keyframe")."""
        open_, self._open = self._open, None
        if open_ is None:
            return False
        t0 = time.perf_counter()
        disputed = {k: r.pose for k, r in self._s.disputed.items()}
        accepted = self.loop_closer.finish_search(
            open_.begun, self._graph, self._s.node_path_m, disputed
        )
        if accepted is not None:
            if open_.checkpoint is not None:
                self._feature_map.restore(open_.checkpoint)
            self._add_closures(accepted)
        t0 = self.timer.add("loop_closure", t0)
        if accepted is None or open_.checkpoint is None:
            return accepted is not None
        self._update_map(*open_.map_update)
        self.timer.add("feature_map", t0)
        return True

    def _add_closures(self, accepted: AcceptedClosures) -> None:
        """Accepted closures as factors, with the scan-match factors of the disputed steps
        they confirmed, then the iSAM2 update (or a batch solve). The disputed steps before
        the newest closure's node are dropped: a later closure's chain no longer runs open
        through them."""
        disputed = self._s.disputed
        for k in accepted.confirmed_steps:
            link = next(
                r
                for r in reversed(self._graph.factors)
                if r.kind is FactorKind.ODOMETRY and r.j == k
            )
            self._add_scan_match(k - 1, k, disputed.pop(k), link.measured, link.cov)
            self._s.node_matched[k] = True
        newest = max(c.node_to for c in accepted.closures)
        for k in [k for k in disputed if k <= newest]:
            del disputed[k]
        for c in accepted.closures:
            self._add_factor(
                FactorKind.LOOP_CLOSURE,
                c.node_from,
                c.node_to,
                c.measured,
                c.cov,
                c.correlation,
                robust=accepted.robust_kernel,
                robust_k=self.config.loop_closure.robust_k,
            )
        if self.config.slam.reuse_nodes:
            c = accepted.closures[-1]
            self._s.reuse_from = self._anchor_of(c.node_to, c.node_from, c.measured, c.cov)
        if accepted.large_correction:
            # A global closure can move the estimate by tens of metres and degrees: a batch
            # Levenberg-Marquardt from the current estimate converges where iSAM2's
            # incremental relinearisation would take many updates (it is rebuilt after).
            self._graph.optimize_batch(correction=True)
        else:
            self._graph.update()

    def _update_map(
        self, node_id: int, feats: ScanFeatures, scan: LaserScan, local: _LocalMatch
    ) -> None:
        """Feature-map association and time-validity at the updated estimates."""
        self._feature_map.update(
            node_id,
            feats,
            scan.stamp_s,
            reference=local.reference,
            match=local.result,
            scan=scan,
            # Only the poses the update reads (same values as the full table, O(k) not O(N)).
            node_poses=self._graph.estimates_of(
                self._feature_map.update_pose_nodes(node_id, local.reference)
            ),
        )

    # ------------------------------------------------------------------ internals

    def _odometry_of(self, scan: LaserScan) -> FloatArray:
        if scan.odom_pose is not None:
            return np.asarray(scan.odom_pose, dtype=np.float64)
        return np.zeros(3)

    def _constant_velocity_delta(self, last: int) -> FloatArray:
        """Motion of the last node pair (estimates), as the prediction of the next one; none
        from the first node of the log (:attr:`SlamState.segment_start`: the node before it
        is another log's, in a continued or localizing run)."""
        if last <= self._s.segment_start:
            return np.zeros(3)
        return se2.between(self._graph.estimate(last - 1), self._graph.estimate(last))

    def _step_m(self, motion: _Motion, last: int) -> float:
        """Path travelled from node ``last`` to the scan of ``motion`` (m): the odometry's, or
        the predicted motion's across an odometry break."""
        d = motion.delta if motion.odometry_break else motion.odom - self._s.node_odom[last]
        return float(np.hypot(d[0], d[1]))

    def _add_node(
        self,
        scan: LaserScan,
        odom: FloatArray,
        initial: FloatArray,
        odom_measured: bool,
        step_m: float = 0.0,
        matched: bool = True,
    ) -> int:
        """Node of ``scan``; ``step_m`` is the path travelled since the last node (m);
        ``matched``: its initial pose comes from a match (not the odometry alone)."""
        s = self._s
        s.node_odom_measured.append(odom_measured)
        s.node_matched.append(matched)
        node_id = len(s.node_odom)
        s.node_path_m.append((s.node_path_m[-1] if s.node_path_m else 0.0) + step_m)
        s.node_odom.append(odom)
        s.node_scan_index.append(len(s.scans) - 1)
        s.records.append(scan.stamp_s, node_id)
        self._graph.add_node(node_id, initial)
        return node_id

    def _add_factor(
        self,
        kind: FactorKind,
        i: int,
        j: int,
        measured: FloatArray,
        cov: FloatArray,
        correlation: float = float("nan"),
        robust: Literal["huber", "cauchy"] | None = None,
        robust_k: float | None = None,
    ) -> None:
        """Add a between-factor and keep its correlation; ``robust_k`` ``None``: the kernel's
        95 %-efficiency width."""
        record = self._graph.add_between(
            i, j, measured, cov, kind=kind, robust=robust, robust_k=robust_k
        )
        if np.isfinite(correlation):
            self._s.correlations[record.index] = correlation

    # ------------------------------------------------------------------ results

    def _rematch_unmatched_keyframes(self) -> int:
        """Offline second chance for the keyframes whose local match failed online (part of
        the final refinement, :meth:`finish`): each is matched again against the landmarks of
        the same nodes as online (the ``local_map_nodes`` nodes before it, within its log, as
        the feature map holds them now), predicted from the current estimate instead of the
        odometry alone. Online, the prediction was the
        odometry from the node before; now the estimate holds every later match and loop
        closure, so a keyframe that a fast turn's lagging odometry or a stale reading put
        beyond the bounds can be inside them. A match that agrees with the keyframe's odometry
        factor (:func:`consistent_with_prediction`: a second chance has no tracking after it
        to expose a wrong basin) adds the scan-match factor the keyframe would have had. The
        factors enter the final batch only: iSAM2 is not updated, so a
        session saved after :meth:`finish` continues from the online state
        (:func:`iceg.session.load` leaves them out with the final batch).

        Returns:
            The number of scan-match factors added.
        """
        s = self._s
        odometry = {r.j: r for r in self._graph.factors if r.kind is FactorKind.ODOMETRY}
        log_start = 0
        added = 0
        for node in range(1, len(s.node_odom)):
            link = odometry.get(node)
            if link is None or link.i != node - 1:  # the first node of another log
                log_start = node
                continue
            if s.node_matched[node]:
                continue
            last = node - 1
            predicted = se2.between(self._graph.estimate(last), self._graph.estimate(node))
            motion = _Motion(s.node_odom[node], predicted, link.cov, is_keyframe=True)
            feats = self._unmatched_features.get(node)
            if feats is None:  # not kept (past the cap, or a loaded session's keyframe)
                feats = extract(s.scans[s.node_scan_index[node]], self.config.features)
            local = self._match_local(feats, motion, last, log_start)
            if local.result.success and consistent_with_prediction(
                local.result, link.measured, link.cov
            ):
                self._add_scan_match(last, node, local.result, link.measured, link.cov)
                added += 1
        return added

    def trajectory(self) -> tuple[FloatArray, FloatArray]:
        """Current estimate of every processed scan: ``(stamps_s (N,), poses (N, 3))``.

        A scan that is not a graph node takes its node's estimate composed with the
        odometry delta from the node's scan, bent to meet the next node's estimate
        (:func:`iceg.scan_poses.scan_poses`; docs/design.md "Scans between two nodes").
        """
        ids, poses = self.graph.estimates()
        stamps, node, delta = self._s.records.arrays()
        recs = self._graph.factors
        step_from, steps = odometry_steps(
            [r.kind is FactorKind.ODOMETRY for r in recs],
            [(r.i, -1 if r.j is None else r.j) for r in recs],
            [r.measured for r in recs],
            [r.cov for r in recs],
            self.config.slam.no_odometry_covariance(),
        )
        node_scan = np.asarray(self._s.node_scan_index, dtype=np.int64)  # rows of ``ids``
        return stamps, scan_poses(
            stamps, node, delta, ids, poses, node_scan, step_from, steps, self.config.odometry_noise
        )

    def finish(self) -> SlamResult:
        """Optionally batch-refine and return the :class:`SlamResult` (idempotent: a second
        call returns the same result; :meth:`process` is refused afterwards).

        The occupancy grid is not rendered here: the result carries the scans, and
        :meth:`SlamResult.render_map` (called by :meth:`SlamResult.save` after the trajectory,
        graph and metrics are written) renders it along the optimized poses.
        """
        if self._result is not None:
            return self._result
        self._online_factors = self.graph.n_factors
        t0 = time.perf_counter()
        if self.config.slam.batch_refinement and self._s.node_odom:
            added = self._rematch_unmatched_keyframes()
            t0 = self.timer.add("rematch", t0)
            logger.info("finish: %d keyframes without a match online matched now", added)
            # The final estimate satisfies every closure the run accepted: their kernels
            # guarded the online estimate, but a kernel a few match sigmas wide all but
            # ignores a true closure against a drifted chain (docs/design.md, "Loop closure").
            self._graph.optimize_batch(loop_closure_kernels=False)
            t0 = self.timer.add("batch_refinement", t0)
        stamps, poses = self.trajectory()
        ids, node_poses = self._graph.estimates()
        self._result = SlamResult(
            stamps_s=stamps,
            poses=poses,
            node_ids=ids,
            node_poses=node_poses,
            node_scan_index=np.array(self._s.node_scan_index, dtype=np.int64),
            factors=self._graph.factors,
            correlations=dict(self._s.correlations),
            loop_closures=self.loop_stats,
            match_failures=dict(self._s.match_failures),
            point_fallbacks=dict(self._s.point_fallbacks),
            reused_keyframes=self._s.reused_keyframes,
            stage_seconds=dict(self.timer.seconds),
            feature_map=self._feature_map,
            graph=self._graph,
            config=self.config,
            scans=self._s.scans,
            slam=self,
        )
        return self._result


def _path_m(origin: Anchor, motion: _Motion) -> float:
    """Odometry path length (m) at the scan of ``motion``, an :meth:`Slam._anchored_motion`
    from ``origin`` (no odometry: none travelled)."""
    step = 0.0 if motion.raw is None else float(np.hypot(motion.raw[0][0], motion.raw[0][1]))
    return origin.path_m + step


def consistent_with_prediction(
    result: MatchResult, prediction: FloatArray, prediction_cov: FloatArray
) -> bool:
    """Whether a point match agrees with the prediction: the squared Mahalanobis distance of
    their difference under the sum of their covariances is within the chi-square quantile of
    :data:`CONSISTENCY_PROBABILITY` (3 degrees of freedom). A point match has no feature
    correspondences to vouch for it, only the basin ICP slid into, so it is a factor only
    where the odometry does not contradict it.

    Args:
        result: A successful match: ``pose`` ``(3,)`` float64 ``[x_m, y_m, theta_rad]``
            (frame of the last node) and ``cov`` ``(3, 3)`` in the tangent space at it.
        prediction: ``(3,)`` float64 the predicted (odometry) motion, same frame.
        prediction_cov: ``(3, 3)`` float64 its covariance.

    Returns:
        True when the difference passes the test; False otherwise or when the summed
        covariance is singular.
    """
    try:
        _, chi2 = innovation_chi2(prediction, result.pose, prediction_cov, result.cov)
    except np.linalg.LinAlgError:
        return False
    return chi2 <= chi2_3dof()


def points_prefer_prediction(
    points_xy: FloatArray,
    reference_xy: FloatArray,
    pose: FloatArray,
    prediction: FloatArray,
    gate_m: float,
) -> str:
    """Why a match is contradicted by the scan's own points, or "" when it is not.

    A scan point is explained at a pose when a reference point lies within ``gate_m`` of it
    there. The match is contradicted when the points explained at the prediction only
    outnumber those explained at the match only beyond chance: a one-sided sign test
    (McNemar 1947) at :data:`CONSISTENCY_PROBABILITY`. A correct match explains the scan at
    least as well as the odometry does; a cluster of look-alike features (tree trunks, posts)
    that turns the scan by 5-20 degrees from an accurate prediction explains a third of it.

    Args:
        points_xy: ``(P, 2)`` float64 the new scan's points, its robot frame, metres.
        reference_xy: ``(R, 2)`` float64 reference points (the recent nodes' scans), the
            reference frame, metres.
        pose: ``(3,)`` float64 the matched pose of the scan in the reference frame.
        prediction: ``(3,)`` float64 the predicted (odometry) pose, same frame.
        gate_m: Distance within which a reference point explains a scan point, metres.

    Returns:
        The failure reason ("contradicted by the points: ..."), or "" (also when either
        point set is empty). Raises nothing.
    """
    if reference_xy.shape[0] == 0 or points_xy.shape[0] == 0:
        return ""
    at_pose, at_prediction = points_within(
        points_xy, np.array([pose, prediction]), reference_xy, gate_m
    )
    return _contradiction(
        points_xy.shape[0],
        int(np.count_nonzero(at_pose)),
        int(np.count_nonzero(at_prediction)),
        int(np.count_nonzero(at_pose > at_prediction)),
        int(np.count_nonzero(at_prediction > at_pose)),
    )


def blocks_prefer_prediction(
    points_xy: FloatArray,
    blocks: PointBlocks,
    pose: FloatArray,
    prediction: FloatArray,
    gate_m: float,
) -> str:
    """:func:`points_prefer_prediction` against reference points given in blocks (the recent
    nodes' scans, each in its node's frame: :data:`PointBlocks`), moved, gridded and queried
    in one compiled call (:func:`~iceg.matching._kernels.blocks_explained_counts`): the same
    kernels on the same arrays, so the same reason as ``points_prefer_prediction(points_xy,
    move_point_blocks(*blocks), ...)``, without the calls' round trips through Python.

    Args:
        points_xy: ``(P, 2)`` float64 the new scan's points, its robot frame, metres.
        blocks: The reference points in blocks, each block's pose in the reference frame.
        pose, prediction, gate_m: As :func:`points_prefer_prediction`.

    Returns:
        The failure reason, or "" (also when either point set is empty). Raises nothing.
    """
    block_poses, counts, block_points = blocks
    if block_points.shape[0] == 0 or points_xy.shape[0] == 0:
        return ""
    finite, *counted = blocks_explained_counts(
        np.ascontiguousarray(points_xy, dtype=np.float64),
        np.ascontiguousarray(pose, dtype=np.float64),
        np.ascontiguousarray(prediction, dtype=np.float64),
        block_poses,
        counts,
        block_points,
        gate_m,
    )
    if not finite:  # points_within's general path
        reference_xy = move_point_blocks(block_poses, counts, block_points)
        return points_prefer_prediction(points_xy, reference_xy, pose, prediction, gate_m)
    return _contradiction(points_xy.shape[0], *counted)


def _contradiction(
    n_points: int, at_pose: int, at_prediction: int, only_pose: int, only_prediction: int
) -> str:
    """The reason of :func:`points_prefer_prediction` from its counts of the ``n_points``
    scan points explained at the match, at the prediction and at only one of them."""
    if only_prediction <= only_pose or not sign_test_rejects(only_prediction, only_pose):
        return ""
    return (
        f"{REASON_CONTRADICTED}: {at_prediction} of {n_points} scan points are explained at "
        f"the prediction, {at_pose} at the match"
    )


def sign_test_rejects(more: int, fewer: int) -> bool:
    """The one-sided sign test (McNemar 1947) of :func:`points_prefer_prediction`: whether
    ``P(X >= more)`` for ``X ~ Binomial(more + fewer, 1/2)`` is below ``1 -``
    :data:`CONSISTENCY_PROBABILITY`.

    Exact: the tail's count of outcomes, summed in integers, is compared with the
    threshold's binary fraction, so no rounding decides (scipy's ``bdtrc`` gives the same
    decisions up to 1200 trials, ``test_the_exact_sign_test_decides_as_scipy``, without
    importing ``scipy.special``). The tail has ``fewer + 1`` terms.

    Args:
        more, fewer: Non-negative counts of the two outcomes.

    Returns:
        True where the test rejects chance (the ``more`` side wins beyond it).

    Raises:
        ValueError: a negative count (from ``math.comb``).
    """
    n = more + fewer
    term = math.comb(n, more)
    tail = 0
    for k in range(more, n + 1):
        tail += term
        term = term * (n - k) // (k + 1)
    num, den = (1.0 - CONSISTENCY_PROBABILITY).as_integer_ratio()
    return tail * den < num << n


def _no_weak_direction(cov: FloatArray, prediction_cov: FloatArray) -> bool:
    """Whether the whitened translation information ``M = W^T cov_xy^-1 W`` of
    :func:`remap_weak_directions` has no eigenvalue below 1 (``M - I`` positive semidefinite:
    both diagonal entries and the determinant of ``M - I`` non-negative), decided in floats
    without the eigendecomposition: 1815 of MIT CSAIL's 1834 matches. False also where a
    covariance is not positive definite (the eigendecomposition's path decides then)."""
    (p00, _), (p10, p11) = prediction_cov[:2, :2].tolist()
    (c00, c01), (c10, c11) = cov[:2, :2].tolist()
    det = c00 * c11 - c01 * c10
    if not (p00 > 0.0 and det > 0.0):
        return False
    w00 = math.sqrt(p00)  # W = [[w00, 0], [w10, w11]], lower Cholesky factor
    w10 = p10 / w00
    if not p11 - w10 * w10 > 0.0:
        return False
    w11 = math.sqrt(p11 - w10 * w10)
    i00, i01, i10, i11 = c11 / det, -c01 / det, -c10 / det, c00 / det  # cov_xy^-1
    # M = W^T (info W)
    a00, a01 = i00 * w00 + i01 * w10, i01 * w11
    a10, a11 = i10 * w00 + i11 * w10, i11 * w11
    m00, m01 = w00 * a00 + w10 * a10, w00 * a01 + w10 * a11
    m10, m11 = w11 * a10, w11 * a11
    return m00 >= 1.0 and m11 >= 1.0 and (m00 - 1.0) * (m11 - 1.0) >= m01 * m10


def remap_weak_directions(
    measured: FloatArray, cov: FloatArray, prediction: FloatArray, prediction_cov: FloatArray
) -> FloatArray:
    """Solution remapping of a scan match along its degenerate translation directions (Zhang,
    Kaess & Singh, ICRA 2016, "On degeneracy of optimization-based state estimation
    problems"), where the match agrees with the prediction within their joint noise.

    In the coordinates ``y = W^-1 d`` whitened by the prediction's translation covariance
    (``W W^T``, ``d`` the translation from the match to the prediction), the match's
    translation information ``W^T cov_xy^-1 W`` has eigenvalues ``lambda_i`` and unit
    eigenvectors ``e_i``. Along an ``e_i`` with ``lambda_i < 1`` the scene tells less than
    the prediction: the optimum the match found there is where the nonlinear search slid to
    (biased by ends of wall whose detection depends on where the end falls between two
    beams), not a measurement. If moreover the match does not contradict the prediction
    there - the difference ``y_i = e_i . y`` is within :data:`AGREE_SIGMAS` standard
    deviations of the joint noise (variance ``1 + 1 / lambda_i``) - the translation along
    ``e_i`` is set to the prediction's and the heading follows by its regression on the
    translation under ``cov``. A weak match that contradicts the prediction significantly
    (wheel slip, a bad odometry model) keeps its value. The covariance is never changed:
    the factor stays exactly as weak along ``e_i`` as the scene makes it.

    Args:
        measured: ``(3,)`` float64 matched motion ``[dx_m, dy_m, dtheta_rad]`` (frame of
            the first pose).
        cov: ``(3, 3)`` float64 its covariance, tangent space at ``measured`` (m, rad).
        prediction: ``(3,)`` float64 the predicted (odometry) motion, same frame.
        prediction_cov: ``(3, 3)`` float64 its covariance, positive definite.

    Returns:
        ``(3,)`` float64 the remapped motion (``measured`` when no direction is weak and
        consistent, or a covariance is not positive definite).
    """
    if _no_weak_direction(cov, prediction_cov):  # most matches: nothing to remap
        return measured
    try:
        w = np.linalg.cholesky(prediction_cov[:2, :2])
        info_xy = np.linalg.inv(cov[:2, :2])
    except np.linalg.LinAlgError:
        return measured
    evals, evecs = np.linalg.eigh(w.T @ info_xy @ w)
    d = se2.between(measured, prediction)  # prediction in the tangent at measured
    y = evecs.T @ np.linalg.solve(w, d[:2])
    with np.errstate(divide="ignore"):
        joint_var = 1.0 + 1.0 / np.maximum(evals, 0.0)
    remap = (evals < 1.0) & (y**2 <= AGREE_SIGMAS**2 * joint_var)
    if not np.any(remap):
        return measured
    shift = np.zeros(3)
    shift[:2] = w @ (evecs[:, remap] @ y[remap])
    shift[2] = cov[2, :2] @ info_xy @ shift[:2]
    return se2.compose(measured, shift)
