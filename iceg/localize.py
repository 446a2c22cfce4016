"""Localization in a saved map, and placing a new log in it (``iceg localize``, ``iceg run
--continue``; issue 15).

The map is fixed: the session's node poses and feature map are read, nothing is added to
them. :class:`Localizer` is a pure-localization mode in the manner of Cartographer's and
slam_toolbox's: odometry prediction, keyframes matched against the fixed map (bounds grown with
the pose's uncertainty) and against a local tracking map of the log's own recent keyframes
(places the map never saw), global matching (no prediction) at the start without a pose and
when the robot is lost (neither map matches, a kidnapping), and at the end a smoothing pose
graph per segment with the map matches as priors (the map stays fixed).

Frames: poses ``[x_m, y_m, theta_rad]`` in the map frame of the session; covariances ``(3, 3)``
in the tangent space of the pose (body frame, gtsam convention), m² / rad².
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import json
import logging
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path
from typing import Any

import numpy as np
from numpy.typing import NDArray

from frontends import LaserScan
from graph import FactorKind, PoseGraph, odometry_covariance
from iceg.config import IcegConfig
from iceg.feature_map import FeatureMap, MapReference
from iceg.features import extract
from iceg.features.prefetch import auto_workers
from iceg.match_pool import MatchJob, MatchPool
from iceg.matching import IceMatcher, MatchBounds
from iceg.session import Session
from iceg.slam import Slam, remap_weak_directions
from iceg.types import MatchResult, ScanFeatures
from iceg_common import se2
from iceg_common.atomic import atomic_write
from iceg_common.errors import GraphError

logger = logging.getLogger(__name__)

#: Most candidate-place references a :class:`FixedMap` keeps for its global placements
#: (about 0.1 MB each on MIT CSAIL: ten nodes' landmarks, segments and scan points).
_MAX_CACHED_PLACES = 1024

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class Status(IntEnum):
    """How a scan's pose was obtained."""

    LOST = 0  # no pose known (before the first placement); pose NaN
    PREDICTED = 1  # odometry from the last keyframe (or a keyframe that matched nothing)
    TRACKED = 2  # a keyframe matched against the fixed map
    PLACED = 3  # a global match (tentative until confirmed)
    LOCAL = 4  # a match against the local tracking map only (a place the map never saw)


@dataclass(frozen=True)
class LocalizeSettings:
    """Tuning of localization (not part of the run configuration).

    Attributes:
        reference_nodes: map nodes nearest the predicted pose whose landmarks are matched.
        track_translation_m / track_rotation_deg: bounds of a tracking match.
        initial_translation_m / initial_rotation_deg: bounds around a given initial pose.
        min_correlation: least ICE correlation (eq. 1) of an accepted match; None: the
            matcher's own global threshold (``matching.validation.min_correlation_global``,
            :meth:`correlation_floor`), no floor of the localization's above it.
        lost_after: consecutive keyframe scans matching neither the map nor the local
            tracking map before a global search.
        min_fit: least fraction of a globally placed scan's points (within the map's
            reach) lying within ``fit_tolerance_m`` of a map segment.
        ambiguity_margin: a global placement is refused when a distinct place matches
            within this correlation of the best.
        distinct_place_m / distinct_place_deg: two placements more than this far apart, in
            position or heading, are distinct places (:func:`distinct_places`); nearer, they
            are the same place, however confident their covariances. A global placement is
            corroborated by another scan's, taken at a distinct place, that lands at the
            same place (:class:`iceg.continuation.StartSearch`).
        confirm_keyframes: tracked keyframes that confirm a global placement.
        candidate_spacing_m: global search: one candidate place per square of this side.
        keyframe_distance_m / keyframe_rotation_deg: odometry motion between matched scans.
        max_global_tries: global searches before giving up (bounds the cost of a log
            outside the map).
        lost_retry_scans: a lost robot searches globally every this many scans.
        search_n_sigma: a tracking match against the map searches this many standard
            deviations of the predicted pose (at least the tracking bounds).
        check_every_nodes: localization in a saved map: every this many new nodes (and
            every ``lost_retry_scans`` scans after ``lost_after`` unmatched keyframes) the
            scan is placed globally; ``confirm_keyframes`` placements in a row at a place
            distinct from the track's, disagreeing with it and agreeing with each other,
            mean the robot was carried away.
    """

    reference_nodes: int = 12
    track_translation_m: float = 1.0
    track_rotation_deg: float = 20.0
    initial_translation_m: float = 2.0
    initial_rotation_deg: float = 45.0
    min_correlation: float | None = None
    lost_after: int = 6
    confirm_keyframes: int = 3
    min_fit: float = 0.6
    fit_tolerance_m: float = 0.15
    ambiguity_margin: float = 0.1
    distinct_place_m: float = 1.0
    distinct_place_deg: float = 10.0
    candidate_spacing_m: float = 1.5
    keyframe_distance_m: float = 0.5
    keyframe_rotation_deg: float = 15.0
    max_global_tries: int = 1_000_000
    lost_retry_scans: int = 5
    search_n_sigma: float = 3.0
    check_every_nodes: int = 10

    def correlation_floor(self, config: IcegConfig) -> float:
        """The least correlation of an accepted match with the run configuration ``config``."""
        if self.min_correlation is not None:
            return self.min_correlation
        return config.matching.validation.min_correlation_global


@dataclass(frozen=True, eq=False)
class Placement:
    """A scan's match against the map.

    Attributes:
        anchor: the map node whose frame the reference is in.
        reference: the reference (built by the map's feature map).
        match: the match; ``match.pose`` is the scan's pose in ``anchor``'s frame.
        pose: ``(3,)`` the scan's pose in the map frame.
    """

    anchor: int
    reference: MapReference
    match: MatchResult
    pose: FloatArray


class FixedMap:
    """A map to match against: node poses ``(ids (N,), poses (N, 3))`` and the feature map.

    Args:
        node_ids: ``(N,)`` int64 ascending node ids.
        node_poses: ``(N, 3)`` map-frame poses.
        feature_map: landmarks anchored to those nodes.
        config: the session's configuration (features, matching).
    """

    def __init__(
        self,
        node_ids: IntArray,
        node_poses: FloatArray,
        feature_map: FeatureMap,
        config: IcegConfig,
    ) -> None:
        self.ids = np.asarray(node_ids, dtype=np.int64)
        self.poses = np.asarray(node_poses, dtype=np.float64)
        self.feature_map = feature_map
        self.config = config
        self.matcher = IceMatcher(config.matching)
        #: The saved session the map comes from (None: a live map); with it,
        #: :func:`localize_scans` runs the session's SLAM against the frozen map.
        self.session: Session | None = None
        #: References of candidate places, by (row, nodes): every global placement matches
        #: the same places of the frozen map (at most ``_MAX_CACHED_PLACES`` kept).
        self._places: dict[tuple[int, int], tuple[int, MapReference]] = {}
        #: Runs a global placement's matches beside this process while set
        #: (:func:`match_helper`); the same placements either way.
        self.match_pool: MatchPool | None = None

    def reference_near(self, pose: FloatArray, k: int) -> tuple[int, MapReference]:
        """Reference of the ``k`` nodes nearest ``pose`` (position), in the nearest one's
        frame: ``(anchor row, reference)``."""
        d = np.hypot(*(self.poses[:, :2] - pose[:2]).T)
        near = np.argsort(d, kind="stable")[:k]
        anchor = int(near[0])
        ref = self.feature_map.reference(
            (self.ids, self.poses), np.sort(self.ids[near]), self.poses[anchor]
        )
        return anchor, ref

    def candidates(self, spacing_m: float) -> IntArray:
        """Rows of nodes spread over the map: the first node in each square of ``spacing_m``."""
        cells = np.floor(self.poses[:, :2] / spacing_m).astype(np.int64)
        _, first = np.unique(cells, axis=0, return_index=True)
        return np.sort(first)

    def match_at(
        self, feats: ScanFeatures, pose: FloatArray, bounds: MatchBounds, k: int
    ) -> Placement | None:
        """Match around a predicted map-frame ``pose`` (None: failed)."""
        return self._match_reference(feats, *self.reference_near(pose, k), pose, bounds)

    def _place_reference(self, row: int, k: int) -> tuple[int, MapReference]:
        """:meth:`reference_near` the pose of node row ``row``, kept for the next global
        placements (at most ``_MAX_CACHED_PLACES``)."""
        key = (row, k)
        got = self._places.get(key)
        if got is None:
            got = self.reference_near(self.poses[row], k)
            if len(self._places) < _MAX_CACHED_PLACES:
                self._places[key] = got
        return got

    def _kept_places(self, rows: list[int], k: int) -> Iterator[ScanFeatures]:
        """The references of the places of node rows ``rows`` (``k`` nodes each) that this map
        keeps (:meth:`_place_reference`), each built now, until the first one it does not
        keep."""
        for row in rows:
            self._place_reference(row, k)
            kept = self._places.get((row, k))
            if kept is None:
                return
            yield kept[1].features

    def _match_reference(
        self,
        feats: ScanFeatures,
        anchor: int,
        ref: MapReference,
        pose: FloatArray,
        bounds: MatchBounds,
    ) -> Placement | None:
        """Match against ``ref`` (in anchor row ``anchor``'s frame) around the map-frame
        ``pose`` (None: failed)."""
        prediction = se2.between(self.poses[anchor], pose)
        return self._placement(
            anchor, ref, self.matcher.match(feats, ref.features, prediction, bounds)
        )

    def _placement(self, anchor: int, ref: MapReference, res: MatchResult) -> Placement | None:
        """The placement a match against ``ref`` (anchor row ``anchor``) makes (None: failed)."""
        if not res.success:
            return None
        return Placement(int(self.ids[anchor]), ref, res, se2.compose(self.poses[anchor], res.pose))

    def placements(self, feats: ScanFeatures, settings: LocalizeSettings) -> list[Placement]:
        """The scan matched globally (no prediction) against the place of every candidate
        node (:meth:`candidates` at ``settings.candidate_spacing_m``; a place is its
        ``reference_nodes`` nearest nodes, its reference built once): the placements the
        matcher accepted, in the candidates' order. With :attr:`match_pool` set the matches
        are shared with its helper; the same placements either way.

        Args:
            feats: The scan's features, robot frame.
            settings: localization tuning.

        Returns:
            The accepted placements, each with ``match.pose`` in its anchor node's frame
            and ``pose`` ``(3,)`` in the map frame ``[x_m, y_m, theta_rad]``.

        Raises:
            MatchingError: inconsistent features (from the matcher).
        """
        st = settings
        places: list[tuple[int, MapReference]] = []
        rows = self.candidates(st.candidate_spacing_m).tolist()
        pool = self.match_pool
        if pool is not None:  # before its helper starts: the places it will hold from the fork
            pool.share(self._kept_places(rows, st.reference_nodes))

        def jobs() -> Iterator[MatchJob]:  # each reference built as its match is sent
            for row in rows:
                anchor, ref = self._place_reference(row, st.reference_nodes)
                places.append((anchor, ref))
                prediction = se2.between(self.poses[anchor], self.poses[row])
                yield MatchJob(feats, ref.features, prediction, MatchBounds.global_())

        if pool is not None:
            results = pool.run_all(jobs())
        else:
            results = [self.matcher.match(*job) for job in jobs()]
        return [
            p
            for (anchor, ref), res in zip(places, results, strict=True)
            if (p := self._placement(anchor, ref, res)) is not None
        ]

    def place(self, feats: ScanFeatures, settings: LocalizeSettings) -> Placement | None:
        """Global placement: the scan matched (no prediction) against every candidate place.

        The best match by correlation is returned when it reaches ``min_correlation``, its
        points fit the map's segments (:func:`segment_fit` ``>= min_fit``), and no distinct
        place matches almost as well (``ambiguity_margin``); otherwise None (never a guess).
        Every place the matcher accepted is a rival, whether or not it reaches the floors: a
        place that looks the same is an ambiguity even where its fit or correlation falls
        short of a placement's.
        """
        st = settings
        matched = self.placements(feats, st)
        found = [
            p
            for p in matched
            if p.match.correlation >= st.correlation_floor(self.config)
            and segment_fit(feats, p, st.fit_tolerance_m) >= st.min_fit
        ]
        if not found:
            return None
        best = max(found, key=lambda p: p.match.correlation)
        for other in sorted(matched, key=lambda p: -p.match.correlation):
            distinct = distinct_places(best.pose, other.pose, st)
            if distinct and other.match.correlation >= best.match.correlation - st.ambiguity_margin:
                logger.info(
                    "global placement ambiguous (%.2f vs %.2f)",
                    best.match.correlation,
                    other.match.correlation,
                )
                return None
        return best


@contextlib.contextmanager
def match_helper(fixed: FixedMap) -> Iterator[FixedMap]:
    """``fixed`` with its global placements' matches shared with a forked helper process
    (:class:`~iceg.match_pool.MatchPool`) while in the block, where the session's
    configuration runs more than one process (``slam.workers``, 0:
    :func:`~iceg.features.prefetch.auto_workers`): the same placements, in about two thirds
    of the wall time on two cores. A placement compares a scan with every candidate place of
    the map: most of a localization's time (its kidnapping checks), and a continued log's
    start and a merge's placements."""
    workers = fixed.config.slam.workers or auto_workers()
    with MatchPool(fixed.matcher, helper=workers > 1) as pool:
        fixed.match_pool = pool
        try:
            yield fixed
        finally:
            fixed.match_pool = None


def distinct_places(a: FloatArray, b: FloatArray, settings: LocalizeSettings) -> bool:
    """Whether two map-frame poses ``(3,)`` ``[x_m, y_m, theta_rad]`` are distinct places:
    more than ``distinct_place_m`` apart in position or ``distinct_place_deg`` in heading."""
    d = se2.between(a, b)
    return bool(
        np.hypot(d[0], d[1]) > settings.distinct_place_m
        or abs(d[2]) > np.radians(settings.distinct_place_deg)
    )


def segment_fit(feats: ScanFeatures, p: Placement, tolerance_m: float) -> float:
    """Fraction of the scan's points, placed by ``p``, within ``tolerance_m`` of a reference
    segment, among those within 1 m of one (points in parts the map never saw do not count
    against the fit); 0 when fewer than 20 points are near the map."""
    seg = p.reference.features.seg_endpoints  # (M, 2, 2) reference frame
    if seg.shape[0] == 0 or feats.points_xy.shape[0] == 0:
        return 0.0
    pts = se2.transform_points(p.match.pose, feats.points_xy)
    a, b = seg[:, 0], seg[:, 1]
    ab = b - a
    t = np.einsum("pmk,mk->pm", pts[:, None, :] - a[None], ab) / np.maximum(
        np.einsum("mk,mk->m", ab, ab), 1e-12
    )
    closest = a[None] + np.clip(t, 0.0, 1.0)[..., None] * ab[None]
    d = np.hypot(*(pts[:, None, :] - closest).transpose(2, 0, 1)).min(axis=1)
    near = d < 1.0
    if near.sum() < 20:
        return 0.0
    return float(np.mean(d[near] < tolerance_m))


@dataclass
class LocalizationResult:
    """The new log's trajectory in the map frame.

    Attributes:
        stamps_s: ``(R,)`` scan stamps.
        poses: ``(R, 3)`` map-frame poses ``[x_m, y_m, theta_rad]`` (NaN while lost).
        covs: ``(R, 3, 3)`` pose covariances, body frame, m² / rad² (NaN while lost).
        status: ``(R,)`` int64 :class:`Status` values.
        correlations: ``(R,)`` ICE correlation of the scan's map match (NaN: not matched
            against the map).
        relocalizations: global placements made (the start without a pose, kidnappings).
        summary: scans per status (lower-case names) and keyframe counts.
    """

    stamps_s: FloatArray
    poses: FloatArray
    covs: FloatArray
    status: IntArray
    correlations: FloatArray
    relocalizations: int = 0
    summary: dict[str, float] = field(default_factory=dict)


@dataclass
class _Keyframe:
    """A keyframe of the new log: its causal pose and the measurements that placed it."""

    scan_index: int
    segment: int
    pose: FloatArray  # causal (filtered) map-frame estimate
    cov: FloatArray  # its covariance, body frame
    odom: FloatArray | None = None  # odometry from the previous keyframe of the segment
    odom_cov: FloatArray | None = None
    local: MatchResult | None = None  # match against the previous keyframes (from ``local_from``)
    local_from: int = -1
    prior: tuple[FloatArray, FloatArray] | None = None  # map match: map-frame pose, body cov


@dataclass(frozen=True)
class _Row:
    """One processed scan: its keyframe (-1: lost), the odometry since it (``(3,)``, the
    keyframe's frame) with its covariance, status, map-match correlation, and the same
    relative to the replaced track while a global placement is tentative."""

    kf: int
    since: FloatArray
    since_cov: FloatArray
    status: Status
    corr: float
    alt: tuple[int, FloatArray, FloatArray] | None


@dataclass
class _Track:
    pose: FloatArray | None = None
    cov: FloatArray = field(default_factory=lambda: np.full((3, 3), np.nan))
    odom: FloatArray | None = None  # odometry of the last scan
    since_kf: FloatArray = field(default_factory=lambda: np.zeros(3))  # odometry motion
    since_kf_cov: FloatArray = field(default_factory=lambda: np.zeros((3, 3)))
    fails: int = 0  # consecutive keyframes matched neither to the map nor to the local map
    tentative: int = 0  # >0: map matches still needed to confirm a global placement
    global_tries: int = 0
    lost_scans: int = 0  # scans since the robot was lost
    segment: int = -1  # current segment (a new one at each global placement)
    segment_start: int = 0  # first keyframe of the current segment
    last_kf: int = -1  # the current segment's last keyframe


class Localizer:
    """Scan-by-scan localization in a :class:`FixedMap` (nothing is added to the map).

    Pure localization in the manner of Cartographer's localization mode and slam_toolbox's
    localization mode (a frozen map plus a trimmed local map of the new trajectory):

    - **Odometry prediction** between scans (covariance grown by the odometry motion model,
      or by the no-odometry sigmas across a break).
    - Each keyframe (``keyframe_distance_m`` / ``keyframe_rotation_deg`` of odometry) is
      ICE-matched against the **fixed map** around the predicted pose, within bounds that
      grow with the pose's uncertainty (``search_n_sigma`` sigmas, at least the tracking
      bounds, at most the run's ``loop_closure.max_search_radius_m``), and against the
      **local tracking map**: the landmarks of the log's own last ``slam.local_map_nodes``
      keyframes, in a :class:`~iceg.feature_map.FeatureMap` of its own (trimmed to those
      keyframes for matching; discarded at the end). The local map keeps the track where the
      old map never saw the place; the fixed map anchors it where it did.
    - A keyframe that matches neither the fixed map nor its local map is retried on the next
      scan, the prediction going on with a growing covariance. After ``lost_after`` such
      scans in a row the pose may be wrong (a kidnapping, dropped scans): every
      ``lost_retry_scans`` scans the keyframe is matched **globally** (no prediction,
      unbounded rotation) against candidate places spread over the map
      (:meth:`FixedMap.place`), as at the start without a pose. A global placement that
      agrees with the prediction (``loop_closure.consistency_chi2``) is a map match; one that
      does not starts a new segment of the trajectory (no odometry across), trusted after
      ``confirm_keyframes`` map matches and withdrawn (its scans LOST) when the next keyframe
      fails the map. LOST means no pose: before the first placement only.

    :meth:`process` returns the causal (filtered) estimate; :meth:`smoothed` solves each
    segment's pose graph (odometry and local-match factors between keyframes, the map
    matches as priors: the map is fixed) by batch Levenberg–Marquardt and gives every scan
    its smoothed pose and marginal covariance.

    Args:
        fixed: the map.
        settings: tuning.
        initial_pose: ``(3,)`` map-frame pose of the first scan, if known (may be wrong: a
            failed match there falls back to global placement).
    """

    def __init__(
        self,
        fixed: FixedMap,
        settings: LocalizeSettings | None = None,
        initial_pose: FloatArray | None = None,
    ) -> None:
        self.fixed = fixed
        self.settings = settings or LocalizeSettings()
        self._t = _Track()
        self._initial = None if initial_pose is None else np.asarray(initial_pose, dtype=float)
        self.relocalizations = 0
        self._local_map = FeatureMap(fixed.config.feature_map)
        self._kfs: list[_Keyframe] = []
        self._withdrawn: set[int] = set()  # segments whose placement was not confirmed
        # the track before a tentative global placement, carried on by odometry: restored if
        # the placement is withdrawn
        self._fallback: _Track | None = None
        self._rows: list[_Row] = []
        self._n_scans = 0
        # the newest keyframe's index and scan points (its frame)
        self._last_points: tuple[int, FloatArray] = (-1, np.zeros((0, 2)))

    def process(self, scan: LaserScan) -> tuple[FloatArray, FloatArray, Status, float]:
        """One scan: its causal ``(pose (3,), cov (3, 3), status, correlation)``."""
        out = self._process(scan)
        t, fb = self._t, self._fallback
        kf = t.last_kf if t.pose is not None else -1
        alt = None if fb is None else (fb.last_kf, fb.since_kf.copy(), fb.since_kf_cov.copy())
        self._rows.append(_Row(kf, t.since_kf.copy(), t.since_kf_cov.copy(), out[2], out[3], alt))
        self._n_scans += 1
        return out

    def _process(self, scan: LaserScan) -> tuple[FloatArray, FloatArray, Status, float]:
        t = self._t
        delta, q = self._odometry_step(scan)
        if t.pose is not None:
            ad = se2.adjoint(se2.inverse(delta))
            t.pose, t.cov = se2.compose(t.pose, delta), ad @ t.cov @ ad.T + q
        for track in (t, self._fallback):
            if track is None:
                continue
            ad = se2.adjoint(se2.inverse(delta))
            if track is not t and track.pose is not None:
                track.pose, track.cov = se2.compose(track.pose, delta), ad @ track.cov @ ad.T + q
            track.since_kf = se2.compose(track.since_kf, delta)
            track.since_kf_cov = ad @ track.since_kf_cov @ ad.T + q
        if not self._keyframe(scan):
            return self._out(Status.PREDICTED if t.pose is not None else Status.LOST, np.nan)
        self._scan = scan
        feats = extract(scan, self.fixed.config.features)
        if self._initial is not None:
            return self._try_initial(feats)
        if t.pose is not None:
            return self._track(feats)
        return self._relocalize(feats)

    # ------------------------------------------------------------------ steps

    def _odometry_step(self, scan: LaserScan) -> tuple[FloatArray, FloatArray]:
        t = self._t
        odom = None if scan.odom_pose is None else np.asarray(scan.odom_pose, dtype=float)
        usable = odom is not None and t.odom is not None and not scan.odom_break
        delta = se2.between(t.odom, odom) if usable else np.zeros(3)  # type: ignore[arg-type]
        first = t.odom is None and odom is not None and self._n_scans == 0
        t.odom = odom
        cfg = self.fixed.config
        if usable:
            return delta, odometry_covariance(delta, cfg.odometry_noise)
        if first:
            return delta, np.zeros((3, 3))
        return delta, cfg.slam.no_odometry_covariance()

    def _keyframe(self, scan: LaserScan) -> bool:
        t, st = self._t, self.settings
        d = t.since_kf
        moved = np.hypot(d[0], d[1]) >= st.keyframe_distance_m or abs(d[2]) >= np.radians(
            st.keyframe_rotation_deg
        )
        if t.pose is None:  # lost: a global search every ``lost_retry_scans`` scans
            t.lost_scans += 1
            return (t.lost_scans - 1) % st.lost_retry_scans == 0
        return bool(moved or scan.odom_pose is None or scan.odom_break or t.tentative > 0)

    def _try_initial(self, feats: ScanFeatures) -> tuple[FloatArray, FloatArray, Status, float]:
        st = self.settings
        pose, self._initial = self._initial, None
        bounds = MatchBounds.local(st.initial_translation_m, st.initial_rotation_deg)
        p = self.fixed.match_at(feats, pose, bounds, st.reference_nodes)  # type: ignore[arg-type]
        if p is None or p.match.correlation < st.correlation_floor(self.fixed.config):
            logger.info("the initial pose does not match the map; searching globally")
            p = self.fixed.place(feats, st)
            if p is None or _far(p.pose, pose, st):  # type: ignore[arg-type]
                self._t.global_tries += 1
                self.relocalizations += p is not None
                return (
                    self._out(Status.LOST, np.nan) if p is None else self._start_segment(feats, p)
                )
        return self._start_segment(feats, p)

    def _bounds(self, cov: FloatArray, on_map: bool) -> MatchBounds:
        """Match bounds around a prediction of covariance ``cov``: ``search_n_sigma`` of its
        standard deviations, at least the tracking bounds (the map's, or the run's local
        match bounds for the local map), at most ``loop_closure.max_search_radius_m``.

        For a scan without odometry, the tracking bounds: its covariance holds the
        no-odometry sigmas (``slam.no_odometry_sigma_*``, 0.5 m and 20° a scan), a weak prior
        that keeps a graph connected, not the motion between two scans; three of them (1.5 m,
        60°) are beyond the matcher's tracking bounds, so every match asked for the global
        evidence and a laser-only log's placement was withdrawn at its first corridor scan.
        A laser-only run's own tracking matches within its local bounds the same way."""
        st, cfg = self.settings, self.fixed.config
        base_m = st.track_translation_m if on_map else cfg.slam.match_max_translation_m
        base_deg = st.track_rotation_deg if on_map else cfg.slam.match_max_rotation_deg
        if self._scan.odom_pose is None:
            return MatchBounds.local(base_m, base_deg)
        sxy = float(np.sqrt(max(np.linalg.eigvalsh(cov[:2, :2]).max(), 0.0)))
        sth = float(np.sqrt(max(cov[2, 2], 0.0)))
        trans = min(max(base_m, st.search_n_sigma * sxy), cfg.loop_closure.max_search_radius_m)
        rot = min(max(base_deg, np.degrees(st.search_n_sigma * sth)), 180.0)
        return MatchBounds.local(trans, rot)

    def _track(self, feats: ScanFeatures) -> tuple[FloatArray, FloatArray, Status, float]:
        t, st = self._t, self.settings
        pred = t.pose
        p = self.fixed.match_at(feats, pred, self._bounds(t.cov, True), st.reference_nodes)  # type: ignore[arg-type]
        on_map = p is not None and self._good(feats, p)
        if t.tentative > 0 and not on_map:
            logger.info("a global placement was not confirmed by the next keyframe")
            self._withdrawn.add(t.segment)
            if self._fallback is not None:  # back to the track it replaced
                self._fallback.odom, self._t, self._fallback = t.odom, self._fallback, None
                return self._out(Status.PREDICTED, np.nan)
            t.pose, t.cov, t.tentative = None, np.full((3, 3), np.nan), 0
            return self._relocalize(feats)
        local, ref, last = self._match_local(feats)
        if not on_map and local is None:
            # Not a keyframe: the next scan tries again (the odometry since the last keyframe
            # keeps accumulating, the covariance grows). After ``lost_after`` scans in a row
            # the pose may be wrong (a kidnapping): a global search every
            # ``lost_retry_scans`` scans while the prediction goes on.
            t.fails += 1
            if t.fails < st.lost_after or (t.fails - st.lost_after) % st.lost_retry_scans:
                return self._out(Status.PREDICTED, np.nan)
            p = self.fixed.place(feats, st)
            if p is None:
                return self._out(Status.PREDICTED, np.nan)
            if not self._agrees(p):
                logger.info(
                    "placed globally at %s, away from the prediction %s: a new segment",
                    np.round(p.pose, 2).tolist(),
                    np.round(np.asarray(t.pose), 2).tolist(),
                )
                self.relocalizations += 1
                return self._start_segment(feats, p)
            on_map = True
        t.fails = 0
        kf = _Keyframe(len(self._rows), t.segment, pred.copy(), t.cov.copy())  # type: ignore[union-attr]
        kf.odom, kf.odom_cov = t.since_kf.copy(), t.since_kf_cov.copy()
        if local is not None:
            kf.local, kf.local_from = local, last
            ad = se2.adjoint(se2.inverse(local.pose))
            t.pose = se2.compose(self._kfs[last].pose, local.pose)
            t.cov = ad @ self._kfs[last].cov @ ad.T + local.cov
        corr = np.nan
        status = Status.LOCAL
        if on_map:
            kf.prior = (p.pose, p.match.cov)  # type: ignore[union-attr]
            t.pose, t.cov = p.pose, p.match.cov  # type: ignore[union-attr]
            t.tentative = max(t.tentative - 1, 0)
            if t.tentative == 0:
                self._fallback = None  # confirmed
            status, corr = Status.TRACKED, p.match.correlation  # type: ignore[union-attr]
        kf.pose, kf.cov = t.pose.copy(), t.cov.copy()  # type: ignore[union-attr]
        self._add_keyframe(kf, feats, ref, local)
        return self._out(status, corr)

    def _agrees(self, p: Placement) -> bool:
        """A global placement agrees with the predicted pose: its innovation is within the
        ``consistency_chi2`` gate of the run's loop closure under the prediction's and the
        match's covariances (both body frame)."""
        t = self._t
        chi2 = self.fixed.config.loop_closure.consistency_chi2
        return _agrees(t.pose, t.cov, p, chi2)  # type: ignore[arg-type]

    def _match_local(
        self, feats: ScanFeatures
    ) -> tuple[MatchResult | None, MapReference | None, int]:
        """Match against the local tracking map (the segment's last keyframes)."""
        t, cfg = self._t, self.fixed.config.slam
        last = t.last_kf
        if last < 0:
            return None, None, last
        recent = [last]
        for i in range(last - 1, t.segment_start - 1, -1):
            if len(recent) >= cfg.local_map_nodes:
                break
            if self._kfs[i].segment == t.segment:
                recent.append(i)
        ids = np.arange(len(self._kfs), dtype=np.int64)
        poses = np.array([k.pose for k in self._kfs])
        ref = self._local_map.reference((ids, poses), np.array(recent), poses[last])
        kf, (newest, points) = self._kfs[last], self._last_points
        matched = kf.local is not None or kf.prior is not None
        if cfg.drop_walls_seen_through and matched and newest == last:
            # as the run's tracking (Slam._match_local): walls the last matched keyframe
            # sees through are gone
            tolerance = self.fixed.config.matching.validation.see_through_tolerance_m
            ref = ref.without_walls_seen_through(points, tolerance)
        bounds = self._bounds(t.since_kf_cov, False)
        res = self.fixed.matcher.match(feats, ref.features, t.since_kf, bounds)
        if not res.success:
            return None, ref, last
        measured = remap_weak_directions(res.pose, res.cov, t.since_kf, t.since_kf_cov)
        res = dataclasses.replace(res, pose=measured)
        return res, ref, last

    def _add_keyframe(
        self,
        kf: _Keyframe,
        feats: ScanFeatures,
        ref: MapReference | None,
        local: MatchResult | None,
    ) -> None:
        """Record the keyframe and add its features to the local tracking map."""
        t = self._t
        self._kfs.append(kf)
        t.last_kf = len(self._kfs) - 1
        self._last_points = (t.last_kf, feats.points_xy)
        ids = np.arange(len(self._kfs), dtype=np.int64)
        poses = np.array([k.pose for k in self._kfs])
        self._local_map.update(
            len(self._kfs) - 1,
            feats,
            self._scan.stamp_s,
            reference=ref if local is not None else None,
            match=local,
            scan=self._scan,
            node_poses=(ids, poses),
        )
        t.since_kf, t.since_kf_cov = np.zeros(3), np.zeros((3, 3))

    def _good(self, feats: ScanFeatures, p: Placement) -> bool:
        """A map match is kept when well correlated, or when its points fit the map
        (a refinement on few features, correlation 0, can still be exact)."""
        st = self.settings
        if p.match.correlation >= st.correlation_floor(self.fixed.config):
            return True
        return segment_fit(feats, p, st.fit_tolerance_m) >= st.min_fit

    def _relocalize(self, feats: ScanFeatures) -> tuple[FloatArray, FloatArray, Status, float]:
        t, st = self._t, self.settings
        t.global_tries += 1
        found = None if t.global_tries > st.max_global_tries else self.fixed.place(feats, st)
        if found is None:
            t.pose = None
            return self._out(Status.LOST, np.nan)
        self.relocalizations += 1
        return self._start_segment(feats, found)

    def _start_segment(
        self, feats: ScanFeatures, p: Placement
    ) -> tuple[FloatArray, FloatArray, Status, float]:
        """A global (or initial-pose) placement: a new segment, tentative until confirmed."""
        t, st = self._t, self.settings
        self._fallback = dataclasses.replace(t) if t.pose is not None else None
        t.segment = max((k.segment for k in self._kfs), default=-1) + 1
        t.segment_start = len(self._kfs)
        t.pose, t.cov, t.fails, t.tentative = p.pose, p.match.cov, 0, st.confirm_keyframes
        t.lost_scans = 0
        kf = _Keyframe(
            len(self._rows), t.segment, p.pose.copy(), p.match.cov, prior=(p.pose, p.match.cov)
        )
        self._add_keyframe(kf, feats, None, None)
        return self._out(Status.PLACED, p.match.correlation)

    def _out(self, status: Status, corr: float) -> tuple[FloatArray, FloatArray, Status, float]:
        t = self._t
        if t.pose is None:
            return np.full(3, np.nan), np.full((3, 3), np.nan), Status.LOST, np.nan
        return t.pose.copy(), t.cov.copy(), status, corr

    # ------------------------------------------------------------------ smoothing

    def smoothed(self) -> tuple[FloatArray, FloatArray]:
        """Every processed scan's smoothed pose ``(R, 3)`` and covariance ``(R, 3, 3)``
        (map frame / body frame; NaN while lost or in a withdrawn placement).

        Each segment is one pose graph (:class:`graph.PoseGraph`, no automatic prior):
        keyframe nodes, odometry factors between consecutive keyframes (the motion model's
        covariance accumulated scan by scan), local-match factors from the keyframe the
        local reference was built in, and each map match as a prior (the map is fixed, so a
        map match is an absolute measurement of the keyframe). Batch Levenberg–Marquardt,
        then marginal covariances; a scan between keyframes takes its keyframe's pose
        composed with the odometry since it, the covariance grown accordingly.

        Raises:
            GraphError: gtsam failed.
        """
        n = len(self._rows)
        poses = np.full((n, 3), np.nan)
        covs = np.full((n, 3, 3), np.nan)
        kf_pose = np.full((len(self._kfs), 3), np.nan)
        kf_cov = np.full((len(self._kfs), 3, 3), np.nan)
        segs = sorted({k.segment for k in self._kfs} - self._withdrawn)
        for seg in segs:
            rows = [i for i, k in enumerate(self._kfs) if k.segment == seg]
            g = PoseGraph(self.fixed.config.graph, auto_prior=False)
            for i in rows:
                g.add_node(i, self._kfs[i].pose)
            for a, b in itertools.pairwise(rows):
                k = self._kfs[b]
                if k.odom is not None and k.odom_cov is not None:
                    g.add_between(a, b, k.odom, _pd(k.odom_cov), kind=FactorKind.ODOMETRY)
            for i in rows:
                k = self._kfs[i]
                if k.local is not None:
                    g.add_between(
                        k.local_from, i, k.local.pose, k.local.cov, kind=FactorKind.SCAN_MATCH
                    )
                if k.prior is not None:
                    g.add_prior(i, k.prior[0], k.prior[1])
            g.optimize_batch()
            ids, est = g.estimates()
            kf_pose[ids] = est
            for i in rows:
                kf_cov[i] = g.marginal_covariance(i)
        for r in range(n):
            kf, delta, q, _, _ = self._effective(r)
            if kf < 0:
                continue
            poses[r] = se2.compose(kf_pose[kf], delta)
            ad = se2.adjoint(se2.inverse(delta))
            covs[r] = ad @ kf_cov[kf] @ ad.T + q
        return poses, covs

    def statuses(self) -> tuple[IntArray, FloatArray]:
        """``(R,)`` :class:`Status` and map-match correlation of every processed scan
        (LOST for the scans of a withdrawn placement)."""
        rows = [self._effective(r) for r in range(len(self._rows))]
        status = np.array([int(r[3]) for r in rows], dtype=np.int64)
        corr = np.array([r[4] for r in rows], dtype=np.float64)
        return status, corr

    def _effective(self, r: int) -> tuple[int, FloatArray, FloatArray, Status, float]:
        """Row ``r`` with withdrawn placements undone: its keyframe (-1: lost), odometry
        since it and covariance, status and correlation."""
        row = self._rows[r]
        if row.kf < 0 or self._kfs[row.kf].segment not in self._withdrawn:
            return row.kf, row.since, row.since_cov, row.status, row.corr
        if row.alt is not None:
            return row.alt[0], row.alt[1], row.alt[2], Status.PREDICTED, np.nan
        return -1, row.since, row.since_cov, Status.LOST, np.nan


def _pd(cov: FloatArray) -> FloatArray:
    """A covariance made positive definite (a zero odometry step has zero covariance)."""
    return 0.5 * (cov + cov.T) + np.diag([1e-10, 1e-10, 1e-12])


def localize_scans(
    fixed: FixedMap,
    scans: Sequence[LaserScan],
    settings: LocalizeSettings | None = None,
    initial_pose: FloatArray | None = None,
) -> LocalizationResult:
    """Localize every scan of a log in a fixed map.

    With a saved session (``fixed.session``, as :func:`fixed_map_of_session` makes): pure
    localization in the manner of Cartographer's localization mode, a new trajectory
    optimized in the pose graph of the frozen one (:func:`_localize_in_session`). Without
    (a live map): the causal :class:`Localizer` and its per-segment smoothing.

    Args:
        fixed: the map.
        scans: the log's scans in time order.
        settings: tuning.
        initial_pose: ``(3,)`` map-frame guess of the first scan (may be wrong).

    Returns:
        The trajectory in the map frame with per-scan covariance and status.

    Raises:
        GraphError: gtsam failed.
        SessionError: the session's scans cannot be re-read.
    """
    if fixed.session is not None:
        with match_helper(fixed):
            return _localize_in_session(fixed, scans, settings or LocalizeSettings(), initial_pose)
    loc = Localizer(fixed, settings, initial_pose)
    for s in scans:
        loc.process(s)
    status, corr = loc.statuses()
    poses, covs = loc.smoothed()
    return _result(scans, poses, covs, status, corr, loc.relocalizations)


def _result(
    scans: Sequence[LaserScan],
    poses: FloatArray,
    covs: FloatArray,
    status: IntArray,
    corr: FloatArray,
    relocalizations: int,
) -> LocalizationResult:
    result = LocalizationResult(
        stamps_s=np.array([s.stamp_s for s in scans], dtype=np.float64),
        poses=poses,
        covs=covs,
        status=status,
        correlations=corr,
        relocalizations=relocalizations,
    )
    result.summary = {s.name.lower(): int(np.sum(status == s)) for s in Status}
    return result


def _localize_in_session(
    fixed: FixedMap,
    scans: Sequence[LaserScan],
    st: LocalizeSettings,
    initial_pose: FloatArray | None,
) -> LocalizationResult:
    """Localization against a frozen saved map, segment by segment.

    A segment starts where a scan is placed in the map, the placement confirmed by the next
    scans and, when global, corroborated by another scan's global placement
    (:class:`iceg.continuation.StartSearch`: around ``initial_pose`` for the first segment
    when given, else by global matching; an offline run may look ahead).
    It runs the session's own SLAM with the map frozen (:func:`_run_segment`) until the
    track is lost: ``lost_after`` keyframes in a row matched nothing and a global placement
    of the current scan disagrees with the estimate (a kidnapping). Scans that cannot be
    placed are LOST; the next placement is searched after them.
    """
    from iceg.continuation import StartSearch, next_search
    from iceg_common.errors import SessionError

    n = len(scans)
    poses = np.full((n, 3), np.nan)
    covs = np.full((n, 3, 3), np.nan)
    status = np.full(n, int(Status.LOST), dtype=np.int64)
    corr = np.full(n, np.nan)
    relocalizations = 0
    guess = None if initial_pose is None else np.asarray(initial_pose, dtype=np.float64)
    search = StartSearch(fixed, scans, st)
    i = 0
    while i < n:
        try:
            first, placed, placement = search.place(i, guess)
        except SessionError as exc:
            after = next_search(scans, i)
            logger.info("scans %d-%d not placed: %s", i, after - 1, exc)
            guess, i = None, after
            continue
        relocalizations += guess is None or _far(placement.pose, guess, st)
        guess = None
        out = (poses, covs, status, corr)
        i = _run_segment(fixed, scans, (first, placed), placement, st, out)
    return _result(scans, poses, covs, status, corr, relocalizations)


def _frozen_slam(fixed: FixedMap) -> Slam:
    """The session loaded in memory with each of its nodes held by a prior at its saved
    estimate (``graph.prior_sigma_*``, the gauge prior's sigmas): the frozen map. It adds a
    node per keyframe (``slam.reuse_nodes`` off).

    The saved estimates are the run's final ones (``Session.node_poses``: the trajectory and
    map it exported, and the frame of the global placements), not the online ones that
    :func:`iceg.session.load` replays so that a continued run is the uninterrupted one; on
    MIT CSAIL those lie 0.15 m from the final ones at the median.

    Its loop-closure search starts from half the matcher's tracking bounds
    (``matching.validation.tracking_max_*``) instead of the run's ``search_radius_m`` and
    ``max_rotation_deg`` (2 m, 30°, for an estimate that may have drifted; wider than tracking,
    they always ask for the global evidence). The search grows them by ``search_n_sigma``
    marginal sigmas, so while the track's uncertainty fills less than the other half, a
    closure to the map is a tracking match (:meth:`~iceg.matching.IceMatcher.is_strict`: one
    feature pair, the bounded correlation), as tracking against the map is; an uncertain
    track still needs the global evidence. The chi-square gate and the kernels are the run's.
    """
    from iceg import session as sess

    if fixed.session is None:
        raise GraphError("a frozen map needs a map read from a saved session")
    slam = sess.load(fixed.session.path)
    tracking = slam.config.matching.validation
    closing = slam.config.loop_closure.model_copy(
        update={
            "search_radius_m": 0.5 * tracking.tracking_max_translation_m,
            "max_rotation_deg": 0.5 * tracking.tracking_max_rotation_deg,
        }
    )
    # Every keyframe a node: the segment's statuses, covariances and kidnapping checks are
    # read off its own nodes (a scan hanging from a map node would have none).
    slam.config = slam.config.model_copy(
        update={
            "slam": slam.config.slam.model_copy(update={"reuse_nodes": False}),
            "loop_closure": closing,
        }
    )
    slam.loop_closer.config = closing
    ids, saved = fixed.session.node_poses  # final estimates (the loaded graph's: online)
    g = slam.config.graph
    hold = np.diag([g.prior_sigma_xy_m**2] * 2 + [g.prior_sigma_theta_rad**2])
    for i, pose in zip(ids.tolist(), saved, strict=True):
        slam.graph.add_prior(i, pose, hold)
    slam.graph.update()
    return slam


def _run_segment(
    fixed: FixedMap,
    scans: Sequence[LaserScan],
    span: tuple[int, int],
    placement: Placement,
    st: LocalizeSettings,
    out: tuple[FloatArray, FloatArray, IntArray, FloatArray],
) -> int:
    """One segment, from scan ``first`` to the placed scan ``placed`` (``span``) and on,
    against the frozen map. The placed scan starts the segment
    (:meth:`iceg.slam.Slam.start_segment`; the scans before it are tracked backwards from it):
    the run's SLAM (local matching against the segment's recent nodes, loop closures to its
    own nodes and to the map's, batch refinement) in a copy of the session whose nodes are
    held fixed (:func:`_frozen_slam`; discarded after: the saved map is not changed). Fills
    ``out`` = (poses, covs, status, correlation) for the segment's scans and returns the
    stop index (the scan where the track was found lost, or the log's end).

    Poses are the refined estimates (map frame); covariances the nodes' marginals, a scan
    between nodes its node's moved by the odometry since (grown by the odometry noise).
    Status: PLACED (first scan), TRACKED (a node with a closure to a map node), LOCAL (a node
    with a local match), PREDICTED (no match; scans between nodes).
    """
    slam = _frozen_slam(fixed)
    ids, saved = slam.graph.estimates()
    n_map = int(ids.max()) + 1
    live = FixedMap(ids, saved, slam.feature_map, slam.config)
    first, placed = span
    feats = extract(scans[placed], slam.config.features)
    bounds = MatchBounds.local(st.track_translation_m, st.track_rotation_deg)
    p = live.match_at(feats, placement.pose, bounds, st.reference_nodes)
    if p is None:  # the placement's match was made in the saved map, not this live copy
        anchor, ref = live.reference_near(placement.pose, st.reference_nodes)
        rel = se2.between(saved[anchor], placement.pose)
        p = Placement(
            int(ids[anchor]),
            ref,
            dataclasses.replace(placement.match, pose=rel),
            placement.pose,
        )
    saved_scans = slam.export_state().scans
    n_before = len(saved_scans)
    # The map's time-validity needs scans after its own: a log recorded before the map (or
    # overlapping it) is shifted in time as a whole, which changes nothing else.
    shift = max(0.0, saved_scans[-1].stamp_s - scans[first].stamp_s) if saved_scans else 0.0
    before = [_shifted(scan, shift) for scan in scans[first:placed]]
    slam.start_segment(_shifted(scans[placed], shift), p.anchor, p.match, before=before)
    stop = _track_segment(slam, fixed, scans, placed, shift, st)
    _fill_segment(slam, placement, span, stop, (n_before, n_map), out)
    return stop


def _track_segment(
    slam: Slam,
    fixed: FixedMap,
    scans: Sequence[LaserScan],
    first: int,
    shift: float,
    st: LocalizeSettings,
) -> int:
    """Run the frozen-map SLAM on the scans after ``first`` (stamps shifted by ``shift``
    seconds) until a kidnapping is confirmed; return the stop index (the first scan of the
    confirming placements, or the log's end). Every ``check_every_nodes`` nodes, and while
    keyframes go unmatched, the scan is also placed globally in ``fixed``, unless the
    keyframe has just closed a loop to a map node: the map has confirmed the track there
    (a kidnapped robot's scans do not match the map where its track is)."""
    fails, stop, checked = 0, len(scans), 0
    chi2 = slam.config.loop_closure.consistency_chi2
    n_map = int(fixed.ids.max()) + 1  # the map's nodes; the segment's come after them
    doubts: list[tuple[int, FloatArray, Placement]] = []  # placements against the track
    for j in range(first + 1, len(scans)):
        n_nodes, n_factors = slam.graph.n_nodes, slam.graph.n_factors
        slam.process(_shifted(scans[j], shift))
        if slam.graph.n_nodes == n_nodes:
            continue
        added = slam.graph.factors[n_factors:]
        matched = any(f.kind in (FactorKind.SCAN_MATCH, FactorKind.LOOP_CLOSURE) for f in added)
        fails = 0 if matched else fails + 1
        checked += 1
        unmatched = fails >= st.lost_after and (fails - st.lost_after) % st.lost_retry_scans == 0
        if not (unmatched or checked % st.check_every_nodes == 0):
            continue
        if any(
            f.kind is FactorKind.LOOP_CLOSURE and f.j is not None and f.i < n_map <= f.j
            for f in added
        ):
            # the track closed to the map just now, where it is: no global check needed
            doubts.clear()
            continue
        node = slam.graph.n_nodes - 1
        est = slam.graph.estimate(node)
        again = fixed.place(extract(scans[j], slam.config.features), st)
        if again is None:
            continue
        if not _elsewhere(est, slam.graph.marginal_covariance(node), again, chi2, st):
            doubts.clear()
            continue
        doubts.append((j, est, again))
        if _kidnapped(doubts[-st.confirm_keyframes :], st.confirm_keyframes, chi2):
            stop = doubts[-st.confirm_keyframes][0]
            logger.info("scans %d-%d: placed in the map away from the track: lost", stop, j)
            break
    return stop


def _fill_segment(
    slam: Slam,
    placement: Placement,
    span: tuple[int, int],
    stop: int,
    counts: tuple[int, int],
    out: tuple[FloatArray, FloatArray, IntArray, FloatArray],
) -> None:
    """Finish the segment's SLAM and write the poses, covariances, status and correlation of
    scans ``first``..``stop - 1`` into ``out`` (see :func:`_run_segment`; ``span`` is
    ``(first, placed)``). ``counts`` are the session's scans and nodes before the segment."""
    first, placed = span
    n_before, n_map = counts
    result = slam.finish()
    poses, covs, status, corr = out
    poses[first:stop] = result.poses[n_before : n_before + stop - first]
    node_row = np.searchsorted(result.node_scan_index, np.arange(len(result.poses)), "right") - 1
    # the scans before the placed one hang off the segment's first node
    node_row[n_before : n_before + placed - first] = node_row[n_before + placed - first]
    seg_nodes = result.node_ids[node_row[n_before : n_before + stop - first]]
    to_map: dict[int, float] = {}
    local: set[int] = set()
    for f in result.factors:
        if f.j is None or f.j < n_map:
            continue
        if f.kind is FactorKind.LOOP_CLOSURE and f.i < n_map:
            to_map[f.j] = result.correlations.get(f.index, np.nan)
        elif f.kind is FactorKind.SCAN_MATCH:
            local.add(f.j)
    marg: dict[int, FloatArray] = {}
    for r, node in enumerate(seg_nodes.tolist()):
        if node not in marg:
            marg[node] = slam.graph.marginal_covariance(node)
        row = node_row[n_before + r]
        delta = se2.between(result.node_poses[row], result.poses[n_before + r])
        ad = se2.adjoint(se2.inverse(delta))
        q = odometry_covariance(delta, slam.config.odometry_noise)
        covs[first + r] = ad @ marg[node] @ ad.T + q
        is_node = result.node_scan_index[row] == n_before + r
        if first + r == placed:
            status[placed], corr[placed] = int(Status.PLACED), placement.match.correlation
        elif is_node and node in to_map:
            status[first + r], corr[first + r] = int(Status.TRACKED), to_map[node]
        elif is_node and node in local:
            status[first + r] = int(Status.LOCAL)
        else:
            status[first + r] = int(Status.PREDICTED)


def _kidnapped(doubts: list[tuple[int, FloatArray, Placement]], need: int, chi2: float) -> bool:
    """``need`` global placements against the track that agree with each other: each
    consecutive pair's relative pose matches the track's relative motion between the two
    scans (short, hence accurate even when the track is in the wrong place) within the
    ``chi2`` gate under the two placements' covariances."""
    if len(doubts) < need:
        return False
    for (_, e1, p1), (_, e2, p2) in itertools.pairwise(doubts):
        d = se2.between(se2.between(e1, e2), se2.between(p1.pose, p2.pose))
        rel = se2.between(p1.pose, p2.pose)
        ad = se2.adjoint(se2.inverse(rel))
        s = ad @ p1.match.cov @ ad.T + p2.match.cov
        try:
            if float(d @ np.linalg.solve(s, d)) > chi2:
                return False
        except np.linalg.LinAlgError:
            return False
    return True


def _elsewhere(
    pose: FloatArray, cov: FloatArray, p: Placement, chi2: float, st: LocalizeSettings
) -> bool:
    """A global placement says the robot is elsewhere than its track (a doubt of the
    kidnapping check): at a place distinct from the estimate ``pose`` (:func:`distinct_places`)
    and beyond the ``chi2`` gate under both covariances (:func:`_agrees`; ``cov`` body frame).
    A placement at the same place is no kidnapping, however confident the two covariances:
    a track 0.15 m from the map's placements with a sigma of 1.5 cm (the frozen map at the
    online estimates, twenty-eighth session) was declared carried away on MIT CSAIL."""
    return distinct_places(pose, p.pose, st) and not _agrees(pose, cov, p, chi2)


def _far(pose: FloatArray, guess: FloatArray, st: LocalizeSettings) -> bool:
    """A placement outside the initial pose's bounds (found by the global search)."""
    d = se2.between(guess, pose)
    return bool(
        np.hypot(d[0], d[1]) > st.initial_translation_m
        or abs(d[2]) > np.radians(st.initial_rotation_deg)
    )


def _shifted(scan: LaserScan, shift_s: float) -> LaserScan:
    return dataclasses.replace(scan, stamp_s=scan.stamp_s + shift_s) if shift_s else scan


def _agrees(pose: FloatArray, cov: FloatArray, p: Placement, chi2: float) -> bool:
    """A placement agrees with an estimate ``pose`` of covariance ``cov`` (body frame): its
    innovation is within the ``chi2`` gate under both covariances."""
    e = se2.between(pose, p.pose)
    ad = se2.adjoint(se2.inverse(e))
    s = ad @ cov @ ad.T + p.match.cov
    try:
        return float(e @ np.linalg.solve(s, e)) <= chi2
    except np.linalg.LinAlgError:
        return False


def fixed_map_of_session(session: Session) -> FixedMap:
    """A saved session's map (saved estimates and feature map) as a :class:`FixedMap`."""
    ids, poses = session.node_poses
    fixed = FixedMap(ids, poses, session.feature_map(), session.config)
    fixed.session = session
    return fixed


def localization_rows(result: LocalizationResult) -> list[list[object]]:
    """Rows of ``localization.csv``: stamp, pose, covariance upper triangle, status, corr."""
    iu = np.triu_indices(3)
    return [
        [t, *p, *c[iu], Status(int(s)).name.lower(), r]
        for t, p, c, s, r in zip(
            result.stamps_s,
            result.poses,
            result.covs,
            result.status,
            result.correlations,
            strict=True,
        )
    ]


#: Columns of ``localization.csv`` (pose in the map frame; covariance in its body frame).
LOCALIZATION_COLUMNS = (
    "stamp_s",
    "x_m",
    "y_m",
    "theta_rad",
    "cov_xx",
    "cov_xy",
    "cov_xt",
    "cov_yy",
    "cov_yt",
    "cov_tt",
    "status",
    "correlation",
)


def save_localization(
    result: LocalizationResult,
    session: Session,
    out: str | Path,
    render_map: bool = True,
    metrics: Mapping[str, Any] | None = None,
) -> Path:
    """Write ``trajectory.tum`` (localized scans only), ``localization.csv`` (every scan,
    with covariance and status), ``metrics.json`` (with the entries of ``metrics``, e.g.
    the odometry time offset read) and ``map.png`` (the session's map with the new
    trajectory drawn over it) into ``out``, each atomically.

    Raises:
        OSError: the folder cannot be written.
        SessionError: the session's scans cannot be re-read for the map.
    """
    from frontends.tum import write_tum
    from iceg.grid import render_tiled, write_png
    from iceg.session import read_scans

    folder = Path(out)
    folder.mkdir(parents=True, exist_ok=True)
    ok = ~np.isnan(result.poses[:, 0])
    write_tum(folder / "trajectory.tum", result.stamps_s[ok], result.poses[ok])
    with atomic_write(folder / "localization.csv") as fh:
        fh.write(",".join(LOCALIZATION_COLUMNS) + "\n")
        for row in localization_rows(result):
            fh.write(",".join(v if isinstance(v, str) else repr(float(v)) for v in row) + "\n")  # type: ignore[arg-type]
    with atomic_write(folder / "metrics.json") as fh:
        json.dump(
            {
                "status": result.summary,
                "relocalizations": result.relocalizations,
                "session": str(session.path.resolve()),
                **(metrics or {}),
            },
            fh,
            indent=2,
        )
        fh.write("\n")
    if render_map:
        _, poses = session.trajectory()
        grid = render_tiled(
            read_scans(session),
            poses,
            session.config.grid,
            range_min_m=session.config.features.robot_body_range_m,
        )
        write_png(grid, folder / "map.png", trajectory=result.poses[ok])
    return folder
