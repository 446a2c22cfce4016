"""Configuration of ICE matching (docs/design.md "ICE matching, step by step", steps 5-10) and the
motion bounds of one match."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, model_validator

from iceg_common.errors import ConfigError


@dataclass(frozen=True)
class MatchBounds:
    """Admissible motion around the prediction for one match (paper §III-C2: "the feasible
    area defined by admissible motion distance").

    Attributes:
        max_translation_m: Largest distance (metres) between the predicted and the true
            position of the new scan in the reference frame; ``inf`` for a global match.
        max_rotation_rad: Largest absolute difference (radians) between the predicted and the
            true heading; ``pi`` (or more) for a global match.

    Raises:
        ConfigError: a negative or NaN bound.
    """

    max_translation_m: float
    max_rotation_rad: float

    def __post_init__(self) -> None:
        t, r = float(self.max_translation_m), float(self.max_rotation_rad)
        if not (t >= 0.0) or not (r >= 0.0):
            raise ConfigError(
                f"MatchBounds: max_translation_m ({t}) and max_rotation_rad ({r}) must be >= 0"
            )
        # Python floats whatever the caller passed (numpy floats compare to numpy.bool)
        object.__setattr__(self, "max_translation_m", t)
        object.__setattr__(self, "max_rotation_rad", r)

    @classmethod
    def global_(cls) -> MatchBounds:
        """Unbounded search: no usable prediction (relocalisation, loop-closure search)."""
        return cls(math.inf, math.pi)

    @classmethod
    def local(cls, max_translation_m: float, max_rotation_deg: float) -> MatchBounds:
        """Bounds from a translation in metres and a rotation in degrees."""
        return cls(float(max_translation_m), math.radians(max_rotation_deg))

    @property
    def is_global(self) -> bool:
        """True when the rotation is unbounded (``>= pi``) and the translation infinite."""
        return self.max_rotation_rad >= math.pi and math.isinf(self.max_translation_m)

    @property
    def rotation_unbounded(self) -> bool:
        """True when any heading is admissible."""
        return self.max_rotation_rad >= math.pi


class FilterConfig(BaseModel):
    """Hierarchical candidate filter and hypotheses (paper §III-C2; docs/design.md step 5-6)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    corner_eow_matching: bool = Field(
        default=True,
        description="Allow a Corner to match an EOW through one of its edges (paper §III-C2: "
        "'only one exception ... a Corner may be matched with an EOW', Fig. 1-2).",
    )
    max_opening_diff_deg: float = Field(
        default=12.0,
        gt=0.0,
        le=90.0,
        description="Largest difference between the opening angles of two matched Corners or "
        "Intersections (paper §III-C2: 'should not be more than a low threshold').",
    )
    direction_tolerance_deg: float = Field(
        default=8.0,
        ge=0.0,
        le=90.0,
        description="Noise allowance added to the rotation bound when checking a pair's "
        "direction against the predicted rotation (paper §III-C2, direction filter; "
        "feature directions of short edges are noisy by a few degrees).",
    )
    feasible_margin_m: float = Field(
        default=0.3,
        ge=0.0,
        description="Noise allowance added to the feasible-area radius (paper §III-C2, "
        "'feasible area defined by admissible motion distance') for feature position noise.",
    )
    intersection_pair_tolerance_m: float = Field(
        default=0.15,
        gt=0.0,
        description="Two Intersection pairs form a hypothesis only if the distance between "
        "the two new Intersections equals that between the two reference ones within this "
        "(docs/design.md step 6: two Intersection pairs fix a transform).",
    )
    intersection_min_baseline_m: float = Field(
        default=0.8,
        gt=0.0,
        description="Smallest distance between the two Intersections of a two-pair hypothesis "
        "(a short baseline gives a poorly determined rotation; docs/design.md step 6).",
    )
    max_intersection_pairs: int = Field(
        default=600,
        ge=2,
        description="Cap on candidate Intersection pairs combined two by two (quadratic cost); "
        "beyond it the nearest-to-prediction pairs are kept (docs/design.md step 6).",
    )


class VotingConfig(BaseModel):
    """Voting and choice of the hypotheses to refine (paper §III-C3; docs/design.md step 6)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    vote_cell_m: float = Field(
        default=0.15,
        gt=0.0,
        description="Grid cell (x and y) for clustering transform hypotheses (paper §III-C3: "
        "'we start from the conversion with the most count'); neighbouring cells vote "
        "together.",
    )
    vote_cell_deg: float = Field(
        default=3.0,
        gt=0.0,
        le=45.0,
        description="Grid cell (theta) for clustering transform hypotheses (paper §III-C3).",
    )
    max_clusters: int = Field(
        default=12,
        ge=1,
        description="Most-voted hypothesis clusters whose correlation is evaluated (paper "
        "§III-C3: most count first, then correlation).",
    )
    max_refined: int = Field(
        default=3,
        ge=1,
        description="Best-correlated clusters refined by Gauss-Newton in a bounded match "
        "(docs/design.md step 8).",
    )
    max_refined_global: int = Field(
        default=8,
        ge=1,
        description="Best-correlated clusters refined in a global match (no prediction: more "
        "rival hypotheses must be checked before one is trusted).",
    )
    refine_correlation_margin: float = Field(
        default=0.3,
        ge=0.0,
        le=1.0,
        description="Only clusters whose correlation is within this of the best are refined.",
    )
    use_prediction_hypothesis: bool = Field(
        default=True,
        description="For a bounded (local) match, also refine from the prediction itself, so a "
        "scene with few features (a corridor) still yields a point-to-line match whose "
        "covariance shows the degeneracy (docs/design.md step 9).",
    )


class CorrelationConfig(BaseModel):
    """The correlation of paper eq. 1-3 (docs/design.md step 7)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    gate_distance_m: float = Field(
        default=0.4,
        gt=0.0,
        description="g_d of the correlation's dis term (docs/design.md step 7, paper eq. 1): a new "
        "feature pairs with the nearest compatible reference feature within this distance.",
    )
    gate_angle_deg: float = Field(
        default=15.0,
        gt=0.0,
        le=90.0,
        description="g_a of the correlation's Angle term (docs/design.md step 7, paper eq. 1).",
    )
    fimp_near: float = Field(
        default=0.65,
        gt=0.0,
        le=1.0,
        description="fImp(0) of paper eq. 3: importance of a feature next to the robot.",
    )
    fimp_far: float = Field(
        default=0.1,
        gt=0.0,
        le=1.0,
        description="fImp(range_max) of paper eq. 3: importance at the sensor's reliable "
        "range; fImp(d) = fimp_near / (1 + k d) with k set by this value.",
    )
    fimp_range_m: float | None = Field(
        default=None,
        gt=0.0,
        description="Range at which fImp reaches fimp_far (paper eq. 3: 'the laser reliable "
        "range is 20 meter'); None uses the scan's ScanFeatures.range_max_m.",
    )
    weight_dis: float = Field(default=0.4, ge=0.0, description="Weight of dis in paper eq. 1.")
    weight_ang: float = Field(default=0.2, ge=0.0, description="Weight of ang in paper eq. 1.")
    weight_count: float = Field(default=0.2, ge=0.0, description="Weight of count in paper eq. 1.")
    weight_acc: float = Field(default=0.6, ge=0.0, description="Weight of acc in paper eq. 1-2.")
    occlusion_tolerance_m: float = Field(
        default=0.25,
        gt=0.0,
        description="A reference feature counts as visible in the new scan (count term of eq. "
        "1) unless the new scan's range at its bearing is shorter than its distance minus "
        "this (docs/design.md 'Feature map and time-validity').",
    )

    @model_validator(mode="after")
    def _check_fimp(self) -> CorrelationConfig:
        if self.fimp_far >= self.fimp_near:
            raise ConfigError(
                f"matching.correlation: fimp_far ({self.fimp_far}) must be below fimp_near "
                f"({self.fimp_near})"
            )
        return self


class RefinementConfig(BaseModel):
    """Gauss-Newton refinement (paper §III-C3 "an optimization problem"; docs/design.md step 8;
    off-segment points: PL-ICP, Censi 2008)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    max_iterations: int = Field(
        default=16,
        ge=2,
        description="Gauss-Newton iterations (paper §III-C3: 'an optimization problem').",
    )
    association_gate_m: float = Field(
        default=0.3,
        gt=0.0,
        description="Point-to-segment association gate of the refinement's coarse phase "
        "(docs/design.md step 8; Corner/Intersection position pairs also pull then); once the "
        "steps are small it shrinks to association_gate_sigmas times the estimated point noise and "
        "only EOW pairs (along their wall) stay, since a Corner's position is its lines'.",
    )
    association_gate_sigmas: float = Field(
        default=4.0,
        gt=1.0,
        description="Final association gate in units of the estimated point noise (docs/design.md "
        "step 8: points not on a matched segment must not pull).",
    )
    association_gate_min_m: float = Field(
        default=0.04,
        gt=0.0,
        description="Smallest association gate, metres (covers unmodelled wall roughness).",
    )
    segment_end_tolerance_m: float = Field(
        default=0.15,
        ge=0.0,
        description="A point may associate with a reference segment up to this beyond its "
        "endpoints (endpoints of extracted segments are noisy; docs/design.md step 3).",
    )
    normal_gate_deg: float = Field(
        default=20.0,
        gt=0.0,
        lt=90.0,
        description="A point associates only with a reference segment whose line is within "
        "this angle of the point's own segment's line (after the hypothesis' rotation).",
    )
    point_sigma_min_m: float = Field(
        default=0.005,
        gt=0.0,
        description="Floor of the point-to-line noise estimated from the residuals (an honest "
        "point noise for sigma^2 (J^T J)^-1, docs/design.md step 9).",
    )
    wall_end_sigma_m: float = Field(
        default=0.0,
        ge=0.0,
        description="Standard deviation (metres) of each end of a reference wall off the line "
        "fitted to it, independent at the two ends: the laser's systematic range error (about "
        "1 cm for SICK LMS and Hokuyo UTM scanners) and walls that are not straight lines, "
        "which do not average out over the wall's beams. Adds an angle variance "
        "2 sigma^2 / L^2 and an offset variance sigma^2 / 2 (at the midpoint) to the line fit "
        "covariance of a wall of length L (docs/design.md step 9). 0 (the default) keeps the "
        "fit covariance alone, honest for straight simulated walls; 0.01 halves the outdoor "
        "world's error and the ACES log's with synthetic odometry but costs MIT CSAIL 10 % "
        "in translation and 30 % in rotation (docs/design.md, 'Wall model error').",
    )
    use_off_segment_points: bool = Field(
        default=True,
        description="Also use the scan's points that lie on no segment (clutter, short "
        "structures such as door frames) with point-to-point residuals against the "
        "reference's points, when the reference has points (docs/design.md step 8 extension: they "
        "constrain what long parallel walls leave open).",
    )
    local_line_max_gap_m: float = Field(
        default=0.5,
        gt=0.0,
        description="A reference point's local line (for the off-segment points' "
        "point-to-line rows, Censi 2008 PL-ICP) runs through its beam neighbours closer than "
        "this; a point without one gets a point-to-point residual.",
    )
    max_points: int = Field(
        default=400,
        ge=20,
        description="Most scan points used by the refinement (evenly subsampled beyond this).",
    )


class CovarianceConfig(BaseModel):
    """Covariance from the correlation landscape (Olson 2009; docs/design.md step 9) and its
    degeneracy limits (docs/design.md step 10)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    lattice_steps: int = Field(
        default=5,
        ge=3,
        description="Lattice points per axis for the correlation-landscape covariance (Olson "
        "2009, 'Real-time correlative scan matching'); odd so that it contains the estimate.",
    )
    lattice_sigmas: float = Field(
        default=3.0,
        gt=0.0,
        description="Half-width of the lattice in standard deviations of the least-squares "
        "covariance along each principal axis (Olson 2009).",
    )
    lattice_kappa: float = Field(
        default=1.0,
        gt=0.0,
        description="kappa of the lattice weights exp(kappa (s - s_max)); the score s is the "
        "robust log-likelihood of the refinement residuals, so 1 is the Bayesian value.",
    )
    lattice_max_half_width_m: float = Field(
        default=1.0,
        gt=0.0,
        description="Cap of the lattice half-width in translation (degenerate directions).",
    )
    lattice_max_half_width_deg: float = Field(
        default=10.0,
        gt=0.0,
        description="Cap of the lattice half-width in rotation (degenerate directions).",
    )
    max_std_m: float = Field(
        default=0.5,
        gt=0.0,
        description="A result whose translation standard deviation along any direction exceeds "
        "this is degenerate and fails (docs/design.md step 10). Bounded matches cap unobserved "
        "directions at the uniform variance of the bounds first.",
    )
    max_std_deg: float = Field(
        default=5.0,
        gt=0.0,
        description="A result whose rotation standard deviation exceeds this is degenerate.",
    )

    @model_validator(mode="after")
    def _check_lattice(self) -> CovarianceConfig:
        if self.lattice_steps % 2 == 0:
            raise ConfigError(
                f"matching.covariance: lattice_steps must be odd (the lattice must contain "
                f"the estimate), got {self.lattice_steps}"
            )
        return self


class ValidationConfig(BaseModel):
    """Acceptance checks and the choice among refined hypotheses (docs/design.md step 10)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    tracking_max_translation_m: float = Field(
        default=1.0,
        gt=0.0,
        description="Bounds up to this translation (and tracking_max_rotation_deg) are "
        "tracking: one feature pair, the bounded correlation threshold and the first passing "
        "hypothesis suffice. Wider bounds (loop closure) use the global thresholds and "
        "compare all refined hypotheses (docs/design.md step 10).",
    )
    tracking_max_rotation_deg: float = Field(
        default=30.0,
        gt=0.0,
        description="Rotation limit of tracking bounds (see tracking_max_translation_m).",
    )
    min_correlation: float = Field(
        default=0.25,
        ge=0.0,
        le=1.0,
        description="A bounded match whose correlation (paper eq. 1) is below this fails "
        "(docs/design.md step 10). Real scans of cluttered rooms reach 0.25-0.45 at the true pose "
        "(many new features lower acc), simulated ones 0.6-1.",
    )
    min_correlation_global: float = Field(
        default=0.45,
        ge=0.0,
        le=1.0,
        description="The same for a global match (a far larger hypothesis space needs stronger "
        "evidence).",
    )
    min_matched_features: int = Field(
        default=1,
        ge=1,
        description="Fewest feature pairs a feature-supported bounded match needs "
        "(docs/design.md step 10); one directed pair fixes a full pose, and the bounds exclude "
        "far look-alikes.",
    )
    min_matched_features_global: int = Field(
        default=2,
        ge=1,
        description="Fewest feature pairs a global (or wide-bounds) match needs: over the "
        "whole map a single Corner or EOW has many look-alikes, a configuration of two is "
        "distinctive.",
    )
    min_point_overlap: float = Field(
        default=0.3,
        ge=0.0,
        le=1.0,
        description="Fewest fraction of the scan's segment points that must lie on reference "
        "segments after refinement (docs/design.md step 10: too few inliers fails).",
    )
    min_point_overlap_global: float = Field(
        default=0.5,
        ge=0.0,
        le=1.0,
        description="The same for a global match (no prediction to rule out look-alikes; "
        "correct simulated global matches: 1st percentile 0.46 with the 180-degree scanner, "
        "0.84 with a full turn).",
    )
    min_point_overlap_featureless: float = Field(
        default=0.6,
        ge=0.0,
        le=1.0,
        description="The same for a bounded match from the prediction without any feature pair "
        "(a corridor, or features too unstable to pair): the points alone must agree.",
    )
    ambiguity_margin: float = Field(
        default=0.1,
        ge=0.0,
        description="A match fails as ambiguous when a distinct refined hypothesis that passes "
        "every check scores (correlation + point overlap) within this of the best "
        "(docs/design.md step 10: never a confident wrong pose in a self-similar scene).",
    )
    ambiguity_distance_m: float = Field(
        default=0.3,
        gt=0.0,
        description="Two refined hypotheses farther apart than this (or ambiguity_angle_deg) "
        "are distinct.",
    )
    ambiguity_angle_deg: float = Field(
        default=5.0, gt=0.0, description="Angular distinctness threshold of two refined hypotheses."
    )
    see_through_tolerance_m: float = Field(
        default=0.3,
        gt=0.0,
        description="A wall of one scan is contradicted when the other scan's beam at its "
        "bearing reaches farther than its distance plus this (free-space consistency).",
    )
    max_see_through_fraction: float = Field(
        default=0.25,
        ge=0.0,
        le=1.0,
        description="A match fails when more than this fraction of the checked wall length "
        "lies where the other scan sees free space (a confident wrong pose is worse than none).",
    )
    see_through_min_length_m: float = Field(
        default=1.0,
        ge=0.0,
        description="The see-through test fails a match only if at least this much wall length "
        "is contradicted.",
    )
    see_through_max_length_m: float = Field(
        default=1.5,
        gt=0.0,
        description="A match also fails when this much wall length (metres) is contradicted, "
        "whatever the fraction (real consecutive ACES scans at their corrected poses: at most "
        "1.2 m, 99th percentile 0.56 m).",
    )
    robot_clearance_m: float = Field(
        default=0.25,
        ge=0.0,
        description="No wall of one scan may pass closer than this to the other scan's sensor "
        "(a robot has a body; real ACES/CSAIL scans keep at least 0.37 m from their own and "
        "their neighbours' walls).",
    )


class MatchingConfig(BaseModel):
    """Thresholds and weights of the ICE matcher, one sub-model per step of the matcher.

    Distances are metres, angles degrees (converted once to radians by the matcher). Each
    field's description cites the paper section or equation (or the reference paper) it
    comes from; "docs/design.md" refers to ``docs/design.md``, "ICE matching, step by step".

    Raises:
        ConfigError: from a sub-model's cross-field check (``lattice_steps`` even,
            ``fimp_far >= fimp_near``); single out-of-range values raise pydantic's
            ``ValidationError`` (``iceg.config`` turns both into one ``ConfigError``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    filter: FilterConfig = Field(default_factory=FilterConfig)
    voting: VotingConfig = Field(default_factory=VotingConfig)
    correlation: CorrelationConfig = Field(default_factory=CorrelationConfig)
    refinement: RefinementConfig = Field(default_factory=RefinementConfig)
    covariance: CovarianceConfig = Field(default_factory=CovarianceConfig)
    validation: ValidationConfig = Field(default_factory=ValidationConfig)
    method: Literal["ice", "plicp", "small_gicp", "kiss_icp", "open3d_point", "open3d_plane"] = (
        Field(
            default="ice",
            description="Scan matcher behind the same graph back-end: 'ice' (this matcher), "
            "'plicp' (point-to-line ICP, Censi 2008, on the project's refinement), or an "
            "adapter of an installed peer library (extra 'peers'): 'small_gicp' (GICP), "
            "'kiss_icp' (KISS-ICP registration), 'open3d_point' / 'open3d_plane' (Open3D "
            "point-to-point / point-to-plane ICP). See iceg.matching.peers.",
        )
    )
    cauchy_scale_sigmas: float = Field(
        default=2.5,
        gt=0.0,
        description="Cauchy robust kernel scale in units of each row's standard deviation, "
        "for every robust row of the refinement (point-to-line, feature pairs, off-segment "
        "points; docs/design.md step 8) and of the covariance lattice (docs/design.md step 9).",
    )
