"""The ICE matcher: docs/design.md steps 5-10 (paper §III-C2, §III-C3).

One call of :meth:`IceMatcher.match` builds a :class:`MatchContext` (the scans' features,
the reference, the prediction, the bounds, the config and what the steps share) and runs
the named steps on it: hypotheses (§III-C2), correlation (§III-C3, eq. 1-3), refinement
(Gauss-Newton with point-to-line rows and PL-ICP rows after Censi 2008), validation and
decision (docs/design.md step 10), covariance (Olson 2009, moved to the new scan's frame).
"""

from __future__ import annotations

import functools
import logging
import math
import weakref
from dataclasses import dataclass, field, replace
from typing import NamedTuple

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg.matching._kernels import (
    PointCloud,
    PosePrior,
    SegmentPoints,
    free_space_check,
    is_one_scan,
    local_lines,
    matched_pairs,
    ray_wall_check,
    segment_lengths,
)
from iceg.matching.config import MatchBounds, MatchingConfig
from iceg.matching.correlation import Correlation, CorrelationModel, CorrelationSettings
from iceg.matching.geometry import (
    MAX_GAP_BEAMS,
    FeatureGeometry,
    PolarProfile,
    SegmentSet,
    feature_geometry,
    point_segment_index,
)
from iceg.matching.hypotheses import (
    INCOMPATIBLE,
    generate_hypotheses,
    pair_codes,
    segment_rotation,
    vote,
)
from iceg.matching.refine import (
    Refined,
    RefineProblem,
    RefineSettings,
    bounds_prior_information,
    build_cloud,
    covariance_at,
    effective_line_info,
    empty_cloud,
    refine,
)
from iceg.types import MatchResult, ScanFeatures
from iceg_common.errors import MatchingError
from iceg_common.se2 import wrap_float

log = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Failure reasons (``MatchResult.reason`` starts with one of these).
REASON_NO_CANDIDATES = "too few candidates"
REASON_LOW_CORRELATION = "correlation below threshold"
REASON_FEW_INLIERS = "too few inliers"
REASON_DEGENERATE = "degenerate"
REASON_INCONSISTENT = "inconsistent with free space"
REASON_AMBIGUOUS = "ambiguous"
REASON_OUT_OF_BOUNDS = "outside the bounds"
REASON_WEAK_CLUSTER = "weak cluster"
#: Failures of a hypothesis that passed the bounds and free space (``IceMatcher._unverified``).
_EVIDENCE_REASONS = (REASON_FEW_INLIERS, REASON_LOW_CORRELATION)

#: Ranking (fitness) of a refined hypothesis: correlation + point overlap, plus this per
#: feature pair up to ``FITNESS_MAX_PAIRS``, minus this times the see-through fraction.
FITNESS_PAIR_BONUS = 0.1
FITNESS_MAX_PAIRS = 5
FITNESS_SEE_THROUGH_PENALTY = 2.0
#: A refined pose this close (metres, radians) to an earlier one is the same solution.
DUPLICATE_DISTANCE_M = 0.05
DUPLICATE_ANGLE_RAD = math.radians(1.0)
#: Rotation start from the prediction (:func:`~iceg.matching.hypotheses.segment_rotation`):
#: kernel width (rad), least agreeing segment length (m), largest deviation (rad).
START_KERNEL_RAD = math.radians(1.0)
START_MIN_SUPPORT_M = 1.0
START_MAX_DEVIATION_RAD = math.pi / 2
#: Walls met at more than this incidence (degrees) are not judged by the ray check.
MAX_INCIDENCE_DEG = 70.0
#: Its cosine, as the compiled ray check takes it.
_COS_MAX_INCIDENCE = math.cos(math.radians(MAX_INCIDENCE_DEG))
#: No segments: the second side of a one-sided free-space check.
_NO_SEGMENTS = np.zeros((0, 2, 2))
#: The off-segment cloud of a match without one (every match reads it; no kernel writes it).
_EMPTY_CLOUD = empty_cloud()
#: A bearing decrease larger than this (radians) between consecutive points breaks beam
#: order (the points are not one scan).
_BEARING_BACKSTEP_RAD = 0.05


@dataclass(eq=False)
class _Candidate:
    """A refined hypothesis with its correlation and checks."""

    from_prediction: bool
    refined: Refined
    corr: Correlation
    failure: str = ""
    rival: bool = False
    see_through: float = 0.0
    #: Failed a strict match's evidence check, free space not checked yet (``_settle_rivals``).
    free_space_pending: bool = False

    @property
    def fitness(self) -> float:
        """Ranking score: correlation (eq. 1) plus the point overlap of the refinement, plus
        ``FITNESS_PAIR_BONUS`` per feature pair (up to ``FITNESS_MAX_PAIRS``), minus
        ``FITNESS_SEE_THROUGH_PENALTY`` times the fraction of walls that the other scan sees
        through."""
        return (
            float(self.corr.score[0])
            + self.refined.overlap
            + FITNESS_PAIR_BONUS * min(int(self.corr.n_matched[0]), FITNESS_MAX_PAIRS)
            - FITNESS_SEE_THROUGH_PENALTY * self.see_through
        )


@dataclass(frozen=True, eq=False)
class _Starts:
    """Starting poses ``(S, 3)`` of the refinement (vote clusters, then the prediction),
    which of them is the prediction, the hypothesis count and the candidate pair count."""

    poses: FloatArray
    from_prediction: list[bool]
    n_hypotheses: int
    n_pairs: int


@dataclass(eq=False)
class MatchContext:
    """One call of :meth:`IceMatcher.match`: its inputs and what the steps share.

    Attributes:
        features: The new scan's features (robot frame).
        reference: The reference's features, segments and points (reference frame).
        prediction: ``(3,)`` float64 predicted pose of the new scan in the reference frame.
        bounds: Admissible motion around the prediction.
        config: The matcher's configuration.
        new_geom, ref_geom: Feature geometry of the new scan and of the reference.
        profile: Polar profile of the new scan's points (range ``range_max_m``).
        ref_profile: The reference's, when its points are one scan seen from its origin.
        correlation: The correlation (eq. 1-3) and feature pairing of this match.
        strict: Global-match thresholds apply (see :meth:`IceMatcher.is_strict`).
    """

    features: ScanFeatures
    reference: ScanFeatures
    prediction: FloatArray
    bounds: MatchBounds
    config: MatchingConfig
    new_geom: FeatureGeometry = field(init=False)
    ref_geom: FeatureGeometry = field(init=False)
    profile: PolarProfile = field(init=False)
    ref_profile: PolarProfile | None = field(init=False)
    correlation: CorrelationModel = field(init=False)
    strict: bool = field(init=False)

    def __post_init__(self) -> None:
        c, f, r = self.config, self.features, self.reference
        derived = scan_derived(f)
        self.new_geom = derived.geometry
        self.ref_geom, self.ref_profile = reference_derived(r)
        range_max = float(f.range_max_m)
        self.profile = derived.profile
        codes = pair_codes(
            self.new_geom,
            self.ref_geom,
            c.filter.corner_eow_matching,
            math.radians(c.filter.max_opening_diff_deg),
        )
        settings = CorrelationSettings.from_config(c.correlation, range_max)
        self.correlation = CorrelationModel(
            self.new_geom, self.ref_geom, codes, self.profile, settings
        )
        self.strict = IceMatcher.is_strict(c, self.bounds)

    @functools.cached_property
    def ref_segments(self) -> SegmentSet:
        """The reference's segments prepared for point association (built once per match:
        the prediction's rotation start reads their lengths, the refinement all of them)."""
        return SegmentSet.from_features(self.reference)

    def fail(self, reason: str, n_hypotheses: int) -> MatchResult:
        """A failed :class:`~iceg.types.MatchResult` at the prediction with ``reason``."""
        log.debug("ICE match failed: %s", reason)
        return MatchResult.failed(self.prediction, reason, n_hypotheses)


class ScanDerived(NamedTuple):
    """What every match of one new scan derives from its features alone (pose-independent):
    its feature geometry, its polar profile (range ``range_max_m``), the segment of each
    point (``(P,)`` int64, -1: none), the points on a segment with their segment's line
    angle (the refinement's point-to-line rows before any subsampling) and the indices
    (``(Q,)`` int64, ascending) of the points on none."""

    geometry: FeatureGeometry
    profile: PolarProfile
    point_segment: IntArray
    segment_points: SegmentPoints
    off_segment: IntArray


#: :func:`scan_derived` results by features object (identity; dropped with the object).
_DERIVED: weakref.WeakKeyDictionary[ScanFeatures, ScanDerived] = weakref.WeakKeyDictionary()


def scan_derived(features: ScanFeatures) -> ScanDerived:
    """The pose-independent quantities of a new scan's features, computed once per
    features object (a keyframe is matched locally and then against loop-closure
    candidates), or ahead by :func:`remember_scan_derived`. ``ScanFeatures`` are never
    modified after extraction, so the cached values are exactly those a fresh computation
    would give."""
    got = _DERIVED.get(features)
    if got is None:
        got = _DERIVED[features] = compute_scan_derived(features)
    return got


def compute_scan_derived(features: ScanFeatures) -> ScanDerived:
    """What :func:`scan_derived` caches, computed afresh (e.g. in a feature worker,
    :mod:`iceg.scan_products`)."""
    pseg = point_segment_index(features)
    on_segment = np.flatnonzero(pseg >= 0)
    alpha = features.seg_lines[pseg[on_segment], 0] if on_segment.shape[0] else np.zeros(0)
    return ScanDerived(
        feature_geometry(features),
        PolarProfile.from_points(features.points_xy, float(features.range_max_m)),
        pseg,
        SegmentPoints(features.points_xy[on_segment], alpha),
        np.flatnonzero(pseg < 0),
    )


def remember_scan_derived(features: ScanFeatures, derived: ScanDerived) -> None:
    """Let :func:`scan_derived` serve ``derived``, which :func:`compute_scan_derived`
    computed for these features (or for a copy of them, bit for bit: a worker's)."""
    _DERIVED[features] = derived


#: A reference's feature geometry and polar profile (None: its points are not one scan).
RefDerived = tuple[FeatureGeometry, PolarProfile | None]
#: :func:`reference_derived` results by reference object (identity; dropped with the object).
_REF_DERIVED: weakref.WeakKeyDictionary[ScanFeatures, RefDerived] = weakref.WeakKeyDictionary()


def reference_derived(reference: ScanFeatures) -> RefDerived:
    """A reference's feature geometry and, when its points are one scan seen from its
    origin, its polar profile (a feature-map reference gathers several nodes' points, whose
    beams cannot be checked): computed once per reference object, as :func:`scan_derived`
    does for new scans (a fixed map's places are matched by every global placement).

    Args:
        reference: Features, segments and ``points_xy`` ``(P, 2)`` float64 (metres) of a
            scan or a feature-map reference, in the reference frame; never modified after
            it is built, so the cached values are those a fresh computation gives.

    Returns:
        ``(geometry, profile)``: the :class:`FeatureGeometry` of its features and the
        :class:`PolarProfile` of its points up to ``range_max_m`` (None when the points are
        not one scan in beam order).
    """
    got = _REF_DERIVED.get(reference)
    if got is None:
        r = reference
        profile = (
            PolarProfile.from_points(r.points_xy, float(r.range_max_m))
            if is_one_scan(
                np.ascontiguousarray(r.points_xy, dtype=np.float64), _BEARING_BACKSTEP_RAD
            )
            else None
        )
        got = (feature_geometry(r), profile)
        _REF_DERIVED[reference] = got
    return got


#: Relative distance from the threshold beyond which :func:`largest_std_exceeds` trusts the
#: closed form (far above the rounding of either eigenvalue computation, about 1e-15).
_EIGENVALUE_MARGIN = 1e-9


def largest_std_exceeds(cov_xy: FloatArray, limit: float) -> bool:
    """Whether the largest standard deviation of a symmetric ``(2, 2)`` covariance exceeds
    ``limit`` (``sqrt(max(eigvalsh(cov_xy)[-1], 0)) > limit``, the same answer): the
    closed-form eigenvalue ``(a + d) / 2 + hypot((a - d) / 2, b)`` decides unless it lies
    within :data:`_EIGENVALUE_MARGIN` of ``limit^2``, where LAPACK's does.

    Args:
        cov_xy: ``(2, 2)`` float64 finite symmetric covariance, m^2.
        limit: Standard deviation, metres (>= 0).
    """
    (a, b), (_, d) = cov_xy.tolist()
    largest = 0.5 * (a + d) + math.hypot(0.5 * (a - d), b)
    bound = limit * limit
    if abs(largest - bound) > _EIGENVALUE_MARGIN * (abs(a) + abs(b) + abs(d) + bound):
        return largest > bound
    return math.sqrt(max(float(np.linalg.eigvalsh(cov_xy)[-1]), 0.0)) > limit


def _even_pick(n: int, k: int) -> IntArray:
    """``(k,)`` int64 indices of ``k`` of ``n`` items, evenly spread (first and last kept)."""
    return np.linspace(0, n - 1, k).astype(np.int64)


def _same_pose(a: FloatArray, b: FloatArray, dist_m: float, angle_rad: float) -> bool:
    return (
        math.hypot(a[0] - b[0], a[1] - b[1]) <= dist_m
        and abs(wrap_float(float(a[2] - b[2]))) <= angle_rad
    )


#: The feature arrays whose shapes :func:`_check_features` checks.
_SHAPED = ("xy", "cov", "directions", "opening_rad", "ids", "seg_endpoints", "seg_lines", "seg_cov")


def _check_features(f: ScanFeatures, what: str) -> None:
    k = f.kind.shape[0]
    m = f.seg_endpoints.shape[0]
    got = (
        f.xy.shape,
        f.cov.shape,
        f.directions.shape,
        f.opening_rad.shape,
        f.ids.shape,
        f.seg_endpoints.shape,
        f.seg_lines.shape,
        f.seg_cov.shape,
    )
    want = ((k, 2), (k, 2, 2), (k, 2, 2), (k,), (k,), (m, 2, 2), (m, 2), (m, 2, 2))
    if got != want:  # one tuple comparison on the common path; the first mismatch named
        for name, g, w in zip(_SHAPED, got, want, strict=True):
            if tuple(g) != w:
                raise MatchingError(
                    f"{what}.{name} has shape {tuple(g)}, expected {w} "
                    "(see iceg.types.ScanFeatures)"
                )
    if f.points_xy.ndim != 2 or f.points_xy.shape[1] != 2:
        raise MatchingError(f"{what}.points_xy must have shape (P, 2), got {f.points_xy.shape}")


def _refine_settings(c: MatchingConfig) -> RefineSettings:
    """The refinement's settings in metres and radians."""
    r, cov = c.refinement, c.covariance
    return RefineSettings(
        max_iterations=r.max_iterations,
        gate_m=r.association_gate_m,
        gate_sigmas=r.association_gate_sigmas,
        gate_min_m=r.association_gate_min_m,
        end_tol_m=r.segment_end_tolerance_m,
        normal_gate_rad=math.radians(r.normal_gate_deg),
        cauchy_sigmas=c.cauchy_scale_sigmas,
        sigma_min_m=r.point_sigma_min_m,
        wall_end_sigma_m=r.wall_end_sigma_m,
        lattice_steps=cov.lattice_steps,
        lattice_sigmas=cov.lattice_sigmas,
        lattice_kappa=cov.lattice_kappa,
        lattice_cap_m=cov.lattice_max_half_width_m,
        lattice_cap_rad=math.radians(cov.lattice_max_half_width_deg),
    )


def _checked_prediction(
    features: ScanFeatures, reference: ScanFeatures, prediction: ArrayLike
) -> FloatArray:
    """The prediction as a ``(3,)`` float64 pose, after checking all inputs.

    Raises:
        MatchingError: a non-finite or mis-shaped prediction, or inconsistent features.
    """
    pred = np.asarray(prediction, dtype=np.float64).reshape(-1)
    if pred.shape != (3,) or not all(map(math.isfinite, pred.tolist())):
        raise MatchingError(f"prediction must be a finite (3,) pose, got {prediction!r}")
    _check_features(features, "features")
    _check_features(reference, "reference")
    return pred


class IceMatcher:
    """ICE scan matching (paper §III-C2/C3; docs/design.md "ICE matching, step by step", 5-10).

    Steps: hierarchical candidate filter (type, Corner<->EOW exception, feasible area via a
    KD-tree, opening angle, direction against the predicted rotation); SE(2) hypotheses from
    directed pairs and Intersection pair pairs; voting; correlation (eq. 1-3); Gauss-Newton
    refinement over feature pairs and point-to-line residuals; covariance from the
    correlation landscape (Olson 2009) floored by the least-squares covariance; validation
    (correlation, inliers, free-space consistency, degeneracy). A failure is a
    :class:`~iceg.types.MatchResult` with ``success=False`` and a reason.

    Args:
        config: Matcher configuration (defaults: the paper's weights and fImp).
    """

    def __init__(self, config: MatchingConfig | None = None) -> None:
        self.config = config or MatchingConfig()
        self._settings = _refine_settings(self.config)

    def __repr__(self) -> str:
        return f"IceMatcher({self.config!r})"

    @staticmethod
    def is_strict(config: MatchingConfig, bounds: MatchBounds) -> bool:
        """A global match, or one whose bounds are wider than tracking's (loop closure,
        relocalisation): the hypothesis space is large, so the global evidence thresholds
        apply and every chosen hypothesis is refined and compared (ambiguity)."""
        v = config.validation
        return (
            bounds.is_global
            or bounds.max_translation_m > v.tracking_max_translation_m
            or bounds.max_rotation_rad > math.radians(v.tracking_max_rotation_deg)
        )

    def compile_checks(self, features: ScanFeatures) -> None:
        """Run the covariance (docs/design.md step 9) and the free-space checks (step 10) of
        a tracking match of ``features`` with themselves at the identity, without its
        hypotheses and refinement (steps 5-8), and drop the results. Their compiled kernels
        load then, or on a cold numba cache compile, apart from those of the steps before
        (:mod:`iceg.kernel_warmup`).

        Raises:
            MatchingError: ``features`` are inconsistent (as :meth:`match`).
        """
        pose = np.zeros(3)
        v = self.config.validation
        bounds = MatchBounds.local(v.tracking_max_translation_m, v.tracking_max_rotation_deg)
        pred = _checked_prediction(features, features, pose)
        ctx = MatchContext(features, features, pred, bounds, self.config)
        covariance_at(self._refine_problem(ctx), pose)
        self._free_space(ctx, pose)

    # ------------------------------------------------------------------------------------
    def match(
        self,
        features: ScanFeatures,
        reference: ScanFeatures,
        prediction: ArrayLike,
        bounds: MatchBounds | None = None,
    ) -> MatchResult:
        """Match a new scan's features against a reference.

        Args:
            features: The new scan's :class:`~iceg.types.ScanFeatures`, robot frame, with
                its ``points_xy`` (point-to-line refinement) and segments.
            reference: Features and segments of the reference (a scan or a feature-map
                reference) in the reference frame; ``points_xy`` may be empty.
            prediction: ``(3,)`` float64 predicted pose of the new scan's robot frame in the
                reference frame ``[x_m, y_m, theta_rad]``.
            bounds: Admissible motion around the prediction; ``None`` or
                :meth:`MatchBounds.global_` for a global match.

        Returns:
            A :class:`~iceg.types.MatchResult`: the pose of the new scan in the reference
            frame, its covariance in the tangent space at that pose in the new scan's frame
            (gtsam ``BetweenFactorPose2`` convention), the correlation of eq. 1, the inlier
            feature pairs ``[new index, reference index]``; or a failure with its reason.

        Raises:
            MatchingError: inconsistent inputs (array shapes, a non-finite prediction).
        """
        pred = _checked_prediction(features, reference, prediction)
        ctx = MatchContext(features, reference, pred, bounds or MatchBounds.global_(), self.config)
        too_few = self._too_few_pairs(ctx)
        if too_few:
            return ctx.fail(too_few, 0)
        starts = self._hypotheses(ctx)
        if starts.poses.shape[0] == 0:
            return ctx.fail(
                f"{REASON_NO_CANDIDATES}: no transform hypothesis "
                f"({ctx.new_geom.n} new, {ctx.ref_geom.n} reference features, "
                f"{starts.n_pairs} candidate pairs)",
                starts.n_hypotheses,
            )
        corr0, chosen = self._correlation(ctx, starts)
        cands = self._refinement(ctx, starts, corr0, chosen)
        return self._decision(ctx, cands, starts.n_hypotheses)

    @staticmethod
    def _too_few_pairs(ctx: MatchContext) -> str:
        """The failure reason of a strict match (global or wide bounds) that cannot pass
        step 10's evidence check, or "". It needs ``min_matched_features_global`` feature
        pairs, and the correlation pairs a new feature only with a reference feature of a
        compatible type and opening (:func:`~iceg.matching.hypotheses.pair_codes`), each at
        most once: fewer new features with a compatible reference feature, or fewer
        reference features with a compatible new one, fail whatever the hypotheses (a
        loop-closure candidate seen past a corner, a scan of bare walls). Decided before the
        hypotheses."""
        if not ctx.strict:
            return ""
        need = ctx.config.validation.min_matched_features_global
        compatible = ctx.correlation.codes != INCOMPATIBLE
        n_new = int(np.count_nonzero(compatible.any(axis=1)))
        n_ref = int(np.count_nonzero(compatible.any(axis=0)))
        if min(n_new, n_ref) >= need:
            return ""
        return (
            f"{REASON_NO_CANDIDATES}: {n_new} of {ctx.new_geom.n} new and {n_ref} of "
            f"{ctx.ref_geom.n} reference features have a compatible feature, fewer than the "
            f"{need} feature pairs a global match needs"
        )

    # --- step 5-6: hypotheses -----------------------------------------------------------
    def _hypotheses(self, ctx: MatchContext) -> _Starts:
        """Candidate filter, SE(2) hypotheses and voting (paper §III-C2, §III-C3 "the
        conversion with the most count"; docs/design.md steps 5-6), plus the prediction itself for
        a bounded match. Poses ``(S, 3)`` of the new scan in the reference frame."""
        f, v = ctx.config.filter, ctx.config.voting
        hyps = generate_hypotheses(
            ctx.new_geom,
            ctx.ref_geom,
            ctx.correlation.codes,
            ctx.prediction,
            ctx.bounds,
            margin_m=f.feasible_margin_m,
            direction_tolerance_rad=math.radians(f.direction_tolerance_deg),
            intersection_tolerance_m=f.intersection_pair_tolerance_m,
            intersection_min_baseline_m=f.intersection_min_baseline_m,
            max_intersection_pairs=f.max_intersection_pairs,
        )
        clusters = vote(hyps.poses, v.vote_cell_m, math.radians(v.vote_cell_deg), v.max_clusters)
        starts = clusters.poses
        from_prediction = [False] * starts.shape[0]
        if v.use_prediction_hypothesis and not ctx.bounds.is_global:
            starts = np.concatenate([starts, _prediction_start(ctx)[None]], axis=0)
            from_prediction.append(True)
        return _Starts(starts, from_prediction, int(hyps.poses.shape[0]), hyps.n_pairs)

    # --- step 7: correlation --------------------------------------------------------------
    def _correlation(self, ctx: MatchContext, starts: _Starts) -> tuple[Correlation, list[int]]:
        """Correlation (paper eq. 1-3) of every start and the ones to refine: the best
        correlated first (paper §III-C3: most count first, then correlation), those within
        ``refine_correlation_margin`` of the best, at most ``max_refined`` (global:
        ``max_refined_global``); the prediction competes like any cluster and is always
        refined."""
        v = ctx.config.voting
        corr0 = ctx.correlation.score(starts.poses)
        score = corr0.score.tolist()
        order = np.argsort(-corr0.score, kind="stable").tolist()
        best0 = score[order[0]]
        n_refine = v.max_refined_global if ctx.strict else v.max_refined
        chosen = [k for k in order if score[k] >= best0 - v.refine_correlation_margin]
        chosen = chosen[:n_refine]
        if True in starts.from_prediction:
            kp = starts.from_prediction.index(True)
            if kp not in chosen:
                chosen.append(kp)
        return corr0, chosen

    # --- step 8-9: refinement -------------------------------------------------------------
    def _refinement(
        self, ctx: MatchContext, starts: _Starts, corr0: Correlation, chosen: list[int]
    ) -> list[_Candidate]:
        """Refine the chosen starts (docs/design.md step 8) and check each result (step 10). A start
        next to an already refined pose is skipped (it would converge to it again), a
        result equal to an earlier one dropped.

        A bounded match stops at the first hypothesis that passes (rivals come from the
        bounds' small neighbourhood only) if that hypothesis is the prediction's own basin or
        carries the evidence a global match needs (:meth:`_global_evidence`). A weaker
        cluster that passes first (one feature pair, or a fit most of the scan disagrees
        with) is no reason to leave the basin the odometry predicts unexplored: the
        prediction's start is refined too, and where it passes it is the answer
        (docs/design.md step 8, "A weak cluster does not overrule the prediction")."""
        problem = self._refine_problem(ctx)
        va = ctx.config.validation
        near_d, near_a = va.ambiguity_distance_m, math.radians(va.ambiguity_angle_deg)
        cands: list[_Candidate] = []
        weak: list[_Candidate] = []  # passing clusters without global evidence
        for k in chosen:
            if weak and not starts.from_prediction[k]:
                continue
            if any(_same_pose(starts.poses[k], o.refined.pose, near_d, near_a) for o in cands):
                continue
            pairs = matched_pairs(corr0.match[k])
            ref = refine(problem, starts.poses[k], pairs)
            if not ctx.strict:
                ref = self._held_along_weak_directions(ctx, problem, ref, pairs)
            if any(
                _same_pose(ref.pose, o.refined.pose, DUPLICATE_DISTANCE_M, DUPLICATE_ANGLE_RAD)
                for o in cands
            ):
                continue
            cand = _Candidate(starts.from_prediction[k], ref, ctx.correlation.score(ref.pose[None]))
            cand.failure = self._validation(ctx, cand)
            cands.append(cand)
            if ctx.strict or cand.failure:
                continue
            if cand.from_prediction:
                for other in weak:
                    other.failure = f"{REASON_WEAK_CLUSTER}: the prediction's basin passes too"
                    other.rival = False
                break
            if self._global_evidence(ctx, cand) or True not in starts.from_prediction:
                break
            weak.append(cand)
        return cands

    @staticmethod
    def _held_along_weak_directions(
        ctx: MatchContext, problem: RefineProblem, ref: Refined, pairs: IntArray
    ) -> Refined:
        """Solution remapping inside a tracking match (after Zhang, Kaess & Singh, ICRA 2016,
        "On degeneracy of optimization-based state estimation problems"): a refinement that
        ended beyond the bounds' translation from the prediction, along translation
        directions where the scene's own information (the least-squares information less the
        bounds' prior) is below the prior's, slid there because nothing stopped it (a
        corridor), not because the scene says so. It is refined again from its pose with
        those directions moved back to the prediction and held there
        (:func:`~iceg.matching.refine.refine`, ``held``); its covariance stays the scene's,
        as weak along them as it is. ``ref`` itself otherwise (docs/design.md, "Solution
        remapping inside the match")."""
        pose = ref.pose
        d = pose[:2] - ctx.prediction[:2]
        if not math.hypot(d[0], d[1]) > ctx.bounds.max_translation_m:
            return ref
        cov_ls = ref.cov_ls
        if not np.all(np.isfinite(cov_ls)):
            return ref
        prior = problem.prior.info[:2, :2]
        try:
            scene = np.linalg.inv(cov_ls)[:2, :2] - prior
        except np.linalg.LinAlgError:
            return ref
        evals, evecs = np.linalg.eigh(0.5 * (scene + scene.T))
        weak = evecs[:, evals < prior[0, 0]]
        if weak.shape[1] == 0:
            return ref
        start = pose.copy()
        start[:2] -= weak @ (weak.T @ d)
        return refine(problem, start, pairs, held=weak)

    @staticmethod
    def _global_evidence(ctx: MatchContext, cand: _Candidate) -> bool:
        """Whether a refined hypothesis has the feature pairs, correlation and point overlap
        that a global match requires (``validation.*_global``)."""
        v = ctx.config.validation
        return (
            int(cand.corr.n_matched[0]) >= v.min_matched_features_global
            and float(cand.corr.score[0]) >= v.min_correlation_global
            and cand.refined.overlap >= v.min_point_overlap_global
        )

    def _refine_problem(self, ctx: MatchContext) -> RefineProblem:
        """What the refinements of this match share: the new scan's points on its segments
        (at most ``max_points``, evenly subsampled), the reference segments, the bounds'
        prior centred on the prediction and the off-segment point cloud."""
        c = ctx.config.refinement
        derived = scan_derived(ctx.features)
        points = derived.segment_points
        if points.xy.shape[0] > c.max_points:
            pick = _even_pick(points.xy.shape[0], c.max_points)
            points = SegmentPoints(points.xy[pick], points.alpha[pick])
        segs = ctx.ref_segments
        s = self._settings
        _, line_info = effective_line_info(segs, s.wall_end_sigma_m)
        b = ctx.bounds
        prior = PosePrior(
            ctx.prediction, bounds_prior_information(b.max_translation_m, b.max_rotation_rad)
        )
        return RefineProblem(
            points,
            segs,
            line_info,
            ctx.new_geom,
            ctx.ref_geom,
            ctx.correlation.feature_pairing,
            prior,
            self._cloud(ctx, derived.off_segment),
            s,
        )

    def _cloud(self, ctx: MatchContext, new_off: IntArray) -> PointCloud:
        """Off-segment points of the new scan (clutter, short structures) against all the
        reference's points, point-to-line on the local line through a reference point and
        its beam neighbours (Censi 2008, PL-ICP), so that points on walls add nothing along
        the walls; an isolated reference point gives a point-to-point residual whose noise
        includes half the distance to its nearest neighbour. Empty when the reference has
        fewer than 3 points or ``use_off_segment_points`` is off."""
        c = ctx.config.refinement
        rp = ctx.reference.points_xy
        if not c.use_off_segment_points or rp.shape[0] < 3 or new_off.shape[0] == 0:
            return _EMPTY_CLOUD
        if new_off.shape[0] > c.max_points // 2:
            new_off = new_off[_even_pick(new_off.shape[0], c.max_points // 2)]
        spacing, normal = local_lines(
            np.ascontiguousarray(rp, dtype=np.float64), c.local_line_max_gap_m
        )
        points = ctx.features.points_xy[new_off]
        return build_cloud(points, rp, spacing, normal, c.association_gate_m)

    # --- step 10: validation --------------------------------------------------------------
    def _validation(self, ctx: MatchContext, cand: _Candidate) -> str:
        """docs/design.md step 10 checks of one refined hypothesis: inside the bounds, consistent
        with free space, enough evidence. Returns the failure reason or an empty string.

        A strict match checks the evidence (a few comparisons) before free space (a ray cast
        of both scans): most of its hypotheses lack the evidence (MIT CSAIL: 3106 of its
        3207 strict validations), and a hypothesis that fails either check fails. Its free space
        is checked later only where a rival's ranking needs it (:meth:`_settle_rivals`), so
        every decision is the one of the checks in the order above; a failed match may name
        the evidence where that order named free space."""
        pose = cand.refined.pose.tolist()
        if not all(map(math.isfinite, pose)):
            return f"{REASON_DEGENERATE}: refinement diverged"
        out_of_bounds = self._check_bounds(ctx, pose)
        if out_of_bounds or not ctx.strict:
            return (
                out_of_bounds
                or self._check_free_space(ctx, cand)
                or self._check_evidence(ctx, cand)
            )
        lacking = self._check_evidence(ctx, cand)
        if lacking:
            cand.free_space_pending = True
            return lacking
        inconsistent = self._check_free_space(ctx, cand)
        if inconsistent:
            cand.rival = False  # as if the evidence had not been checked
        return inconsistent

    def _settle_rivals(self, ctx: MatchContext, cands: list[_Candidate]) -> None:
        """Check the free space of the candidates :meth:`_validation` failed on evidence alone
        that would be rivals (feature support) were they consistent with it: one that is not
        is no rival, and the fraction of wall seen through lowers the fitness of one that is.
        Their rivalry and fitness are then those of the checks in their documented order."""
        for cand in cands:
            if cand.free_space_pending and cand.rival:
                cand.free_space_pending = False
                if self._check_free_space(ctx, cand):
                    cand.rival = False

    def _check_bounds(self, ctx: MatchContext, pose: list[float]) -> str:
        """The refined pose ``[x_m, y_m, theta_rad]`` lies within the bounds (plus the
        filter's noise allowances)."""
        f = ctx.config.filter
        d = [a - b for a, b in zip(pose, ctx.prediction.tolist(), strict=True)]
        dist, dth = math.hypot(d[0], d[1]), abs(wrap_float(d[2]))
        if dist > ctx.bounds.max_translation_m + f.feasible_margin_m or dth > (
            ctx.bounds.max_rotation_rad + math.radians(f.direction_tolerance_deg)
        ):
            return (
                f"{REASON_OUT_OF_BOUNDS}: refined pose {dist:.2f} m / {math.degrees(dth):.1f} deg "
                "from the prediction"
            )
        return ""

    def _check_free_space(self, ctx: MatchContext, cand: _Candidate) -> str:
        """Free-space consistency (a hypothesis that contradicts what a scan sees is no
        answer and no rival either): little wall seen through, no wall through a robot,
        neither origin behind a wall. Sets ``cand.see_through``."""
        v = ctx.config.validation
        frac, length, clear, origins_visible = self._free_space(ctx, cand.refined.pose)
        cand.see_through = frac
        if (
            frac > v.max_see_through_fraction and length >= v.see_through_min_length_m
        ) or length >= v.see_through_max_length_m:
            return (
                f"{REASON_INCONSISTENT}: {frac:.0%} ({length:.1f} m) of the walls lie where "
                "the other scan sees free space"
            )
        if clear < v.robot_clearance_m:
            return (
                f"{REASON_INCONSISTENT}: a wall of one scan passes {clear:.2f} m from the other "
                f"scan's sensor (< {v.robot_clearance_m} m)"
            )
        if not origins_visible:
            return (
                f"{REASON_INCONSISTENT}: one scan's origin lies behind a wall the other scan sees"
            )
        return ""

    def _check_evidence(self, ctx: MatchContext, cand: _Candidate) -> str:
        """Enough feature pairs and correlation (paper §III-C3, eq. 1), or a featureless
        bounded match from the prediction; then enough point overlap. Sets ``cand.rival``:
        a consistent hypothesis with feature support is a rival of the best even if too
        weak to be accepted itself."""
        v = ctx.config.validation
        score = float(cand.corr.score[0])
        n_matched = int(cand.corr.n_matched[0])
        cand.rival = n_matched >= 1
        min_pairs = v.min_matched_features_global if ctx.strict else v.min_matched_features
        min_corr = v.min_correlation_global if ctx.strict else v.min_correlation
        if n_matched >= min_pairs:
            if score < min_corr:
                return f"{REASON_LOW_CORRELATION}: {score:.3f} < {min_corr}"
            min_overlap = v.min_point_overlap_global if ctx.strict else v.min_point_overlap
        elif not ctx.strict and cand.from_prediction and n_matched == 0:
            # No feature pairs (a corridor, or features too unstable to pair), tracked from
            # the prediction: the points decide, and the covariance shows what the walls
            # leave unconstrained.
            min_overlap = v.min_point_overlap_featureless
        else:
            return (
                f"{REASON_FEW_INLIERS}: {n_matched} feature pairs (< {min_pairs}; "
                f"{ctx.new_geom.n} new, {int(cand.corr.n_visible[0])} visible reference "
                "features)"
            )
        if cand.refined.overlap < min_overlap:
            return (
                f"{REASON_FEW_INLIERS}: {cand.refined.overlap:.0%} of the scan's points on "
                f"reference segments (< {min_overlap:.0%})"
            )
        return ""

    # --- step 10: decision ----------------------------------------------------------------
    def _decision(self, ctx: MatchContext, cands: list[_Candidate], n_hyp: int) -> MatchResult:
        """Pick the best refined hypothesis (by fitness) that passes the checks; fail when
        none does, when a distinct rival scores nearly as well (ambiguous), or when the
        covariance is degenerate (docs/design.md step 10)."""
        ok = sorted((k for k in cands if not k.failure), key=lambda k: -k.fitness)
        if not ok:
            worst_first = sorted(cands, key=lambda k: -k.fitness)
            failed = ctx.fail(worst_first[0].failure, n_hyp)
            return replace(failed, unverified=self._unverified(ctx, worst_first, n_hyp))
        best = ok[0]
        reason = self._ambiguity(ctx, cands, best)
        if reason:
            return ctx.fail(reason, n_hyp)
        return self._covariance(ctx, best, n_hyp)

    def _unverified(
        self, ctx: MatchContext, best_first: list[_Candidate], n_hyp: int
    ) -> MatchResult | None:
        """A failed tracking match's best hypothesis from the prediction that passed the
        bounds and free space and lacked only the evidence (feature pairs, correlation,
        point overlap), as a result with its covariance; ``None`` for a strict match, where
        there is none, or where its covariance is degenerate. Not a measurement: a later loop
        closure may confirm it (docs/design.md, "A disputed step confirmed by a loop
        closure")."""
        if ctx.strict:
            return None
        for cand in best_first:
            if cand.from_prediction and cand.failure.startswith(_EVIDENCE_REASONS):
                result = self._covariance(ctx, cand, n_hyp)
                return result if result.success else None
        return None

    def _ambiguity(self, ctx: MatchContext, cands: list[_Candidate], best: _Candidate) -> str:
        """The failure reason when a rival distinct from ``best`` scores within
        ``ambiguity_margin`` of it (never a confident wrong pose in a self-similar scene)."""
        v = ctx.config.validation
        self._settle_rivals(ctx, cands)
        rivals = sorted((k for k in cands if k.rival and k is not best), key=lambda k: -k.fitness)
        near_a = math.radians(v.ambiguity_angle_deg)
        for other in rivals:
            a, b = best.refined.pose, other.refined.pose
            distinct = not _same_pose(a, b, v.ambiguity_distance_m, near_a)
            if distinct and other.fitness >= best.fitness - v.ambiguity_margin:
                d = b - a
                return (
                    f"{REASON_AMBIGUOUS}: two distinct hypotheses score {best.fitness:.2f} and "
                    f"{other.fitness:.2f} (apart {math.hypot(d[0], d[1]):.2f} m, "
                    f"{math.degrees(abs(wrap_float(float(d[2])))):.1f} deg)"
                )
        return ""

    # --- step 9: covariance -----------------------------------------------------------------
    def _covariance(self, ctx: MatchContext, best: _Candidate, n_hyp: int) -> MatchResult:
        """The result of ``best``: fail as degenerate when its covariance (Olson 2009 lattice
        floored by least squares, reference frame) exceeds ``max_std_m`` / ``max_std_deg``,
        else move it into the tangent space at the pose in the new scan's frame (gtsam
        ``Pose2`` local coordinates: ``M C M^T`` with ``M = diag(R^T, 1)``)."""
        cv = ctx.config.covariance
        ref = best.refined
        cov_param = ref.cov
        if (
            not all(map(math.isfinite, cov_param.ravel().tolist()))
            or largest_std_exceeds(cov_param[:2, :2], cv.max_std_m)
            or math.sqrt(max(cov_param[2, 2], 0.0)) > math.radians(cv.max_std_deg)
        ):
            return ctx.fail(
                f"{REASON_DEGENERATE}: the scene does not constrain the pose (std beyond "
                f"{cv.max_std_m} m / {cv.max_std_deg} deg)",
                n_hyp,
            )
        # M = diag(R^T, 1), the rotation's cosine and sine from libm (numpy's, bit for bit)
        c, s = math.cos(ref.pose[2]), math.sin(ref.pose[2])
        m = np.array([[c, s, 0.0], [-s, c, 0.0], [0.0, 0.0, 1.0]])
        cov_body = m @ cov_param @ m.T
        cov_body = 0.5 * (cov_body + cov_body.T)
        pose = ref.pose.copy()
        pose[2] = wrap_float(float(pose[2]))
        return MatchResult(
            success=True,
            pose=pose,
            cov=cov_body,
            correlation=float(best.corr.score[0]),
            inlier_pairs=matched_pairs(best.corr.match[0]),
            n_hypotheses=n_hyp,
            reason="",
        )

    # --- free-space helper ----------------------------------------------------------------
    @staticmethod
    def _free_space(ctx: MatchContext, pose: FloatArray) -> tuple[float, float, float, bool]:
        """:func:`~iceg.matching._kernels.free_space_check` of ``pose``: the fraction and
        length (metres) of checked wall that one scan places where the other scan's beams
        pass through, the clearance (metres) between each scan's sensor and the other's
        walls, and whether neither sensor lies behind a wall the other sees. The reference
        segments are cast along the new scan's beams; when the reference has points (a
        scan), the new segments along the reference's beams too."""
        # R(theta) from libm's cosine and sine (numpy's, bit for bit), the products numpy's
        c, s = math.cos(pose[2]), math.sin(pose[2])
        r = np.array([[c, -s], [s, c]])
        ref_ep, new_ep = ctx.reference.seg_endpoints, ctx.features.seg_endpoints
        two_sided = ctx.ref_profile is not None
        return free_space_check(
            pose,
            (ref_ep - pose[:2]) @ r,
            new_ep @ r.T + pose[:2] if two_sided else _NO_SEGMENTS,
            ref_ep,
            new_ep,
            ctx.profile.rays,
            (ctx.ref_profile or ctx.profile).rays,
            two_sided,
            ctx.config.validation.see_through_tolerance_m,
            _COS_MAX_INCIDENCE,
            MAX_GAP_BEAMS,
        )


def _prediction_start(ctx: MatchContext) -> FloatArray:
    """The prediction as a start, its rotation replaced by the best alignment of the
    segment directions near it when one has enough support (docs/design.md step 9: a scene with
    few features still yields a point-to-line match)."""
    f, r = ctx.features, ctx.reference
    start = ctx.prediction.copy()
    th = segment_rotation(
        f.seg_lines,
        segment_lengths(np.ascontiguousarray(f.seg_endpoints, dtype=np.float64)),
        r.seg_lines,
        ctx.ref_segments.length,
        float(start[2]),
        min(ctx.bounds.max_rotation_rad, START_MAX_DEVIATION_RAD),
        START_KERNEL_RAD,
        START_MIN_SUPPORT_M,
    )
    if th is not None:
        start[2] = th
    return start


def walls_seen_through(
    seg_endpoints: FloatArray, profile: PolarProfile, tolerance_m: float
) -> tuple[FloatArray, FloatArray]:
    """Free-space test of each wall against one scan: cast the segments ``seg_endpoints``
    ``(M, 2, 2)`` float64 (metres, the scan's frame) along the scan's beams (``profile``). A
    beam that reaches more than ``tolerance_m`` beyond the nearest segment it crosses sees
    through that wall; one that ends within ``tolerance_m`` of it confirms it. Each beam
    counts the wall length it covers (``distance * spacing / cos(incidence)``) on the nearest
    segment only; walls met at more than :data:`MAX_INCIDENCE_DEG` incidence and beams without
    a return are not judged.

    Returns:
        ``(see, confirmed)``: ``(M,)`` float64 wall length (metres) of each segment seen
        through and confirmed.
    """
    m = seg_endpoints.shape[0]
    if m == 0 or profile.bearing.shape[0] == 0:
        return np.zeros(m), np.zeros(m)
    see, cons = ray_wall_check(
        np.ascontiguousarray(seg_endpoints, dtype=np.float64),
        profile.bearing,
        *profile.directions,
        profile.range,
        profile.spacing,
        profile.range_max_m,
        tolerance_m,
        _COS_MAX_INCIDENCE,
    )
    return see, cons
