"""Refinement of a hypothesis (paper §III-C3 "an optimization problem"; docs/design.md step 8) and
its covariance (docs/design.md step 9).

Gauss-Newton over

- point-to-line residuals of the new scan's points against the reference segments
  (``r_i = n_m · (R p_i + t) - rho_m``; the segments are the ones ICE already extracted),
  with gated association and Cauchy robust weights, solved as generalised least squares:
  the reference line's own ``(alpha, rho)`` uncertainty is an error shared by all points on
  that line (per-line Woodbury inverse), so a small angle error of a long wall cannot pose
  as information along it;
- feature pairs of the correlation: an EOW pair constrains the position along its wall
  (what the lines cannot tell); Corner and Intersection pairs pull a coarse hypothesis in
  during the first (wide-gate) phase and are then dropped (their position is the lines');
- optionally, the new scan's off-segment points against the reference's points on local
  lines (PL-ICP, Censi 2008) when the reference has points;
- the bounds' prior (uniform variance of the admissible motion) pulling toward the
  prediction, which only matters along directions the scene leaves unconstrained.

All of it runs in one compiled call (:func:`~iceg.matching._kernels.refine_pose`): a
Gauss-Newton loop in two phases, a coarse one with the wide gate and full feature positions,
then a fine one with a gate of a few estimated sigmas, and the point-to-line rows at the
result.

The least-squares covariance is the inverse of that information (point noise ``sigma``
estimated from the residuals, floored). It is the floor of the correlation-landscape
covariance of Olson 2009 ("Real-time correlative scan matching"): the robust
log-likelihood evaluated on a small lattice of perturbations, weights
``exp(kappa (s - s_max))``, second moment. Both are perturbations of ``(x, y, theta)`` in the
reference frame; the matcher moves them to the new scan's frame.
"""

from __future__ import annotations

import functools
import math
from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from iceg.matching._kernels import (
    GATE_TO_SIGMA0,
    FeaturePairing,
    GnSettings,
    LatticeSettings,
    LineSegments,
    PairGeometry,
    PointCloud,
    PosePrior,
    SegmentPoints,
    all_finite,
    final_covariances,
    finite_points_within,
    line_covariances,
    point_line_system,
    points_explained,
    refine_pose,
    segment_grid,
    sorted_cells,
)
from iceg.matching._kernels import (  # the contradiction test's counts, for iceg.slam
    blocks_explained_counts as blocks_explained_counts,
)
from iceg.matching.geometry import EOW, FeatureGeometry, SegmentSet

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Points evaluated on the lattice (evenly subsampled beyond; the cost is scaled up).
LATTICE_POINTS = 100
#: Smallest cell of the reference segments' association grid (metres; the cell is the
#: association's reach, gate plus end tolerance, when larger).
SEGMENT_GRID_MIN_CELL_M = 1.0
#: Guard of the wall-length division in :func:`effective_line_cov` (metres).
_MIN_WALL_LENGTH_M = 1e-3


@dataclass(frozen=True, eq=False)
class RefineSettings:
    """Numbers of the refinement in internal units (metres, radians); built from
    :class:`~iceg.matching.config.MatchingConfig` (``refinement``, ``covariance`` and
    ``cauchy_scale_sigmas``) by the matcher."""

    max_iterations: int
    gate_m: float
    gate_sigmas: float
    gate_min_m: float
    end_tol_m: float
    normal_gate_rad: float
    cauchy_sigmas: float
    sigma_min_m: float
    wall_end_sigma_m: float
    lattice_steps: int
    lattice_sigmas: float
    lattice_kappa: float
    lattice_cap_m: float
    lattice_cap_rad: float

    def kernel(self) -> GnSettings:
        """The settings the compiled Gauss-Newton loop needs (built once per settings)."""
        return self._kernel

    def lattice(self) -> LatticeSettings:
        """The settings the compiled covariance lattice needs (built once per settings)."""
        return self._lattice

    @functools.cached_property
    def _kernel(self) -> GnSettings:
        return GnSettings(
            float(self.end_tol_m),
            math.sin(self.normal_gate_rad),
            float(self.sigma_min_m),
            float(self.cauchy_sigmas),
            float(self.gate_m),
            float(self.gate_sigmas),
            float(self.gate_min_m),
            int(EOW),
        )

    @functools.cached_property
    def _lattice(self) -> LatticeSettings:
        return LatticeSettings(
            _unit_lattice(self.lattice_steps),
            float(self.lattice_sigmas),
            float(self.lattice_cap_m),
            float(self.lattice_cap_rad),
            float(self.lattice_kappa),
            float(self.end_tol_m),
            float(self.cauchy_sigmas),
        )


@dataclass(frozen=True, eq=False)
class RefineProblem:
    """What every refinement of one match shares (docs/design.md step 8).

    Attributes:
        points: The new scan's points on new segments (new frame) and their segments'
            normal angles.
        segs: Reference segments (reference frame).
        line_info: ``(M, 2, 2)`` float64 information (inverse covariance) of each reference
            line ``(alpha, rho)`` (see :func:`effective_line_info`).
        new_geom, ref_geom: New and reference feature geometry.
        pairing: The correlation's feature pairing (no features: no pairs).
        prior: The bounds' prior (mean: the prediction; information: uniform variance of
            the admissible motion, zeros when unbounded).
        cloud: Off-segment new points against the reference's points (may hold none).
        settings: Refinement settings.
    """

    points: SegmentPoints
    segs: SegmentSet
    line_info: FloatArray
    new_geom: FeatureGeometry
    ref_geom: FeatureGeometry
    pairing: FeaturePairing
    prior: PosePrior
    cloud: PointCloud
    settings: RefineSettings

    @functools.cached_property
    def lines(self) -> LineSegments:
        """Reference segments with their line information, for the kernels."""
        s = self.segs
        reach = self.settings.gate_m + self.settings.end_tol_m  # every gate is <= gate_m
        grid = segment_grid(s.a, s.u, s.length, reach, max(reach, SEGMENT_GRID_MIN_CELL_M))
        return LineSegments(s.a, s.u, s.length, s.normal, s.rho, self.line_info, grid)

    @functools.cached_property
    def pair_geometry(self) -> PairGeometry:
        """Feature geometry of both scans, for the kernels."""
        n, r = self.new_geom, self.ref_geom
        return PairGeometry(
            n.xy,
            n.cov,
            n.kind,
            np.ascontiguousarray(n.edge[:, 0]),
            r.xy,
            r.cov,
            r.kind,
            np.ascontiguousarray(r.edge[:, 0]),
        )

    @functools.cached_property
    def kernel_settings(self) -> GnSettings:
        """:meth:`RefineSettings.kernel` of ``settings``."""
        return self.settings.kernel()

    @functools.cached_property
    def lattice_settings(self) -> LatticeSettings:
        """:meth:`RefineSettings.lattice` of ``settings``."""
        return self.settings.lattice()


@dataclass(frozen=True, eq=False)
class _FinalSystem:
    """What the covariance of a refined pose needs (computed on first use of
    :attr:`Refined.cov`): the problem, the point-to-line information ``(3, 3)`` at the pose,
    each point's segment ``(P,)`` (-1: none) and residual ``(P,)`` there (its rows, selected
    when the covariance is read), the feature pairs, the point noise and the gate (m)."""

    problem: RefineProblem
    pose: FloatArray
    point_hess: FloatArray
    point_segment: IntArray
    point_residual: FloatArray
    pairs: IntArray
    sigma: float
    gate: float


@dataclass(frozen=True, eq=False)
class Refined:
    """Result of :func:`refine`.

    The covariances are computed on first access (a match reads them of its chosen
    hypothesis only); the values are those of an eager computation.

    Attributes:
        pose: ``(3,)`` float64 refined pose of the new scan in the reference frame.
        sigma_m: Estimated point-to-line noise, metres.
        overlap: Fraction of the used points associated with a reference segment.
        n_points: Points associated in the last iteration.
        point_segment: ``(P,)`` int64 reference segment of each used point (-1: none).
        iterations: Gauss-Newton iterations run.
    """

    pose: FloatArray
    sigma_m: float
    overlap: float
    n_points: int
    point_segment: IntArray
    iterations: int
    _system: _FinalSystem = field(repr=False)

    @functools.cached_property
    def _covariances(self) -> tuple[FloatArray, FloatArray]:
        f = self._system
        return refined_covariances(
            f.problem,
            f.pose,
            f.point_hess,
            f.point_segment,
            f.point_residual,
            f.pairs,
            f.gate,
            f.sigma,
        )

    @property
    def cov_ls(self) -> FloatArray:
        """``(3, 3)`` least-squares (sandwich) covariance of ``pose`` as a perturbation of
        ``(x, y, theta)`` in the **reference** frame (prior from the bounds included)."""
        return self._covariances[0]

    @property
    def cov(self) -> FloatArray:
        """``(3, 3)`` final covariance (lattice second moment, floored by ``cov_ls``), same
        frame as ``cov_ls``."""
        return self._covariances[1]


def empty_cloud() -> PointCloud:
    """A :class:`~iceg.matching._kernels.PointCloud` without points (no PL-ICP rows)."""
    z2 = np.zeros((0, 2))
    zi = np.zeros(0, dtype=np.int64)
    return PointCloud(z2, z2, np.zeros(0), z2, 1.0, np.zeros(2), np.ones(2, np.int64), zi, zi)


def no_feature_pairing() -> FeaturePairing:
    """A :class:`~iceg.matching._kernels.FeaturePairing` without features (no pairs)."""
    z2 = np.zeros((0, 2))
    z = np.zeros(0)
    return FeaturePairing(z2, z, z2, z, z2, z, z2, z, np.zeros((0, 0), np.int64), 0.0, 0.0)


def build_cloud(
    points: FloatArray,
    ref_points: FloatArray,
    ref_spacing: FloatArray,
    ref_normal: FloatArray,
    cell_m: float,
) -> PointCloud:
    """Grid the reference points (cells of ``cell_m`` metres, at least the largest gate) for
    :func:`~iceg.matching._kernels.cloud_nearest`.

    Args:
        points: ``(C, 2)`` float64 off-segment new points (new frame), metres.
        ref_points: ``(R, 2)`` float64 reference points (reference frame), ``R >= 1``.
        ref_spacing: ``(R,)`` float64 distance to the nearest beam neighbour, metres.
        ref_normal: ``(R, 2)`` float64 unit normal of each point's local line (NaN: none).
        cell_m: Grid cell, metres.
    """
    origin, n_cells, key, order = grid_points(ref_points, cell_m)
    return PointCloud(
        np.ascontiguousarray(points, dtype=np.float64),
        np.ascontiguousarray(ref_points, dtype=np.float64),
        np.ascontiguousarray(ref_spacing, dtype=np.float64),
        np.ascontiguousarray(ref_normal, dtype=np.float64),
        float(cell_m),
        origin,
        n_cells,
        key,
        order,
    )


def points_within(
    points_xy: FloatArray, poses: FloatArray, reference_xy: FloatArray, gate_m: float
) -> NDArray[np.bool_]:
    """Whether a reference point lies closer than ``gate_m`` to each point, moved by each
    pose: the reference gridded in cells of the gate (:func:`grid_points`), each moved point
    scanning the 3 x 3 cells around it (:func:`~iceg.matching._kernels.points_explained`).

    Args:
        points_xy: ``(P, 2)`` float64 points in their own frame, metres.
        poses: ``(K, 3)`` float64 poses of that frame in the reference frame.
        reference_xy: ``(R, 2)`` float64 reference points, reference frame, metres.
        gate_m: Distance gate, metres (> 0).

    Returns:
        ``(K, P)`` bool (all False without reference points). Raises nothing.
    """
    ref = np.ascontiguousarray(reference_xy, dtype=np.float64).reshape(-1, 2)
    if ref.shape[0] == 0:
        return np.zeros((np.shape(poses)[0], np.shape(points_xy)[0]), dtype=bool)
    points = np.ascontiguousarray(points_xy, dtype=np.float64)
    poses = np.ascontiguousarray(poses, dtype=np.float64)
    if all_finite(ref):  # the grid and the query in one compiled call
        return finite_points_within(points, poses, ref, gate_m)
    origin, n_cells, key, order = grid_points(ref, gate_m)
    return points_explained(points, poses, ref, key, order, origin, n_cells, gate_m)


def grid_points(
    points: FloatArray, cell_m: float
) -> tuple[FloatArray, IntArray, IntArray, IntArray]:
    """A uniform grid over points for the 3 x 3-cell neighbour searches of the kernels
    (:func:`~iceg.matching._kernels.cloud_nearest`,
    :func:`~iceg.matching._kernels.points_explained`).

    Args:
        points: ``(R, 2)`` float64 points, metres, ``R >= 1``.
        cell_m: Cell side, metres.

    Returns:
        ``origin`` ``(2,)`` float64 corner of cell ``(0, 0)`` (one cell below the lowest
        point); ``n_cells`` ``(2,)`` int64 cells along x and y; ``key`` ``(R,)`` int64 the
        sorted cell keys ``ix * n_cells[1] + iy``; ``order`` ``(R,)`` int64 the point of
        each key (points of one cell in their input order).
    """
    if np.isfinite(points).all():  # compiled: the same arrays (sorted_cells)
        return sorted_cells(np.ascontiguousarray(points, dtype=np.float64), cell_m)
    # Column by column: numpy reduces an (R, 2) array along axis 0 ten times slower.
    origin = np.array([points[:, 0].min(), points[:, 1].min()]) - cell_m
    cells = np.floor((points - origin) / cell_m).astype(np.int64)
    n_cells = np.array([cells[:, 0].max(), cells[:, 1].max()]) + 2
    key = cells[:, 0] * n_cells[1] + cells[:, 1]
    order = np.argsort(key, kind="stable").astype(np.int64)
    return origin, n_cells, np.ascontiguousarray(key[order]), order


def effective_line_cov(segs: SegmentSet, wall_end_sigma_m: float) -> FloatArray:
    """``(M, 2, 2)`` covariance of each reference line ``(alpha, rho)``: the fit covariance
    plus the model error of the wall: its two ends off the fitted line by independent
    offsets of standard deviation ``wall_end_sigma_m`` (systematic range error, walls that
    are not straight). For a wall of length ``L`` that is an angle variance
    ``2 sigma^2 / L^2`` (a rotation about the midpoint) and an offset variance
    ``sigma^2 / 2`` at the midpoint, moved to ``(alpha, rho)`` through
    ``d rho / d alpha`` about the midpoint. Unlike the fit covariance it does not shrink with
    the number of beams on the wall, so the information one wall gives saturates."""
    return effective_line_info(segs, wall_end_sigma_m)[0]


def effective_line_info(segs: SegmentSet, wall_end_sigma_m: float) -> tuple[FloatArray, FloatArray]:
    """:func:`effective_line_cov` and its inverse (``1e-12`` added to the diagonal), each
    ``(M, 2, 2)`` float64, in one compiled pass (:func:`~iceg.matching._kernels.
    line_covariances`)."""
    return line_covariances(
        segs.a, segs.u, segs.length, segs.alpha, segs.cov, wall_end_sigma_m, _MIN_WALL_LENGTH_M
    )


#: Information (1 / m^2) that holds a refinement at the prediction along a direction
#: (:func:`refine`, ``held``): a 1 mm standard deviation.
HOLD_INFORMATION = 1.0e6


def refine(
    problem: RefineProblem,
    pose0: FloatArray,
    initial_pairs: IntArray | None = None,
    held: FloatArray | None = None,
) -> Refined:
    """Gauss-Newton refinement and covariance of one hypothesis (docs/design.md steps 8-9; paper
    §III-C3 "an optimization problem"; covariance after Olson 2009).

    The two phases: the wide gate with full feature positions until the steps are small (a
    coarse hypothesis is pulled in), then a gate of a few estimated sigmas with the pairing
    fixed at the coarse result until convergence (points off the matched segments stop
    pulling); all in one compiled call (:func:`~iceg.matching._kernels.refine_pose`).

    Args:
        problem: What the match's refinements share (points, segments, features, prior).
        pose0: ``(3,)`` float64 starting pose of the new scan in the reference frame
            ``[x_m, y_m, theta_rad]``.
        initial_pairs: ``(Q, 2)`` int64 feature pairs ``[new, ref]`` at ``pose0`` if already
            known (else from ``problem.pairing``).
        held: ``(2, m)`` float64 unit translation directions (reference frame) along which
            the refinement is held at the prior's mean (:data:`HOLD_INFORMATION` added to the
            prior there), or ``None``. The covariances stay those of ``problem`` (unheld) at
            the held pose: the factor is as weak there as the scene makes it.

    Returns:
        A :class:`Refined`; its covariances are perturbations of ``(x, y, theta)`` in the
        reference frame.
    """
    prior = problem.prior
    if held is not None:
        info = prior.info.copy()
        info[:2, :2] += HOLD_INFORMATION * (held @ held.T)
        prior = PosePrior(prior.mean, info)
    pose, sigma, gate, iterations, pairs, hess, idx, res = refine_pose(
        np.asarray(pose0, dtype=np.float64),
        None if initial_pairs is None else np.ascontiguousarray(initial_pairs, dtype=np.int64),
        prior,
        problem.points,
        problem.lines,
        problem.pair_geometry,
        problem.pairing,
        problem.cloud,
        problem.kernel_settings,
        problem.settings.max_iterations,
    )
    n_on = int(np.count_nonzero(idx >= 0))
    overlap = float(n_on) / max(1, problem.points.xy.shape[0])
    system = _FinalSystem(problem, pose.copy(), hess, idx, res, pairs, sigma, gate)
    return Refined(pose, sigma, overlap, n_on, idx, iterations, system)


def covariance_at(problem: RefineProblem, pose: FloatArray) -> tuple[FloatArray, FloatArray]:
    """``(cov_ls, cov)`` of ``pose`` as :attr:`Refined.cov_ls` and :attr:`Refined.cov` give
    them for a refinement that ended there with the coarse gate and no feature pairs: the
    rows linearised at ``pose``, with the point noise estimated there (the starting noise
    when too few points associate; docs/design.md step 9; lattice after Olson 2009). Each
    ``(3, 3)`` float64, a perturbation of ``(x, y, theta)`` in the reference frame. For a
    covariance at a pose that no refinement produced, e.g. to load (or compile) the
    covariance's kernels without the refinement's (:mod:`iceg.kernel_warmup`).

    Args:
        problem: What the match's refinements share (points, segments, prior).
        pose: ``(3,)`` float pose of the new scan in the reference frame
            ``[x_m, y_m, theta_rad]``.

    Returns:
        ``(cov_ls, cov)``; both infinite where the information is singular. Raises nothing.
    """
    s = problem.kernel_settings
    gate = s.gate_m
    sigma = max(s.sigma_min_m, gate / GATE_TO_SIGMA0)
    return _covariances_at(problem, np.asarray(pose, dtype=np.float64), gate, sigma)


def _covariances_at(
    problem: RefineProblem, pose: FloatArray, gate: float, sigma: float
) -> tuple[FloatArray, FloatArray]:
    """:func:`refined_covariances` with no feature pairs, the point-to-line rows linearised at
    ``pose`` (:func:`~iceg.matching._kernels.point_line_system`, which also estimates the
    point noise there)."""
    point_hess, _, sigma, idx, res = point_line_system(
        pose, problem.points, problem.lines, gate, sigma, problem.kernel_settings
    )
    no_pairs = np.zeros((0, 2), np.int64)
    return refined_covariances(problem, pose, point_hess, idx, res, no_pairs, gate, sigma)


def refined_covariances(
    problem: RefineProblem,
    pose: FloatArray,
    point_hess: FloatArray,
    point_segment: IntArray,
    point_residual: FloatArray,
    pairs: IntArray,
    gate: float,
    sigma: float,
) -> tuple[FloatArray, FloatArray]:
    """Least-squares covariance ``(information + prior)^-1`` (infinite when singular) and
    the final covariance: the lattice second moment (Olson 2009) floored by it, at most
    ``LATTICE_POINTS`` point-to-line rows evaluated, evenly spread; one compiled call
    (:func:`~iceg.matching._kernels.final_covariances`).

    Args:
        problem: What the match's refinements share.
        pose: ``(3,)`` float64 the refined pose (new scan in the reference frame).
        point_hess: ``(3, 3)`` float64 information of the point-to-line rows at ``pose``.
        point_segment: ``(P,)`` int64 each point's reference segment there (-1: none).
        point_residual: ``(P,)`` float64 its point-to-line residual (metres).
        pairs: ``(Q, 2)`` int64 feature pairs ``[new, ref]``.
        gate: The association gate (metres); ``sigma`` the point noise (metres).

    Returns:
        ``(cov_ls, cov)``, each ``(3, 3)`` float64, perturbations of ``(x, y, theta)`` in the
        reference frame; both infinite where the information is singular. Raises nothing.
    """
    n_associated = int(np.count_nonzero(point_segment >= 0))
    return final_covariances(
        pose,
        np.ascontiguousarray(pairs, dtype=np.int64),
        problem.pair_geometry,
        problem.cloud,
        point_hess,
        point_segment,
        point_residual,
        problem.points.xy,
        problem.segs.normal,
        problem.prior.info,
        problem.lines,
        _lattice_pick(n_associated),
        gate,
        sigma,
        problem.kernel_settings,
        problem.lattice_settings,
    )


@functools.lru_cache(maxsize=4)
def _unit_lattice(steps: int) -> FloatArray:
    """``(steps^3, 3)`` lattice of ``[-1, 1]^3``."""
    k = np.linspace(-1.0, 1.0, steps)
    return np.stack(np.meshgrid(k, k, k, indexing="ij"), axis=-1).reshape(-1, 3)


@functools.lru_cache(maxsize=256)
def _lattice_pick(n_rows: int) -> IntArray:
    """``(m,)`` int64 the rows of ``n_rows`` point-to-line rows the lattice evaluates: at
    most ``LATTICE_POINTS``, evenly spread (read-only)."""
    pick = np.linspace(0, n_rows - 1, min(n_rows, LATTICE_POINTS)).astype(np.int64)
    pick.flags.writeable = False
    return pick


def bounds_prior_information(max_translation_m: float, max_rotation_rad: float) -> FloatArray:
    """Information ``diag(3 / t^2, 3 / t^2, 3 / r^2)`` of a uniform distribution over the
    admissible motion (zeros where unbounded)."""
    info = np.zeros((3, 3))
    if math.isfinite(max_translation_m) and max_translation_m > 0:
        info[0, 0] = info[1, 1] = 3.0 / max_translation_m**2
    if max_rotation_rad < math.pi and max_rotation_rad > 0:
        info[2, 2] = 3.0 / max_rotation_rad**2
    return info
