"""ICE feature extraction: one laser scan in, segments and Corner / EOW / Intersection out.

docs/design.md "ICE matching, step by step", steps 1-4; paper §III-B (the features) and §III-C1
(split-and-merge with maximum-likelihood line fitting). :func:`extract` composes the stages:
points (:mod:`~iceg.features.points`), segments (:mod:`~iceg.features.segments`), steep
segment pairs (:mod:`~iceg.features.pairs`), corners (:mod:`~iceg.features.corners`), ends of
wall (:mod:`~iceg.features.ends`) and intersections (:mod:`~iceg.features.intersections`).
"""

from __future__ import annotations

import logging

import numpy as np

from frontends.scan import LaserScan
from iceg.features.config import FeatureConfig
from iceg.features.corners import Corners, find_corners
from iceg.features.ends import EndsOfWall, find_ends_of_wall
from iceg.features.intersections import Intersections, find_intersections
from iceg.features.pairs import meeting_pairs
from iceg.features.points import BeamPoints, beam_points, check_bearings
from iceg.features.segments import Segments, line_segments
from iceg.types import FeatureKind, ScanFeatures

log = logging.getLogger(__name__)


def extract(scan: LaserScan, config: FeatureConfig | None = None) -> ScanFeatures:
    """Segments and ICE features (Corner, End of wall, Intersection) of one scan.

    Steps (docs/design.md "ICE matching, step by step", 1-4):

    1. Valid beams (``range_min < r < min(range_max, config.range_max_m)``) to robot-frame
       points, laser offset applied; beams at or beyond the usable range are "no return"
       (:func:`~iceg.features.points.beam_points`).
    2. Clusters by adaptive breakpoints (Borges & Aldon 2004), also broken at invalid beams;
    3. split-and-merge inside clusters (paper §III-C1, Nguyen et al. 2005), segments refit
       by maximum-likelihood weighted total least squares in Hessian form with covariances
       (Pfister et al. 2003; Arras & Siegwart 1997); short segments are dropped
       (:func:`~iceg.features.segments.line_segments`).
    4. Features (paper §III-B, Fig. 1-2) from the segment pairs meeting at 30°-150°
       (:func:`~iceg.features.pairs.meeting_pairs`): Corners
       (:func:`~iceg.features.corners.find_corners`), ends of wall
       (:func:`~iceg.features.ends.find_ends_of_wall`) and Intersections
       (:func:`~iceg.features.intersections.find_intersections`); the thresholds are the
       :class:`FeatureConfig` fields, documented there.

    Work and memory are linear in the number of beams and segments: feature tests only
    relate segments within a bounded neighbourhood (issue 12).

    Args:
        scan: One laser scan.
        config: Thresholds; defaults to :class:`FeatureConfig`.

    Returns:
        :class:`~iceg.types.ScanFeatures` in the robot frame of the scan: features ordered
        corners, then EOWs, then intersections; ``ids = arange(K)``.

    Raises:
        ScanError: the scan's beams are not in strictly increasing bearing order.
    """
    cfg = FeatureConfig() if config is None else config
    beams = extract_beams(scan, cfg)
    range_max = beams.range_max
    stamp = float(scan.stamp_s)
    if beams.points.shape[0] < cfg.min_segment_points:
        return ScanFeatures.empty(beams.points, range_max, stamp)
    segs = line_segments(beams, cfg)
    if segs.lines.shape[0] == 0:
        return ScanFeatures.empty(beams.points, range_max, stamp)
    pairs = meeting_pairs(segs, cfg)
    corners = find_corners(segs, pairs, cfg)
    eows = find_ends_of_wall(beams, segs, corners.endpoint_mask(segs.lines.shape[0]), cfg)
    inters = find_intersections(beams, segs, pairs, corners, cfg)
    if log.isEnabledFor(logging.DEBUG):
        log.debug(
            "%s: %d points, %d segments, %d corners, %d EOWs, %d intersections",
            scan.source,
            beams.points.shape[0],
            segs.lines.shape[0],
            corners.xy.shape[0],
            eows.xy.shape[0],
            inters.xy.shape[0],
        )
    return assemble(beams.points, segs, (corners, eows, inters), range_max, stamp)


def extract_points(scan: LaserScan, config: FeatureConfig | None = None) -> np.ndarray:
    """The scan's points as :func:`extract` gives them (``ScanFeatures.points_xy``, the same
    array bit for bit) without the segments and features: step 1 alone, for a node whose
    points are needed again (a point match against it, an offline second match).

    Args:
        scan: One laser scan.
        config: Thresholds (only ``range_max_m``, ``robot_body_range_m`` and
            ``robot_body_dark_deg`` are read); defaults to
            :class:`FeatureConfig`.

    Returns:
        ``(P, 2)`` float64 valid beam endpoints, metres, robot frame.

    Raises:
        ScanError: the scan's beams are not in strictly increasing bearing order.
    """
    return extract_beams(scan, config).points


def extract_beams(scan: LaserScan, config: FeatureConfig | None = None) -> BeamPoints:
    """The scan's beams as :func:`extract`'s step 1 reads them: which are points, which are
    no-returns (the usable range, the robot's body and its dark bearings applied), and the
    points themselves (robot frame).

    Args:
        scan: One laser scan.
        config: Thresholds (only ``range_max_m``, ``robot_body_range_m`` and
            ``robot_body_dark_deg`` are read); defaults to :class:`FeatureConfig`.

    Raises:
        ScanError: the scan's beams are not in strictly increasing bearing order.
    """
    cfg = FeatureConfig() if config is None else config
    check_bearings(scan)
    range_max = float(min(cfg.range_max_m, scan.range_max_m))
    return beam_points(scan, range_max, _range_min(scan, cfg), _dark_body(cfg))


def _range_min(scan: LaserScan, cfg: FeatureConfig) -> float:
    """A beam is a point only beyond this range: the scan's ``range_min_m``, or the robot's
    own body (``cfg.robot_body_range_m``) where that reaches farther."""
    return float(max(scan.range_min_m, cfg.robot_body_range_m))


def _dark_body(cfg: FeatureConfig) -> np.ndarray | None:
    """``cfg.robot_body_dark_deg`` as ``(K, 2)`` float64 radians, or None where empty."""
    if not cfg.robot_body_dark_deg:
        return None
    return np.radians(np.array(cfg.robot_body_dark_deg, dtype=np.float64).reshape(-1, 2))


#: The feature kinds in :func:`assemble`'s order.
_KINDS = np.array([FeatureKind.CORNER, FeatureKind.EOW, FeatureKind.INTERSECTION], dtype=np.int64)


def assemble(
    points: np.ndarray,
    segs: Segments,
    features: tuple[Corners, EndsOfWall, Intersections],
    range_max_m: float,
    stamp_s: float,
) -> ScanFeatures:
    """Concatenate corners, then EOWs, then intersections into :class:`ScanFeatures`.

    Args:
        points: ``(P, 2)`` float64 the scan's points, metres, robot frame.
        segs: Its M segments.
        features: The three feature stages' outputs.
        range_max_m: Usable maximum range, metres.
        stamp_s: Scan time, seconds.

    Returns:
        :class:`ScanFeatures` with ``ids = arange(K)``; an EOW's second segment id is -1,
        its direction ``[1]`` and opening NaN; an Intersection's directions are NaN.
    """
    corners, eows, inters = features
    n_c, n_e, n_i = corners.xy.shape[0], eows.xy.shape[0], inters.xy.shape[0]
    kind = np.repeat(_KINDS, [n_c, n_e, n_i])
    eow_ids = np.stack([eows.seg, np.full(n_e, -1, dtype=np.int64)], axis=1)
    return ScanFeatures(
        points_xy=points,
        seg_endpoints=segs.endpoints,
        seg_lines=segs.lines,
        seg_cov=segs.cov,
        seg_point_range=segs.point_range,
        kind=kind,
        xy=np.concatenate([corners.xy, eows.xy, inters.xy]),
        cov=np.concatenate([corners.cov, eows.cov, inters.cov]),
        directions=np.concatenate([corners.dirs, eows.dirs, np.full((n_i, 2, 2), np.nan)]),
        opening_rad=np.concatenate([corners.opening, np.full(n_e, np.nan), inters.opening]),
        segment_ids=np.concatenate([corners.pairs, eow_ids, inters.pairs]),
        ids=np.arange(kind.shape[0], dtype=np.int64),
        range_max_m=range_max_m,
        stamp_s=stamp_s,
    )
