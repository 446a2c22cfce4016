"""Refinement of a hypothesis (paper §III-C3 "an optimization problem"; DESIGN step 8) and
its covariance (DESIGN step 9).

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
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from iceg.matching._kernels import (
    feature_system,
    gn_phase,
    lattice_point_cost,
    point_line_system,
)
from iceg.matching.geometry import EOW, FeatureGeometry, SegmentSet, associate_points, rot

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]


@dataclass(frozen=True, eq=False)
class RefineSettings:
    """Numbers of the refinement in internal units (metres, radians); built from
    :class:`~iceg.matching.config.MatchingConfig` by the matcher."""

    max_iterations: int
    gate_m: float
    gate_sigmas: float
    gate_min_m: float
    end_tol_m: float
    normal_gate_rad: float
    cauchy_sigmas: float
    sigma_min_m: float
    line_angle_sigma_min_rad: float
    line_offset_sigma_min_m: float
    lattice_steps: int
    lattice_sigmas: float
    lattice_kappa: float
    lattice_cap_m: float
    lattice_cap_rad: float


@dataclass(frozen=True, eq=False)
class Refined:
    """Result of :func:`refine`.

    Attributes:
        pose: ``(3,)`` float64 refined pose of the new scan in the reference frame.
        cov_ls: ``(3, 3)`` least-squares (sandwich) covariance of ``pose`` as a perturbation
            of ``(x, y, theta)`` in the **reference** frame (prior from the bounds included).
        cov: ``(3, 3)`` final covariance (lattice second moment, floored by ``cov_ls``), same
            frame as ``cov_ls``.
        sigma_m: Estimated point-to-line noise, metres.
        overlap: Fraction of the used points associated with a reference segment.
        n_points: Points associated in the last iteration.
        point_segment: ``(P,)`` int64 reference segment of each used point (-1: none).
        iterations: Gauss-Newton iterations run.
    """

    pose: FloatArray
    cov_ls: FloatArray
    cov: FloatArray
    sigma_m: float
    overlap: float
    n_points: int
    point_segment: IntArray
    iterations: int


def _cauchy_weight(r: FloatArray, c: float) -> FloatArray:
    return 1.0 / (1.0 + (r / c) ** 2)


def _cauchy_cost(r: FloatArray, c: float) -> FloatArray:
    return 0.5 * c * c * np.log1p((r / c) ** 2)


@dataclass(frozen=True, eq=False)
class _Rows:
    """Linearised residual rows at one pose: residual, Jacobian (w.r.t. a perturbation of
    ``(x, y, theta)`` in the reference frame), robust weight and variance."""

    r: FloatArray
    jac: FloatArray
    w: FloatArray
    var: FloatArray


_EMPTY_ROWS = _Rows(np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0))


def _feature_rows(
    pose: FloatArray,
    gn: FeatureGeometry,
    gr: FeatureGeometry,
    pairs: IntArray,
    use_positions: bool,
) -> _Rows:
    """Rows of the feature pairs ``(P, 2)`` ``[new, ref]``: a scalar along-wall row for each
    pair that involves an EOW, two whitened position rows for the others when
    ``use_positions`` (plain arithmetic on the 2x2 blocks: this runs every iteration)."""
    if pairs.shape[0] == 0:
        return _EMPTY_ROWS
    c, s = math.cos(pose[2]), math.sin(pose[2])
    i, j = pairs[:, 0], pairs[:, 1]
    nx, ny = gn.xy[i, 0], gn.xy[i, 1]
    rnx = c * nx - s * ny
    rny = s * nx + c * ny
    ex = rnx + pose[0] - gr.xy[j, 0]
    ey = rny + pose[1] - gr.xy[j, 1]
    cn = gn.cov[i]
    a, b, d = cn[:, 0, 0], cn[:, 0, 1], cn[:, 1, 1]
    cr = gr.cov[j]
    ca = c * c * a - 2 * c * s * b + s * s * d + cr[:, 0, 0]
    cb = c * s * (a - d) + (c * c - s * s) * b + cr[:, 0, 1]
    cd = s * s * a + 2 * c * s * b + c * c * d + cr[:, 1, 1]
    is_eow_r = gr.kind[j] == EOW
    along = is_eow_r | (gn.kind[i] == EOW)
    rr_l, jj_l, vv_l = [], [], []
    if np.any(along):
        ang = np.where(is_eow_r, gr.edge[j, 0], gn.edge[i, 0] + pose[2])[along]
        dx, dy = np.cos(ang), np.sin(ang)
        rr_l.append(dx * ex[along] + dy * ey[along])
        jj_l.append(np.column_stack([dx, dy, dy * rnx[along] - dx * rny[along]]))
        vv_l.append(dx * dx * ca[along] + 2 * dx * dy * cb[along] + dy * dy * cd[along])
    if use_positions and not np.all(along):
        p = ~along
        l11 = np.sqrt(ca[p])
        l21 = cb[p] / l11
        l22 = np.sqrt(np.maximum(cd[p] - l21 * l21, 1e-18))
        u1 = ex[p] / l11
        u2 = (ey[p] - l21 * u1) / l22
        n = u1.shape[0]
        j1 = np.zeros((n, 3))
        j1[:, 0] = 1.0 / l11
        j1[:, 2] = -rny[p] / l11
        j2 = np.zeros((n, 3))
        j2[:, 0] = -l21 / l11 / l22
        j2[:, 1] = 1.0 / l22
        j2[:, 2] = (rnx[p] - l21 * (-rny[p]) / l11) / l22
        rr_l.append(np.concatenate([u1, u2]))
        jj_l.append(np.concatenate([j1, j2]))
        vv_l.append(np.ones(2 * n))
    if not rr_l:
        return _EMPTY_ROWS
    rr = np.concatenate(rr_l)
    vv = np.concatenate(vv_l)
    return _Rows(rr, np.concatenate(jj_l), _cauchy_weight(rr / np.sqrt(vv), 2.5), vv)


@dataclass(frozen=True, eq=False)
class Cloud:
    """New-scan points that lie on no segment (clutter, short structures) and the
    reference's points, for point-to-line rows on local lines (PL-ICP, Censi 2008) or
    point-to-point rows where a reference point has no near neighbour.

    Attributes:
        points: ``(C, 2)`` float64 new points, new frame, metres.
        tree: ``scipy.spatial.cKDTree`` of ``ref_points``.
        ref_points: ``(R, 2)`` float64 reference points, reference frame.
        ref_spacing: ``(R,)`` float64 distance from each reference point to its nearest
            neighbour in beam order, metres (noise of a point-to-point residual).
        ref_normal: ``(R, 2)`` float64 unit normal of the local line through each
            reference point's beam neighbours (NaN: isolated point).
    """

    points: FloatArray
    tree: object
    ref_points: FloatArray
    ref_spacing: FloatArray
    ref_normal: FloatArray


def _cloud_rows(pose: FloatArray, cloud: Cloud | None, gate_m: float, sigma: float) -> _Rows:
    """Rows of the cloud points whose nearest reference point is within the gate: one
    point-to-line row (variance ``2 sigma^2``) on the reference point's local line, or two
    point-to-point rows (variance ``2 sigma^2 + (spacing / 2)^2`` each) for an isolated
    reference point."""
    empty = _Rows(np.zeros(0), np.zeros((0, 3)), np.zeros(0), np.zeros(0))
    if cloud is None or cloud.points.shape[0] == 0:
        return empty
    r = rot(pose[2])
    rp = cloud.points @ r.T
    q = rp + pose[:2]
    dist, idx = cloud.tree.query(q, distance_upper_bound=gate_m)  # type: ignore[attr-defined]
    ok = np.isfinite(dist)
    if not np.any(ok):
        return empty
    idx = idx[ok]
    e = q[ok] - cloud.ref_points[idx]
    rps = rp[ok]
    n = e.shape[0]
    jac = np.zeros((n, 2, 3))
    jac[:, 0, 0] = 1.0
    jac[:, 1, 1] = 1.0
    jac[:, 0, 2] = -rps[:, 1]
    jac[:, 1, 2] = rps[:, 0]
    nrm = cloud.ref_normal[idx]
    line = np.isfinite(nrm[:, 0])
    rows = empty
    if np.any(line):
        nl = nrm[line]
        rr = np.einsum("na,na->n", nl, e[line])
        jj = np.einsum("na,nak->nk", nl, jac[line])
        vv = np.full(rr.shape[0], 2.0 * sigma**2)
        rows = _Rows(rr, jj, _cauchy_weight(rr / np.sqrt(vv), 2.5), vv)
    pt = ~line
    if np.any(pt):
        var = 2.0 * sigma**2 + (0.5 * np.minimum(cloud.ref_spacing[idx[pt]], 1e3)) ** 2
        ep = e[pt]
        w = np.repeat(_cauchy_weight(np.hypot(ep[:, 0], ep[:, 1]) / np.sqrt(var), 2.5), 2)
        rows = _cat_rows(rows, _Rows(ep.reshape(-1), jac[pt].reshape(-1, 3), w, np.repeat(var, 2)))
    return rows


def _cat_rows(a: _Rows, b: _Rows) -> _Rows:
    if b.r.shape[0] == 0:
        return a
    if a.r.shape[0] == 0:
        return b
    return _Rows(
        np.concatenate([a.r, b.r]),
        np.concatenate([a.jac, b.jac]),
        np.concatenate([a.w, b.w]),
        np.concatenate([a.var, b.var]),
    )


@dataclass(frozen=True, eq=False)
class _PointRows:
    idx: IntArray  # used point -> segment (-1)
    sel: NDArray[np.bool_]
    r: FloatArray
    jac: FloatArray
    q: FloatArray  # associated points in the reference frame


def _point_rows(
    pose: FloatArray,
    points: FloatArray,
    point_alpha: FloatArray,
    segs: SegmentSet,
    gate_m: float,
    s: RefineSettings,
) -> _PointRows:
    r = rot(pose[2])
    rp = points @ r.T
    q = rp + pose[:2]
    idx, res = associate_points(
        q, point_alpha + pose[2], segs, gate_m, s.end_tol_m, s.normal_gate_rad
    )
    sel = idx >= 0
    n = segs.normal[idx[sel]]
    rps = rp[sel]
    jac = np.column_stack([n[:, 0], n[:, 1], n[:, 1] * rps[:, 0] - n[:, 0] * rps[:, 1]])
    return _PointRows(idx, sel, res[sel], jac, q[sel])


def effective_line_cov(
    segs: SegmentSet, angle_sigma_min_rad: float, offset_sigma_min_m: float
) -> FloatArray:
    """``(M, 2, 2)`` covariance of each reference line ``(alpha, rho)``: the fit covariance
    plus a floor for how far real walls are from straight lines (a rotation of
    ``angle_sigma_min_rad`` about the segment's midpoint and a shift of
    ``offset_sigma_min_m``)."""
    mid = segs.a + 0.5 * segs.length[:, None] * segs.u
    tang = np.stack([-np.sin(segs.alpha), np.cos(segs.alpha)], axis=1)
    k = np.einsum("ma,ma->m", tang, mid)  # d rho / d alpha about the midpoint
    jac = np.zeros((segs.n, 2, 2))
    jac[:, 0, 0] = 1.0
    jac[:, 1, 1] = 1.0
    jac[:, 1, 0] = k
    floor = np.diag([angle_sigma_min_rad**2, offset_sigma_min_m**2])
    return segs.cov + jac @ floor @ np.swapaxes(jac, 1, 2)


def _gls_system(
    pr: _PointRows, w: FloatArray, sigma: float, segs: SegmentSet, line_cov: FloatArray
) -> tuple[FloatArray, FloatArray]:
    """Normal equations ``(H, g)`` of the point-to-line residuals with the reference lines'
    own uncertainty as a shared error of all points on a line (generalised least squares):
    per segment, ``C = W^-1 + B S B^T`` with ``B`` the residuals' derivative w.r.t. the line's
    ``(alpha, rho)`` and ``S`` its covariance; ``C^-1`` by the Woodbury identity, so each
    segment costs a 2x2 inverse. A small angle error of a long line then no longer
    masquerades as information along it (a corridor's axis)."""
    seg = pr.idx[pr.sel]
    if seg.shape[0] == 0:
        return np.zeros((3, 3)), np.zeros(3)
    al = segs.alpha[seg]
    b = np.column_stack(
        [-np.sin(al) * pr.q[:, 0] + np.cos(al) * pr.q[:, 1], -np.ones(seg.shape[0])]
    )
    jac, r = pr.jac, pr.r
    wt = (w / sigma**2)[:, None]
    feats = (
        np.concatenate(
            [
                (jac[:, :, None] * jac[:, None, :]).reshape(-1, 9),
                (jac[:, :, None] * b[:, None, :]).reshape(-1, 6),
                (b[:, :, None] * b[:, None, :]).reshape(-1, 4),
                jac * r[:, None],
                b * r[:, None],
            ],
            axis=1,
        )
        * wt
    )
    order = np.argsort(seg, kind="stable")
    ss = seg[order]
    starts = np.flatnonzero(np.concatenate([[True], ss[1:] != ss[:-1]]))
    sums = np.add.reduceat(feats[order], starts, axis=0)
    u = ss[starts]
    jj = sums[:, :9].reshape(-1, 3, 3)
    jb = sums[:, 9:15].reshape(-1, 3, 2)
    bb = sums[:, 15:19].reshape(-1, 2, 2)
    jr = sums[:, 19:22]
    br = sums[:, 22:24]
    k = np.linalg.inv(np.linalg.inv(line_cov[u]) + bb)
    hess = jj.sum(axis=0) - np.einsum("uab,ubc,udc->ad", jb, k, jb)
    grad = jr.sum(axis=0) - np.einsum("uab,ubc,uc->a", jb, k, br)
    return hess, grad


def refine(
    pose0: FloatArray,
    points: FloatArray,
    point_alpha: FloatArray,
    segs: SegmentSet,
    gn: FeatureGeometry,
    gr: FeatureGeometry,
    pair_fn,
    prior_info: FloatArray,
    settings: RefineSettings,
    prior_mean: FloatArray | None = None,
    cloud: Cloud | None = None,
    initial_pairs: IntArray | None = None,
) -> Refined:
    """Gauss-Newton refinement and covariance of one hypothesis (DESIGN steps 8-9).

    Args:
        pose0: ``(3,)`` float64 starting pose of the new scan in the reference frame.
        points: ``(P, 2)`` float64 new scan points (new frame) that lie on new segments.
        point_alpha: ``(P,)`` float64 normal angle of each point's own segment (new frame).
        segs: Reference segments (reference frame).
        gn, gr: New and reference feature geometry.
        pair_fn: ``pair_fn(pose) -> (Q, 2) int64`` feature pairs ``[new, ref]`` at ``pose``
            (the correlation's pairing).
        prior_info: ``(3, 3)`` information of the bounds' prior (uniform variance of the
            admissible motion; zeros for a global match). It regularises unobservable
            directions and enters the covariance.
        settings: Refinement settings.
        prior_mean: ``(3,)`` centre of the prior (the prediction); default ``pose0``.
        cloud: Off-segment points of the new scan and the reference's points for
            point-to-point rows (gated like the point-to-line rows); ``None``: none.
        initial_pairs: Feature pairs at ``pose0`` if already known (else ``pair_fn``).

    Returns:
        A :class:`Refined`.
    """
    s = settings
    pose = np.asarray(pose0, dtype=np.float64).copy()
    prior_mean = pose.copy() if prior_mean is None else np.asarray(prior_mean, dtype=np.float64)
    line_cov = effective_line_cov(segs, s.line_angle_sigma_min_rad, s.line_offset_sigma_min_m)
    gate = s.gate_m
    sigma = max(s.sigma_min_m, s.gate_m / 3.0)
    n_pts = points.shape[0]
    it = 0
    # Two phases: the wide gate until the steps are small (a coarse hypothesis is pulled
    # in, Corner/Intersection positions help), then a gate of a few estimated sigmas until
    # convergence (points off the matched segments stop pulling).
    coarse = True
    coarse_pairs: IntArray | None = initial_pairs
    fine_pairs: IntArray | None = None
    line_info = np.linalg.inv(line_cov + 1e-12 * np.eye(2))
    new_edge0 = np.ascontiguousarray(gn.edge[:, 0])
    ref_edge0 = np.ascontiguousarray(gr.edge[:, 0])
    sin_gate = math.sin(s.normal_gate_rad)

    def system(pose: FloatArray, gate: float, sigma: float) -> tuple:  # type: ignore[type-arg]
        """Point-to-line normal equations at ``pose`` (see :func:`point_line_system`)."""
        return point_line_system(  # type: ignore[no-any-return]
            pose,
            points,
            point_alpha,
            segs.a,
            segs.u,
            segs.length,
            segs.normal,
            segs.rho,
            line_info,
            gate,
            s.end_tol_m,
            sin_gate,
            sigma,
            s.sigma_min_m,
            s.cauchy_sigmas,
        )

    if cloud is None:
        # Both phases compiled (the usual case: a map reference has no points).
        if coarse_pairs is None:
            coarse_pairs = pair_fn(pose)
        phase_args = (
            prior_mean,
            prior_info,
            points,
            point_alpha,
            segs.a,
            segs.u,
            segs.length,
            segs.normal,
            segs.rho,
            line_info,
            s.end_tol_m,
            sin_gate,
            s.sigma_min_m,
            s.cauchy_sigmas,
        )
        feat_args = (gn.xy, gn.cov, gn.kind, new_edge0, gr.xy, gr.cov, gr.kind, ref_edge0, EOW)
        pose, sigma, gate, it = gn_phase(
            pose,
            *phase_args,
            np.ascontiguousarray(coarse_pairs[:, 0]),
            np.ascontiguousarray(coarse_pairs[:, 1]),
            *feat_args,
            True,
            gate,
            sigma,
            max(1, s.max_iterations // 2),
            s.gate_m,
            s.gate_sigmas,
            s.gate_min_m,
            1e-2,
            5e-3,
        )
        gate = min(s.gate_m, max(s.gate_min_m, s.gate_sigmas * sigma))
        fine_pairs = pair_fn(pose)
        pose, sigma, gate, it2 = gn_phase(
            pose,
            *phase_args,
            np.ascontiguousarray(fine_pairs[:, 0]),
            np.ascontiguousarray(fine_pairs[:, 1]),
            *feat_args,
            False,
            gate,
            sigma,
            max(1, s.max_iterations - it),
            s.gate_m,
            s.gate_sigmas,
            s.gate_min_m,
            5e-4,
            1e-4,
        )
        it += it2
    else:
        for it in range(1, s.max_iterations + 1):
            hess, grad, sigma, _, _ = system(pose, gate, sigma)
            if coarse:
                if coarse_pairs is None:
                    coarse_pairs = pair_fn(pose)
                pairs = coarse_pairs
            else:
                # The pairing is fixed once the coarse phase has converged.
                if fine_pairs is None:
                    fine_pairs = pair_fn(pose)
                pairs = fine_pairs
            if pairs.shape[0]:
                fh, fg = feature_system(
                    pose,
                    pairs[:, 0],
                    pairs[:, 1],
                    gn.xy,
                    gn.cov,
                    gn.kind,
                    new_edge0,
                    gr.xy,
                    gr.cov,
                    gr.kind,
                    ref_edge0,
                    EOW,
                    coarse,
                    2.5,
                )
                hess += fh
                grad += fg
            fr = _cloud_rows(pose, cloud, gate, sigma)
            if fr.r.shape[0] > 0:
                hess += (fr.jac.T * (fr.w / fr.var)) @ fr.jac
                grad += (fr.jac.T * (fr.w / fr.var)) @ fr.r
            # The bounds' prior pulls toward the prediction (MAP): it only matters along
            # directions the scene leaves unconstrained (a corridor's axis).
            dp = pose - prior_mean
            dp[2] = (dp[2] + math.pi) % (2.0 * math.pi) - math.pi
            grad += prior_info @ dp
            a = hess + prior_info + 1e-9 * np.eye(3)
            try:
                delta = -np.linalg.solve(a, grad)
            except np.linalg.LinAlgError:
                break
            pose[:2] += delta[:2]
            pose[2] = (pose[2] + delta[2] + math.pi) % (2.0 * math.pi) - math.pi
            step_xy, step_th = math.hypot(delta[0], delta[1]), abs(delta[2])
            if coarse:
                if (step_xy < 1e-2 and step_th < 5e-3) or it >= s.max_iterations // 2:
                    coarse = False
            elif step_xy < 5e-4 and step_th < 1e-4:
                break
            if not coarse:
                gate = min(s.gate_m, max(s.gate_min_m, s.gate_sigmas * sigma))
    # Final linearisation at the refined pose.
    hess, _, sigma, idx, res = system(pose, gate, sigma)
    c = s.cauchy_sigmas * sigma
    sel = idx >= 0
    rp = points[sel] @ rot(pose[2]).T
    nrm = segs.normal[idx[sel]]
    pr = _PointRows(
        idx,
        sel,
        res[sel],
        np.column_stack([nrm[:, 0], nrm[:, 1], nrm[:, 1] * rp[:, 0] - nrm[:, 0] * rp[:, 1]]),
        rp + pose[:2],
    )
    pairs = fine_pairs if fine_pairs is not None else pair_fn(pose)
    fr = _cat_rows(_feature_rows(pose, gn, gr, pairs, False), _cloud_rows(pose, cloud, gate, sigma))
    if fr.r.shape[0] > 0:
        hess += (fr.jac.T * (fr.w / fr.var)) @ fr.jac
    a = hess + prior_info
    try:
        a_inv = np.asarray(np.linalg.inv(a), dtype=np.float64)
    except np.linalg.LinAlgError:
        a_inv = np.full((3, 3), np.inf)
    cov_ls = 0.5 * (a_inv + a_inv.T) if np.all(np.isfinite(a_inv)) else np.full((3, 3), np.inf)
    cov = cov_ls
    if np.all(np.isfinite(cov_ls)):
        lat = _lattice_covariance(pose, pr, segs, fr, sigma, c, gate, a_inv, s)
        if lat is not None:
            cov = psd_max(cov_ls, lat)
    overlap = float(pr.sel.sum()) / max(1, n_pts)
    return Refined(pose, cov_ls, cov, sigma, overlap, int(pr.sel.sum()), pr.idx, it)


#: Points evaluated on the lattice (evenly subsampled beyond; the cost is scaled up).
_LATTICE_POINTS = 100


@functools.lru_cache(maxsize=4)
def _unit_lattice(steps: int) -> FloatArray:
    """``(steps^3, 3)`` lattice of ``[-1, 1]^3``."""
    k = np.linspace(-1.0, 1.0, steps)
    return np.stack(np.meshgrid(k, k, k, indexing="ij"), axis=-1).reshape(-1, 3)


def _lattice_covariance(
    pose: FloatArray,
    pr: _PointRows,
    segs: SegmentSet,
    fr: _Rows,
    sigma: float,
    c: float,
    gate: float,
    lik_cov: FloatArray,
    s: RefineSettings,
) -> FloatArray | None:
    """Second moment of ``exp(kappa (score - score_max))`` on a lattice of perturbations
    (Olson 2009). The score is the robust log-likelihood of the refinement with the final
    associations: a point that slides beyond its segment's extent (plus tolerance) counts as
    an outlier at the gate, so the landscape is flat where the walls give no constraint.

    The lattice spans ``lattice_sigmas`` standard deviations of the likelihood covariance
    along its principal axes (capped), ``lattice_steps`` points per axis.
    """
    evals, evecs = np.linalg.eigh(0.5 * (lik_cov + lik_cov.T))
    if not np.all(np.isfinite(evals)) or np.any(evals <= 0):
        return None
    cap = 1.0 / np.sqrt(
        (evecs[0] ** 2 + evecs[1] ** 2) / s.lattice_cap_m**2 + evecs[2] ** 2 / s.lattice_cap_rad**2
    )
    half = np.minimum(s.lattice_sigmas * np.sqrt(evals), cap)
    g = _unit_lattice(s.lattice_steps) * half
    deltas = g @ evecs.T  # (L, 3) in (x, y, theta)
    cost = np.zeros(deltas.shape[0])
    if pr.r.shape[0] > 0:
        # At most _LATTICE_POINTS points, evenly spread, their cost scaled up to all.
        n_all = pr.r.shape[0]
        pick = np.linspace(0, n_all - 1, min(n_all, _LATTICE_POINTS)).astype(np.int64)
        pr = _PointRows(pr.idx, pr.sel, pr.r[pick], pr.jac[pick], pr.q[pick])
        seg = pr.idx[pr.sel][pick]
        u = segs.u[seg]
        # Along-segment coordinate and its derivative.
        along = np.einsum("na,na->n", pr.q - segs.a[seg], u)
        rq = pr.q - pose[:2]
        j_along = np.column_stack([u[:, 0], u[:, 1], u[:, 1] * rq[:, 0] - u[:, 0] * rq[:, 1]])
        cost += (n_all / pick.shape[0]) * lattice_point_cost(
            deltas,
            np.ascontiguousarray(pr.r),
            np.ascontiguousarray(pr.jac),
            along,
            j_along,
            np.ascontiguousarray(segs.length[seg]),
            s.end_tol_m,
            gate,
            c,
            sigma,
        )
    if fr.r.shape[0] > 0:
        rf = (fr.r[:, None] + fr.jac @ deltas.T) / np.sqrt(fr.var)[:, None]
        cost += _cauchy_cost(rf, 2.5).sum(axis=0)
    score = -cost
    w = np.exp(s.lattice_kappa * (score - score.max()))
    w /= w.sum()
    return (deltas.T * w) @ deltas


def psd_max(a: FloatArray, b: FloatArray) -> FloatArray:
    """A covariance that dominates both ``a`` and ``b`` (``a`` positive definite): in the
    frame whitened by ``a``, ``b``'s eigenvalues are raised to at least 1."""
    try:
        lc = np.linalg.cholesky(a)
    except np.linalg.LinAlgError:
        return a
    li = np.linalg.inv(lc)
    m = li @ b @ li.T
    evals, evecs = np.linalg.eigh(0.5 * (m + m.T))
    d = np.maximum(evals, 1.0)
    out = lc @ (evecs * d) @ evecs.T @ lc.T
    return 0.5 * (out + out.T)


def bounds_prior_information(max_translation_m: float, max_rotation_rad: float) -> FloatArray:
    """Information ``diag(3 / t^2, 3 / t^2, 3 / r^2)`` of a uniform distribution over the
    admissible motion (zeros where unbounded)."""
    info = np.zeros((3, 3))
    if math.isfinite(max_translation_m) and max_translation_m > 0:
        info[0, 0] = info[1, 1] = 3.0 / max_translation_m**2
    if max_rotation_rad < math.pi and max_rotation_rad > 0:
        info[2, 2] = 3.0 / max_rotation_rad**2
    return info
