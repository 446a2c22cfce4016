"""Data contracts between ICE feature extraction, matching, the feature map and the pipeline.

Plain arrays in frozen dataclasses; no gtsam objects. Frames are stated per field.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import IntEnum

import numpy as np
from numpy.typing import NDArray

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


class FeatureKind(IntEnum):
    """ICE feature types (paper §III-B)."""

    CORNER = 0
    EOW = 1  # end of wall
    INTERSECTION = 2


@dataclass(frozen=True, eq=False)
class ScanFeatures:
    """Line segments and ICE features of one scan (or of a map reference), in one frame.

    For a single scan the frame is the robot frame at the scan's time; for a map
    reference built by the feature map it is the frame of the chosen reference node.

    Segments (``M`` of them):
        seg_endpoints: ``(M, 2, 2)`` float64 metres; ``[m, 0]`` first, ``[m, 1]`` last
            endpoint (in beam order), both on the fitted line.
        seg_lines: ``(M, 2)`` float64 Hessian form ``(alpha_rad, rho_m)``: points ``p`` on the
            line satisfy ``p·(cos alpha, sin alpha) = rho``, ``rho >= 0``.
        seg_cov: ``(M, 2, 2)`` float64 covariance of ``(alpha, rho)``.
        seg_point_range: ``(M, 2)`` int64 ``[start, stop)`` indices into ``points_xy``
            (for a map reference, -1 where the points are not kept).

    Features (``K`` of them):
        kind: ``(K,)`` int64 :class:`FeatureKind` values.
        xy: ``(K, 2)`` float64 positions in metres.
        cov: ``(K, 2, 2)`` float64 position covariance, m².
        directions: ``(K, 2, 2)`` float64 unit vectors starting at the feature and pointing
            along its walls: Corner both edges, EOW ``[k, 0]`` its wall and ``[k, 1]`` NaN,
            Intersection both NaN.
        opening_rad: ``(K,)`` float64 angle between the two edges/lines in ``(0, pi)``; NaN
            for an EOW.
        segment_ids: ``(K, 2)`` int64 indices of the segments each feature came from
            (-1 where none).
        ids: ``(K,)`` int64 identities: ``arange(K)`` for a scan, landmark ids for a map
            reference.

    Points:
        points_xy: ``(P, 2)`` float64 valid beam endpoints (may be empty for a reference).
        range_max_m: range of the sensor used to weight features (paper eq. 3).
    """

    points_xy: FloatArray
    seg_endpoints: FloatArray
    seg_lines: FloatArray
    seg_cov: FloatArray
    seg_point_range: IntArray
    kind: IntArray
    xy: FloatArray
    cov: FloatArray
    directions: FloatArray
    opening_rad: FloatArray
    segment_ids: IntArray
    ids: IntArray
    range_max_m: float = 20.0
    stamp_s: float = 0.0

    @classmethod
    def empty(
        cls, points_xy: FloatArray | None = None, range_max_m: float = 20.0, stamp_s: float = 0.0
    ) -> ScanFeatures:
        """No segments and no features (``points_xy`` ``(P, 2)`` kept if given)."""
        return cls(
            points_xy=np.zeros((0, 2)) if points_xy is None else points_xy,
            seg_endpoints=np.zeros((0, 2, 2)),
            seg_lines=np.zeros((0, 2)),
            seg_cov=np.zeros((0, 2, 2)),
            seg_point_range=np.zeros((0, 2), dtype=np.int64),
            kind=np.zeros(0, dtype=np.int64),
            xy=np.zeros((0, 2)),
            cov=np.zeros((0, 2, 2)),
            directions=np.zeros((0, 2, 2)),
            opening_rad=np.zeros(0),
            segment_ids=np.zeros((0, 2), dtype=np.int64),
            ids=np.zeros(0, dtype=np.int64),
            range_max_m=range_max_m,
            stamp_s=stamp_s,
        )

    @property
    def n_features(self) -> int:
        """Number of features ``K``."""
        return int(self.kind.shape[0])

    @property
    def n_segments(self) -> int:
        """Number of segments ``M``."""
        return int(self.seg_endpoints.shape[0])


@dataclass(frozen=True, eq=False)
class MatchResult:
    """Outcome of one ICE match of a scan against a reference.

    Attributes:
        success: False when the matcher found no trustworthy answer (see ``reason``).
        pose: ``(3,)`` float64 pose of the new scan's robot frame in the reference frame,
            ``[x_m, y_m, theta_rad]`` (on failure: the prediction).
        cov: ``(3, 3)`` float64 covariance of ``pose`` in ``(x, y, theta)`` order, expressed
            in the tangent space at ``pose`` in the **new scan's** frame (the convention of a
            gtsam ``BetweenFactorPose2`` measurement). On failure: NaN.
        correlation: score of eq. 1 in ``[0, 1]`` of the chosen hypothesis (0 on failure).
        inlier_pairs: ``(I, 2)`` int64 ``[new feature index, reference feature index]``.
        n_hypotheses: number of transform hypotheses that were scored.
        reason: empty on success, otherwise why the match failed.
        unverified: on a tracking match's failure, its best hypothesis from the prediction
            that passed the bounds and free space and lacked only the evidence (a result
            with its pose, covariance and correlation), which a later loop closure may
            confirm (docs/design.md, "A disputed step confirmed by a loop closure"); else
            ``None``.
    """

    success: bool
    pose: FloatArray
    cov: FloatArray
    correlation: float
    inlier_pairs: IntArray = field(default_factory=lambda: np.zeros((0, 2), dtype=np.int64))
    n_hypotheses: int = 0
    reason: str = ""
    unverified: MatchResult | None = None

    @classmethod
    def failed(cls, prediction: FloatArray, reason: str, n_hypotheses: int = 0) -> MatchResult:
        """A failed match: ``pose`` a copy of the ``(3,)`` prediction, NaN covariance,
        correlation 0, no inlier pairs, and ``reason`` (its category before the first colon)."""
        return cls(
            False,
            np.array(prediction, dtype=np.float64),
            np.full((3, 3), np.nan),
            0.0,
            n_hypotheses=n_hypotheses,
            reason=reason,
        )
