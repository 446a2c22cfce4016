"""Point-to-line ICP (PL-ICP, Censi 2008) on the project's own refinement.

The new scan's points are matched against the reference's points; each reference point
carries the local line through its beam neighbours (:func:`reference_cloud`), so a residual
is the distance of a new point to that line (an isolated reference point gives a
point-to-point residual). The Gauss-Newton loop, the Cauchy weights, the bounds' prior and
the covariance (Olson 2009 lattice floored by least squares) are those of
:mod:`iceg.matching.refine`, used with no segments and no feature pairs. When the
reference keeps no points (a feature-map reference by default), its segments are sampled.

:func:`lattice_covariance` gives the same covariance at any final pose: the peers whose
library exposes no Hessian use it.
"""

from __future__ import annotations

import dataclasses
import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg.matching._kernels import (
    PointCloud,
    PosePrior,
    SegmentPoints,
    cloud_nearest,
    local_lines,
)
from iceg.matching.config import MatchBounds, MatchingConfig
from iceg.matching.geometry import SegmentSet, feature_geometry, rot
from iceg.matching.matcher import _refine_settings, largest_std_exceeds
from iceg.matching.refine import (
    RefineProblem,
    RefineSettings,
    _covariances_at,
    bounds_prior_information,
    build_cloud,
    no_feature_pairing,
    points_within,
    refine,
)
from iceg.types import MatchResult, ScanFeatures
from iceg_common.errors import MatchingError
from iceg_common.se2 import wrap_angle

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Spacing (metres) of the points sampled along reference segments when it has no points.
SEGMENT_SAMPLE_M = 0.05
#: A reference with fewer points than this is replaced by its sampled segments.
MIN_REFERENCE_POINTS = 20
#: Association gate (metres) of the first PL-ICP pass (wide: pulls a prediction in).
COARSE_GATE_M = 0.5
#: The final gate is this many estimated point sigmas (at least the refinement's minimum).
FINE_GATE_SIGMAS = 4.0
#: Robust sigma from the median absolute residual.
MAD_TO_SIGMA = 1.4826
#: A new point is an inlier (overlap) when it lies this close (metres) to the reference.
INLIER_DISTANCE_M = 0.15
#: Least overlap (fraction of the new points that are inliers) of a successful match.
MIN_OVERLAP = 0.35
#: Allowance (metres, degrees) added to the bounds when checking the final pose.
BOUNDS_MARGIN_M = 0.3
BOUNDS_MARGIN_DEG = 8.0
#: Least number of new points for a match.
MIN_POINTS = 10


def reference_points(reference: ScanFeatures) -> FloatArray:
    """``(R, 2)`` points of the reference: its own points, or (fewer than
    :data:`MIN_REFERENCE_POINTS`) points every :data:`SEGMENT_SAMPLE_M` along its
    segments, in segment order."""
    if reference.points_xy.shape[0] >= MIN_REFERENCE_POINTS or reference.n_segments == 0:
        return np.asarray(reference.points_xy, dtype=np.float64).reshape(-1, 2)
    out = []
    for a, b in np.asarray(reference.seg_endpoints, dtype=np.float64):
        n = max(2, math.ceil(math.hypot(*(b - a)) / SEGMENT_SAMPLE_M) + 1)
        t = np.linspace(0.0, 1.0, n)[:, None]
        out.append(a + t * (b - a))
    return np.concatenate(out)


def subsample(points: FloatArray, max_points: int) -> FloatArray:
    """At most ``max_points`` of ``points`` ``(P, 2)``, evenly spread, order kept."""
    if points.shape[0] <= max_points:
        return points
    return points[np.linspace(0, points.shape[0] - 1, max_points).astype(np.int64)]


def reference_cloud(
    new_points: FloatArray, ref_points: FloatArray, config: MatchingConfig, cell_m: float
) -> PointCloud:
    """The PL-ICP rows' data: the new points against the reference points with the normals
    of their local lines (through beam neighbours within ``local_line_max_gap_m``)."""
    spacing, normal = local_lines(
        np.ascontiguousarray(ref_points, dtype=np.float64), config.refinement.local_line_max_gap_m
    )
    return build_cloud(new_points, ref_points, spacing, normal, cell_m)


def plicp_problem(
    new_points: FloatArray,
    ref_points: FloatArray,
    prediction: FloatArray,
    bounds: MatchBounds,
    config: MatchingConfig,
) -> RefineProblem:
    """A :class:`~iceg.matching.refine.RefineProblem` with PL-ICP rows only: no segments,
    no feature pairs, the bounds' prior centred on the prediction."""
    settings = dataclasses.replace(
        _refine_settings(config), gate_m=max(COARSE_GATE_M, config.refinement.association_gate_m)
    )
    empty = ScanFeatures.empty()
    geom = feature_geometry(empty)
    prior = PosePrior(
        prediction, bounds_prior_information(bounds.max_translation_m, bounds.max_rotation_rad)
    )
    return RefineProblem(
        SegmentPoints(np.zeros((0, 2)), np.zeros(0)),
        SegmentSet.from_features(empty),
        np.zeros((0, 2, 2)),
        geom,
        geom,
        no_feature_pairing(),
        prior,
        reference_cloud(new_points, ref_points, config, settings.gate_m),
        settings,
    )


def point_residuals(problem: RefineProblem, pose: FloatArray, gate_m: float) -> FloatArray:
    """Residuals (metres) of the new points associated within ``gate_m`` at ``pose``:
    distance to the local line, or point distance over sqrt 2 for an isolated point."""
    cloud = problem.cloud
    near = cloud_nearest(pose, cloud, gate_m)
    ok = near >= 0
    if not np.any(ok):
        return np.zeros(0)
    idx = near[ok]
    e = cloud.points[ok] @ rot(pose[2]).T + pose[:2] - cloud.ref_points[idx]
    nrm = cloud.ref_normal[idx]
    line = np.isfinite(nrm[:, 0])
    r = np.where(line, np.einsum("na,na->n", np.nan_to_num(nrm), e), 0.0)
    r[~line] = np.hypot(e[~line, 0], e[~line, 1]) / math.sqrt(2.0)
    return np.asarray(r, dtype=np.float64)


def robust_sigma(problem: RefineProblem, pose: FloatArray) -> float:
    """Point noise (metres) from the median absolute residual at ``pose``, floored."""
    s = problem.settings
    r = point_residuals(problem, pose, s.gate_m)
    if r.shape[0] < 3:
        return float(s.gate_m / 3.0)
    return max(s.sigma_min_m, MAD_TO_SIGMA * float(np.median(np.abs(r))))


def lattice_covariance(problem: RefineProblem, pose: FloatArray) -> FloatArray:
    """Covariance ``(3, 3)`` at a final ``pose`` in the tangent space at the pose in the new
    scan's frame (gtsam ``Pose2`` local coordinates): the Olson 2009 lattice of the PL-ICP
    rows floored by their least-squares covariance (:mod:`iceg.matching.refine`), with the
    point noise estimated at ``pose``. Infinite where the rows leave it singular."""
    s: RefineSettings = problem.settings
    sigma = robust_sigma(problem, pose)
    gate = min(s.gate_m, max(s.gate_min_m, FINE_GATE_SIGMAS * sigma))
    _, cov_ref = _covariances_at(problem, pose, gate, sigma)
    return to_body(cov_ref, float(pose[2]))


def to_body(cov_ref: FloatArray, theta: float) -> FloatArray:
    """A covariance of ``(x, y, theta)`` perturbations in the reference frame moved to the
    new scan's frame: ``M C M^T``, ``M = diag(R(theta)^T, 1)``."""
    m = np.eye(3)
    m[:2, :2] = rot(theta).T
    out = m @ cov_ref @ m.T
    return np.asarray(0.5 * (out + out.T), dtype=np.float64)


def overlap(new_points: FloatArray, ref_points: FloatArray, pose: FloatArray) -> float:
    """Fraction of the new points closer than :data:`INLIER_DISTANCE_M` to a reference
    point when moved by ``pose`` (:func:`~iceg.matching.refine.points_within`, the gridded
    query of the contradiction test)."""
    if new_points.shape[0] == 0 or ref_points.shape[0] == 0:
        return 0.0
    explained = points_within(new_points, np.asarray(pose)[None], ref_points, INLIER_DISTANCE_M)
    return float(np.mean(explained[0]))


def check_result(
    pose: FloatArray,
    cov: FloatArray,
    fraction: float,
    prediction: FloatArray,
    bounds: MatchBounds,
    config: MatchingConfig,
) -> str:
    """Why a point matcher's final pose is not trusted ("" when it is): not finite, outside
    the bounds (plus :data:`BOUNDS_MARGIN_M` / :data:`BOUNDS_MARGIN_DEG`), overlap below
    :data:`MIN_OVERLAP`, or a covariance beyond the ICE matcher's ``max_std_m`` /
    ``max_std_deg`` (degenerate scene)."""
    if not (np.all(np.isfinite(pose))):
        return "degenerate: registration diverged"
    d = pose - prediction
    if math.hypot(d[0], d[1]) > bounds.max_translation_m + BOUNDS_MARGIN_M or abs(
        float(wrap_angle(d[2]))
    ) > bounds.max_rotation_rad + math.radians(BOUNDS_MARGIN_DEG):
        return "outside the bounds"
    if fraction < MIN_OVERLAP:
        return f"too few inliers: overlap {fraction:.2f} < {MIN_OVERLAP}"
    cv = config.covariance
    if not np.all(np.isfinite(cov)):
        return "degenerate: singular covariance"
    heading_open = math.sqrt(max(cov[2, 2], 0.0)) > math.radians(cv.max_std_deg)
    if largest_std_exceeds(cov[:2, :2], cv.max_std_m) or heading_open:
        return "degenerate: the scene does not constrain the pose"
    return ""


def point_result(
    pose: FloatArray,
    cov: FloatArray,
    fraction: float,
    prediction: FloatArray,
    bounds: MatchBounds,
    config: MatchingConfig,
) -> MatchResult:
    """The :class:`~iceg.types.MatchResult` of a point matcher (correlation: the overlap)."""
    reason = check_result(pose, cov, fraction, prediction, bounds, config)
    if reason:
        return MatchResult.failed(prediction, reason)
    out = pose.copy()
    out[2] = float(wrap_angle(out[2]))
    return MatchResult(True, out, cov, fraction, n_hypotheses=1)


def checked_prediction(prediction: ArrayLike) -> FloatArray:
    """The prediction as a finite ``(3,)`` float64 pose.

    Raises:
        MatchingError: a mis-shaped or non-finite prediction.
    """
    pred = np.asarray(prediction, dtype=np.float64).reshape(-1)
    if pred.shape != (3,) or not np.all(np.isfinite(pred)):
        raise MatchingError(f"prediction must be a finite (3,) pose, got {prediction!r}")
    return pred


def point_inputs(
    features: ScanFeatures, reference: ScanFeatures, prediction: ArrayLike, max_points: int
) -> tuple[FloatArray, FloatArray, FloatArray, MatchResult | None]:
    """What a point matcher starts from: the prediction ``(3,)``, the new scan's points
    ``(P, 2)`` (at most ``max_points``, robot frame) and the reference's points ``(Q, 2)``
    (reference frame); and a failed :class:`MatchResult` when either has fewer than
    ``MIN_POINTS`` points, else ``None``.

    Raises:
        MatchingError: a mis-shaped or non-finite prediction.
    """
    pred = checked_prediction(prediction)
    new = subsample(features.points_xy, max_points)
    ref = reference_points(reference)
    if new.shape[0] < MIN_POINTS or ref.shape[0] < MIN_POINTS:
        failed = MatchResult.failed(pred, "too few candidates: points")
        return pred, new, ref, failed
    return pred, new, ref, None


class PlIcpMatcher:
    """Point-to-line ICP (Censi 2008) from the prediction, on the project's refinement.

    Two passes of :func:`~iceg.matching.refine.refine`: a wide gate
    (:data:`COARSE_GATE_M`) pulls the prediction in, then a gate of
    :data:`FINE_GATE_SIGMAS` estimated sigmas; covariance by :func:`lattice_covariance`.
    A global match (no prediction) starts from the prediction all the same: ICP is local.

    Args:
        config: Matching configuration (refinement and covariance settings, limits).
    """

    def __init__(self, config: MatchingConfig | None = None) -> None:
        self.config = config or MatchingConfig()

    def match(
        self,
        features: ScanFeatures,
        reference: ScanFeatures,
        prediction: ArrayLike,
        bounds: MatchBounds | None = None,
    ) -> MatchResult:
        """See :class:`~iceg.matching.protocol.Matcher`."""
        pred, new, ref, failure = point_inputs(
            features, reference, prediction, self.config.refinement.max_points
        )
        if failure is not None:
            return failure
        b = bounds or MatchBounds.global_()
        pose, cov = self._register(new, ref, pred, b)
        if cov is None:
            cov = lattice_covariance(plicp_problem(new, ref, pred, b, self.config), pose)
        return point_result(pose, cov, overlap(new, ref, pose), pred, b, self.config)

    def _register(
        self, new: FloatArray, ref: FloatArray, pred: FloatArray, bounds: MatchBounds
    ) -> tuple[FloatArray, FloatArray | None]:
        """Final pose ``(3,)`` and its covariance (``None``: the lattice covariance of the
        final pose is used): two refinement passes from the prediction, coarse then fine."""
        problem = plicp_problem(new, ref, pred, bounds, self.config)
        pose = refine(problem, pred, np.zeros((0, 2), np.int64)).pose
        if not np.all(np.isfinite(pose)):
            return pose, np.full((3, 3), np.inf)
        sigma = robust_sigma(problem, pose)
        s = problem.settings
        fine_gate = min(s.gate_m, max(s.gate_min_m, FINE_GATE_SIGMAS * sigma))
        fine = dataclasses.replace(problem, settings=dataclasses.replace(s, gate_m=fine_gate))
        pose = refine(fine, pose, np.zeros((0, 2), np.int64)).pose
        if not np.all(np.isfinite(pose)):
            return pose, np.full((3, 3), np.inf)
        return pose, lattice_covariance(problem, pose)
