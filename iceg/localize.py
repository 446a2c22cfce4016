"""Localization in a saved map, and placing a new log in it (``iceg localize``, ``iceg run
--continue``; issue 15).

The map is fixed: the session's node poses and feature map are read, nothing is added. Each
keyframe of the new log is ICE-matched against the landmarks of the map nodes nearest its
predicted pose (odometry from the last matched pose); its pose is ``anchor ∘ match`` with the
match covariance, and scans between keyframes follow odometry with the covariance grown by the
odometry noise. When no pose is known (start without an initial pose, or after
``lost_after`` failed keyframes: a kidnapping, dropped scans) the keyframe is matched
globally (no prediction, unbounded rotation) against candidate places spread over the map;
a global placement is only trusted after ``confirm_keyframes`` consecutive tracked keyframes.

Frames: poses ``[x_m, y_m, theta_rad]`` in the map frame of the session; covariances ``(3, 3)``
in the tangent space of the pose (body frame, gtsam convention), m² / rad².
"""

from __future__ import annotations

import json
import logging
from collections.abc import Sequence
from dataclasses import dataclass, field
from enum import IntEnum
from pathlib import Path

import numpy as np
from numpy.typing import NDArray

from frontends import LaserScan
from graph import odometry_covariance
from iceg.config import IcegConfig
from iceg.feature_map import FeatureMap, MapReference
from iceg.features import extract
from iceg.matching import IceMatcher, MatchBounds
from iceg.session import Session
from iceg.types import MatchResult, ScanFeatures
from iceg_common import se2
from iceg_common.atomic import atomic_write

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class Status(IntEnum):
    """How a scan's pose was obtained."""

    LOST = 0  # no pose known (before the first placement); pose NaN
    PREDICTED = 1  # odometry from the last matched pose
    TRACKED = 2  # a local match against the map
    PLACED = 3  # a global match (tentative until confirmed)


@dataclass(frozen=True)
class LocalizeSettings:
    """Tuning of localization (not part of the run configuration).

    Attributes:
        reference_nodes: map nodes nearest the predicted pose whose landmarks are matched.
        track_translation_m / track_rotation_deg: bounds of a tracking match.
        initial_translation_m / initial_rotation_deg: bounds around a given initial pose.
        min_correlation: least ICE correlation (eq. 1) of an accepted match.
        lost_after: failed tracking keyframes before a global search.
        min_fit: least fraction of a globally placed scan's points (within the map's
            reach) lying within ``fit_tolerance_m`` of a map segment.
        ambiguity_margin: a global placement is refused when a distinct place (more than
            ``distinct_place_m`` away) matches within this correlation of the best.
        confirm_keyframes: tracked keyframes that confirm a global placement.
        candidate_spacing_m: global search: one candidate place per square of this side.
        keyframe_distance_m / keyframe_rotation_deg: odometry motion between matched scans.
        max_global_tries: global searches before giving up (bounds the cost of a log
            outside the map).
        lost_retry_scans: a lost robot searches globally every this many scans.
    """

    reference_nodes: int = 12
    track_translation_m: float = 1.0
    track_rotation_deg: float = 20.0
    initial_translation_m: float = 2.0
    initial_rotation_deg: float = 45.0
    min_correlation: float = 0.5
    lost_after: int = 6
    confirm_keyframes: int = 3
    min_fit: float = 0.6
    fit_tolerance_m: float = 0.15
    ambiguity_margin: float = 0.1
    distinct_place_m: float = 1.0
    candidate_spacing_m: float = 1.5
    keyframe_distance_m: float = 0.5
    keyframe_rotation_deg: float = 15.0
    max_global_tries: int = 1_000_000
    lost_retry_scans: int = 5


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
        anchor, ref = self.reference_near(pose, k)
        prediction = se2.between(self.poses[anchor], pose)
        res = self.matcher.match(feats, ref.features, prediction, bounds)
        if not res.success:
            return None
        return Placement(int(self.ids[anchor]), ref, res, se2.compose(self.poses[anchor], res.pose))

    def place(self, feats: ScanFeatures, settings: LocalizeSettings) -> Placement | None:
        """Global placement: the scan matched (no prediction) against every candidate place.

        The best match by correlation is returned when it reaches ``min_correlation``, its
        points fit the map's segments (:func:`segment_fit` ``>= min_fit``), and no distinct
        place matches almost as well (``ambiguity_margin``); otherwise None (never a guess).
        """
        st = settings
        found = []
        for row in self.candidates(st.candidate_spacing_m).tolist():
            p = self.match_at(feats, self.poses[row], MatchBounds.global_(), st.reference_nodes)
            if (
                p is not None
                and p.match.correlation >= st.min_correlation
                and segment_fit(feats, p, st.fit_tolerance_m) >= st.min_fit
            ):
                found.append(p)
        found.sort(key=lambda p: -p.match.correlation)
        if not found:
            return None
        best = found[0]
        for other in found[1:]:
            d = se2.between(best.pose, other.pose)
            distinct = np.hypot(d[0], d[1]) > st.distinct_place_m or abs(d[2]) > np.radians(10)
            if distinct and other.match.correlation >= best.match.correlation - st.ambiguity_margin:
                logger.info(
                    "global placement ambiguous (%.2f vs %.2f)",
                    best.match.correlation,
                    other.match.correlation,
                )
                return None
        return best


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
        poses: ``(R, 3)`` map-frame poses (NaN while lost).
        covs: ``(R, 3, 3)`` pose covariances, body frame (NaN while lost).
        status: ``(R,)`` int64 :class:`Status` values.
        correlations: ``(R,)`` ICE correlation of the scan's match (NaN: not matched).
    """

    stamps_s: FloatArray
    poses: FloatArray
    covs: FloatArray
    status: IntArray
    correlations: FloatArray
    relocalizations: int = 0
    summary: dict[str, float] = field(default_factory=dict)


@dataclass
class _Track:
    pose: FloatArray | None = None
    cov: FloatArray = field(default_factory=lambda: np.full((3, 3), np.nan))
    odom: FloatArray | None = None  # odometry of the last scan
    since_match: FloatArray = field(default_factory=lambda: np.zeros(3))  # odometry motion
    fails: int = 0
    tentative: int = 0  # >0: confirmations still needed after a global placement
    global_tries: int = 0
    lost_scans: int = 0  # scans since the robot was lost


class Localizer:
    """Scan-by-scan localization in a :class:`FixedMap` (nothing is added to the map).

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

    def process(self, scan: LaserScan) -> tuple[FloatArray, FloatArray, Status, float]:
        """One scan: ``(pose (3,), cov (3, 3), status, correlation)``."""
        t = self._t
        delta, q = self._odometry_step(scan)
        if t.pose is not None:
            ad = se2.adjoint(se2.inverse(delta))
            t.pose, t.cov = se2.compose(t.pose, delta), ad @ t.cov @ ad.T + q
        t.since_match = se2.compose(t.since_match, delta)
        if not self._keyframe(scan):
            return self._out(Status.PREDICTED if t.pose is not None else Status.LOST, np.nan)
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
        t.odom = odom
        cfg = self.fixed.config
        if usable:
            return delta, odometry_covariance(delta, cfg.odometry_noise)
        s = cfg.slam
        q = np.diag([s.no_odometry_sigma_m**2] * 2 + [np.radians(s.no_odometry_sigma_deg) ** 2])
        return delta, q

    def _keyframe(self, scan: LaserScan) -> bool:
        t, st = self._t, self.settings
        d = t.since_match
        moved = np.hypot(d[0], d[1]) >= st.keyframe_distance_m or abs(d[2]) >= np.radians(
            st.keyframe_rotation_deg
        )
        if t.pose is None:  # lost: a global search every ``lost_retry_scans`` scans
            t.lost_scans += 1
            return (t.lost_scans - 1) % st.lost_retry_scans == 0
        return bool(moved or scan.odom_pose is None or t.tentative > 0)

    def _try_initial(self, feats: ScanFeatures) -> tuple[FloatArray, FloatArray, Status, float]:
        st = self.settings
        pose, self._initial = self._initial, None
        bounds = MatchBounds.local(st.initial_translation_m, st.initial_rotation_deg)
        p = self.fixed.match_at(feats, pose, bounds, st.reference_nodes)  # type: ignore[arg-type]
        if p is None or p.match.correlation < st.min_correlation:
            logger.info("the initial pose does not match the map; searching globally")
            return self._relocalize(feats)
        return self._accept(p, Status.PLACED, tentative=st.confirm_keyframes)

    def _track(self, feats: ScanFeatures) -> tuple[FloatArray, FloatArray, Status, float]:
        t, st = self._t, self.settings
        bounds = MatchBounds.local(st.track_translation_m, st.track_rotation_deg)
        p = self.fixed.match_at(feats, t.pose, bounds, st.reference_nodes)  # type: ignore[arg-type]
        if p is not None and self._good(feats, p):
            t.tentative = max(t.tentative - 1, 0)
            return self._accept(p, Status.TRACKED, t.tentative)
        t.fails += 1
        if t.tentative > 0 or t.fails >= st.lost_after:
            logger.info("lost after %d failed matches; searching globally", t.fails)
            t.pose, t.cov, t.tentative = None, np.full((3, 3), np.nan), 0
            return self._relocalize(feats)
        return self._out(Status.PREDICTED, np.nan)

    def _good(self, feats: ScanFeatures, p: Placement) -> bool:
        """A tracking match is kept when well correlated, or when its points fit the map
        (a refinement on few features, correlation 0, can still be exact)."""
        st = self.settings
        if p.match.correlation >= st.min_correlation:
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
        return self._accept(found, Status.PLACED, tentative=st.confirm_keyframes)

    def _accept(
        self, p: Placement, status: Status, tentative: int
    ) -> tuple[FloatArray, FloatArray, Status, float]:
        t = self._t
        t.pose, t.cov, t.fails, t.tentative = p.pose, p.match.cov, 0, tentative
        t.lost_scans = 0
        t.since_match = np.zeros(3)
        return self._out(status, p.match.correlation)

    def _out(self, status: Status, corr: float) -> tuple[FloatArray, FloatArray, Status, float]:
        t = self._t
        if t.pose is None:
            return np.full(3, np.nan), np.full((3, 3), np.nan), Status.LOST, np.nan
        return t.pose.copy(), t.cov.copy(), status, corr


def localize_scans(
    fixed: FixedMap,
    scans: Sequence[LaserScan],
    settings: LocalizeSettings | None = None,
    initial_pose: FloatArray | None = None,
) -> LocalizationResult:
    """Localize every scan of a log in a fixed map (see :class:`Localizer`)."""
    loc = Localizer(fixed, settings, initial_pose)
    rows = [loc.process(s) for s in scans]
    status = np.array([int(r[2]) for r in rows], dtype=np.int64)
    result = LocalizationResult(
        stamps_s=np.array([s.stamp_s for s in scans], dtype=np.float64),
        poses=np.array([r[0] for r in rows]).reshape(-1, 3),
        covs=np.array([r[1] for r in rows]).reshape(-1, 3, 3),
        status=status,
        correlations=np.array([r[3] for r in rows], dtype=np.float64),
        relocalizations=loc.relocalizations,
    )
    result.summary = {s.name.lower(): int(np.sum(status == s)) for s in Status}
    return result


def fixed_map_of_session(session: Session) -> FixedMap:
    """A saved session's map (saved estimates and feature map) as a :class:`FixedMap`."""
    ids, poses = session.node_poses
    return FixedMap(ids, poses, session.feature_map(), session.config)


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
    result: LocalizationResult, session: Session, out: str | Path, render_map: bool = True
) -> Path:
    """Write ``trajectory.tum`` (localized scans only), ``localization.csv`` (every scan,
    with covariance and status), ``metrics.json`` and ``map.png`` (the session's map with
    the new trajectory drawn over it) into ``out``, each atomically.

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
            },
            fh,
            indent=2,
        )
        fh.write("\n")
    if render_map:
        _, poses = session.trajectory()
        grid = render_tiled(read_scans(session), poses, session.config.grid)
        write_png(grid, folder / "map.png", trajectory=result.poses[ok])
    return folder
