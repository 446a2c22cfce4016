"""The ICE matcher: DESIGN.md steps 5-10 (paper §III-C2, §III-C3)."""

from __future__ import annotations

import functools
import logging
import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray
from scipy.spatial import cKDTree

from iceg.matching._kernels import ray_wall_check
from iceg.matching.config import MatchBounds, MatchingConfig
from iceg.matching.correlation import Correlation, correlate
from iceg.matching.geometry import (
    FeatureGeometry,
    PolarProfile,
    SegmentSet,
    feature_geometry,
    point_segment_index,
    rot,
)
from iceg.matching.hypotheses import generate_hypotheses, pair_codes, segment_rotation, vote
from iceg.matching.refine import (
    Cloud,
    Refined,
    RefineSettings,
    bounds_prior_information,
    refine,
)
from iceg.types import MatchResult, ScanFeatures
from iceg_common.errors import MatchingError
from iceg_common.se2 import inverse, wrap_angle

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


@dataclass(eq=False)
class _Candidate:
    """A refined hypothesis with its correlation and checks."""

    from_prediction: bool
    refined: Refined
    corr: Correlation
    failure: str = ""
    rival: bool = False
    see_through: float = 0.0

    @property
    def fitness(self) -> float:
        """Ranking score: correlation (eq. 1) plus the point overlap of the refinement, plus
        0.1 per feature pair (up to 5), minus twice the fraction of walls that the other
        scan sees through."""
        return (
            float(self.corr.score[0])
            + self.refined.overlap
            + 0.1 * min(int(self.corr.n_matched[0]), 5)
            - 2.0 * self.see_through
        )


def _is_one_scan(points_xy: FloatArray) -> bool:
    """Whether points look like one scan from the frame's origin: bearings increase along
    the array (beam order), with at most one wrap-around."""
    if points_xy.shape[0] < 3:
        return False
    d = np.diff(np.arctan2(points_xy[:, 1], points_xy[:, 0]))
    back = d < -0.05
    return int(back.sum()) == 0 or (int(back.sum()) == 1 and float(d[back][0]) < -math.pi)


def _segment_distance(p: FloatArray, endpoints: FloatArray) -> float:
    """Distance (metres) from point ``p`` (2,) to the nearest of segments ``(M, 2, 2)``."""
    if endpoints.shape[0] == 0:
        return math.inf
    a = endpoints[:, 0]
    e = endpoints[:, 1] - a
    l2 = np.maximum(np.einsum("ma,ma->m", e, e), 1e-12)
    t = np.clip(np.einsum("ma,ma->m", p - a, e) / l2, 0.0, 1.0)
    d = p - (a + t[:, None] * e)
    return float(np.sqrt(np.einsum("ma,ma->m", d, d).min()))


def _lengths(endpoints: FloatArray) -> FloatArray:
    d = endpoints[:, 1] - endpoints[:, 0]
    return np.hypot(d[:, 0], d[:, 1])


def _same_pose(a: FloatArray, b: FloatArray, dist_m: float, angle_rad: float) -> bool:
    return (
        math.hypot(a[0] - b[0], a[1] - b[1]) <= dist_m
        and abs(float(wrap_angle(a[2] - b[2]))) <= angle_rad
    )


def _check_features(f: ScanFeatures, what: str) -> None:
    k = f.kind.shape[0]
    shapes = {
        "xy": (f.xy.shape, (k, 2)),
        "cov": (f.cov.shape, (k, 2, 2)),
        "directions": (f.directions.shape, (k, 2, 2)),
        "opening_rad": (f.opening_rad.shape, (k,)),
        "ids": (f.ids.shape, (k,)),
    }
    m = f.seg_endpoints.shape[0]
    shapes.update(
        {
            "seg_endpoints": (f.seg_endpoints.shape, (m, 2, 2)),
            "seg_lines": (f.seg_lines.shape, (m, 2)),
            "seg_cov": (f.seg_cov.shape, (m, 2, 2)),
        }
    )
    for name, (got, want) in shapes.items():
        if tuple(got) != want:
            raise MatchingError(
                f"{what}.{name} has shape {tuple(got)}, expected {want} "
                "(see iceg.types.ScanFeatures)"
            )
    if f.points_xy.ndim != 2 or f.points_xy.shape[1] != 2:
        raise MatchingError(f"{what}.points_xy must have shape (P, 2), got {f.points_xy.shape}")


class IceMatcher:
    """ICE scan matching (paper §III-C2/C3; DESIGN.md "ICE matching, step by step", 5-10).

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
        c = self.config
        self._settings = RefineSettings(
            max_iterations=c.max_iterations,
            gate_m=c.association_gate_m,
            gate_sigmas=c.association_gate_sigmas,
            gate_min_m=c.association_gate_min_m,
            end_tol_m=c.segment_end_tolerance_m,
            normal_gate_rad=math.radians(c.normal_gate_deg),
            cauchy_sigmas=c.cauchy_scale_sigmas,
            sigma_min_m=c.point_sigma_min_m,
            line_angle_sigma_min_rad=math.radians(c.line_angle_sigma_min_deg),
            line_offset_sigma_min_m=c.line_offset_sigma_min_m,
            lattice_steps=c.lattice_steps,
            lattice_sigmas=c.lattice_sigmas,
            lattice_kappa=c.lattice_kappa,
            lattice_cap_m=c.lattice_max_half_width_m,
            lattice_cap_rad=math.radians(c.lattice_max_half_width_deg),
        )

    def __repr__(self) -> str:
        return f"IceMatcher({self.config!r})"

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
        c = self.config
        bounds = bounds or MatchBounds.global_()
        pred = np.asarray(prediction, dtype=np.float64).reshape(-1)
        if pred.shape != (3,) or not np.all(np.isfinite(pred)):
            raise MatchingError(f"prediction must be a finite (3,) pose, got {prediction!r}")
        _check_features(features, "features")
        _check_features(reference, "reference")

        gn = feature_geometry(features)
        gr = feature_geometry(reference)
        codes = pair_codes(gn, gr, c.corner_eow_matching, math.radians(c.max_opening_diff_deg))
        hyps = generate_hypotheses(
            gn,
            gr,
            codes,
            pred,
            bounds,
            margin_m=c.feasible_margin_m,
            direction_tolerance_rad=math.radians(c.direction_tolerance_deg),
            intersection_tolerance_m=c.intersection_pair_tolerance_m,
            intersection_min_baseline_m=c.intersection_min_baseline_m,
            max_intersection_pairs=c.max_intersection_pairs,
        )
        clusters = vote(hyps.poses, c.vote_cell_m, math.radians(c.vote_cell_deg), c.max_clusters)
        starts = clusters.poses
        from_prediction = np.zeros(starts.shape[0], dtype=bool)
        if c.use_prediction_hypothesis and not bounds.is_global:
            start = pred.copy()
            th = segment_rotation(
                features.seg_lines,
                _lengths(features.seg_endpoints),
                reference.seg_lines,
                _lengths(reference.seg_endpoints),
                float(pred[2]),
                min(bounds.max_rotation_rad, math.pi / 2),
                math.radians(1.0),
                1.0,
            )
            if th is not None:
                start[2] = th
            starts = np.concatenate([starts, start[None]], axis=0)
            from_prediction = np.append(from_prediction, True)
        n_hyp = int(hyps.poses.shape[0])
        if starts.shape[0] == 0:
            return self._fail(
                pred,
                f"{REASON_NO_CANDIDATES}: no transform hypothesis "
                f"({gn.n} new, {gr.n} reference features, {hyps.n_pairs} "
                "candidate pairs)",
                n_hyp,
            )

        range_max = float(features.range_max_m)
        profile = PolarProfile.from_points(features.points_xy, range_max)
        # The reference's beams can be checked only if its points are one scan seen from
        # the reference origin (a feature-map reference gathers several nodes' points).
        ref_profile = (
            PolarProfile.from_points(reference.points_xy, float(reference.range_max_m))
            if _is_one_scan(reference.points_xy)
            else None
        )
        fimp_range = c.fimp_range_m or range_max
        corr_fn = functools.partial(
            correlate,
            gate_distance_m=c.gate_distance_m,
            gate_angle_rad=math.radians(c.gate_angle_deg),
            fimp_near=c.fimp_near,
            fimp_far=c.fimp_far,
            fimp_range_m=fimp_range,
            range_max_m=range_max,
            occlusion_tolerance_m=c.occlusion_tolerance_m,
            weights=(c.weight_dis, c.weight_ang, c.weight_count, c.weight_acc),
        )

        def correlation_at(poses: FloatArray) -> Correlation:
            return corr_fn(poses, gn, gr, codes, profile)

        corr0 = correlation_at(starts)
        # Order: correlation first (paper §III-C3: most count first, then correlation);
        # the prediction competes like any cluster.
        order = np.argsort(-corr0.score, kind="stable")
        best0 = float(corr0.score[order[0]])
        strict = self._strict(bounds)
        n_refine = c.max_refined_global if strict else c.max_refined
        chosen = [int(k) for k in order if corr0.score[k] >= best0 - c.refine_correlation_margin][
            :n_refine
        ]
        if from_prediction.any():
            kp = int(np.flatnonzero(from_prediction)[0])
            if kp not in chosen:
                chosen.append(kp)

        # Points for the refinement: those on the new scan's segments.
        pseg = point_segment_index(features)
        on_seg = np.flatnonzero(pseg >= 0)
        if on_seg.shape[0] > c.max_points:
            on_seg = on_seg[np.linspace(0, on_seg.shape[0] - 1, c.max_points).astype(np.int64)]
        points = features.points_xy[on_seg]
        point_alpha = features.seg_lines[pseg[on_seg], 0] if on_seg.shape[0] else np.zeros(0)
        segs = SegmentSet.from_features(reference)
        cloud = self._cloud(features, reference, pseg)
        prior = bounds_prior_information(bounds.max_translation_m, bounds.max_rotation_rad)

        def pairs_at(pose: FloatArray) -> IntArray:
            m = corr_fn(pose[None], gn, gr, codes, profile, pairing_only=True).match[0]
            i = np.flatnonzero(m >= 0)
            return np.column_stack([i, m[i]]).astype(np.int64)

        cands: list[_Candidate] = []
        near_d, near_a = c.ambiguity_distance_m, math.radians(c.ambiguity_angle_deg)
        for k in chosen:
            # A start next to an already refined pose would converge to it again.
            if any(_same_pose(starts[k], o.refined.pose, near_d, near_a) for o in cands):
                continue
            m0 = corr0.match[k]
            i0 = np.flatnonzero(m0 >= 0)
            ref = refine(
                starts[k],
                points,
                point_alpha,
                segs,
                gn,
                gr,
                pairs_at,
                prior,
                self._settings,
                pred,
                cloud,
                np.column_stack([i0, m0[i0]]).astype(np.int64),
            )
            if any(_same_pose(ref.pose, o.refined.pose, 0.05, math.radians(1.0)) for o in cands):
                continue
            corr = correlation_at(ref.pose[None])
            cand = _Candidate(bool(from_prediction[k]), ref, corr)
            cand.failure = self._check(
                cand, features, reference, gn, pred, bounds, profile, ref_profile
            )
            cands.append(cand)
            if not strict and not cand.failure:
                # Bounded match: the best-correlated hypothesis that passes is the answer
                # (rivals come from the bounds' small neighbourhood only).
                break
        return self._decide(cands, pred, n_hyp)

    def _cloud(
        self, features: ScanFeatures, reference: ScanFeatures, pseg: IntArray
    ) -> Cloud | None:
        """Off-segment points of the new scan (clutter, short structures) against all the
        reference's points, point-to-line on the local line through a reference point and
        its beam neighbours (Censi 2008, PL-ICP), so that points on walls add nothing along
        the walls; an isolated reference point gives a point-to-point residual whose noise
        includes half the distance to its nearest neighbour."""
        c = self.config
        if not c.use_off_segment_points or reference.points_xy.shape[0] < 3:
            return None
        new_off = np.flatnonzero(pseg < 0)
        if new_off.shape[0] == 0:
            return None
        if new_off.shape[0] > c.max_points // 2:
            pick = np.linspace(0, new_off.shape[0] - 1, c.max_points // 2).astype(np.int64)
            new_off = new_off[pick]
        rp = reference.points_xy
        d = np.diff(rp, axis=0)
        gaps = np.hypot(d[:, 0], d[:, 1])
        g_prev = np.insert(gaps, 0, np.inf)
        g_next = np.append(gaps, np.inf)
        nn = np.minimum(g_prev, g_next)
        # Local line: through the previous and next points when both are near, else the
        # nearer one.
        prev_pt = np.vstack([rp[:1], rp[:-1]])
        next_pt = np.vstack([rp[1:], rp[-1:]])
        lim = c.local_line_max_gap_m
        a = np.where((g_prev <= lim)[:, None], prev_pt, rp)
        b = np.where((g_next <= lim)[:, None], next_pt, rp)
        t = b - a
        tl = np.hypot(t[:, 0], t[:, 1])
        has = tl > 1e-6
        normal = np.full(rp.shape, np.nan)
        normal[has] = np.stack([-t[has, 1], t[has, 0]], axis=1) / tl[has, None]
        return Cloud(features.points_xy[new_off], cKDTree(rp), rp, nn, normal)

    def _strict(self, bounds: MatchBounds) -> bool:
        """A global match, or one whose bounds are wider than tracking's (loop closure,
        relocalisation): the hypothesis space is large, so the global evidence thresholds
        apply and every chosen hypothesis is refined and compared (ambiguity)."""
        c = self.config
        return (
            bounds.is_global
            or bounds.max_translation_m > c.tracking_max_translation_m
            or bounds.max_rotation_rad > math.radians(c.tracking_max_rotation_deg)
        )

    # ------------------------------------------------------------------------------------
    def _fail(self, pred: FloatArray, reason: str, n_hyp: int) -> MatchResult:
        log.debug("ICE match failed: %s", reason)
        return MatchResult(
            success=False,
            pose=pred.copy(),
            cov=np.full((3, 3), np.nan),
            correlation=0.0,
            n_hypotheses=n_hyp,
            reason=reason,
        )

    def _check(
        self,
        cand: _Candidate,
        features: ScanFeatures,
        reference: ScanFeatures,
        gn: FeatureGeometry,
        pred: FloatArray,
        bounds: MatchBounds,
        profile: PolarProfile,
        ref_profile: PolarProfile | None,
    ) -> str:
        """DESIGN step 10 checks of one refined hypothesis; returns the failure reason or
        an empty string."""
        c = self.config
        ref = cand.refined
        score = float(cand.corr.score[0])
        n_matched = int(cand.corr.n_matched[0])
        n_visible = int(cand.corr.n_visible[0])
        if not np.all(np.isfinite(ref.pose)):
            return f"{REASON_DEGENERATE}: refinement diverged"
        d = ref.pose - pred
        dist, dth = math.hypot(d[0], d[1]), abs(float(wrap_angle(d[2])))
        if dist > bounds.max_translation_m + c.feasible_margin_m or dth > (
            bounds.max_rotation_rad + math.radians(c.direction_tolerance_deg)
        ):
            return (
                f"{REASON_OUT_OF_BOUNDS}: refined pose {dist:.2f} m / {math.degrees(dth):.1f} deg "
                "from the prediction"
            )
        # Free space first: a hypothesis that contradicts what a scan sees is no answer and
        # no rival either.
        frac, length = self._see_through(ref.pose, features, reference, profile, ref_profile)
        cand.see_through = frac
        if (
            frac > c.max_see_through_fraction and length >= c.see_through_min_length_m
        ) or length >= c.see_through_max_length_m:
            return (
                f"{REASON_INCONSISTENT}: {frac:.0%} ({length:.1f} m) of the walls lie where "
                "the other scan sees free space"
            )
        clear = min(
            _segment_distance(ref.pose[:2], reference.seg_endpoints),
            _segment_distance(inverse(ref.pose)[:2], features.seg_endpoints),
        )
        if clear < c.robot_clearance_m:
            return (
                f"{REASON_INCONSISTENT}: a wall of one scan passes {clear:.2f} m from the other "
                f"scan's sensor (< {c.robot_clearance_m} m)"
            )
        if not self._origins_visible(ref.pose, profile, ref_profile):
            return (
                f"{REASON_INCONSISTENT}: one scan's origin lies behind a wall the other scan sees"
            )
        # A consistent hypothesis with feature support is a rival of the best even if it
        # is too weak to be accepted itself (one pair in a global match, few points).
        cand.rival = n_matched >= 1
        strict = self._strict(bounds)
        min_pairs = c.min_matched_features_global if strict else c.min_matched_features
        min_corr = c.min_correlation_global if strict else c.min_correlation
        if n_matched >= min_pairs:
            # Feature-supported: eq. 1 decides (paper §III-C3).
            if score < min_corr:
                return f"{REASON_LOW_CORRELATION}: {score:.3f} < {min_corr}"
            min_overlap = c.min_point_overlap_global if strict else c.min_point_overlap
        elif not strict and cand.from_prediction and n_matched == 0:
            # No feature pairs (a corridor, or features too unstable to pair), tracked from
            # the prediction: the points decide, and the covariance shows what the walls
            # leave unconstrained.
            min_overlap = c.min_point_overlap_featureless
        else:
            return (
                f"{REASON_FEW_INLIERS}: {n_matched} feature pairs (< {min_pairs}; "
                f"{gn.n} new, {n_visible} visible reference features)"
            )
        if ref.overlap < min_overlap:
            return (
                f"{REASON_FEW_INLIERS}: {ref.overlap:.0%} of the scan's points on reference "
                f"segments (< {min_overlap:.0%})"
            )
        return ""

    def _decide(self, cands: list[_Candidate], pred: FloatArray, n_hyp: int) -> MatchResult:
        """Pick the best refined hypothesis that passes the checks; fail when none does, when
        a distinct rival scores nearly as well (ambiguous), or when the covariance is
        degenerate (DESIGN step 10)."""
        c = self.config
        ok = [k for k in cands if not k.failure]
        if not ok:
            worst_first = sorted(cands, key=lambda k: -k.fitness)
            return self._fail(pred, worst_first[0].failure, n_hyp)
        ok.sort(key=lambda k: -k.fitness)
        best = ok[0]
        rivals = sorted((k for k in cands if k.rival and k is not best), key=lambda k: -k.fitness)
        for other in rivals:
            distinct = not _same_pose(
                best.refined.pose,
                other.refined.pose,
                c.ambiguity_distance_m,
                math.radians(c.ambiguity_angle_deg),
            )
            if distinct and other.fitness >= best.fitness - c.ambiguity_margin:
                d = other.refined.pose - best.refined.pose
                return self._fail(
                    pred,
                    f"{REASON_AMBIGUOUS}: two distinct hypotheses score {best.fitness:.2f} and "
                    f"{other.fitness:.2f} (apart {math.hypot(d[0], d[1]):.2f} m, "
                    f"{math.degrees(abs(float(wrap_angle(d[2])))):.1f} deg)",
                    n_hyp,
                )
        ref = best.refined
        cov_param = ref.cov
        evals = np.linalg.eigvalsh(cov_param[:2, :2]) if np.all(np.isfinite(cov_param)) else None
        if (
            evals is None
            or math.sqrt(max(evals[-1], 0.0)) > c.max_std_m
            or math.sqrt(max(cov_param[2, 2], 0.0)) > math.radians(c.max_std_deg)
        ):
            return self._fail(
                pred,
                f"{REASON_DEGENERATE}: the scene does not constrain the pose (std beyond "
                f"{c.max_std_m} m / {c.max_std_deg} deg)",
                n_hyp,
            )
        # Covariance into the tangent space at the pose, new scan frame (Pose2 local coords).
        m = np.eye(3)
        m[:2, :2] = rot(ref.pose[2]).T
        cov_body = m @ cov_param @ m.T
        cov_body = 0.5 * (cov_body + cov_body.T)
        mt = best.corr.match[0]
        i = np.flatnonzero(mt >= 0)
        pose = ref.pose.copy()
        pose[2] = float(wrap_angle(pose[2]))
        return MatchResult(
            success=True,
            pose=pose,
            cov=cov_body,
            correlation=float(best.corr.score[0]),
            inlier_pairs=np.column_stack([i, mt[i]]).astype(np.int64),
            n_hypotheses=n_hyp,
            reason="",
        )

    def _origins_visible(
        self, pose: FloatArray, profile: PolarProfile, ref_profile: PolarProfile | None
    ) -> bool:
        """Neither scan's origin lies behind a wall the other scan sees (a robot stands in
        free space): the other scan's beams around its bearing must not be shorter than its
        distance minus the see-through tolerance. Untestable cases pass."""
        tol = self.config.see_through_tolerance_m
        checks = [(inverse(pose)[:2], profile)]
        if ref_profile is not None:
            checks.append((pose[:2], ref_profile))
        for xy, prof in checks:
            if prof.bearing.shape[0] == 0:
                continue
            dist = math.hypot(xy[0], xy[1])
            _, hi, _ = _bracket(prof, np.array([math.atan2(xy[1], xy[0])]))
            if np.isfinite(hi[0]) and hi[0] < dist - tol:
                return False
        return True

    def _see_through(
        self,
        pose: FloatArray,
        features: ScanFeatures,
        reference: ScanFeatures,
        profile: PolarProfile,
        ref_profile: PolarProfile | None,
    ) -> tuple[float, float]:
        """Free-space consistency: the fraction (and length, metres) of checked wall that
        one scan places where the other scan's beams pass through. The reference segments
        are cast along the new scan's beams; when the reference has points (a scan), the new
        segments along the reference's beams too."""
        c = self.config
        len_see = 0.0
        len_cons = 0.0
        inv_r = rot(pose[2]).T
        ep_ref_new = (reference.seg_endpoints - pose[:2]) @ inv_r.T
        checks = [(ep_ref_new, profile)]
        if ref_profile is not None:
            ep_new_ref = features.seg_endpoints @ rot(pose[2]).T + pose[:2]
            checks.append((ep_new_ref, ref_profile))
        for ep, prof in checks:
            see, cons = _ray_check(ep, prof, c.see_through_tolerance_m)
            len_see += see
            len_cons += cons
        total = len_see + len_cons
        if total <= 0.0:
            return 0.0, 0.0
        return len_see / total, len_see


def _ray_check(ep: FloatArray, prof: PolarProfile, tol_m: float) -> tuple[float, float]:
    """Cast the segments ``ep`` (M, 2, 2) (the checking scan's frame) along its beams (its
    profile): a beam that reaches more than ``tol_m`` beyond the nearest segment it crosses
    sees through that wall; one that ends within ``tol_m`` of it confirms it. Returns the
    wall length (metres) seen through and confirmed; each beam counts the wall it covers
    (``distance * spacing / cos(incidence)``) once, however many copies of the wall a map
    reference holds. Walls met at more than 70 degrees incidence are not judged."""
    if ep.shape[0] == 0 or prof.bearing.shape[0] == 0:
        return 0.0, 0.0
    see, cons = ray_wall_check(
        np.ascontiguousarray(ep, dtype=np.float64),
        prof.bearing,
        prof.range,
        prof.spacing,
        prof.range_max_m,
        tol_m,
        math.cos(math.radians(70.0)),
    )
    return float(see), float(cons)


def _bracket(prof: PolarProfile, bearing: FloatArray) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Ranges of the two returns bracketing each bearing (their min and max) and of the
    nearest; NaN where the bracket spans a gap of more than 1.6 beam spacings."""
    n = prof.bearing.shape[0]
    k = np.searchsorted(prof.bearing, bearing)
    k0 = np.clip(k - 1, 0, n - 1)
    k1 = np.clip(k, 0, n - 1)
    b0, b1 = prof.bearing[k0], prof.bearing[k1]
    ok = (k > 0) & (k < n) & (b1 - b0 <= 1.6 * prof.spacing)
    r0, r1 = prof.range[k0], prof.range[k1]
    near = np.where(np.abs(bearing - b0) <= np.abs(b1 - bearing), r0, r1)
    lo = np.where(ok, np.minimum(r0, r1), np.nan)
    hi = np.where(ok, np.maximum(r0, r1), np.nan)
    return lo, hi, np.where(ok, near, np.nan)
