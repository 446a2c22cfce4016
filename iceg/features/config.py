"""Configuration of ICE feature extraction (docs/design.md "ICE matching, step by step", 1-4)."""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict, Field


class FeatureConfig(BaseModel):
    """Thresholds of scan segmentation and Intersection / Corner / End-of-wall extraction.

    Every distance is in metres and every angle in degrees (converted to radians by the
    stage of :func:`iceg.features.extract` that reads it; degrees never reach the
    arithmetic). Every field is read by one of the stages, except ``measure_robot_body`` and
    ``measure_wall_dropouts``, which the run of a log reads before them. The defaults suit a
    SICK LMS200-class scanner (1 cm range noise, 0.5°-1° beam spacing) indoors.
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    # --- step 1: points -------------------------------------------------------------------
    range_max_m: float = Field(
        default=20.0,
        gt=0.0,
        description="Usable maximum range (docs/design.md step 1; paper §IV: SICK LMS200, "
        "20 m). Beams at or beyond min(this, scan.range_max_m) are dropped as points and "
        "remembered as 'no return' for the end-of-wall test; it is also "
        "ScanFeatures.range_max_m (paper eq. 3).",
    )
    robot_body_range_m: float = Field(
        default=0.0,
        ge=0.0,
        description="Returns at or within this range of the laser are the robot itself (the "
        "posts or mast around a lidar, the chassis): they give no point, feature or map cell, "
        "they occlude (an end of wall is not seen past them, unlike the scan's own "
        "range_min_m, below which a ROS driver's beam is a no-return), and a wall is one "
        "segment across them. 0: none. A run of a log raises it to the body its scans show "
        "(measure_robot_body), and warns where its trajectory shows more "
        "(iceg.robot_body.robot_body_range; docs/design.md, 'The robot's own body').",
    )
    robot_body_dark_deg: tuple[tuple[float, float], ...] = Field(
        default=(),
        description="Bearings [from, to] (degrees, robot frame: the beam's bearing plus the "
        "laser's mounting yaw, in -180..180) where the robot's own body hides the view and "
        "the driver reports no return (+inf, or range_max) for it: there a beam without a "
        "return is read as a return too close to measure (-inf, ROS REP 117), which "
        "occludes (no end of wall at its edges) and across which a wall is one segment, as "
        "across the body's returns. A run of a log measures them with robot_body_range_m "
        "(measure_robot_body). The grid does not read them: with grid.no_return_clear_m set, "
        "such beams clear the cells behind the body.",
    )
    measure_robot_body: bool = Field(
        default=True,
        description="Before a log's first scan (iceg run, iceg batch), measure the robot's "
        "own body from its scans along its odometry (returns that keep their bearing and "
        "range as the robot turns in place, and bearings without a return where the turned "
        "scan sees the world: iceg.robot_body.robot_body_range), raise robot_body_range_m "
        "to it where it reaches farther and set robot_body_dark_deg where it is empty. A "
        "robot that never turns in place (within 1 m of travel) shows nothing, and keeps "
        "both.",
    )
    sigma_range_m: float = Field(
        default=0.01,
        gt=0.0,
        description="Standard deviation of a beam's range noise: the 3 sigma_r term of the "
        "adaptive breakpoint threshold (Borges & Aldon 2004) and the point variance of the "
        "maximum-likelihood line fit (Pfister et al. 2003).",
    )
    line_variance_from_residuals: bool = Field(
        default=True,
        description="Scale each scan's line covariances by the a-posteriori variance factor "
        "of its line fits (the weighted squared residuals per degree of freedom, floored at "
        "1; iceg.features.lines.fit_lines): a scanner noisier than sigma_range_m, or walls "
        "that are not straight, make every line and feature as uncertain as the scan shows.",
    )
    sigma_bearing_deg: float = Field(
        default=0.01,
        ge=0.0,
        description="Standard deviation of a beam's bearing: the across-beam part of a point's "
        "covariance in the line fit (Pfister et al. 2003, eq. 4); matters at grazing incidence.",
    )
    # --- step 2: breakpoints --------------------------------------------------------------
    breakpoint_lambda_deg: float = Field(
        default=10.0,
        gt=0.0,
        lt=90.0,
        description="Borges & Aldon 2004 lambda: the shallowest angle between a beam and a "
        "surface for which consecutive points still belong to one surface; D_max = r_prev "
        "sin(dphi) / sin(lambda - dphi) + 3 sigma_r.",
    )
    # --- step 3: split-and-merge, line fit ------------------------------------------------
    split_distance_m: float = Field(
        default=0.05,
        gt=0.0,
        description="Split-and-merge (paper §III-C1, Nguyen et al. 2005): a cluster is split "
        "at its point farthest from the chord of its end points when that distance exceeds "
        "this.",
    )
    merge_distance_m: float = Field(
        default=0.05,
        gt=0.0,
        description="Split-and-merge merge step (Nguyen et al. 2005): two adjacent segments "
        "are merged when every point of their union lies within this of the union's "
        "total-least-squares line.",
    )
    dropout_max_beams: int = Field(
        default=1,
        ge=0,
        description="Adjacent collinear segments separated only by at most this many invalid "
        "beams (single-beam dropouts, common in real SICK data) are merged across the "
        "breakpoint the dropout caused (merge step of Nguyen et al. 2005).",
    )
    min_segment_points: int = Field(
        default=5,
        ge=3,
        description="Minimum number of points of a line segment (Nguyen et al. 2005, P_min); "
        "shorter pieces are dropped.",
    )
    min_segment_length_m: float = Field(
        default=0.2,
        ge=0.0,
        description="Minimum length of a line segment between its projected endpoints "
        "(Nguyen et al. 2005, L_min); shorter pieces are dropped.",
    )
    # --- step 4: features ------------------------------------------------------------------
    meeting_angle_min_deg: float = Field(
        default=30.0,
        gt=0.0,
        lt=90.0,
        description="Corner and Intersection: the two lines meet at an angle in [this, 180 - "
        "this] degrees (docs/design.md step 4: 30°-150°; paper §III-B, Fig. 1-2).",
    )
    corner_gap_m: float = Field(
        default=0.3,
        gt=0.0,
        description="Corner (paper §III-B): the facing endpoints of the two segments, and the "
        "lines' intersection, must lie within this of each other, plus the along-wall beam "
        "spacing at each endpoint (r dphi / cos(incidence), incidence capped at "
        "eow_max_incidence_deg): at grazing incidence the last point before a corner may lie "
        "a whole beam gap away from it.",
    )
    eow_check_beams: int = Field(
        default=2,
        ge=1,
        description="End of wall (paper §III-B, Fig. 1): this many beams just beyond the "
        "endpoint (in beam order) must all see past the wall's extension; one beam alone may "
        "be a dropout. Fewer beams left before the scan's angular limit: no EOW.",
    )
    eow_range_margin_m: float = Field(
        default=0.15,
        gt=0.0,
        description="End of wall: a beam beyond the endpoint sees past the wall when its range "
        "exceeds the range at which it would hit the wall's extension by more than this.",
    )
    eow_max_incidence_deg: float = Field(
        default=80.0,
        gt=0.0,
        lt=90.0,
        description="End of wall: when the beams beyond the endpoint would meet the wall's "
        "extension at a larger incidence angle (from the wall normal) the wall may continue "
        "unseen (grazing), so the endpoint is not an EOW.",
    )
    eow_dropout_max_gap_m: float = Field(
        default=0.0,
        ge=0.0,
        description="End of wall: beams without a return beyond an endpoint, after which the "
        "wall's line returns within this distance of the endpoint, are a dropout patch in the "
        "wall (a dark or glossy surface), not a view past its end; a wider gap is an opening "
        "(a doorway is 0.7 m or more) and is seen past even when nothing returns through it. "
        "0: every returnless beam sees past. A run of a log sets it to 0.5 where its scanner "
        "loses returns on walls (measure_wall_dropouts).",
    )
    measure_wall_dropouts: bool = Field(
        default=True,
        description="Before a log's first scan (iceg run, iceg batch), measure how often its "
        "scanner loses the return on a wall (patches: runs of 2 or more beams without a "
        "return between two returns under 0.5 m apart, per 1000 returns, over up to 400 "
        "scans spread along the odometry's path: iceg.wall_dropouts) and, from 2.5, set "
        "eow_dropout_max_gap_m to 0.5 where it is 0 and most patches are not lost again in "
        "the next scan (at random, not a dark surface: docs/design.md, 'A scanner that loses "
        "returns at random').",
    )
    intersection_max_distance_m: float = Field(
        default=3.0,
        gt=0.0,
        description="Intersection (paper §III-B, Fig. 1-2; docs/design.md step 4): the meeting "
        "point of the two infinite lines must lie within this of both segments.",
    )
    intersection_duplicate_m: float = Field(
        default=0.3,
        gt=0.0,
        description="Intersection: a meeting point within this of a Corner, or of a better "
        "determined Intersection, is the same feature and is dropped (docs/design.md step 4).",
    )
    intersection_max_std_m: float = Field(
        default=0.25,
        gt=0.0,
        description="Intersection: dropped when the square root of the largest eigenvalue of "
        "its position covariance exceeds this (a far meeting of short, nearly parallel "
        "segments carries no usable position; paper eq. 3 weights by distance likewise).",
    )
