"""The SLAM pipeline: ICE matching factors and wheel odometry in a GTSAM iSAM2 pose graph.

Per scan (DESIGN "Data flow of one scan"): ICE features; prediction from odometry; keyframe
decision; ICE match against the feature map of the recent nodes; odometry and scan-match
factors (covariance from the match); iSAM2 update; feature-map update with time-validity
pruning; and, every few nodes, a loop-closure search among older nodes near the current
estimate. After the run an optional batch Levenberg–Marquardt refinement.

The pipeline never reads files: it takes :class:`frontends.LaserScan` records.
"""

from __future__ import annotations

import logging
import time
from collections import defaultdict
from dataclasses import dataclass, field
from typing import Literal

import numpy as np
from numpy.typing import NDArray

from frontends import LaserScan
from graph import PoseGraph, odometry_covariance
from iceg.config import IcegConfig
from iceg.feature_map import FeatureMap
from iceg.features import extract
from iceg.matching import IceMatcher, MatchBounds
from iceg.results import SlamResult
from iceg.types import MatchResult, ScanFeatures
from iceg_common import se2
from iceg_common.errors import GraphError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]


class StageTimer:
    """Accumulates wall time per pipeline stage (seconds)."""

    def __init__(self) -> None:
        self.seconds: dict[str, float] = defaultdict(float)

    def add(self, stage: str, t0: float) -> float:
        """Add ``now - t0`` to ``stage``; return now."""
        now = time.perf_counter()
        self.seconds[stage] += now - t0
        return now


@dataclass
class LoopClosureStats:
    """Loop-closure bookkeeping: searches run, matches tried, accepted and rejected."""

    searches: int = 0
    attempts: int = 0
    accepted: int = 0
    rejected_match: int = 0
    rejected_consistency: int = 0

    def as_dict(self) -> dict[str, int]:
        """Plain dict for JSON output."""
        return dict(self.__dict__)


@dataclass(frozen=True, eq=False)
class _LoopCandidate:
    node_from: int
    node_to: int
    measured: FloatArray
    cov: FloatArray
    correlation: float
    implied: FloatArray  # (3,) map-frame pose of node_to that the closure implies


@dataclass
class _ScanRecord:
    stamp_s: float
    node_id: int
    delta_from_node: FloatArray  # odometry delta from the node's scan to this scan


@dataclass
class SlamState:
    """Mutable per-run bookkeeping of :class:`Slam` (scans, nodes, match statistics)."""

    scans: list[LaserScan] = field(default_factory=list)
    records: list[_ScanRecord] = field(default_factory=list)
    node_scan_index: list[int] = field(default_factory=list)
    node_odom: list[FloatArray] = field(default_factory=list)
    node_path_m: list[float] = field(default_factory=list)  # odometry path length at node
    correlations: dict[int, float] = field(default_factory=dict)  # factor index -> eq. 1
    match_failures: dict[str, int] = field(default_factory=lambda: defaultdict(int))


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
        self.graph = PoseGraph(self.config.graph)
        self.matcher = IceMatcher(self.config.matching)
        self.feature_map = FeatureMap(self.config.feature_map)
        self.timer = StageTimer()
        self.loop_stats = LoopClosureStats()
        self._s = SlamState()
        self._pending_loops: list[_LoopCandidate] = []
        self._result: SlamResult | None = None

    # ------------------------------------------------------------------ per scan

    def process(self, scan: LaserScan) -> FloatArray:
        """Process one scan; return its current pose estimate ``(3,)`` in the map frame.

        The map frame is the odometry frame of the first scan (the first node is fixed at
        the first odometry pose, or at the origin when the log has no odometry).
        """
        if self._result is not None:
            raise GraphError("Slam.process() after finish(): start a new Slam for a new run")
        cfg = self.config.slam
        s = self._s
        t0 = time.perf_counter()
        odom = self._odometry_of(scan)
        s.scans.append(scan)
        if not s.node_odom:
            feats = extract(scan, self.config.features)
            t0 = self.timer.add("features", t0)
            self._add_node(scan, odom, initial=odom)
            self.graph.update()
            self.feature_map.update(0, feats, scan.stamp_s, scan=scan)
            self.timer.add("feature_map", t0)
            return odom.copy()

        last = len(s.node_odom) - 1
        if scan.odom_pose is None:
            # No wheel odometry: every scan is a node, predicted by constant velocity, and a
            # weak motion prior keeps the graph connected where matching fails.
            delta = self._constant_velocity_delta(last)
            odom = se2.compose(s.node_odom[last], delta)
            odom_cov = np.diag(
                [cfg.no_odometry_sigma_m**2] * 2 + [np.radians(cfg.no_odometry_sigma_deg) ** 2]
            )
            is_keyframe = True
        else:
            delta = se2.between(s.node_odom[last], odom)
            odom_cov = odometry_covariance(delta, self.config.odometry_noise)
            dt = scan.stamp_s - s.scans[s.node_scan_index[last]].stamp_s
            is_keyframe = bool(
                np.hypot(delta[0], delta[1]) >= cfg.keyframe_distance_m
                or abs(delta[2]) >= np.radians(cfg.keyframe_rotation_deg)
                or dt >= cfg.keyframe_max_interval_s
            )
        if not is_keyframe:
            s.records.append(_ScanRecord(scan.stamp_s, last, delta))
            return se2.compose(self.graph.estimate(last), delta)

        feats = extract(scan, self.config.features)
        t0 = self.timer.add("features", t0)
        ids, poses = self.graph.estimates()
        recent = ids[max(0, last - cfg.local_map_nodes + 1) : last + 1]
        reference = self.feature_map.reference((ids, poses), recent, poses[last])
        bounds = MatchBounds.local(cfg.match_max_translation_m, cfg.match_max_rotation_deg)
        result = self.matcher.match(feats, reference, delta, bounds)
        t0 = self.timer.add("matching", t0)
        if not result.success:
            # Count by the reason's category (the text before the first colon).
            s.match_failures[(result.reason or "unknown").split(":")[0]] += 1
        new_id = self._add_node(
            scan, odom, initial=se2.compose(poses[last], result.pose if result.success else delta)
        )
        self._add_factor("odometry", last, new_id, delta, odom_cov)
        if result.success:
            self._add_factor(
                "scan_match", last, new_id, result.pose, result.cov, result.correlation
            )
        t0 = self.timer.add("graph_build", t0)
        self.graph.update()
        t0 = self.timer.add("isam2", t0)
        lc = self.config.loop_closure
        if lc.enabled and new_id % lc.every_n_nodes == 0:
            self._search_loop_closure(new_id, feats)
            t0 = self.timer.add("loop_closure", t0)
        self.feature_map.update(
            new_id,
            feats,
            scan.stamp_s,
            reference=reference,
            match=result,
            scan=scan,
            node_poses=self.graph.estimates(),
        )
        self.timer.add("feature_map", t0)
        return self.graph.estimate(new_id)

    # ------------------------------------------------------------------ internals

    def _odometry_of(self, scan: LaserScan) -> FloatArray:
        if scan.odom_pose is not None:
            return np.asarray(scan.odom_pose, dtype=np.float64)
        return np.zeros(3)

    def _constant_velocity_delta(self, last: int) -> FloatArray:
        """Motion of the last node pair (estimates), as the prediction of the next one."""
        if last == 0:
            return np.zeros(3)
        return se2.between(self.graph.estimate(last - 1), self.graph.estimate(last))

    def _add_node(self, scan: LaserScan, odom: FloatArray, initial: FloatArray) -> int:
        s = self._s
        node_id = len(s.node_odom)
        step = float(np.hypot(*(odom[:2] - s.node_odom[-1][:2]))) if s.node_odom else 0.0
        s.node_path_m.append((s.node_path_m[-1] if s.node_path_m else 0.0) + step)
        s.node_odom.append(odom)
        s.node_scan_index.append(len(s.scans) - 1)
        s.records.append(_ScanRecord(scan.stamp_s, node_id, np.zeros(3)))
        self.graph.add_node(node_id, initial)
        return node_id

    def _add_factor(
        self,
        kind: str,
        i: int,
        j: int,
        measured: FloatArray,
        cov: FloatArray,
        correlation: float = float("nan"),
        robust: Literal["huber", "cauchy"] | None = None,
    ) -> None:
        robust_k = self.config.loop_closure.robust_k if robust else None
        record = self.graph.add_between(
            i, j, measured, cov, kind=kind, robust=robust, robust_k=robust_k
        )
        if np.isfinite(correlation):
            self._s.correlations[record.index] = correlation

    def _search_loop_closure(self, node_id: int, feats: ScanFeatures) -> None:
        """Search older nodes near the current estimate and add a robust loop closure.

        Candidates are nodes at least ``min_node_gap`` nodes and ``min_path_m`` metres of
        path back, within ``radius = base + n_sigma * sqrt(lambda_max(cov_xy))`` of the
        current estimate (``cov_xy`` from the current node's marginal, capped at
        ``max_search_radius_m``); up to ``max_candidates`` of the nearest, from distinct
        places, are matched against the landmarks of the ``reference_nodes`` old nodes
        nearest each candidate, and the best-correlated match is kept. It is accepted when it
        is consistent with the current estimate (Mahalanobis distance of the innovation under
        the marginal plus the match covariance below a chi-square gate), or when it agrees
        with a recent closure that failed the gate (see :meth:`_agree`); it enters with a
        robust kernel.
        """
        lc = self.config.loop_closure
        ids, poses = self.graph.estimates()
        current = poses[node_id]
        path = np.asarray(self._s.node_path_m)
        # A loop candidate is old in node count and far along the path: a node reached again
        # after a detour, not the corridor just driven.
        older = ids[
            (ids <= node_id - lc.min_node_gap) & (path[node_id] - path[ids] >= lc.min_path_m)
        ]
        if older.size == 0:
            return
        self.loop_stats.searches += 1
        marginal = self.graph.marginal_covariance(node_id)
        sigma_xy = float(np.sqrt(max(np.linalg.eigvalsh(marginal[:2, :2]).max(), 0.0)))
        radius = min(lc.search_radius_m + lc.search_n_sigma * sigma_xy, lc.max_search_radius_m)
        dist = np.hypot(*(poses[older, :2] - current[:2]).T)
        order = np.argsort(dist, kind="stable")
        candidates: list[int] = []
        for k in order[dist[order] <= radius]:
            if all(abs(int(older[k]) - c) > lc.reference_nodes for c in candidates):
                candidates.append(int(older[k]))
            if len(candidates) == lc.max_candidates:
                break
        bounds = MatchBounds(
            max_translation_m=radius,
            max_rotation_rad=np.radians(lc.max_rotation_deg)
            + lc.search_n_sigma * float(np.sqrt(max(marginal[2, 2], 0.0))),
        )
        best: tuple[int, FloatArray, MatchResult] | None = None
        for candidate in candidates:
            # The place's reference: the old nodes nearest the candidate (any pass through it).
            near_cand = np.hypot(*(poses[older, :2] - poses[candidate, :2]).T)
            window = older[np.argsort(near_cand, kind="stable")[: lc.reference_nodes]]
            reference = self.feature_map.reference((ids, poses), window, poses[candidate])
            prediction = se2.between(poses[candidate], current)
            self.loop_stats.attempts += 1
            result = self.matcher.match(feats, reference, prediction, bounds)
            if not result.success or result.correlation < lc.min_correlation:
                self.loop_stats.rejected_match += 1
                logger.debug(
                    "loop closure %d->%d (radius %.2f m) not matched: %s (correlation %.2f)",
                    candidate,
                    node_id,
                    radius,
                    result.reason,
                    result.correlation,
                )
            elif best is None or result.correlation > best[2].correlation:
                best = (candidate, prediction, result)
        if best is None:
            return
        candidate, prediction, result = best
        innovation = se2.between(prediction, result.pose)
        innovation_cov = marginal + result.cov
        d2 = float(innovation @ np.linalg.solve(innovation_cov, innovation))
        closure = _LoopCandidate(
            candidate,
            node_id,
            result.pose,
            result.cov,
            result.correlation,
            implied=se2.compose(poses[candidate], result.pose),
        )
        if d2 <= lc.consistency_chi2:
            self._accept_loop_closures([closure])
            logger.debug(
                "loop closure %d->%d accepted: innovation %s, chi2 %.1f, correlation %.2f",
                candidate,
                node_id,
                np.round(innovation, 3),
                d2,
                result.correlation,
            )
            return
        agreeing = [c for c in self._pending_loops if self._agree(c, closure)]
        if agreeing:
            # Two independent places agree: the pair is its own outlier test, and a robust
            # kernel would all but ignore the large residual the drift gives it.
            self._accept_loop_closures([*agreeing, closure], robust=False)
            self._pending_loops = [c for c in self._pending_loops if c not in agreeing]
            logger.debug(
                "loop closures %s->%d accepted by pairwise agreement (chi2 %.1f vs estimate)",
                [c.node_from for c in agreeing],
                node_id,
                d2,
            )
            return
        self.loop_stats.rejected_consistency += 1
        self._pending_loops = [
            c for c in self._pending_loops if node_id - c.node_to <= lc.agreement_window_nodes
        ] + [closure]
        logger.debug(
            "loop closure %d->%d held back: innovation %s, chi2 %.1f",
            candidate,
            node_id,
            np.round(innovation, 3),
            d2,
        )

    def _agree(self, a: _LoopCandidate, b: _LoopCandidate) -> bool:
        """Two closures agree when ``a``'s implied pose, carried to ``b``'s node along the
        current estimate of the short path between them, lands on ``b``'s implied pose
        (pairwise consistency after Olson 2009, "Recognizing places using spectrally
        clustered local matches", reduced to pairs)."""
        lc = self.config.loop_closure
        path = self._s.node_path_m
        if (
            b.node_to - a.node_to > lc.agreement_window_nodes
            # independent evidence: two different stretches of the old path
            or abs(path[b.node_from] - path[a.node_from]) < lc.agreement_min_separation_m
        ):
            return False
        carry = se2.between(self.graph.estimate(a.node_to), self.graph.estimate(b.node_to))
        diff = se2.between(se2.compose(a.implied, carry), b.implied)
        return bool(
            np.hypot(diff[0], diff[1]) <= lc.agreement_translation_m
            and abs(diff[2]) <= np.radians(lc.agreement_rotation_deg)
        )

    def _accept_loop_closures(self, closures: list[_LoopCandidate], robust: bool = True) -> None:
        kernel = self.config.loop_closure.robust_kernel if robust else None
        for c in closures:
            self._add_factor(
                "loop_closure",
                c.node_from,
                c.node_to,
                c.measured,
                c.cov,
                c.correlation,
                robust=kernel,
            )
        self.graph.update()
        self.loop_stats.accepted += len(closures)

    # ------------------------------------------------------------------ results

    def trajectory(self) -> tuple[FloatArray, FloatArray]:
        """Current estimate of every processed scan: ``(stamps_s (N,), poses (N, 3))``.

        A scan that is not a graph node takes its node's estimate composed with the
        odometry delta from the node's scan (DESIGN "Data flow of one scan").
        """
        _, poses = self.graph.estimates()
        recs = self._s.records
        stamps = np.array([r.stamp_s for r in recs])
        node = np.array([r.node_id for r in recs], dtype=np.int64)
        delta = np.array([r.delta_from_node for r in recs]).reshape(-1, 3)
        return stamps, se2.compose(poses[node], delta)

    def finish(self) -> SlamResult:
        """Optionally batch-refine and return the :class:`SlamResult` (idempotent: a second
        call returns the same result; :meth:`process` is refused afterwards).

        The occupancy grid is not rendered here: the result carries the scans, and
        :meth:`SlamResult.render_map` (called by :meth:`SlamResult.save` after the trajectory,
        graph and metrics are written) renders it along the optimized poses.
        """
        if self._result is not None:
            return self._result
        t0 = time.perf_counter()
        if self.config.slam.batch_refinement and self._s.node_odom:
            self.graph.optimize_batch()
            t0 = self.timer.add("batch_refinement", t0)
        stamps, poses = self.trajectory()
        ids, node_poses = self.graph.estimates()
        self._result = SlamResult(
            stamps_s=stamps,
            poses=poses,
            node_ids=ids,
            node_poses=node_poses,
            node_scan_index=np.array(self._s.node_scan_index, dtype=np.int64),
            factors=self.graph.factors,
            correlations=dict(self._s.correlations),
            loop_closures=self.loop_stats,
            match_failures=dict(self._s.match_failures),
            stage_seconds=dict(self.timer.seconds),
            feature_map=self.feature_map,
            graph=self.graph,
            config=self.config,
            scans=tuple(self._s.scans),
        )
        return self._result
