"""Compiled kernels of the matcher (numba): the Gauss-Newton loop of the refinement with its
normal equations (point-to-line GLS rows, feature-pair rows, off-segment PL-ICP rows), the
covariance of a refined pose (its rows, the Olson 2009 lattice, the floor), the reference's
segment arrays and line information, the correlation's feature pairing, visibility count and
terms, the hypotheses' vote, the free-space ray check, the prediction start's kernel-density
peak and the gridded point query of the contradiction test.

numpy builds (points x segments) temporaries and spends most of its time in call overhead
for scans of a few hundred points; these loops do the arithmetic without temporaries.
Kernels take grouped inputs (the named tuples below) rather than long positional lists.
"""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np

from iceg.landmark_frames import move_point_blocks
from iceg.numpy_sums import median, pairwise_sum
from iceg_common.numba_loading import njit

#: Fewest associated points for a noise estimate from the residuals (else the previous one).
MIN_POINTS_FOR_SIGMA = 6
#: Median absolute deviation to standard deviation of a normal distribution.
MAD_TO_SIGMA = 1.4826
#: Damping added to the Gauss-Newton system's diagonal (keeps it invertible).
GN_DAMPING = 1e-9
#: Step below which the refinement's coarse phase ends (metres, radians).
COARSE_TOL_XY_M = 1e-2
COARSE_TOL_THETA_RAD = 5e-3
#: Step below which the refinement's fine phase has converged (metres, radians).
FINE_TOL_XY_M = 5e-4
FINE_TOL_THETA_RAD = 1e-4
#: The refinement's starting point noise is the coarse gate divided by this (floored).
GATE_TO_SIGMA0 = 3.0


#: Slack (metres) added to a segment grid's reach: far above the rounding of the distances
#: involved (~1e-15 m), so a segment the exact test would accept is never left out.
GRID_SLACK_M = 1e-6


class SegmentGrid(NamedTuple):
    """Uniform grid over reference segments for the point association (:func:`associate`):
    cell ``(ix, iy)`` lists, in ascending order, every segment that passes within
    ``reach_m`` of some point of the cell. Built by :func:`segment_grid`; ``reach_m = 0``
    (:func:`no_segment_grid`) means no grid (every segment is tested).

    Attributes:
        origin: ``(2,)`` float64 corner of cell ``(0, 0)``, metres.
        cell_m: Cell side, metres.
        n_cells: ``(2,)`` int64 cells along x and y.
        start: ``(n_cells[0] * n_cells[1] + 1,)`` int64 offsets of each cell's list in
            ``segs`` (cell key ``ix * n_cells[1] + iy``).
        segs: ``(K,)`` int64 segment indices, cell by cell, ascending within a cell.
        reach_m: Largest ``gate + end tolerance`` the grid answers exactly, metres.
    """

    origin: np.ndarray
    cell_m: float
    n_cells: np.ndarray
    start: np.ndarray
    segs: np.ndarray
    reach_m: float


class LineSegments(NamedTuple):
    """Reference segments for the kernels (reference frame, metres/radians).

    Attributes:
        a: ``(M, 2)`` float64 first endpoint.
        u: ``(M, 2)`` float64 unit direction.
        length: ``(M,)`` float64 length.
        normal: ``(M, 2)`` float64 unit line normal ``(cos alpha, sin alpha)``.
        rho: ``(M,)`` float64 line distance from the origin.
        line_info: ``(M, 2, 2)`` float64 inverse covariance of each line's ``(alpha, rho)``.
        grid: The segments gridded for the association (:func:`segment_grid`), or
            :func:`no_segment_grid`.
    """

    a: np.ndarray
    u: np.ndarray
    length: np.ndarray
    normal: np.ndarray
    rho: np.ndarray
    line_info: np.ndarray
    grid: SegmentGrid


def no_segment_grid() -> SegmentGrid:
    """An empty :class:`SegmentGrid`: :func:`associate` tests every segment."""
    return SegmentGrid(
        np.zeros(2), 1.0, np.ones(2, np.int64), np.zeros(2, np.int64), np.zeros(0, np.int64), 0.0
    )


@njit(cache=True, nogil=True)
def _segment_distance2(px: float, py: float, ax: float, ay: float, bx: float, by: float) -> float:
    """Squared distance from point ``p`` to segment ``a b``."""
    ex = bx - ax
    ey = by - ay
    l2 = ex * ex + ey * ey
    t = 0.0 if l2 <= 0.0 else max(0.0, min(1.0, ((px - ax) * ex + (py - ay) * ey) / l2))
    dx = px - (ax + t * ex)
    dy = py - (ay + t * ey)
    return dx * dx + dy * dy


@njit(cache=True, nogil=True)
def nearest_segment_distance(p: np.ndarray, endpoints: np.ndarray) -> float:
    """Distance (metres) from point ``p`` ``(2,)`` to the nearest of the segments
    ``endpoints`` ``(M, 2, 2)`` (inf when there are none)."""
    best = np.inf
    for m in range(endpoints.shape[0]):
        a, b = endpoints[m, 0], endpoints[m, 1]
        best = min(best, _segment_distance2(p[0], p[1], a[0], a[1], b[0], b[1]))
    return math.sqrt(best)


@njit(cache=True, nogil=True)
def _grid_cells(
    a: np.ndarray, u: np.ndarray, length: np.ndarray, reach: float, origin: np.ndarray,
    cell_m: float, n_cells: np.ndarray, out_key: np.ndarray, out_seg: np.ndarray,
) -> int:  # fmt: skip
    """Cells (key) and segment of every (cell, segment) incidence, segments in ascending
    order; written into ``out_*`` when they are long enough. Returns the count."""
    half_diag = 0.5 * math.sqrt(2.0) * cell_m
    k = 0
    for j in range(a.shape[0]):
        ax = a[j, 0]
        ay = a[j, 1]
        bx = ax + length[j] * u[j, 0]
        by = ay + length[j] * u[j, 1]
        x0 = math.floor((min(ax, bx) - reach - origin[0]) / cell_m)
        x1 = math.floor((max(ax, bx) + reach - origin[0]) / cell_m)
        y0 = math.floor((min(ay, by) - reach - origin[1]) / cell_m)
        y1 = math.floor((max(ay, by) + reach - origin[1]) / cell_m)
        lim = (reach + half_diag) * (reach + half_diag)
        for ix in range(max(x0, 0), min(x1, n_cells[0] - 1) + 1):
            cx = origin[0] + (ix + 0.5) * cell_m
            for iy in range(max(y0, 0), min(y1, n_cells[1] - 1) + 1):
                cy = origin[1] + (iy + 0.5) * cell_m
                if _segment_distance2(cx, cy, ax, ay, bx, by) <= lim:
                    if k < out_key.shape[0]:
                        out_key[k] = ix * n_cells[1] + iy
                        out_seg[k] = j
                    k += 1
    return k


@njit(cache=True, nogil=True)
def segment_grid(
    a: np.ndarray, u: np.ndarray, length: np.ndarray, reach_m: float, cell_m: float
) -> SegmentGrid:
    """Grid reference segments ``a + t u``, ``0 <= t <= length`` (``(M, 2)``, ``(M, 2)``,
    ``(M,)``, metres) for :func:`associate` with any ``gate + end tolerance <= reach_m``: a
    cell lists each segment within ``reach_m`` (plus :data:`GRID_SLACK_M`) of its centre's
    half diagonal, so a point is never further than ``reach_m`` from a segment its cell
    leaves out, and the exact test then decides on the listed ones."""
    reach = reach_m + GRID_SLACK_M
    m = a.shape[0]
    empty = SegmentGrid(
        np.zeros(2), cell_m, np.ones(2, np.int64), np.zeros(2, np.int64),
        np.zeros(0, np.int64), 0.0,
    )  # fmt: skip
    if m == 0:
        return empty
    for j in range(m):
        # The association's distance is a distance to the segment only for a unit direction
        # (a zero-length segment has u = 0 and matches anywhere) and finite numbers: else
        # no grid, every segment is tested.
        n2 = u[j, 0] * u[j, 0] + u[j, 1] * u[j, 1]
        if not (abs(n2 - 1.0) <= 1e-9) or not (
            math.isfinite(a[j, 0]) and math.isfinite(a[j, 1]) and math.isfinite(length[j])
        ):
            return empty
    lo = np.empty(2)
    hi = np.empty(2)
    for d in range(2):
        lo[d] = np.inf
        hi[d] = -np.inf
        for j in range(m):
            e = a[j, d] + length[j] * u[j, d]
            lo[d] = min(lo[d], a[j, d], e)
            hi[d] = max(hi[d], a[j, d], e)
    origin = lo - reach - cell_m
    n_cells = np.empty(2, np.int64)
    for d in range(2):
        n_cells[d] = math.floor((hi[d] + reach - origin[d]) / cell_m) + 2
    # Room for every cell of every segment's box (an upper bound of the incidences).
    room = 0
    for j in range(m):
        wx = abs(length[j] * u[j, 0]) + 2.0 * reach
        wy = abs(length[j] * u[j, 1]) + 2.0 * reach
        room += (math.floor(wx / cell_m) + 2) * (math.floor(wy / cell_m) + 2)
    key = np.empty(room, np.int64)
    seg = np.empty(room, np.int64)
    n = _grid_cells(a, u, length, reach, origin, cell_m, n_cells, key, seg)
    if n > key.shape[0]:  # never (the bound above), but stay exact if rounding says else
        key = np.empty(n, np.int64)
        seg = np.empty(n, np.int64)
        _grid_cells(a, u, length, reach, origin, cell_m, n_cells, key, seg)
    # Counting sort by cell; segments stay in ascending order within a cell.
    n_all = n_cells[0] * n_cells[1]
    start = np.zeros(n_all + 1, np.int64)
    for k in range(n):
        start[key[k] + 1] += 1
    for c in range(n_all):
        start[c + 1] += start[c]
    fill = start[:-1].copy()
    segs = np.empty(n, np.int64)
    for k in range(n):
        segs[fill[key[k]]] = seg[k]
        fill[key[k]] += 1
    return SegmentGrid(origin, cell_m, n_cells, start, segs, reach_m)


class SegmentPoints(NamedTuple):
    """New-scan points that lie on new segments (new frame).

    Attributes:
        xy: ``(P, 2)`` float64 points, metres.
        alpha: ``(P,)`` float64 normal angle of each point's own segment, radians.
    """

    xy: np.ndarray
    alpha: np.ndarray


class PairGeometry(NamedTuple):
    """Feature geometry of both scans for the feature-pair rows (``new_*``: new frame,
    ``ref_*``: reference frame): ``xy`` ``(K, 2)`` position (m), ``cov`` ``(K, 2, 2)`` its
    covariance (m^2), ``kind`` ``(K,)`` int64 feature kind, ``edge0`` ``(K,)`` direction of
    the first edge (rad)."""

    new_xy: np.ndarray
    new_cov: np.ndarray
    new_kind: np.ndarray
    new_edge0: np.ndarray
    ref_xy: np.ndarray
    ref_cov: np.ndarray
    ref_kind: np.ndarray
    ref_edge0: np.ndarray


class PointCloud(NamedTuple):
    """Off-segment new points against the reference's points (PL-ICP, Censi 2008), with a
    uniform grid over the reference points for the nearest-neighbour search.

    Attributes:
        points: ``(C, 2)`` float64 new points on no segment (new frame), metres.
        ref_points: ``(R, 2)`` float64 reference points (reference frame).
        ref_spacing: ``(R,)`` float64 distance to the nearest beam neighbour, metres.
        ref_normal: ``(R, 2)`` float64 unit normal of the local line (NaN: isolated point).
        cell_m: Grid cell, metres (at least the largest association gate).
        origin: ``(2,)`` float64 corner of cell ``(0, 0)``.
        n_cells: ``(2,)`` int64 cells along x and y.
        cell_key: ``(R,)`` int64 sorted cell keys ``ix * n_cells[1] + iy``.
        cell_order: ``(R,)`` int64 reference point of each sorted key.
    """

    points: np.ndarray
    ref_points: np.ndarray
    ref_spacing: np.ndarray
    ref_normal: np.ndarray
    cell_m: float
    origin: np.ndarray
    n_cells: np.ndarray
    cell_key: np.ndarray
    cell_order: np.ndarray


class GnSettings(NamedTuple):
    """Fixed numbers of the refinement (metres, radians): association gates, noise floor,
    Cauchy scale (in each row's standard deviations), the fine gate rule
    ``min(gate_m, max(gate_min_m, gate_sigmas sigma))`` and the EOW kind code."""

    end_tol_m: float
    sin_normal_gate: float
    sigma_min_m: float
    cauchy_sigmas: float
    gate_m: float
    gate_sigmas: float
    gate_min_m: float
    eow_kind: int


class GnPhase(NamedTuple):
    """One phase of the Gauss-Newton loop: ``coarse`` (full feature positions, fixed gate)
    or fine; the starting gate and noise (m), the iteration cap and the step tolerances
    (m, rad) below which it stops."""

    coarse: bool
    gate_m: float
    sigma_m: float
    max_iterations: int
    tol_xy_m: float
    tol_theta_rad: float


class PosePrior(NamedTuple):
    """The bounds' prior: ``mean`` ``(3,)`` (the prediction) and ``info`` ``(3, 3)``."""

    mean: np.ndarray
    info: np.ndarray


class FeaturePairing(NamedTuple):
    """The correlation's feature pairing (:func:`pair_nearest`) for the refinement: both
    scans' feature positions ``(K, 2)`` (m), headings ``(K,)``, edge directions ``(K, 2)``
    and opening angles ``(K,)`` (rad; ``new_*`` in the new frame, ``ref_*`` in the reference
    frame), the pair codes ``(K_new, K_ref)`` int64 and the distance (m) and angle (rad)
    gates. Zero features: no pairs."""

    new_xy: np.ndarray
    new_heading: np.ndarray
    new_edge: np.ndarray
    new_opening: np.ndarray
    ref_xy: np.ndarray
    ref_heading: np.ndarray
    ref_edge: np.ndarray
    ref_opening: np.ndarray
    codes: np.ndarray
    gate_distance_m: float
    gate_angle_rad: float


@njit(cache=True, nogil=True)
def associate(
    pose: np.ndarray,
    pts: SegmentPoints,
    segs: LineSegments,
    gate_m: float,
    end_tol_m: float,
    sin_normal_gate: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Nearest compatible reference segment of each point within the gate (same rule as
    :func:`iceg.matching.geometry.associate_points`).

    Returns:
        ``idx`` (P,) int64 segment (-1: none) and ``res`` (P,) float64 signed point-to-line
        residual, metres (NaN where none).
    """
    n_p = pts.xy.shape[0]
    n_m = segs.a.shape[0]
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    idx = np.full(n_p, -1, dtype=np.int64)
    res = np.full(n_p, np.nan)
    gate2 = gate_m * gate_m
    g = segs.grid
    # The grid lists, per cell, every segment that can pass the gate (in ascending order,
    # so ties resolve as in the loop over all segments); without one, all are tested.
    gridded = g.reach_m > 0.0 and gate_m + end_tol_m <= g.reach_m
    # Points come segment by segment and neighbours share a cell: the segments of the cell
    # that pass the normal gate are kept while the cell and the point's segment angle repeat
    # (the same list, in the same order, tested once).
    kept = np.empty(n_m, np.int64)
    n_kept = 0
    key_prev = -2
    alpha_prev = np.nan
    for i in range(n_p):
        px = c * pts.xy[i, 0] - s * pts.xy[i, 1] + pose[0]
        py = s * pts.xy[i, 0] + c * pts.xy[i, 1] + pose[1]
        key = -1
        if gridded:
            fx = np.floor((px - g.origin[0]) / g.cell_m)
            fy = np.floor((py - g.origin[1]) / g.cell_m)
            if not (0.0 <= fx < g.n_cells[0] and 0.0 <= fy < g.n_cells[1]):
                continue  # outside the grid (or not finite): no segment within reach
            key = int(fx) * g.n_cells[1] + int(fy)
        if pts.alpha[i] != alpha_prev or key != key_prev:
            alpha_prev = pts.alpha[i]
            key_prev = key
            qa = pts.alpha[i] + pose[2]
            sq = math.sin(qa)
            cq = math.cos(qa)
            lo, hi = (g.start[key], g.start[key + 1]) if gridded else (0, n_m)
            n_kept = 0
            for t in range(lo, hi):
                j = g.segs[t] if gridded else t
                if abs(sq * segs.normal[j, 0] - cq * segs.normal[j, 1]) <= sin_normal_gate:
                    kept[n_kept] = j
                    n_kept += 1
        best = gate2
        bj = -1
        for t in range(n_kept):
            j = kept[t]
            rx = px - segs.a[j, 0]
            ry = py - segs.a[j, 1]
            along = rx * segs.u[j, 0] + ry * segs.u[j, 1]
            perp = rx * segs.u[j, 1] - ry * segs.u[j, 0]
            over = max(-end_tol_m - along, along - segs.length[j] - end_tol_m, 0.0)
            d2 = perp * perp + over * over
            if d2 <= best:
                best = d2
                bj = j
        if bj >= 0:
            idx[i] = bj
            res[i] = px * segs.normal[bj, 0] + py * segs.normal[bj, 1] - segs.rho[bj]
    return idx, res


@njit(cache=True, nogil=True)
def _robust_sigma(idx: np.ndarray, res: np.ndarray, sigma_prev: float, sigma_min: float) -> float:
    """Point noise from the residuals' median absolute deviation (floored), or
    ``sigma_prev`` when fewer than ``MIN_POINTS_FOR_SIGMA`` points associate."""
    n_assoc = 0
    for i in range(idx.shape[0]):
        if idx[i] >= 0:
            n_assoc += 1
    if n_assoc < MIN_POINTS_FOR_SIGMA:
        return sigma_prev
    absr = np.empty(n_assoc)
    k = 0
    for i in range(idx.shape[0]):
        if idx[i] >= 0:
            absr[k] = abs(res[i])
            k += 1
    return max(sigma_min, MAD_TO_SIGMA * np.median(absr))


@njit(cache=True, nogil=True)
def _gls_normal_equations(
    pose: np.ndarray,
    pts: SegmentPoints,
    segs: LineSegments,
    idx: np.ndarray,
    res: np.ndarray,
    sigma: float,
    cauchy_sigmas: float,
) -> tuple[np.ndarray, np.ndarray]:
    """GLS normal equations of the associated point-to-line residuals: per segment
    ``C = W^-1 + B S B^T`` (``B``: derivative w.r.t. the line's ``(alpha, rho)``, ``S`` its
    covariance), inverted by the Woodbury identity (a 2x2 inverse per segment).

    A segment's 24 sums (``J^T W J`` 3x3, ``J^T W B`` 3x2, ``B^T W B`` 2x2, ``J^T W r`` and
    ``B^T W r``) are kept in locals along a run of consecutive points on it (points come
    wall by wall) and stored when the run ends; each sum still takes its terms in the
    order of the points."""
    n_m = segs.a.shape[0]
    n_p = pts.xy.shape[0]
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    cc = cauchy_sigmas * sigma
    # per segment: jj[a, b] at 3a + b, jb[a, b] at 9 + 2a + b, bb[a, b] at 15 + 2a + b,
    # jr[a] at 19 + a, br[a] at 22 + a
    acc = np.zeros((n_m, 24))
    used = np.zeros(n_m, dtype=np.bool_)
    i = 0
    while i < n_p:
        j = idx[i]
        if j < 0:
            i += 1
            continue
        used[j] = True
        ca = segs.normal[j, 0]
        sa = segs.normal[j, 1]
        jj00, jj01, jj02 = acc[j, 0], acc[j, 1], acc[j, 2]
        jj10, jj11, jj12 = acc[j, 3], acc[j, 4], acc[j, 5]
        jj20, jj21, jj22 = acc[j, 6], acc[j, 7], acc[j, 8]
        jb00, jb01, jb10, jb11, jb20, jb21 = (
            acc[j, 9], acc[j, 10], acc[j, 11], acc[j, 12], acc[j, 13], acc[j, 14]
        )  # fmt: skip
        bb00, bb01, bb10, bb11 = acc[j, 15], acc[j, 16], acc[j, 17], acc[j, 18]
        jr0, jr1, jr2, br0, br1 = acc[j, 19], acc[j, 20], acc[j, 21], acc[j, 22], acc[j, 23]
        while i < n_p and idx[i] == j:
            rpx = c * pts.xy[i, 0] - s * pts.xy[i, 1]
            rpy = s * pts.xy[i, 0] + c * pts.xy[i, 1]
            qx = rpx + pose[0]
            qy = rpy + pose[1]
            r = res[i]
            w = 1.0 / (1.0 + (r / cc) ** 2) / (sigma * sigma)
            j0, j1, j2 = ca, sa, sa * rpx - ca * rpy
            b0, b1 = -sa * qx + ca * qy, -1.0
            jr0 += w * j0 * r
            jj00 += w * j0 * j0
            jj01 += w * j0 * j1
            jj02 += w * j0 * j2
            jb00 += w * j0 * b0
            jb01 += w * j0 * b1
            jr1 += w * j1 * r
            jj10 += w * j1 * j0
            jj11 += w * j1 * j1
            jj12 += w * j1 * j2
            jb10 += w * j1 * b0
            jb11 += w * j1 * b1
            jr2 += w * j2 * r
            jj20 += w * j2 * j0
            jj21 += w * j2 * j1
            jj22 += w * j2 * j2
            jb20 += w * j2 * b0
            jb21 += w * j2 * b1
            br0 += w * b0 * r
            bb00 += w * b0 * b0
            bb01 += w * b0 * b1
            br1 += w * b1 * r
            bb10 += w * b1 * b0
            bb11 += w * b1 * b1
            i += 1
        acc[j, 0], acc[j, 1], acc[j, 2] = jj00, jj01, jj02
        acc[j, 3], acc[j, 4], acc[j, 5] = jj10, jj11, jj12
        acc[j, 6], acc[j, 7], acc[j, 8] = jj20, jj21, jj22
        acc[j, 9], acc[j, 10], acc[j, 11], acc[j, 12] = jb00, jb01, jb10, jb11
        acc[j, 13], acc[j, 14] = jb20, jb21
        acc[j, 15], acc[j, 16], acc[j, 17], acc[j, 18] = bb00, bb01, bb10, bb11
        acc[j, 19], acc[j, 20], acc[j, 21], acc[j, 22], acc[j, 23] = jr0, jr1, jr2, br0, br1
    hess = np.zeros((3, 3))
    grad = np.zeros(3)
    for j in range(n_m):
        if not used[j]:
            continue
        m00 = segs.line_info[j, 0, 0] + acc[j, 15]
        m01 = segs.line_info[j, 0, 1] + acc[j, 16]
        m10 = segs.line_info[j, 1, 0] + acc[j, 17]
        m11 = segs.line_info[j, 1, 1] + acc[j, 18]
        det = m00 * m11 - m01 * m10
        k00 = m11 / det
        k01 = -m01 / det
        k10 = -m10 / det
        k11 = m00 / det
        for a in range(3):
            # (JB K) row a
            t0 = acc[j, 9 + 2 * a] * k00 + acc[j, 10 + 2 * a] * k10
            t1 = acc[j, 9 + 2 * a] * k01 + acc[j, 10 + 2 * a] * k11
            grad[a] += acc[j, 19 + a] - (t0 * acc[j, 22] + t1 * acc[j, 23])
            for b in range(3):
                hess[a, b] += acc[j, 3 * a + b] - (t0 * acc[j, 9 + 2 * b] + t1 * acc[j, 10 + 2 * b])
    return hess, grad


@njit(cache=True, nogil=True)
def point_line_system(
    pose: np.ndarray,
    pts: SegmentPoints,
    segs: LineSegments,
    gate_m: float,
    sigma_prev: float,
    settings: GnSettings,
) -> tuple[np.ndarray, np.ndarray, float, np.ndarray, np.ndarray]:
    """Associate each point with its nearest compatible reference segment and build the
    GLS normal equations (perturbation ``(x, y, theta)`` in the reference frame; docs/design.md
    step 8, paper §III-C3).

    Args:
        pose: ``(3,)`` pose of the new scan in the reference frame.
        pts: The new scan's points on segments (new frame).
        segs: Reference segments.
        gate_m: Association gate, metres.
        sigma_prev: Point noise to use if too few points associate, metres.
        settings: Gates, noise floor and Cauchy scale.

    Returns:
        ``H`` (3, 3), ``g`` (3,), the estimated sigma (m), ``idx`` (P,) segment of each point
        (-1: none) and ``res`` (P,) signed residuals (NaN where none).
    """
    idx, res = associate(pose, pts, segs, gate_m, settings.end_tol_m, settings.sin_normal_gate)
    sigma = _robust_sigma(idx, res, sigma_prev, settings.sigma_min_m)
    hess, grad = _gls_normal_equations(pose, pts, segs, idx, res, sigma, settings.cauchy_sigmas)
    return hess, grad, sigma, idx, res


@njit(cache=True, nogil=True)
def _pair_covariance(
    pose: np.ndarray, geom: PairGeometry, i: int, j: int
) -> tuple[float, float, float, float, float, float, float]:
    """Rotated new position ``(rnx, rny)``, position error ``(ex, ey)`` and the entries
    ``(ca, cb, cd)`` of ``R C_new R^T + C_ref`` of pair ``(i, j)``."""
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    rnx = c * geom.new_xy[i, 0] - s * geom.new_xy[i, 1]
    rny = s * geom.new_xy[i, 0] + c * geom.new_xy[i, 1]
    ex = rnx + pose[0] - geom.ref_xy[j, 0]
    ey = rny + pose[1] - geom.ref_xy[j, 1]
    a = geom.new_cov[i, 0, 0]
    b = geom.new_cov[i, 0, 1]
    d = geom.new_cov[i, 1, 1]
    ca = c * c * a - 2 * c * s * b + s * s * d + geom.ref_cov[j, 0, 0]
    cb = c * s * (a - d) + (c * c - s * s) * b + geom.ref_cov[j, 0, 1]
    cd = s * s * a + 2 * c * s * b + c * c * d + geom.ref_cov[j, 1, 1]
    return rnx, rny, ex, ey, ca, cb, cd


@njit(cache=True, nogil=True)
def _eow_row(
    pose: np.ndarray, geom: PairGeometry, i: int, j: int, eow: int, jv: np.ndarray
) -> tuple[float, float]:
    """The along-wall row of a feature pair ``(i, j)`` that involves an EOW (the reference
    EOW's wall, else the new one's rotated): its residual and variance (metres, m^2), its
    Jacobian written into ``jv`` ``(3,)``."""
    rnx, rny, ex, ey, ca, cb, cd = _pair_covariance(pose, geom, i, j)
    ang = geom.ref_edge0[j] if geom.ref_kind[j] == eow else geom.new_edge0[i] + pose[2]
    dx = math.cos(ang)
    dy = math.sin(ang)
    jv[0] = dx
    jv[1] = dy
    jv[2] = dy * rnx - dx * rny
    return dx * ex + dy * ey, dx * dx * ca + 2 * dx * dy * cb + dy * dy * cd


@njit(cache=True, nogil=True)
def _add_row(hess: np.ndarray, grad: np.ndarray, jv: np.ndarray, r: float, w: float) -> None:
    """``H += w j j^T``, ``g += w j r`` for one scalar row."""
    for p in range(3):
        grad[p] += w * jv[p] * r
        for q in range(3):
            hess[p, q] += w * jv[p] * jv[q]


@njit(cache=True, nogil=True)
def feature_system(
    pose: np.ndarray,
    pairs: np.ndarray,
    geom: PairGeometry,
    use_positions: bool,
    settings: GnSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations of the feature pairs ``(Q, 2)`` ``[new, ref]`` (docs/design.md step 8): a
    pair that involves an EOW constrains the position along its wall (the reference EOW's
    wall, else the new one's rotated); other pairs, with ``use_positions``, their full 2D
    position with covariance ``R C_new R^T + C_ref``. Cauchy weights on the whitened
    residuals, scale ``settings.cauchy_sigmas``."""
    cauchy_c = settings.cauchy_sigmas
    eow = settings.eow_kind
    hess = np.zeros((3, 3))
    grad = np.zeros(3)
    jv = np.empty(3)
    ju = np.empty(3)
    for k in range(pairs.shape[0]):
        i = pairs[k, 0]
        j = pairs[k, 1]
        rnx, rny, ex, ey, ca, cb, cd = _pair_covariance(pose, geom, i, j)
        if geom.ref_kind[j] == eow or geom.new_kind[i] == eow:
            r, var = _eow_row(pose, geom, i, j, eow, jv)
            if not (var > 0.0) or not math.isfinite(r):
                continue
            w = 1.0 / (1.0 + r * r / var / (cauchy_c * cauchy_c)) / var
            _add_row(hess, grad, jv, r, w)
        elif use_positions:
            det = ca * cd - cb * cb
            if not (det > 0.0):
                continue
            i00 = cd / det
            i01 = -cb / det
            i11 = ca / det
            m2 = ex * (i00 * ex + i01 * ey) + ey * (i01 * ex + i11 * ey)
            w = 1.0 / (1.0 + m2 / (cauchy_c * cauchy_c))
            # J = [[1, 0, -rny], [0, 1, rnx]]; H += w J^T I J; g += w J^T I e
            jv[0] = 1.0
            jv[1] = 0.0
            jv[2] = -rny
            ju[0] = 0.0
            ju[1] = 1.0
            ju[2] = rnx
            for p in range(3):
                grad[p] += w * (jv[p] * (i00 * ex + i01 * ey) + ju[p] * (i01 * ex + i11 * ey))
                for q in range(3):
                    hess[p, q] += w * (
                        jv[p] * (i00 * jv[q] + i01 * ju[q]) + ju[p] * (i01 * jv[q] + i11 * ju[q])
                    )
    return hess, grad


@njit(cache=True, nogil=True)
def cloud_nearest(pose: np.ndarray, cloud: PointCloud, gate_m: float) -> np.ndarray:
    """Nearest reference point (closer than ``gate_m <= cloud.cell_m``) of each off-segment
    point moved into the reference frame by ``pose``; -1 where none. Searches the 3x3 grid
    cells around the point."""
    n_c = cloud.points.shape[0]
    out = np.full(n_c, -1, dtype=np.int64)
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    for i in range(n_c):
        qx = c * cloud.points[i, 0] - s * cloud.points[i, 1] + pose[0]
        qy = s * cloud.points[i, 0] + c * cloud.points[i, 1] + pose[1]
        fx = (qx - cloud.origin[0]) / cloud.cell_m
        fy = (qy - cloud.origin[1]) / cloud.cell_m
        if not (
            fx > -2.0 and fy > -2.0 and fx < cloud.n_cells[0] + 1 and fy < cloud.n_cells[1] + 1
        ):
            continue
        ix = math.floor(fx)
        iy = math.floor(fy)
        best = gate_m * gate_m
        for cx in range(max(ix - 1, 0), min(ix + 2, cloud.n_cells[0])):
            for cy in range(max(iy - 1, 0), min(iy + 2, cloud.n_cells[1])):
                key = cx * cloud.n_cells[1] + cy
                lo = np.searchsorted(cloud.cell_key, key)
                hi = np.searchsorted(cloud.cell_key, key, side="right")
                for k in range(lo, hi):
                    j = cloud.cell_order[k]
                    dx = qx - cloud.ref_points[j, 0]
                    dy = qy - cloud.ref_points[j, 1]
                    d2 = dx * dx + dy * dy
                    if d2 < best:
                        best = d2
                        out[i] = j
    return out


@njit(cache=True, nogil=True)
def cloud_system(
    pose: np.ndarray, cloud: PointCloud, gate_m: float, sigma: float, cauchy_sigmas: float
) -> tuple[np.ndarray, np.ndarray]:
    """Normal equations of the off-segment points (PL-ICP, Censi 2008): one point-to-line
    row (variance ``2 sigma^2``) on the nearest reference point's local line, or two
    point-to-point rows (variance ``2 sigma^2 + (spacing / 2)^2``) for an isolated
    reference point; Cauchy weights with scale ``cauchy_sigmas`` on the whitened residual."""
    hess = np.zeros((3, 3))
    grad = np.zeros(3)
    r, jac, w, _ = cloud_rows(pose, cloud, gate_m, sigma, cauchy_sigmas)
    for k in range(r.shape[0]):
        _add_row(hess, grad, jac[k], r[k], w[k])
    return hess, grad


@njit(cache=True, nogil=True)
def cloud_rows(
    pose: np.ndarray, cloud: PointCloud, gate_m: float, sigma: float, cauchy_sigmas: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The rows of :func:`cloud_system`, point by point: residuals ``(R,)`` (metres),
    Jacobians ``(R, 3)``, weights ``(R,)`` (Cauchy weight over variance) and variances
    ``(R,)`` (m^2)."""
    near = cloud_nearest(pose, cloud, gate_m)
    c = math.cos(pose[2])
    s = math.sin(pose[2])
    n_rows = 0
    for i in range(near.shape[0]):
        if near[i] >= 0:
            n_rows += 1 if math.isfinite(cloud.ref_normal[near[i], 0]) else 2
    r = np.empty(n_rows)
    jac = np.empty((n_rows, 3))
    w = np.empty(n_rows)
    var_out = np.empty(n_rows)
    k = 0
    for i in range(near.shape[0]):
        j = near[i]
        if j < 0:
            continue
        rpx = c * cloud.points[i, 0] - s * cloud.points[i, 1]
        rpy = s * cloud.points[i, 0] + c * cloud.points[i, 1]
        ex = rpx + pose[0] - cloud.ref_points[j, 0]
        ey = rpy + pose[1] - cloud.ref_points[j, 1]
        nx = cloud.ref_normal[j, 0]
        ny = cloud.ref_normal[j, 1]
        if math.isfinite(nx):
            var = 2.0 * sigma * sigma
            r[k] = nx * ex + ny * ey
            w[k] = 1.0 / (1.0 + (r[k] / math.sqrt(var) / cauchy_sigmas) ** 2) / var
            var_out[k] = var
            jac[k, 0], jac[k, 1], jac[k, 2] = nx, ny, ny * rpx - nx * rpy
            k += 1
            continue
        var = 2.0 * sigma * sigma + (0.5 * min(cloud.ref_spacing[j], 1e3)) ** 2
        wk = 1.0 / (1.0 + (math.hypot(ex, ey) / math.sqrt(var) / cauchy_sigmas) ** 2) / var
        r[k], r[k + 1] = ex, ey
        w[k], w[k + 1] = wk, wk
        var_out[k], var_out[k + 1] = var, var
        jac[k, 0], jac[k, 1], jac[k, 2] = 1.0, 0.0, -rpy
        jac[k + 1, 0], jac[k + 1, 1], jac[k + 1, 2] = 0.0, 1.0, rpx
        k += 2
    return r, jac, w, var_out


@njit(cache=True, nogil=True)
def covariance_rows(
    pose: np.ndarray,
    pairs: np.ndarray,
    geom: PairGeometry,
    cloud: PointCloud,
    gate_m: float,
    sigma: float,
    settings: GnSettings,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The rows of a refined pose's covariance besides the point-to-line ones: the EOW
    pairs' along-wall rows (:func:`feature_system`'s fine phase) and the off-segment rows
    (:func:`cloud_rows`), with their information.

    Returns:
        Residuals ``(R,)`` (metres), Jacobians ``(R, 3)``, variances ``(R,)`` (m^2) and the
        information ``(3, 3)`` ``sum_k w_k j_k j_k^T`` (Cauchy weight over variance).
    """
    cauchy_c = settings.cauchy_sigmas
    eow = settings.eow_kind
    cr, cjac, cw, cvar = cloud_rows(pose, cloud, gate_m, sigma, cauchy_c)
    n_q = pairs.shape[0]
    r = np.empty(n_q + cr.shape[0])
    jac = np.empty((n_q + cr.shape[0], 3))
    var = np.empty(n_q + cr.shape[0])
    hess = np.zeros((3, 3))
    grad = np.zeros(3)  # not used: _add_row's other half
    jv = np.empty(3)
    k = 0
    for q in range(n_q):
        i = pairs[q, 0]
        j = pairs[q, 1]
        if not (geom.ref_kind[j] == eow or geom.new_kind[i] == eow):
            continue
        rk, vk = _eow_row(pose, geom, i, j, eow, jv)
        if not (vk > 0.0) or not math.isfinite(rk):
            continue
        _add_row(hess, grad, jv, rk, 1.0 / (1.0 + rk * rk / vk / (cauchy_c * cauchy_c)) / vk)
        r[k], var[k] = rk, vk
        jac[k, 0], jac[k, 1], jac[k, 2] = jv[0], jv[1], jv[2]
        k += 1
    for m in range(cr.shape[0]):
        _add_row(hess, grad, cjac[m], cr[m], cw[m])
        r[k], var[k] = cr[m], cvar[m]
        jac[k, 0], jac[k, 1], jac[k, 2] = cjac[m, 0], cjac[m, 1], cjac[m, 2]
        k += 1
    return r[:k], jac[:k], var[:k], hess


@njit(cache=True, nogil=True)
def _wrap(t: float) -> float:
    """An angle wrapped to ``[-pi, pi)`` (``se2.wrap_angle``'s arithmetic)."""
    return (t + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True, nogil=True)
def _absw(x: float) -> float:
    return abs(_wrap(x))


@njit(cache=True, nogil=True)
def pair_code_matrix(
    new_kind: np.ndarray,
    new_opening: np.ndarray,
    ref_kind: np.ndarray,
    ref_opening: np.ndarray,
    table: np.ndarray,
    corner: int,
    intersections: int,
    max_opening_diff_rad: float,
) -> np.ndarray:
    """``(K_new, K_ref)`` int64 pair codes (``hypotheses.pair_codes``): ``table[new kind,
    reference kind]`` (``(3, 3)`` int64); 0 instead for a pair of two Corners or of code
    ``intersections`` whose opening angles (radians) differ by more than
    ``max_opening_diff_rad`` or are NaN, and for a kind outside the table."""
    kn = new_kind.shape[0]
    kr = ref_kind.shape[0]
    codes = np.zeros((kn, kr), dtype=np.int64)
    n_kinds = table.shape[0]
    for i in range(kn):
        a = new_kind[i]
        if a < 0 or a >= n_kinds:
            continue
        for j in range(kr):
            b = ref_kind[j]
            if b < 0 or b >= n_kinds:
                continue
            code = table[a, b]
            gated = (a == corner and b == corner) or code == intersections
            if gated and not (abs(new_opening[i] - ref_opening[j]) <= max_opening_diff_rad):
                code = 0
            codes[i, j] = code
    return codes


@njit(cache=True, nogil=True)
def feasible_pair_indices(
    new_xy_rotated: np.ndarray,
    offset: np.ndarray,
    dist: np.ndarray,
    max_translation_m: float,
    chord: float,
    margin_m: float,
    ref_xy: np.ndarray,
    codes: np.ndarray,
) -> tuple[np.ndarray, np.ndarray]:
    """The (new, reference) pairs with a non-zero code whose reference feature lies within
    its new feature's radius of the predicted position (``hypotheses.feasible_pairs``): the
    position ``new_xy_rotated + offset``, the radius ``max_translation_m + dist * chord +
    margin_m``, the test ``dx * dx + dy * dy <= radius * radius``; numpy's expressions, in
    row-major order.

    Args:
        new_xy_rotated: ``(K_new, 2)`` float64 new features rotated by the prediction, m.
        offset: ``(2,)`` float64 the prediction's translation, m.
        dist: ``(K_new,)`` float64 each new feature's distance from the new scan's origin, m.
        max_translation_m: The bounds' translation; ``chord`` the largest displacement of a
            unit-distance point under the bounds' rotation; ``margin_m`` the noise allowance.
        ref_xy: ``(K_ref, 2)`` float64 reference features, m.
        codes: ``(K_new, K_ref)`` int64 pair codes (0: incompatible).

    Returns:
        ``(Q,)`` int64 new and ``(Q,)`` int64 reference indices.
    """
    kn, kr = new_xy_rotated.shape[0], ref_xy.shape[0]
    out_i = np.empty(kn * kr, dtype=np.int64)
    out_j = np.empty(kn * kr, dtype=np.int64)
    q = 0
    for i in range(kn):
        px = new_xy_rotated[i, 0] + offset[0]
        py = new_xy_rotated[i, 1] + offset[1]
        radius = (max_translation_m + dist[i] * chord) + margin_m
        r2 = radius * radius
        for j in range(kr):
            dx = px - ref_xy[j, 0]
            dy = py - ref_xy[j, 1]
            if dx * dx + dy * dy <= r2 and codes[i, j] != 0:
                out_i[q] = i
                out_j[q] = j
                q += 1
    return out_i[:q].copy(), out_j[:q].copy()


@njit(cache=True, nogil=True)
def pairs_of_kind(
    i: np.ndarray, j: np.ndarray, new_kind: np.ndarray, ref_kind: np.ndarray, kind: int
) -> tuple[np.ndarray, np.ndarray]:
    """The pairs ``(i[q], j[q])`` ``(Q,)`` int64 whose new and reference features are both
    of ``kind``, in order: ``(Q',)`` int64 each."""
    out_i = np.empty(i.shape[0], dtype=np.int64)
    out_j = np.empty(i.shape[0], dtype=np.int64)
    n = 0
    for q in range(i.shape[0]):
        if new_kind[i[q]] == kind and ref_kind[j[q]] == kind:
            out_i[n] = i[q]
            out_j[n] = j[q]
            n += 1
    return out_i[:n].copy(), out_j[:n].copy()


#: :func:`pair_nearest` skips ``hypot`` for a pair whose squared distance exceeds the
#: square of the nearest distance so far (at first the gate) by this factor: its distance is
#: then at least ``1 + 5e-10`` times that, far beyond the rounding of the squares (a few
#: 1e-16) and of ``hypot`` (one ulp), so the exact test would reject it too.
_BEYOND_GATE = 1.0 + 1e-9


@njit(cache=True, nogil=True)
def pair_nearest(
    poses: np.ndarray,
    new_xy: np.ndarray,
    new_heading: np.ndarray,
    new_edge: np.ndarray,
    new_opening: np.ndarray,
    ref_xy: np.ndarray,
    ref_heading: np.ndarray,
    ref_edge: np.ndarray,
    ref_opening: np.ndarray,
    codes: np.ndarray,
    gate_distance_m: float,
    gate_angle_rad: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Feature pairing of the correlation (see ``correlation.correlate``) for ``H`` poses:
    each new feature pairs with the nearest compatible reference feature inside both gates,
    and a reference feature keeps only its nearest new feature.

    Pair codes (``hypotheses.pair_codes``): 1 same directed kind (heading difference),
    2 new Corner / reference EOW and 3 new EOW / reference Corner (the closer Corner edge),
    4 Intersections (opening-angle difference), 0 incompatible.

    Returns:
        ``match`` (H, K_new) reference index or -1, ``dist`` and ``angle`` (H, K_new) of the
        pairs (NaN where unpaired).
    """
    h_n = poses.shape[0]
    kn = new_xy.shape[0]
    kr = ref_xy.shape[0]
    match = np.full((h_n, kn), -1, dtype=np.int64)
    dist = np.full((h_n, kn), np.nan)
    angle = np.full((h_n, kn), np.nan)
    owner = np.empty(kr, dtype=np.int64)
    for h in range(h_n):
        c = math.cos(poses[h, 2])
        s = math.sin(poses[h, 2])
        th = poses[h, 2]
        for i in range(kn):
            x = c * new_xy[i, 0] - s * new_xy[i, 1] + poses[h, 0]
            y = s * new_xy[i, 0] + c * new_xy[i, 1] + poses[h, 1]
            best = gate_distance_m
            bj = -1
            ba = 0.0
            for j in range(kr):
                code = codes[i, j]
                if code == 0:
                    continue
                dx = x - ref_xy[j, 0]
                dy = y - ref_xy[j, 1]
                if dx * dx + dy * dy > best * best * _BEYOND_GATE:
                    continue  # hypot(dx, dy) >= best, without it
                d = math.hypot(dx, dy)
                if d >= best:
                    continue
                if code == 1:
                    a = _absw(new_heading[i] + th - ref_heading[j])
                elif code == 2:
                    a = min(
                        _absw(new_edge[i, 0] + th - ref_edge[j, 0]),
                        _absw(new_edge[i, 1] + th - ref_edge[j, 0]),
                    )
                elif code == 3:
                    a = min(
                        _absw(new_edge[i, 0] + th - ref_edge[j, 0]),
                        _absw(new_edge[i, 0] + th - ref_edge[j, 1]),
                    )
                else:
                    a = abs(new_opening[i] - ref_opening[j])
                if not (a < gate_angle_rad):  # NaN fails too
                    continue
                best = d
                bj = j
                ba = a
            if bj >= 0:
                match[h, i] = bj
                dist[h, i] = best
                angle[h, i] = ba
        # One new feature per reference feature: the nearest keeps it.
        owner[:] = -1
        for i in range(kn):
            j = match[h, i]
            if j < 0:
                continue
            o = owner[j]
            if o < 0:
                owner[j] = i
            elif dist[h, i] < dist[h, o]:
                match[h, o] = -1
                dist[h, o] = np.nan
                angle[h, o] = np.nan
                owner[j] = i
            else:
                match[h, i] = -1
                dist[h, i] = np.nan
                angle[h, i] = np.nan
    return match, dist, angle


@njit(cache=True, nogil=True)
def visible_counts(
    poses: np.ndarray,
    ref_xy: np.ndarray,
    bearing: np.ndarray,
    ranges: np.ndarray,
    spacing: float,
    max_gap_rad: float,
    range_max_m: float,
    occlusion_tolerance_m: float,
) -> np.ndarray:
    """How many reference features the new scan could see from each pose (the count term of
    ``correlation.correlate``): inside the new scan's field of view (its first and last
    bearings widened by ``spacing``) and range, and not occluded (the return nearest in
    bearing, when within ``max_gap_rad``, is not shorter than the feature's distance minus
    the tolerance).

    Args:
        poses: ``(H, 3)`` float64 poses of the new scan in the reference frame.
        ref_xy: ``(K, 2)`` float64 reference features, reference frame, metres.
        bearing, ranges: ``(B,)`` float64 the new scan's polar profile, bearings ascending
            (``geometry.PolarProfile``), ``B >= 1``.
        spacing: The profile's beam spacing, radians (widens the field of view).
        max_gap_rad: Largest bearing distance to the nearest return that still judges
            occlusion, radians.
        range_max_m, occlusion_tolerance_m: The new scan's reliable range and the
            occlusion allowance, metres.

    Returns:
        ``(H,)`` int64 counts.
    """
    n_b = bearing.shape[0]
    lo = bearing[0] - spacing
    hi = bearing[n_b - 1] + spacing
    out = np.zeros(poses.shape[0], dtype=np.int64)
    for h in range(poses.shape[0]):
        c = math.cos(poses[h, 2])
        s = math.sin(poses[h, 2])
        for k in range(ref_xy.shape[0]):
            rx = ref_xy[k, 0] - poses[h, 0]
            ry = ref_xy[k, 1] - poses[h, 1]
            lx = c * rx + s * ry
            ly = -s * rx + c * ry
            b = math.atan2(ly, lx)
            d = math.hypot(lx, ly)
            if not (b >= lo and b <= hi and d < range_max_m):
                continue
            q = np.searchsorted(bearing, b)
            k0 = max(q - 1, 0)
            k1 = min(q, n_b - 1)
            d0 = abs(b - bearing[k0])
            d1 = abs(bearing[k1] - b)
            nearest, gap = (k0, d0) if d0 <= d1 else (k1, d1)
            if gap <= max_gap_rad and ranges[nearest] < d - occlusion_tolerance_m:
                continue  # occluded
            out[h] += 1
    return out


@njit(cache=True, nogil=True)
def correlation_terms(
    match: np.ndarray,
    dist: np.ndarray,
    angle: np.ndarray,
    new_importance: np.ndarray,
    ref_importance: np.ndarray,
    n_visible: np.ndarray,
    gate_distance_m: float,
    gate_angle_rad: float,
    weights: tuple[float, float, float, float],
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The four terms of paper eq. 1 and their weighted mean from a pairing (see
    ``correlation.correlate``; sums in numpy's order, so the values are those of the numpy
    expressions bit for bit).

    Args:
        match, dist, angle: ``(H, K_new)`` from :func:`pair_nearest`.
        new_importance, ref_importance: ``(K_new,)``, ``(K_ref,)`` float64 ``fImp`` of each
            feature's distance from its frame's origin (eq. 3); ``K_new >= 1``.
        n_visible: ``(H,)`` int64 from :func:`visible_counts`.
        weights: ``(w_dis, w_ang, w_count, w_acc)``.

    Returns:
        ``(score, dis, ang, count, acc)`` ``(H,)`` float64 and ``n_matched`` ``(H,)`` int64.
    """
    h_n, kn = match.shape
    wd, wa, wc, wacc = weights
    w_total = wd + wa + wc + wacc
    sq = new_importance * new_importance
    all_new = pairwise_sum(sq, 0, kn)
    w = np.empty(kn)
    wdis = np.empty(kn)
    wang = np.empty(kn)
    score = np.empty(h_n)
    dis = np.zeros(h_n)
    ang = np.zeros(h_n)
    count = np.empty(h_n)
    acc = np.empty(h_n)
    n_matched = np.zeros(h_n, dtype=np.int64)
    for h in range(h_n):
        for i in range(kn):
            j = match[h, i]
            if j >= 0:
                w[i] = new_importance[i] * ref_importance[j]
                wdis[i] = w[i] * (1.0 - dist[h, i] / gate_distance_m)
                wang[i] = w[i] * (1.0 - angle[h, i] / gate_angle_rad)
                n_matched[h] += 1
            else:
                w[i] = 0.0
                wdis[i] = 0.0
                wang[i] = 0.0
        sw = pairwise_sum(w, 0, kn)
        if sw > 0:
            dis[h] = pairwise_sum(wdis, 0, kn) / sw
            ang[h] = pairwise_sum(wang, 0, kn) / sw
        denom = max(1, min(kn, n_visible[h]))
        count[h] = min(max(n_matched[h] / denom, 0.0), 1.0)
        acc[h] = min(max(sw / all_new, 0.0), 1.0)
        score[h] = (wd * dis[h] + wa * ang[h] + wc * count[h] + wacc * acc[h]) / w_total
    return score, dis, ang, count, acc, n_matched


@njit(cache=True, nogil=True)
def correlation_scores(
    poses: np.ndarray,
    new_xy: np.ndarray,
    new_heading: np.ndarray,
    new_edge: np.ndarray,
    new_opening: np.ndarray,
    new_dist: np.ndarray,
    ref_xy: np.ndarray,
    ref_heading: np.ndarray,
    ref_edge: np.ndarray,
    ref_opening: np.ndarray,
    ref_dist: np.ndarray,
    codes: np.ndarray,
    bearing: np.ndarray,
    ranges: np.ndarray,
    spacing: float,
    max_gap_rad: float,
    range_max_m: float,
    occlusion_tolerance_m: float,
    gate_distance_m: float,
    gate_angle_rad: float,
    fimp_near: float,
    fimp_k: float,
    weights: tuple[float, float, float, float],
) -> tuple[
    np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray
]:
    """``correlation.correlate`` of ``H`` poses with features on both sides, in one call:
    :func:`visible_counts` (zeros without returns), :func:`pair_nearest`, each feature's
    ``fImp`` ``fimp_near / (1 + fimp_k d)`` of its distance ``new_dist`` / ``ref_dist`` from
    its frame's origin (paper eq. 3, ``correlation.fimp``'s expression) and
    :func:`correlation_terms`; the same numbers as those calls one by one.

    Returns:
        ``(score, dis, ang, count, acc)`` ``(H,)`` float64, ``match`` ``(H, K_new)`` int64,
        ``n_matched`` and ``n_visible`` ``(H,)`` int64 (the fields of
        ``correlation.Correlation`` in order).
    """
    if bearing.shape[0] == 0:
        n_visible = np.zeros(poses.shape[0], dtype=np.int64)
    else:
        n_visible = visible_counts(
            poses, ref_xy, bearing, ranges, spacing, max_gap_rad, range_max_m,
            occlusion_tolerance_m,
        )  # fmt: skip
    match, dist, angle = pair_nearest(
        poses, new_xy, new_heading, new_edge, new_opening, ref_xy, ref_heading, ref_edge,
        ref_opening, codes, gate_distance_m, gate_angle_rad,
    )  # fmt: skip
    new_importance = fimp_near / (1.0 + fimp_k * new_dist)
    ref_importance = fimp_near / (1.0 + fimp_k * ref_dist)
    score, dis, ang, count, acc, n_matched = correlation_terms(
        match, dist, angle, new_importance, ref_importance, n_visible, gate_distance_m,
        gate_angle_rad, weights,
    )  # fmt: skip
    return score, dis, ang, count, acc, match, n_matched, n_visible


@njit(cache=True, nogil=True)
def segment_arrays(
    endpoints: np.ndarray, lines: np.ndarray, cov: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The fields of a :class:`~iceg.matching.geometry.SegmentSet` from segment endpoints
    ``(M, 2, 2)``, Hessian lines ``(M, 2)`` ``(alpha_rad, rho_m)`` and their covariances
    ``(M, 2, 2)`` (float64): first endpoints ``a`` ``(M, 2)``, unit directions ``u``,
    lengths, unit normals ``(cos alpha, sin alpha)``, ``rho``, ``alpha`` and the covariances
    with non-finite entries set to 0."""
    m = endpoints.shape[0]
    a = np.empty((m, 2))
    u = np.empty((m, 2))
    length = np.empty(m)
    normal = np.empty((m, 2))
    rho = np.empty(m)
    alpha = np.empty(m)
    out_cov = np.empty((m, 2, 2))
    for j in range(m):
        a[j, 0], a[j, 1] = endpoints[j, 0, 0], endpoints[j, 0, 1]
        dx = endpoints[j, 1, 0] - a[j, 0]
        dy = endpoints[j, 1, 1] - a[j, 1]
        length[j] = math.hypot(dx, dy)
        guard = max(length[j], 1e-12)
        u[j, 0], u[j, 1] = dx / guard, dy / guard
        alpha[j], rho[j] = lines[j, 0], lines[j, 1]
        normal[j, 0], normal[j, 1] = math.cos(alpha[j]), math.sin(alpha[j])
        for p in range(2):
            for q in range(2):
                c = cov[j, p, q]
                out_cov[j, p, q] = c if math.isfinite(c) else 0.0
    return a, u, length, normal, rho, alpha, out_cov


@njit(cache=True, nogil=True)
def all_finite(points: np.ndarray) -> bool:
    """Whether every coordinate of ``points`` ``(R, 2)`` float64 is finite."""
    for i in range(points.shape[0]):
        if not (math.isfinite(points[i, 0]) and math.isfinite(points[i, 1])):
            return False
    return True


@njit(cache=True, nogil=True)
def segment_lengths(endpoints: np.ndarray) -> np.ndarray:
    """``(M,)`` float64 lengths (``hypot`` of the endpoints' difference) of the segments
    ``endpoints`` ``(M, 2, 2)`` float64, as :func:`segment_arrays` computes them."""
    m = endpoints.shape[0]
    length = np.empty(m)
    for j in range(m):
        length[j] = math.hypot(
            endpoints[j, 1, 0] - endpoints[j, 0, 0], endpoints[j, 1, 1] - endpoints[j, 0, 1]
        )
    return length


@njit(cache=True, nogil=True)
def line_covariances(
    a: np.ndarray,
    u: np.ndarray,
    length: np.ndarray,
    alpha: np.ndarray,
    cov: np.ndarray,
    wall_end_sigma_m: float,
    min_length_m: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Each reference line's effective ``(alpha, rho)`` covariance (``refine.
    effective_line_cov``: the fit covariance ``cov`` plus the model error of a wall whose two
    ends lie off the line by ``wall_end_sigma_m``, lengths floored at ``min_length_m``) and
    its inverse, regularised by ``1e-12`` on the diagonal: ``(M, 2, 2)`` float64 each."""
    m = a.shape[0]
    line_cov = np.empty((m, 2, 2))
    info = np.empty((m, 2, 2))
    var_offset = 0.5 * wall_end_sigma_m**2
    for j in range(m):
        mx = a[j, 0] + 0.5 * length[j] * u[j, 0]
        my = a[j, 1] + 0.5 * length[j] * u[j, 1]
        k = -math.sin(alpha[j]) * mx + math.cos(alpha[j]) * my  # d rho / d alpha at the middle
        var_angle = 2.0 * wall_end_sigma_m**2 / max(length[j], min_length_m) ** 2
        c00 = cov[j, 0, 0] + var_angle
        c01 = cov[j, 0, 1] + k * var_angle
        c10 = cov[j, 1, 0] + k * var_angle
        c11 = cov[j, 1, 1] + (var_offset + k * k * var_angle)
        line_cov[j, 0, 0], line_cov[j, 0, 1] = c00, c01
        line_cov[j, 1, 0], line_cov[j, 1, 1] = c10, c11
        r00, r11 = c00 + 1e-12, c11 + 1e-12
        det = r00 * r11 - c01 * c10
        info[j, 0, 0], info[j, 0, 1] = r11 / det, -c01 / det
        info[j, 1, 0], info[j, 1, 1] = -c10 / det, r00 / det
    return line_cov, info


class LatticeSettings(NamedTuple):
    """The covariance lattice's numbers (Olson 2009; ``refine._covariance``).

    Attributes:
        unit: ``(L, 3)`` float64 lattice of ``[-1, 1]^3`` (``steps`` points per axis).
        sigmas: Half-width in standard deviations of the least-squares covariance along each
            of its principal axes, capped at ``cap_m`` (translation, metres) and ``cap_rad``.
        cap_m: Cap of the half-width in translation, metres.
        cap_rad: Cap of the half-width in rotation, radians.
        kappa: Weights ``exp(kappa (s - s_max))`` of the robust log-likelihood ``s``.
        end_tol_m: A point beyond its segment's extent by more than this is an outlier.
        cauchy_sigmas: Cauchy scale of every row, in its standard deviations.
    """

    unit: np.ndarray
    sigmas: float
    cap_m: float
    cap_rad: float
    kappa: float
    end_tol_m: float
    cauchy_sigmas: float


class LatticePoints(NamedTuple):
    """The point-to-line rows at the refined pose that the lattice evaluates.

    Attributes:
        pick: ``(m,)`` int64 the rows evaluated (evenly spread; their cost is scaled up to
            all ``N``).
        points: ``(N, 2)`` float64 the associated points, new frame, metres.
        normal: ``(N, 2)`` float64 unit normal of each one's segment.
        r: ``(N,)`` float64 point-to-line residuals at the refined pose, metres.
        seg: ``(N,)`` int64 each one's reference segment.
    """

    pick: np.ndarray
    points: np.ndarray
    normal: np.ndarray
    r: np.ndarray
    seg: np.ndarray


#: A running product of :func:`_log1p_into` is folded into its logarithm beyond this (far
#: below overflow: one factor ``1 + (r / c)^2`` would need ``r / c`` above 1e104).
_PRODUCT_FOLD = 1e100


@njit(cache=True, nogil=True)
def _log1p_into(log_sum: float, product: float, x: float) -> tuple[float, float]:
    """One term ``x >= 0`` of ``sum_i log1p(x_i)`` kept as ``log_sum + log(product)``: the
    product ``prod_i (1 + x_i)`` folded into the sum of logarithms before it can overflow,
    so a sum costs one logarithm per many terms instead of one per term (the lattice's
    costs; the rounding of ``1 + x_i``, about 1e-16 absolute per term, is far below the
    differences between lattice points). Start from ``(0.0, 1.0)``."""
    product *= 1.0 + x
    if product > _PRODUCT_FOLD:
        return log_sum + math.log(product), 1.0
    return log_sum, product


@njit(cache=True, nogil=True)
def _lattice_deltas(lik_cov: np.ndarray, s: LatticeSettings) -> np.ndarray:
    """``(L, 3)`` lattice perturbations ``(x, y, theta)``: ``s.sigmas`` standard deviations
    of ``lik_cov`` along its principal axes (capped); ``(0, 3)`` when ``lik_cov`` is not
    positive definite."""
    evals, evecs = np.linalg.eigh(0.5 * (lik_cov + lik_cov.T))
    for j in range(3):
        if not (math.isfinite(evals[j]) and evals[j] > 0.0):
            return np.zeros((0, 3))
    half = np.empty(3)
    for j in range(3):
        cap = 1.0 / math.sqrt(
            (evecs[0, j] ** 2 + evecs[1, j] ** 2) / s.cap_m**2 + evecs[2, j] ** 2 / s.cap_rad**2
        )
        half[j] = min(s.sigmas * math.sqrt(evals[j]), cap)
    n_l = s.unit.shape[0]
    deltas = np.empty((n_l, 3))
    for k in range(n_l):
        g0 = s.unit[k, 0] * half[0]
        g1 = s.unit[k, 1] * half[1]
        g2 = s.unit[k, 2] * half[2]
        for a in range(3):
            deltas[k, a] = g0 * evecs[a, 0] + g1 * evecs[a, 1] + g2 * evecs[a, 2]
    return deltas


@njit(cache=True, nogil=True)
def _lattice_point_cost(
    deltas: np.ndarray,
    pose: np.ndarray,
    pts: LatticePoints,
    segs: LineSegments,
    end_tol_m: float,
    gate_m: float,
    cauchy_c: float,
    sigma: float,
) -> np.ndarray:
    """Robust cost ``(L,)`` (Cauchy, in units of sigma^2) of the sampled point-to-line rows
    at each lattice perturbation, scaled up to all rows: residuals and along-segment
    coordinates move linearly with the perturbation; a point beyond its segment's extent
    or beyond the gate costs as much as one at the gate.

    Point by point, each over the whole lattice (a loop the compiler vectorizes): every
    lattice point's running sum (:func:`_log1p_into`) still takes its terms in the order of
    the points, so the costs are those of a loop over the points per lattice point."""
    n = pts.pick.shape[0]
    c, sn = math.cos(pose[2]), math.sin(pose[2])
    n_l = deltas.shape[0]
    dx = np.ascontiguousarray(deltas[:, 0])
    dy = np.ascontiguousarray(deltas[:, 1])
    dt = np.ascontiguousarray(deltas[:, 2])
    log_sum = np.zeros(n_l)
    product = np.ones(n_l)
    n_out = np.zeros(n_l, dtype=np.int64)
    c2 = cauchy_c * cauchy_c
    for i in range(n):
        p = pts.pick[i]
        m = pts.seg[p]
        # the point in the reference frame, relative to the pose's origin
        rx = c * pts.points[p, 0] - sn * pts.points[p, 1]
        ry = sn * pts.points[p, 0] + c * pts.points[p, 1]
        nx, ny = pts.normal[p, 0], pts.normal[p, 1]
        ux, uy = segs.u[m, 0], segs.u[m, 1]
        r0 = pts.r[p]
        jt = ny * rx - nx * ry
        along0 = (rx + pose[0] - segs.a[m, 0]) * ux + (ry + pose[1] - segs.a[m, 1]) * uy
        jat = uy * rx - ux * ry
        hi = segs.length[m] + end_tol_m
        for k in range(n_l):
            r = r0 + nx * dx[k] + ny * dy[k] + jt * dt[k]
            a = along0 + ux * dx[k] + uy * dy[k] + jat * dt[k]
            term = product[k] * (1.0 + r * r / c2)
            if a < -end_tol_m or a > hi or abs(r) > gate_m:
                n_out[k] += 1
            else:
                product[k] = term
        for k in range(n_l):  # _log1p_into's fold, after each point as there
            if product[k] > _PRODUCT_FOLD:
                log_sum[k] += math.log(product[k])
                product[k] = 1.0
    out = np.zeros(n_l)
    sat = 0.5 * c2 * math.log1p(gate_m * gate_m / c2)
    scale = pts.r.shape[0] / n
    for k in range(n_l):
        inliers = log_sum[k] + math.log(product[k])
        out[k] = scale * ((n_out[k] * sat + 0.5 * c2 * inliers) / (sigma * sigma))
    return out


@njit(cache=True, nogil=True)
def lattice_covariance(
    cov_ls: np.ndarray,
    pose: np.ndarray,
    pts: LatticePoints,
    segs: LineSegments,
    rows_r: np.ndarray,
    rows_jac: np.ndarray,
    rows_var: np.ndarray,
    gate_m: float,
    sigma: float,
    s: LatticeSettings,
) -> np.ndarray:
    """The correlation-landscape covariance of a refinement (Olson 2009, "Real-time
    correlative scan matching"), floored by the least-squares one (:func:`psd_max`).

    The second moment of ``exp(kappa (score - score_max))`` over a lattice of perturbations
    (:func:`_lattice_deltas` of ``cov_ls``), the score being the robust log-likelihood of
    the refinement with its final associations: the point-to-line rows ``pts`` (a point
    that slides beyond its segment's extent counts as an outlier at the gate, so the
    landscape is flat where the walls give no constraint) and the other rows (residual
    ``rows_r`` (R,), Jacobian ``rows_jac`` (R, 3), variance ``rows_var`` (R,)).

    Args:
        cov_ls: ``(3, 3)`` float64 finite least-squares covariance of ``(x, y, theta)``,
            reference frame.
        pose: ``(3,)`` float64 the refined pose (new scan in the reference frame).
        gate_m: The association gate, metres; ``sigma`` the point noise, metres.

    Returns:
        ``(3, 3)`` float64 covariance of ``(x, y, theta)``, reference frame: ``cov_ls``
        itself when it is not positive definite.
    """
    deltas = _lattice_deltas(cov_ls, s)
    n_l = deltas.shape[0]
    if n_l == 0:
        return cov_ls
    cost = np.zeros(n_l)
    if pts.r.shape[0] > 0:
        cost += _lattice_point_cost(
            deltas, pose, pts, segs, s.end_tol_m, gate_m, s.cauchy_sigmas * sigma, sigma
        )
    c = s.cauchy_sigmas
    for k in range(n_l):
        log_sum, product = 0.0, 1.0
        for i in range(rows_r.shape[0]):
            rf = (
                rows_r[i]
                + rows_jac[i, 0] * deltas[k, 0]
                + rows_jac[i, 1] * deltas[k, 1]
                + rows_jac[i, 2] * deltas[k, 2]
            ) / math.sqrt(rows_var[i])
            log_sum, product = _log1p_into(log_sum, product, (rf / c) ** 2)
        cost[k] += 0.5 * c * c * (log_sum + math.log(product))
    low = cost.min()
    w = np.empty(n_l)
    for k in range(n_l):
        w[k] = math.exp(s.kappa * (low - cost[k]))
    w /= w.sum()
    lat = np.zeros((3, 3))
    for k in range(n_l):
        for a in range(3):
            for b in range(3):
                lat[a, b] += w[k] * deltas[k, a] * deltas[k, b]
    return psd_max(cov_ls, lat)


@njit(cache=True, nogil=True)
def final_covariances(
    pose: np.ndarray,
    pairs: np.ndarray,
    geom: PairGeometry,
    cloud: PointCloud,
    point_hess: np.ndarray,
    point_segment: np.ndarray,
    point_residual: np.ndarray,
    points_xy: np.ndarray,
    seg_normal: np.ndarray,
    prior_info: np.ndarray,
    segs: LineSegments,
    pick: np.ndarray,
    gate_m: float,
    sigma: float,
    settings: GnSettings,
    lattice: LatticeSettings,
) -> tuple[np.ndarray, np.ndarray]:
    """The covariances of a refined pose (docs/design.md step 9) in one call: the EOW-pair
    and off-segment rows (:func:`covariance_rows`) added to the point-to-line information,
    the least-squares covariance ``(information + prior)^-1`` (symmetrised), and the
    lattice's (:func:`lattice_covariance`, Olson 2009) over the associated points' rows.

    The inverse is LAPACK's ``gesv`` against the identity, as ``numpy.linalg.inv`` computes
    it (the same bits; ``np.linalg.inv`` here would be ``getri``, whose rounding differs).

    Args:
        pose: ``(3,)`` float64 the refined pose (new scan in the reference frame).
        pairs: ``(Q, 2)`` int64 feature pairs ``[new, ref]`` at the pose.
        geom: Both scans' feature geometry; ``cloud`` the off-segment new points against
            the reference's points (may hold none).
        point_hess: ``(3, 3)`` float64 information of the point-to-line rows at the pose.
        point_segment: ``(P,)`` int64 reference segment of each new point (-1: none).
        point_residual: ``(P,)`` float64 its point-to-line residual (metres).
        points_xy: ``(P, 2)`` float64 the new points (new frame, metres).
        seg_normal: ``(M, 2)`` float64 unit normal of each reference segment.
        prior_info: ``(3, 3)`` float64 information of the bounds' prior.
        segs: The reference segments with their line information (reference frame).
        pick: ``(m,)`` int64 the associated points' rows the lattice evaluates
            (``refine._lattice_pick`` of their count).
        gate_m: The association gate (metres); ``sigma`` the point noise (metres).
        settings, lattice: The refinement's and the lattice's settings.

    Returns:
        ``(cov_ls, cov)``, each ``(3, 3)`` float64, perturbations of ``(x, y, theta)`` in the
        reference frame; both infinite where the information is singular or not finite.
        Raises nothing.
    """
    r, jac, var, hess = covariance_rows(pose, pairs, geom, cloud, gate_m, sigma, settings)
    a = (point_hess + hess) + prior_info
    try:
        a_inv = np.linalg.solve(a, np.eye(3))
    except Exception:  # singular, or not finite
        a_inv = np.full((3, 3), np.inf)
    if not np.all(np.isfinite(a_inv)):
        return np.full((3, 3), np.inf), np.full((3, 3), np.inf)
    cov_ls = 0.5 * (a_inv + a_inv.T)
    n = 0
    for i in range(point_segment.shape[0]):
        if point_segment[i] >= 0:
            n += 1
    seg = np.empty(n, dtype=np.int64)
    res = np.empty(n)
    xy = np.empty((n, 2))
    normal = np.empty((n, 2))
    k = 0
    for i in range(point_segment.shape[0]):
        m = point_segment[i]
        if m >= 0:
            seg[k] = m
            res[k] = point_residual[i]
            xy[k, 0], xy[k, 1] = points_xy[i, 0], points_xy[i, 1]
            normal[k, 0], normal[k, 1] = seg_normal[m, 0], seg_normal[m, 1]
            k += 1
    points = LatticePoints(pick, xy, normal, res, seg)
    cov = lattice_covariance(cov_ls, pose, points, segs, r, jac, var, gate_m, sigma, lattice)
    return cov_ls, cov


@njit(cache=True, nogil=True)
def psd_max(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """A covariance that dominates both ``a`` and ``b`` (``(3, 3)`` float64, ``a`` positive
    definite): in the frame whitened by ``a``, ``b``'s eigenvalues are raised to at least 1;
    ``a`` itself when it is not positive definite."""
    try:
        lc = np.linalg.cholesky(a)
    except Exception:  # not positive definite
        return a
    li = np.linalg.inv(lc)
    m = li @ b @ li.T
    evals, evecs = np.linalg.eigh(0.5 * (m + m.T))
    d = np.maximum(evals, 1.0)
    out = lc @ (evecs * d) @ evecs.T @ lc.T
    return 0.5 * (out + out.T)


@njit(cache=True, nogil=True)
def _solve3(a: np.ndarray, b: np.ndarray) -> tuple[np.ndarray, bool]:
    """Solve the 3x3 system ``a x = b`` by cofactors; ``ok`` False if singular."""
    c00 = a[1, 1] * a[2, 2] - a[1, 2] * a[2, 1]
    c01 = a[1, 2] * a[2, 0] - a[1, 0] * a[2, 2]
    c02 = a[1, 0] * a[2, 1] - a[1, 1] * a[2, 0]
    det = a[0, 0] * c00 + a[0, 1] * c01 + a[0, 2] * c02
    x = np.zeros(3)
    scale = abs(a[0, 0]) + abs(a[1, 1]) + abs(a[2, 2])
    if not (abs(det) > 1e-300) or not math.isfinite(det) or scale == 0.0:
        return x, False
    inv = np.empty((3, 3))
    inv[0, 0] = c00
    inv[1, 0] = c01
    inv[2, 0] = c02
    inv[0, 1] = a[0, 2] * a[2, 1] - a[0, 1] * a[2, 2]
    inv[1, 1] = a[0, 0] * a[2, 2] - a[0, 2] * a[2, 0]
    inv[2, 1] = a[0, 1] * a[2, 0] - a[0, 0] * a[2, 1]
    inv[0, 2] = a[0, 1] * a[1, 2] - a[0, 2] * a[1, 1]
    inv[1, 2] = a[0, 2] * a[1, 0] - a[0, 0] * a[1, 2]
    inv[2, 2] = a[0, 0] * a[1, 1] - a[0, 1] * a[1, 0]
    for i in range(3):
        x[i] = (inv[i, 0] * b[0] + inv[i, 1] * b[1] + inv[i, 2] * b[2]) / det
    return x, True


@njit(cache=True, nogil=True)
def _add_prior(hess: np.ndarray, grad: np.ndarray, pose: np.ndarray, prior: PosePrior) -> None:
    """Add the bounds' prior pulling toward ``prior.mean`` (MAP) and the damping."""
    dp = pose - prior.mean
    dp[2] = (dp[2] + math.pi) % (2.0 * math.pi) - math.pi
    for i in range(3):
        for k in range(3):
            grad[i] += prior.info[i, k] * dp[k]
            hess[i, k] += prior.info[i, k]
        hess[i, i] += GN_DAMPING


@njit(cache=True, nogil=True)
def _gauss_newton_phase(
    pose0: np.ndarray,
    prior: PosePrior,
    pts: SegmentPoints,
    segs: LineSegments,
    pairs: np.ndarray,
    geom: PairGeometry,
    cloud: PointCloud,
    settings: GnSettings,
    phase: GnPhase,
) -> tuple[np.ndarray, float, float, int]:
    """One phase of the Gauss-Newton refinement (paper §III-C3 "an optimization problem";
    docs/design.md step 8). Each step sums the normal equations of the point-to-line GLS rows
    (:func:`point_line_system`), the feature pairs ``(Q, 2)`` ``[new, ref]`` (full positions
    in the coarse phase; :func:`feature_system`), the off-segment PL-ICP rows (Censi 2008;
    :func:`cloud_system`, none when ``cloud`` has no points) and the bounds' prior, solves
    for the step (perturbation ``(x, y, theta)`` in the reference frame, m and rad) and
    applies it. The coarse phase keeps its gate; the fine phase sets it to
    ``gate_sigmas`` sigmas after each step. Stops when a step is below the phase's
    tolerances or after its iteration cap.

    Returns:
        The pose ``(3,)``, the point noise estimate (m), the gate for the next phase (m) and
        the number of iterations run.
    """
    pose = pose0.copy()
    gate = phase.gate_m
    sigma = phase.sigma_m
    it = 0
    while it < phase.max_iterations:
        it += 1
        hess, grad, sigma, _, _ = point_line_system(pose, pts, segs, gate, sigma, settings)
        if pairs.shape[0] > 0:
            fh, fg = feature_system(pose, pairs, geom, phase.coarse, settings)
            hess += fh
            grad += fg
        if cloud.points.shape[0] > 0:
            ch, cg = cloud_system(pose, cloud, gate, sigma, settings.cauchy_sigmas)
            hess += ch
            grad += cg
        _add_prior(hess, grad, pose, prior)
        for i in range(3):
            grad[i] = -grad[i]
        delta, ok = _solve3(hess, grad)
        if not ok:
            break
        pose[0] += delta[0]
        pose[1] += delta[1]
        pose[2] = (pose[2] + delta[2] + math.pi) % (2.0 * math.pi) - math.pi
        if not phase.coarse:
            gate = min(settings.gate_m, max(settings.gate_min_m, settings.gate_sigmas * sigma))
        if math.hypot(delta[0], delta[1]) < phase.tol_xy_m and abs(delta[2]) < phase.tol_theta_rad:
            break
    return pose, sigma, gate, it


@njit(cache=True, nogil=True)
def matched_pairs(match: np.ndarray) -> np.ndarray:
    """``(Q, 2)`` int64 feature pairs ``[new, ref]`` of one pairing ``match`` ``(K_new,)``
    int64 (the reference feature of each new feature, -1: none), by new index."""
    n = 0
    for i in range(match.shape[0]):
        if match[i] >= 0:
            n += 1
    pairs = np.empty((n, 2), np.int64)
    n = 0
    for i in range(match.shape[0]):
        if match[i] >= 0:
            pairs[n, 0] = i
            pairs[n, 1] = match[i]
            n += 1
    return pairs


@njit(cache=True, nogil=True)
def _pairs_at(pose: np.ndarray, p: FeaturePairing) -> np.ndarray:
    """``(Q, 2)`` int64 feature pairs ``[new, ref]`` at one ``(3,)`` pose, by new index
    (:func:`pair_nearest`)."""
    poses = np.empty((1, 3))
    poses[0] = pose
    match, _, _ = pair_nearest(
        poses, p.new_xy, p.new_heading, p.new_edge, p.new_opening, p.ref_xy, p.ref_heading,
        p.ref_edge, p.ref_opening, p.codes, p.gate_distance_m, p.gate_angle_rad,
    )  # fmt: skip
    return matched_pairs(match[0])


@njit(cache=True, nogil=True)
def refine_pose(
    pose0: np.ndarray,
    initial_pairs: np.ndarray | None,
    prior: PosePrior,
    pts: SegmentPoints,
    segs: LineSegments,
    geom: PairGeometry,
    pairing: FeaturePairing,
    cloud: PointCloud,
    settings: GnSettings,
    max_iterations: int,
) -> tuple[np.ndarray, float, float, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The Gauss-Newton refinement of one hypothesis (paper §III-C3 "an optimization
    problem"; docs/design.md step 8) in two phases, and its point-to-line rows at the result.

    The coarse phase keeps the wide gate ``settings.gate_m`` and the feature pairs
    ``initial_pairs`` ``(Q, 2)`` ``[new, ref]`` (the pairs at ``pose0``; ``None`` pairs
    them there) with their full positions, for at most half of ``max_iterations``, until a
    step is below ``COARSE_TOL_*`` (a coarse hypothesis is pulled in). The fine phase pairs
    the features again at the coarse result and keeps that pairing, with a gate of
    ``gate_sigmas`` estimated sigmas, for the remaining iterations (at least one), until a
    step is below ``FINE_TOL_*`` (points off the matched segments stop pulling). Each phase
    is :func:`_gauss_newton_phase`; the starting point noise is the gate over
    :data:`GATE_TO_SIGMA0`, floored.

    Args:
        pose0: ``(3,)`` float64 starting pose of the new scan in the reference frame.
        initial_pairs: ``(Q, 2)`` int64 pairs at ``pose0``, or ``None``.
        max_iterations: Iterations of both phases together.

    Returns:
        The pose ``(3,)``, the point noise (m), the gate (m), the iterations run, the fine
        phase's pairs ``(Q', 2)``, and at the pose (:func:`point_line_system`, with that
        gate and noise): the point-to-line information ``(3, 3)``, the segment of each
        point ``(P,)`` int64 (-1: none) and its residual ``(P,)`` (m, NaN where none); the
        point noise returned is the one estimated there.
    """
    s = settings
    sigma = max(s.sigma_min_m, s.gate_m / GATE_TO_SIGMA0)
    pairs = _pairs_at(pose0, pairing) if initial_pairs is None else initial_pairs
    n_coarse = max(1, max_iterations // 2)
    coarse = GnPhase(True, s.gate_m, sigma, n_coarse, COARSE_TOL_XY_M, COARSE_TOL_THETA_RAD)
    pose, sigma, gate, it = _gauss_newton_phase(
        pose0, prior, pts, segs, pairs, geom, cloud, s, coarse
    )
    gate = min(s.gate_m, max(s.gate_min_m, s.gate_sigmas * sigma))
    pairs = _pairs_at(pose, pairing)
    n_fine = max(1, max_iterations - it)
    fine = GnPhase(False, gate, sigma, n_fine, FINE_TOL_XY_M, FINE_TOL_THETA_RAD)
    pose, sigma, gate, it2 = _gauss_newton_phase(
        pose, prior, pts, segs, pairs, geom, cloud, s, fine
    )
    hess, _, sigma, idx, res = point_line_system(pose, pts, segs, gate, sigma, s)
    return pose, sigma, gate, it + it2, pairs, hess, idx, res


#: Widening of a segment's angular span (radians) in :func:`nearest_walls`: far above the
#: rounding of the bearings (~1e-16 rad), so no beam the exact test accepts is left out.
SPAN_MARGIN_RAD = 1e-6


@njit(cache=True, nogil=True)
def nearest_walls(
    ep: np.ndarray, bearing: np.ndarray, cos_b: np.ndarray, sin_b: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The nearest segment of ``ep`` (M, 2, 2) each beam from the origin meets: ``(B,)``
    float64 distance along the beam (inf: none) and ``(B,)`` int64 segment (-1: none), the
    first one in segment order among equally near ones.

    ``bearing`` ``(B,)`` is ascending (``cos_b``, ``sin_b`` its cosines and sines). A ray
    from the origin meets a segment only at a bearing inside the segment's angular span
    (under pi), so each segment is tested only against the beams of its span widened by
    :data:`SPAN_MARGIN_RAD`, in segment order: the same answer as testing every pair."""
    n_b = bearing.shape[0]
    best_t = np.full(n_b, np.inf)
    best_k = np.full(n_b, -1, dtype=np.int64)
    for k in range(ep.shape[0]):
        ax = ep[k, 0, 0]
        ay = ep[k, 0, 1]
        ex = ep[k, 1, 0] - ax
        ey = ep[k, 1, 1] - ay
        b0 = math.atan2(ay, ax)
        b1 = math.atan2(ep[k, 1, 1], ep[k, 1, 0])
        lo = min(b0, b1)
        hi = max(b0, b1)
        if hi - lo < math.pi - SPAN_MARGIN_RAD:
            spans = ((lo - SPAN_MARGIN_RAD, hi + SPAN_MARGIN_RAD), (np.inf, np.inf))
        elif hi - lo > math.pi + SPAN_MARGIN_RAD:  # across the bearing +-pi
            spans = ((-np.inf, lo + SPAN_MARGIN_RAD), (hi - SPAN_MARGIN_RAD, np.inf))
        else:  # (nearly) through the origin: every beam
            spans = ((-np.inf, np.inf), (np.inf, np.inf))
        for s_lo, s_hi in spans:
            first = np.searchsorted(bearing, s_lo)
            for b in range(first, np.searchsorted(bearing, s_hi, "right")):
                dx = cos_b[b]
                dy = sin_b[b]
                den = dx * ey - dy * ex
                if abs(den) <= 1e-12:
                    continue
                t = (ax * ey - ay * ex) / den
                u = (ax * dy - ay * dx) / den
                if t > 0.0 and 0.0 <= u <= 1.0 and t < best_t[b]:
                    best_t[b] = t
                    best_k[b] = k
    return best_t, best_k


@njit(cache=True, nogil=True)
def is_one_scan(points: np.ndarray, backstep_rad: float) -> bool:
    """Whether points ``(P, 2)`` float64 look like one scan from the frame's origin: their
    bearings (libm's ``atan2``) decrease by more than ``backstep_rad`` from one point to the
    next at most once, and then by more than pi (the wrap-around); fewer than 3 points do
    not. Stops at the second backstep."""
    n = points.shape[0]
    if n < 3:
        return False
    prev = math.atan2(points[0, 1], points[0, 0])
    n_back = 0
    first_back = 0.0
    for i in range(1, n):
        b = math.atan2(points[i, 1], points[i, 0])
        d = b - prev
        prev = b
        if d < -backstep_rad:
            n_back += 1
            if n_back > 1:
                return False
            first_back = d
    return n_back == 0 or first_back < -math.pi


@njit(cache=True, nogil=True)
def local_lines(points: np.ndarray, max_gap_m: float) -> tuple[np.ndarray, np.ndarray]:
    """For points ``(R, 2)`` float64 in beam order: the distance to the nearer beam
    neighbour ``(R,)`` (inf without one; ``np.minimum``'s NaN) and the unit normal
    ``(R, 2)`` of the local line through the previous and next points when both are within
    ``max_gap_m``, else through the nearer one within it (NaN: none within it, or the
    two points closer than 1e-6 m)."""
    n = points.shape[0]
    nn = np.empty(n)
    normal = np.full((n, 2), np.nan)
    for i in range(n):
        g_prev = np.inf
        g_next = np.inf
        if i > 0:
            g_prev = math.hypot(points[i, 0] - points[i - 1, 0], points[i, 1] - points[i - 1, 1])
        if i < n - 1:
            g_next = math.hypot(points[i + 1, 0] - points[i, 0], points[i + 1, 1] - points[i, 1])
        if math.isnan(g_prev) or math.isnan(g_next):
            nn[i] = np.nan
        else:
            nn[i] = min(g_prev, g_next)
        a = i - 1 if i > 0 and g_prev <= max_gap_m else i
        b = i + 1 if i < n - 1 and g_next <= max_gap_m else i
        tx = points[b, 0] - points[a, 0]
        ty = points[b, 1] - points[a, 1]
        tl = math.hypot(tx, ty)
        if tl > 1e-6:
            normal[i, 0] = -ty / tl
            normal[i, 1] = tx / tl
    return nn, normal


@njit(cache=True, nogil=True)
def polar_profile(points: np.ndarray) -> tuple[np.ndarray, np.ndarray, float]:
    """Points ``(P, 2)`` float64 (metres) seen from their frame's origin, by bearing: ``(P,)``
    bearings (rad, libm's ``atan2``) and ranges (m, ``hypot``) in stable bearing order, and
    the median gap between consecutive bearings above 1e-9 rad (0.01 rad where none; 1°
    under three points). ``geometry.PolarProfile.from_points``'s numbers, as numpy gave them
    (a median of an even count is the mean of the middle two)."""
    n = points.shape[0]
    bearing = np.empty(n)
    rng = np.empty(n)
    for i in range(n):
        bearing[i] = math.atan2(points[i, 1], points[i, 0])
        rng[i] = math.hypot(points[i, 0], points[i, 1])
    order = np.argsort(bearing, kind="mergesort")
    bearing, rng = bearing[order], rng[order]
    if n < 3:
        return bearing, rng, math.radians(1.0)
    gaps = np.empty(n - 1)
    m = 0
    for i in range(n - 1):
        gap = bearing[i + 1] - bearing[i]
        if gap > 1e-9:
            gaps[m] = gap
            m += 1
    if m == 0:
        return bearing, rng, 0.01
    return bearing, rng, median(gaps[:m])


@njit(cache=True, nogil=True)
def point_segments(seg_point_range: np.ndarray, n_points: int) -> np.ndarray:
    """``(P,)`` int64 the segment of each of ``n_points`` points (-1: none) from the
    segments' ``[start, stop)`` point ranges ``(M, 2)`` int64 (a range outside the points,
    or empty, is skipped; where ranges overlap the later segment's index stays)."""
    out = np.full(n_points, -1, dtype=np.int64)
    for k in range(seg_point_range.shape[0]):
        start, stop = seg_point_range[k, 0], seg_point_range[k, 1]
        if start >= 0 and stop > start and stop <= n_points:
            out[start:stop] = k
    return out


@njit(cache=True, nogil=True)
def feature_angles(
    kind: np.ndarray,
    xy: np.ndarray,
    cov: np.ndarray,
    directions: np.ndarray,
    min_var_m2: float,
    corner: int,
    eow: int,
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The derived columns of ``geometry.feature_geometry`` in one pass over ``K`` features:
    each edge's direction angle ``atan2(dy, dx)`` ``(K, 2)`` (NaN stays NaN), the heading
    ``(K,)`` (a ``corner``'s bisector angle, the first edge of an ``eow``, else NaN), the
    covariance ``(K, 2, 2)`` with non-finite entries as 0 and ``min_var_m2`` added to the
    diagonal (and 0.0 to the rest, as numpy adds the identity's zeros), and the distance
    ``hypot(x, y)`` ``(K,)`` from the frame's origin. The angles are libm's ``atan2``, as
    ``math.atan2`` gives them on every machine.

    Args:
        kind: ``(K,)`` int64 feature kinds; ``xy`` ``(K, 2)`` float64 positions (m);
            ``cov`` ``(K, 2, 2)`` float64 covariances (m^2); ``directions`` ``(K, 2, 2)``
            float64 unit edge directions (NaN where none).
    """
    n = kind.shape[0]
    edge = np.empty((n, 2))
    heading = np.full(n, np.nan)
    cov_out = np.empty((n, 2, 2))
    dist = np.empty(n)
    for i in range(n):
        for e in range(2):
            edge[i, e] = math.atan2(directions[i, e, 1], directions[i, e, 0])
        if kind[i] == corner:
            heading[i] = math.atan2(
                directions[i, 0, 1] + directions[i, 1, 1], directions[i, 0, 0] + directions[i, 1, 0]
            )
        elif kind[i] == eow:
            heading[i] = edge[i, 0]
        for a in range(2):
            for b in range(2):
                c = cov[i, a, b]
                cov_out[i, a, b] = (c if math.isfinite(c) else 0.0) + (
                    min_var_m2 if a == b else 0.0
                )
        dist[i] = math.hypot(xy[i, 0], xy[i, 1])
    return edge, heading, cov_out, dist


@njit(cache=True, nogil=True)
def beam_directions(bearing: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Cosines and sines ``(B,)`` float64 of the bearings ``(B,)`` (radians), as
    :func:`ray_wall_check` takes them."""
    return np.cos(bearing), np.sin(bearing)


@njit(cache=True, nogil=True)
def ray_wall_check(
    ep: np.ndarray,
    bearing: np.ndarray,
    cos_b: np.ndarray,
    sin_b: np.ndarray,
    ranges: np.ndarray,
    spacing: float,
    range_max_m: float,
    tol_m: float,
    cos_max_incidence: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Cast segments ``ep`` (M, 2, 2) along beams (bearing ascending, its cosines and sines
    from :func:`beam_directions`, range) from the origin; see ``matcher._ray_check``.
    Returns ``(M,)`` float64 arrays: each segment's wall length seen through and confirmed
    (metres), each beam counting on its nearest segment (:func:`nearest_walls`)."""
    n_b = bearing.shape[0]
    see = np.zeros(ep.shape[0])
    cons = np.zeros(ep.shape[0])
    best_t, best_k = nearest_walls(ep, bearing, cos_b, sin_b)
    for b in range(n_b):
        dx = cos_b[b]
        dy = sin_b[b]
        best = best_t[b]
        bk = best_k[b]
        if bk < 0 or best >= range_max_m - tol_m:
            continue
        ex = ep[bk, 1, 0] - ep[bk, 0, 0]
        ey = ep[bk, 1, 1] - ep[bk, 0, 1]
        el = math.hypot(ex, ey)
        if el <= 1e-12:
            continue
        cos_inc = abs(dx * ey - dy * ex) / el
        if cos_inc <= cos_max_incidence:
            continue
        cover = best * spacing / max(cos_inc, 1e-3)
        if ranges[b] > best + tol_m:
            see[bk] += cover
        elif abs(ranges[b] - best) <= tol_m:
            cons[bk] += cover
    return see, cons


class Rays(NamedTuple):
    """A scan's returns by bearing for the free-space tests (``geometry.PolarProfile``).

    Attributes:
        bearing: ``(B,)`` float64 bearings (radians) of the returns, ascending.
        cos_b, sin_b: ``(B,)`` float64 their cosines and sines (:func:`beam_directions`).
        range: ``(B,)`` float64 their ranges, metres.
        spacing: Typical angular spacing of consecutive beams, radians.
        range_max_m: Beams at or beyond this were invalid (not in the profile).
    """

    bearing: np.ndarray
    cos_b: np.ndarray
    sin_b: np.ndarray
    range: np.ndarray
    spacing: float
    range_max_m: float


@njit(cache=True, nogil=True)
def walls_seen_through_length(
    ep: np.ndarray, rays: Rays, tol_m: float, cos_max_incidence: float
) -> tuple[float, float]:
    """Total wall length (metres) of the segments ``ep`` ``(M, 2, 2)`` (the scan's frame)
    seen through and confirmed by the scan of ``rays`` (:func:`ray_wall_check`, each sum in
    numpy's order); ``(0, 0)`` without segments or returns."""
    m = ep.shape[0]
    if m == 0 or rays.bearing.shape[0] == 0:
        return 0.0, 0.0
    see, cons = ray_wall_check(
        ep, rays.bearing, rays.cos_b, rays.sin_b, rays.range, rays.spacing,
        rays.range_max_m, tol_m, cos_max_incidence,
    )  # fmt: skip
    return pairwise_sum(see, 0, m), pairwise_sum(cons, 0, m)


@njit(cache=True, nogil=True)
def far_bracket_range(rays: Rays, bearing: float, max_gap_beams: float) -> float:
    """The range (metres) of the farther of the two returns bracketing ``bearing``
    (radians); NaN outside the returns' bearings or where the bracket spans a gap of more
    than ``max_gap_beams`` beam spacings. A NaN range propagates (``np.maximum``'s)."""
    n = rays.bearing.shape[0]
    k = np.searchsorted(rays.bearing, bearing)
    if k == 0 or k == n:
        return math.nan
    if not rays.bearing[k] - rays.bearing[k - 1] <= max_gap_beams * rays.spacing:
        return math.nan
    r0, r1 = rays.range[k - 1], rays.range[k]
    return r0 if (r0 >= r1 or math.isnan(r0)) else r1


@njit(cache=True, nogil=True)
def _origin_behind_wall(x: float, y: float, rays: Rays, tol_m: float, gap: float) -> bool:
    """Whether the point ``(x, y)`` (the other scan's origin, this scan's frame) lies more
    than ``tol_m`` behind the farther return bracketing its bearing."""
    if rays.bearing.shape[0] == 0:
        return False
    hi = far_bracket_range(rays, math.atan2(y, x), gap)
    return math.isfinite(hi) and hi < math.hypot(x, y) - tol_m


@njit(cache=True, nogil=True)
def free_space_check(
    pose: np.ndarray,
    ref_in_new: np.ndarray,
    new_in_ref: np.ndarray,
    ref_ep: np.ndarray,
    new_ep: np.ndarray,
    new_rays: Rays,
    ref_rays: Rays,
    two_sided: bool,
    tol_m: float,
    cos_max_incidence: float,
    max_gap_beams: float,
) -> tuple[float, float, float, bool]:
    """The free-space consistency of a pose (docs/design.md step 10) in one call.

    Args:
        pose: ``(3,)`` float64 pose of the new scan in the reference frame.
        ref_in_new: ``(M, 2, 2)`` float64 the reference segments in the new scan's frame;
            ``new_in_ref`` ``(N, 2, 2)`` the new segments in the reference frame (read only
            when ``two_sided``).
        ref_ep, new_ep: The segments ``(M, 2, 2)``, ``(N, 2, 2)`` in their own frames.
        new_rays: The new scan's returns; ``ref_rays`` the reference's, when ``two_sided``
            (its points are one scan seen from its origin).
        tol_m: The see-through tolerance, metres.
        cos_max_incidence: Walls met at a larger incidence are not judged.
        max_gap_beams: A bracket of returns wider than this many spacings is a gap.

    Returns:
        ``(fraction, length_m, clearance_m, origins_visible)``: the fraction and length
        (metres) of the judged walls that one scan places where the other sees free space
        (the reference's along the new scan's beams, and the new scan's along the
        reference's when ``two_sided``; ``(0, 0)`` when no wall is judged); the distance from
        each scan's sensor to the nearest wall of the other (the smaller, inf without
        segments); and whether neither sensor lies behind a wall the other scan sees.
        Raises nothing.
    """
    see, cons = walls_seen_through_length(ref_in_new, new_rays, tol_m, cos_max_incidence)
    length = 0.0 + see
    confirmed = 0.0 + cons
    if two_sided:
        see, cons = walls_seen_through_length(new_in_ref, ref_rays, tol_m, cos_max_incidence)
        length += see
        confirmed += cons
    total = length + confirmed
    if total <= 0.0:
        fraction, length = 0.0, 0.0
    else:
        fraction = length / total
    x, y, t = pose[0], pose[1], pose[2]
    c, s = math.cos(t), math.sin(t)
    origin = np.empty(2)  # the reference's origin in the new frame (se2.inverse's)
    origin[0] = -(c * x + s * y)
    origin[1] = -(-s * x + c * y)
    clearance = min(
        nearest_segment_distance(pose[:2], ref_ep), nearest_segment_distance(origin, new_ep)
    )
    behind = _origin_behind_wall(origin[0], origin[1], new_rays, tol_m, max_gap_beams)
    if two_sided and not behind:
        behind = _origin_behind_wall(x, y, ref_rays, tol_m, max_gap_beams)
    return fraction, length, clearance, not behind


#: Kernel density terms beyond this many kernel widths are dropped: ``exp(-0.5 * 12**2)``
#: is below 1e-31, under half an ulp of any partial sum (each starts at its own weight).
DENSITY_WINDOW_WIDTHS = 12.0


@njit(cache=True, nogil=True)
def poses_within_bounds(
    directed: np.ndarray,
    intersection: np.ndarray,
    prediction: np.ndarray,
    max_rotation_rad: float,
    max_translation_m: float,
) -> np.ndarray:
    """The hypotheses ``directed`` ``(N1, 3)`` then ``intersection`` ``(N2, 3)`` (float64
    poses) whose heading lies within ``max_rotation_rad`` of the ``(3,)`` ``prediction``'s
    (wrapped to ``[-pi, pi)``; no test when infinite) and whose position lies within
    ``max_translation_m`` of it (no test when infinite), in order: ``(N, 3)`` float64. The
    numpy masks' comparisons, bit for bit: ``abs(wrap_angle(theta - theta_pred)) <= max``
    and ``hypot(dx, dy) <= max`` (NaN fails a test)."""
    n1 = directed.shape[0]
    n = n1 + intersection.shape[0]
    out = np.empty((n, 3))
    k = 0
    for r in range(n):
        p = directed[r] if r < n1 else intersection[r - n1]
        if math.isfinite(max_rotation_rad) and not (
            abs(_wrap(p[2] - prediction[2])) <= max_rotation_rad
        ):
            continue
        if math.isfinite(max_translation_m) and not (
            math.hypot(p[0] - prediction[0], p[1] - prediction[1]) <= max_translation_m
        ):
            continue
        out[k] = p
        k += 1
    return out[:k]


@njit(cache=True, nogil=True)
def vote_clusters(
    poses: np.ndarray, cell_m: float, n_t: int, cell_t: float, max_clusters: int
) -> tuple[np.ndarray, np.ndarray]:
    """Cluster hypotheses on an ``(x, y, theta)`` grid: the most-voted local maxima first
    (see ``hypotheses.vote``; the arithmetic and the sums' order of its numpy formulation).

    Args:
        poses: ``(N, 3)`` float64 finite hypotheses, ``N >= 1``.
        cell_m: Cell side in x and y, metres; ``n_t`` cells of ``cell_t`` radians in theta.
        max_clusters: Most clusters returned.

    Returns:
        ``(C, 3)`` float64 cluster centres and ``(C,)`` int64 votes.
    """
    n = poses.shape[0]
    kx = np.empty(n, dtype=np.int64)
    ky = np.empty(n, dtype=np.int64)
    kt = np.empty(n, dtype=np.int64)
    for i in range(n):
        kx[i] = math.floor(poses[i, 0] / cell_m)
        ky[i] = math.floor(poses[i, 1] / cell_m)
        kt[i] = math.floor((_wrap(poses[i, 2]) + math.pi) / cell_t) % n_t
    x0, y0 = kx.min() - 1, ky.min() - 1
    nx = kx.max() - x0 + 2
    ny = ky.max() - y0 + 2
    keys = ((kx - x0) * ny + (ky - y0)) * n_t + kt
    keys.sort()
    ukeys = np.empty(n, dtype=np.int64)
    counts = np.zeros(n, dtype=np.int64)
    u = 0
    for i in range(n):
        if u == 0 or keys[i] != ukeys[u - 1]:
            ukeys[u] = keys[i]
            u += 1
        counts[u - 1] += 1
    ukeys, counts = ukeys[:u], counts[:u]
    ut = ukeys % n_t
    uy = (ukeys // n_t) % ny + y0
    ux = ukeys // (n_t * ny) + x0
    dts = (-1, 0, 1) if n_t >= 3 else (0, 0, 0)
    # Neighbour cells of each cell (3 x 3 x 3, theta periodic): their slot, -1 when empty.
    neighbours = np.full((u, 27), -1, dtype=np.int64)
    nsum = np.zeros(u, dtype=np.int64)
    for c in range(u):
        k = 0
        for a in (-1, 0, 1):
            for b in (-1, 0, 1):
                for m in range(3 if n_t >= 3 else 1):
                    cx, cy = ux[c] + a, uy[c] + b
                    if 0 <= cx - x0 < nx and 0 <= cy - y0 < ny:
                        key = ((cx - x0) * ny + (cy - y0)) * n_t + (ut[c] + dts[m]) % n_t
                        pos = min(np.searchsorted(ukeys, key), u - 1)
                        if ukeys[pos] == key:
                            neighbours[c, k] = pos
                            nsum[c] += counts[pos]
                    k += 1
    score = np.empty(u)
    for c in range(u):
        score[c] = nsum[c] + 1e-3 * counts[c] - 1e-9 * c
    is_max = np.zeros(u, dtype=np.bool_)
    for c in range(u):
        best = -np.inf
        for k in range(27):
            if neighbours[c, k] >= 0:
                best = max(best, score[neighbours[c, k]])
        is_max[c] = score[c] >= best
    peaks = np.flatnonzero(is_max)
    peaks = peaks[np.argsort(-score[peaks], kind="mergesort")][:max_clusters]
    out = np.empty((peaks.shape[0], 3))
    wx = np.empty(n)
    wy = np.empty(n)
    wt = np.empty(n)
    for p in range(peaks.shape[0]):
        c = peaks[p]
        centre_t = (ut[c] + 0.5) * cell_t - math.pi
        cnt = 0.0
        for i in range(n):
            member = (
                abs(kx[i] - ux[c]) <= 1
                and abs(ky[i] - uy[c]) <= 1
                and ((kt[i] - ut[c] + 1) % n_t <= 2 or n_t < 3)
            )
            w = 1.0 if member else 0.0
            cnt += w
            wx[i] = w * poses[i, 0]
            wy[i] = w * poses[i, 1]
            wt[i] = w * _wrap(poses[i, 2] - centre_t)
        out[p, 0] = pairwise_sum(wx, 0, n) / cnt
        out[p, 1] = pairwise_sum(wy, 0, n) / cnt
        out[p, 2] = _wrap(centre_t + pairwise_sum(wt, 0, n) / cnt)
    return out, nsum[peaks]


#: Relative slack of a bin's density bound in :func:`density_peak`: far above the rounding
#: of the sums (~1e-13 relative for a few thousand terms), so no sample the exact density
#: would make the peak is ever skipped.
_BOUND_SLACK = 1e-9


@njit(cache=True, nogil=True)
def _density_at(x: int, ds: np.ndarray, ws: np.ndarray, kernel: float, window: float) -> float:
    """Kernel density at the sorted sample ``x``: its own weight, then each sample within
    ``window`` in ascending order, ``ws[y] exp(-0.5 z^2)`` with ``z`` the larger value less
    the smaller over ``kernel`` (the order and terms of a pass over every pair that adds each
    pair's term to both of its samples, smaller index first)."""
    acc = ws[x]
    lo = x
    while lo > 0 and ds[x] - ds[lo - 1] <= window:
        lo -= 1
    for y in range(lo, x):
        z = (ds[x] - ds[y]) / kernel
        acc += ws[y] * math.exp(-0.5 * z * z)
    for y in range(x + 1, ds.shape[0]):
        diff = ds[y] - ds[x]
        if diff > window:
            break
        z = diff / kernel
        acc += ws[y] * math.exp(-0.5 * z * z)
    return acc


#: Bins per kernel width in :func:`density_peak`'s bounds (finer bins bound tighter: on
#: MIT CSAIL's prediction starts 8 leave about a third of the pair terms to evaluate; 16
#: with the near bounds below are the fastest of 8, 16, 32 and 64).
_BINS_PER_KERNEL = 16

#: Kernel widths within which :func:`density_peak` takes each term of its bounds and of its
#: first evaluation of a sample; beyond, the rest of the window counts at most its weight
#: times the term at this distance (``exp(-8)``, 3.4e-4).
_NEAR_WIDTHS = 4.0


@njit(cache=True, nogil=True)
def stable_order(d: np.ndarray, width: float) -> np.ndarray:
    """``np.argsort(d, kind="stable")`` of ``(N,)`` float64 finite ``d`` (``N >= 1``):
    ascending, equal values in index order. A counting sort into buckets of ``width`` (the
    bucket is monotone in the value), then an insertion sort of each bucket's few samples;
    numpy's sort where the buckets would outnumber four times the samples (or ``d`` is not
    finite). Returns ``(N,)`` int64 indices into ``d``; raises nothing."""
    n = d.shape[0]
    lo = d[0]
    hi = d[0]
    for i in range(1, n):
        lo = min(lo, d[i])
        hi = max(hi, d[i])
    if not (hi - lo) / width < 4.0 * n:
        return np.argsort(d, kind="mergesort")
    key = np.empty(n, dtype=np.int64)
    for i in range(n):
        key[i] = int((d[i] - lo) / width)
    start = np.zeros(int((hi - lo) / width) + 2, dtype=np.int64)
    for i in range(n):
        start[key[i] + 1] += 1
    for c in range(start.shape[0] - 1):
        start[c + 1] += start[c]
    order = np.empty(n, dtype=np.int64)
    for i in range(n):  # each bucket in index order; start[c] ends as bucket c's end
        order[start[key[i]]] = i
        start[key[i]] += 1
    first = 0
    for c in range(start.shape[0] - 1):
        for a in range(first + 1, start[c]):
            cur = order[a]
            b = a - 1
            while b >= first and d[order[b]] > d[cur]:
                order[b + 1] = order[b]
                b -= 1
            order[b + 1] = cur
        first = start[c]
    return order


#: ``exp(-j / 4)`` for ``j = 0 .. 33``: the nodes of :func:`_exp_near`.
_EXP_QUARTERS = np.exp(-0.25 * np.arange(34.0))
#: Relative error bound of :func:`_exp_near` (its Taylor remainder is below 1.1e-10 and its
#: rounding a few 1e-16; ten times that).
_EXP_NEAR_ERROR = 1e-9


@njit(cache=True, nogil=True)
def _exp_near(a: float) -> float:
    """``exp(-a)`` for ``a >= 0`` within relative :data:`_EXP_NEAR_ERROR`, for bounds only:
    the nearest node ``exp(-j / 4)`` times a degree-6 Taylor polynomial of the remaining
    ``|r| <= 1/8`` (no library call, so a loop of them pipelines); libm's beyond the nodes."""
    j = int(a * 4.0 + 0.5)
    if j > 33:
        return math.exp(-a)
    r = j * 0.25 - a
    p = 1.0 + r * (
        1.0 + r * (1.0 / 2.0 + r * (1.0 / 6.0 + r * (1.0 / 24.0 + r * (1.0 / 120.0 + r / 720.0))))
    )
    return _EXP_QUARTERS[j] * p


@njit(cache=True, nogil=True)
def _near_density(
    x: int, ds: np.ndarray, ws: np.ndarray, kernel: float, near: float
) -> tuple[float, int, int]:
    """The terms of :func:`_density_at` of the sorted sample ``x`` within ``near`` of it
    (its own weight included), each by :func:`_exp_near` (a bound's terms: within relative
    :data:`_EXP_NEAR_ERROR` of the exact ones), and the range ``[lo, hi)`` of the samples
    they come from."""
    acc = ws[x]
    lo = x
    while lo > 0 and ds[x] - ds[lo - 1] <= near:
        lo -= 1
        z = (ds[x] - ds[lo]) / kernel
        acc += ws[lo] * _exp_near(0.5 * z * z)
    hi = x + 1
    while hi < ds.shape[0] and ds[hi] - ds[x] <= near:
        z = (ds[hi] - ds[x]) / kernel
        acc += ws[hi] * _exp_near(0.5 * z * z)
        hi += 1
    return acc, lo, hi


#: A bin of :func:`density_peak` with at least this many samples that can be the peak
#: bounds their near terms from its moments (:func:`_bin_near_bounds`), fewer one by one.
_MOMENT_MIN_SAMPLES = 3
#: Moments of :func:`_bin_near_bounds` (the Taylor polynomial of ``exp`` has this degree).
_MOMENT_DEGREE = 6


@njit(cache=True, nogil=True)
def _bin_near_bounds(
    a: int,
    b: int,
    ds: np.ndarray,
    ws: np.ndarray,
    kernel: float,
    near: float,
    t_low: np.ndarray,
    t_high: np.ndarray,
) -> tuple[int, int]:
    """Bounds of the kernel density terms of the sorted samples ``a .. b-1`` (one bin, less
    than a kernel width wide) from one pass over their common window, the samples ``[lo,
    hi)`` within ``near`` plus the bin's half extent of its midpoint ``c``; every term of a
    sample within ``near`` is in it, and every one outside lies beyond ``near``.

    With ``s = x - c`` and ``t = y - c``, a term is ``exp(-s^2 / 2h^2) g_y exp(s t / h^2)``
    where ``g_y = w_y exp(-t^2 / 2h^2)``; the last factor's Taylor polynomial of degree
    :data:`_MOMENT_DEGREE` turns the sum over the window into a polynomial in ``s`` whose
    coefficients are the moments ``sum g_y t^j``: one exponential per window sample for the
    bin instead of one per pair. The remainder is at most ``U^(J+1) / (J+1)! e^U`` of the
    sum of ``g``, ``U`` the largest ``|s t| / h^2`` (about 0.13 here); ``g`` comes from
    :func:`_exp_near`. Writes ``t_low[x] <= terms <= t_high[x]`` for each sample ``x`` of
    the bin and returns ``(lo, hi)``."""
    c = 0.5 * (ds[a] + ds[b - 1])
    half = max(c - ds[a], ds[b - 1] - c)
    reach = near + half
    lo = a
    while lo > 0 and c - ds[lo - 1] <= reach:
        lo -= 1
    hi = b
    while hi < ds.shape[0] and ds[hi] - c <= reach:
        hi += 1
    inv_h2 = 1.0 / (kernel * kernel)
    m = np.zeros(_MOMENT_DEGREE + 1)
    t_max = 0.0
    for y in range(lo, hi):
        t = ds[y] - c
        t_max = max(t_max, abs(t))
        g = ws[y] * _exp_near(0.5 * t * t * inv_h2)
        for j in range(_MOMENT_DEGREE + 1):
            m[j] += g
            g *= t
    for j in range(2, _MOMENT_DEGREE + 1):
        m[j] /= math.gamma(j + 1.0)  # the polynomial's coefficients: moment / j!
    u = half * t_max * inv_h2
    e_u = math.exp(u)
    rem = e_u
    for j in range(1, _MOMENT_DEGREE + 2):
        rem *= u / j
    # Absolute error of the polynomial: the Taylor remainder, and the rounding of the
    # moments' sums and of the polynomial (an ulp per operation of sums of absolute value
    # at most m[0] e^U, twice over); the exponentials' relative error comes on top.
    slack = (rem + (hi - lo + 2 * _MOMENT_DEGREE + 4) * 2.3e-16 * e_u) * m[0]
    for x in range(a, b):
        s = (ds[x] - c) * inv_h2
        poly = m[_MOMENT_DEGREE]
        for j in range(_MOMENT_DEGREE - 1, -1, -1):
            poly = poly * s + m[j]
        f = math.exp(-0.5 * (ds[x] - c) * s)
        t_low[x] = max(0.0, f * (poly - slack) * (1.0 - _EXP_NEAR_ERROR))
        t_high[x] = f * (poly + slack) * (1.0 + _EXP_NEAR_ERROR)
    return lo, hi


@njit(cache=True, nogil=True)
def density_peak(d: np.ndarray, w: np.ndarray, kernel: float, max_abs: float) -> tuple[int, float]:
    """The sample of highest weighted Gaussian kernel density among those with
    ``|d| <= max_abs``, and that density:
    ``dens[i] = sum_j w[j] exp(-0.5 ((d[i] - d[j]) / kernel)^2)`` over the ``j`` within
    :data:`DENSITY_WINDOW_WIDTHS` kernel widths of ``d[i]`` (``j = i`` included), the first
    such sample in the order of ``d`` on a tie (``segment_rotation`` in
    :mod:`iceg.matching.hypotheses`).

    Branch and bound instead of every density. The sorted samples
    (:func:`stable_order`) are binned by ``kernel / _BINS_PER_KERNEL``; a bin's densities are
    bounded by the bins within :data:`_NEAR_WIDTHS` kernels at their least possible
    distance, plus the weight of all the others times the term at that distance. Bins are
    visited in decreasing bound until the next bound falls below the best lower bound found.
    A visited sample's density is bounded by its terms within ``_NEAR_WIDTHS`` kernels
    (below) and those plus the rest of the weight times the term there (above); a bin of
    :data:`_MOMENT_MIN_SAMPLES` or more such samples bounds their terms from one pass over
    its window (:func:`_bin_near_bounds`), a smaller one sample by sample. The samples
    whose upper bound reaches the best lower bound get their density summed in one fixed
    order (:func:`_density_at`), so the answer does not depend on which samples were
    bounded. Every bound has a slack (``_BOUND_SLACK``) far above the rounding of the sums.

    Args:
        d: ``(N,)`` float64 finite sample values (radians there).
        w: ``(N,)`` float64 non-negative finite weights.
        kernel: Kernel standard deviation (> 0), same unit as ``d``.
        max_abs: Only samples with ``|d| <= max_abs`` can be the peak.

    Returns:
        ``(index into d, density)``, or ``(-1, -inf)`` when no sample qualifies.
    """
    n = d.shape[0]
    if n == 0:
        return -1, -np.inf
    width = kernel / _BINS_PER_KERNEL
    order = stable_order(d, width)
    ds = d[order]
    ws = w[order]
    window = DENSITY_WINDOW_WIDTHS * kernel
    near = _NEAR_WIDTHS * kernel
    # The non-empty bins, in order: their index, first sample and weight; the samples'
    # cumulative weight.
    bins = np.empty(n, dtype=np.int64)
    first = np.empty(n + 1, dtype=np.int64)
    bin_w = np.zeros(n)
    eligible = np.zeros(n, dtype=np.bool_)
    cum_w = np.empty(n + 1)
    cum_w[0] = 0.0
    m = -1
    for i in range(n):
        cum_w[i + 1] = cum_w[i] + ws[i]
        b = int((ds[i] - ds[0]) / width)
        if m < 0 or b != bins[m]:
            m += 1
            bins[m] = b
            first[m] = i
        bin_w[m] += ws[i]
        if abs(ds[i]) <= max_abs:
            eligible[m] = True
    m += 1
    first[m] = n
    # Samples of bins i and j lie at least (|i - j| - 1) widths apart (less a rounding
    # margin). Bins under `reach` apart count at that distance, the others at `reach`.
    reach = min(int(window / width) + 2, int(near / width) + 2)
    weight_at = np.zeros(reach + 1)
    for delta in range(reach + 1):
        gap = max(0.0, (delta - 1) * width * (1.0 - _BOUND_SLACK))
        if gap <= window:
            z = gap / kernel
            weight_at[delta] = math.exp(-0.5 * z * z)
    cum_bin = np.empty(m + 1)
    cum_bin[0] = 0.0
    for p in range(m):
        cum_bin[p + 1] = cum_bin[p] + bin_w[p]
    # Absolute slack of a cumulative weight's differences (their rounding).
    slack_w = _BOUND_SLACK * cum_bin[m]
    bound = np.full(m, -np.inf)
    for p in range(m):
        if not eligible[p]:
            continue
        acc = bin_w[p]
        q = p - 1
        while q >= 0 and bins[p] - bins[q] < reach:
            acc += bin_w[q] * weight_at[bins[p] - bins[q]]
            q -= 1
        far = cum_bin[q + 1]
        q = p + 1
        while q < m and bins[q] - bins[p] < reach:
            acc += bin_w[q] * weight_at[bins[q] - bins[p]]
            q += 1
        far += cum_bin[m] - cum_bin[q]
        bound[p] = (acc + (far + slack_w) * weight_at[reach]) * (1.0 + _BOUND_SLACK)
    # Terms beyond `near` are at most their weight times this.
    tail = math.exp(-0.5 * _NEAR_WIDTHS * _NEAR_WIDTHS)
    low = -np.inf
    upper = np.full(n, -np.inf)
    t_low = np.empty(n)  # bounds of each visited sample's terms within `near` (and more)
    t_high = np.empty(n)
    for p in np.argsort(-bound, kind="mergesort"):
        if not eligible[p] or bound[p] < low:
            break
        a, b = first[p], first[p + 1]
        lo, hi, n_eligible = a, b, 0
        for x in range(a, b):
            if abs(ds[x]) <= max_abs:
                n_eligible += 1
        if n_eligible >= _MOMENT_MIN_SAMPLES:
            lo, hi = _bin_near_bounds(a, b, ds, ws, kernel, near, t_low, t_high)
        for x in range(a, b):
            if abs(ds[x]) > max_abs:
                continue
            if n_eligible < _MOMENT_MIN_SAMPLES:
                t, lo, hi = _near_density(x, ds, ws, kernel, near)
                t_low[x] = t * (1.0 - _EXP_NEAR_ERROR)
                t_high[x] = t * (1.0 + _EXP_NEAR_ERROR)
            rest = cum_w[lo] + (cum_w[n] - cum_w[hi])
            upper[x] = (t_high[x] + (rest + slack_w) * tail) * (1.0 + _BOUND_SLACK)
            low = max(low, t_low[x] * (1.0 - _BOUND_SLACK))
    best, best_k = -np.inf, -1
    for x in range(n):
        if upper[x] == -np.inf or upper[x] < low:  # not bounded (ineligible), or below
            continue
        v = _density_at(x, ds, ws, kernel, window)
        k = order[x]
        if v > best or (v == best and k < best_k):
            best, best_k = v, k
    return best_k, best


@njit(cache=True, nogil=True)
def segment_rotation_peak(
    new_lines: np.ndarray,
    new_lengths: np.ndarray,
    ref_lines: np.ndarray,
    ref_lengths: np.ndarray,
    theta0: float,
    max_dev_rad: float,
    kernel_rad: float,
    min_support_m: float,
) -> tuple[bool, float]:
    """The arithmetic of ``segment_rotation`` (:mod:`iceg.matching.hypotheses`) in one pass,
    with numpy's operations and summation order (the same bits): the differences of every
    segment pair's line angles less ``theta0`` modulo pi (new segments outer, reference
    inner), weighted by the shorter segment, those within ``max_dev_rad + 2 kernel_rad``
    kept; their :func:`density_peak`; the weighted mean of the pairs within one kernel width
    of the peak (:func:`pairwise_sum`), added to ``theta0`` and wrapped to ``[-pi, pi)``.

    Args:
        new_lines, ref_lines: ``(M, 2)`` float64 Hessian lines ``(alpha_rad, rho_m)``.
        new_lengths, ref_lengths: ``(M,)`` float64 segment lengths, metres.

    Returns:
        ``(found, rotation_rad)``; ``found`` False (rotation NaN) when no pair is kept or
        the peak's density is below ``min_support_m``.
    """
    n_new = new_lines.shape[0]
    n_ref = ref_lines.shape[0]
    d = np.empty(n_new * n_ref)
    w = np.empty(n_new * n_ref)
    reach = max_dev_rad + 2.0 * kernel_rad
    n = 0
    for i in range(n_new):
        for j in range(n_ref):
            x = ref_lines[j, 0] - new_lines[i, 0] - theta0
            x = (x + 0.5 * math.pi) % math.pi - 0.5 * math.pi  # modulo pi, in [-pi/2, pi/2)
            if abs(x) <= reach:
                a = new_lengths[i]
                b = ref_lengths[j]
                d[n] = x
                w[n] = a if (a < b or math.isnan(a)) else b  # np.minimum (NaN propagates)
                n += 1
    if n == 0:
        return False, np.nan
    d = d[:n]
    w = w[:n]
    k, peak = density_peak(d, w, kernel_rad, max_dev_rad)
    if k < 0 or not peak >= min_support_m:
        return False, np.nan
    dw = np.empty(n)
    w_near = np.empty(n)
    m = 0
    for x in range(n):
        if abs(d[x] - d[k]) <= kernel_rad:
            dw[m] = d[x] * w[x]
            w_near[m] = w[x]
            m += 1
    mean = pairwise_sum(dw, 0, m) / pairwise_sum(w_near, 0, m)
    return True, (theta0 + mean + math.pi) % (2.0 * math.pi) - math.pi


@njit(cache=True, nogil=True)
def points_explained(
    points: np.ndarray,
    poses: np.ndarray,
    ref_points: np.ndarray,
    cell_key: np.ndarray,
    cell_order: np.ndarray,
    origin: np.ndarray,
    n_cells: np.ndarray,
    gate_m: float,
) -> np.ndarray:
    """Whether some reference point lies closer than ``gate_m`` to each point moved by each
    pose (``slam.points_prefer_prediction``).

    The reference points are gridded in cells of ``gate_m`` (keys ``ix * n_cells[1] + iy``
    sorted, as :func:`~iceg.matching.refine.grid_points` builds them), so each moved point
    scans the 3 x 3 cells around it and stops at the first reference point within the gate:
    its own cell first (most points that have a reference point within the gate find one
    there), then the rest of its column below and above it, then the columns beside it;
    each a run of consecutive keys found by a binary search among its column's keys. The
    order changes only how soon a point stops, not its answer.

    Args:
        points: ``(P, 2)`` float64 points in their own frame, metres.
        poses: ``(K, 3)`` float64 poses of that frame in the reference frame.
        ref_points: ``(R, 2)`` float64 reference points, reference frame.
        cell_key, cell_order: ``(R,)`` int64 sorted cell keys and the point of each.
        origin: ``(2,)`` float64 corner of cell ``(0, 0)``; ``n_cells`` ``(2,)`` int64.
        gate_m: Distance gate and cell side, metres (> 0).

    Returns:
        ``(K, P)`` bool.
    """
    n_r = cell_key.shape[0]
    nx, ny = n_cells[0], n_cells[1]
    gate2 = gate_m * gate_m
    # The first sorted key of each column of cells (and the end): a cell's search runs over
    # its column's keys only.
    column = np.empty(nx + 1, np.int64)
    m = 0
    for cx in range(nx + 1):
        while m < n_r and cell_key[m] < cx * ny:
            m += 1
        column[cx] = m
    out = np.zeros((poses.shape[0], points.shape[0]), dtype=np.bool_)
    for k in range(poses.shape[0]):
        c = math.cos(poses[k, 2])
        s = math.sin(poses[k, 2])
        for i in range(points.shape[0]):
            qx = c * points[i, 0] - s * points[i, 1] + poses[k, 0]
            qy = s * points[i, 0] + c * points[i, 1] + poses[k, 1]
            fx = (qx - origin[0]) / gate_m
            fy = (qy - origin[1]) / gate_m
            if not (fx > -2.0 and fy > -2.0 and fx < nx + 1.0 and fy < ny + 1.0):
                continue
            ix = math.floor(fx)
            iy = math.floor(fy)
            lo_y, hi_y = max(iy - 1, 0), min(iy + 1, ny - 1)
            # rows [y0, y1] of column ix + dx_cell: the own cell, the own column below and
            # above it, the columns left and right
            found = False
            for step in range(5):
                dx_cell = (0, 0, 0, -1, 1)[step]
                y0 = (max(iy, lo_y), lo_y, max(iy + 1, lo_y), lo_y, lo_y)[step]
                y1 = (min(iy, hi_y), min(iy - 1, hi_y), hi_y, hi_y, hi_y)[step]
                cx = ix + dx_cell
                if cx < 0 or cx >= nx or y0 > y1:
                    continue
                a, b = column[cx], column[cx + 1]
                m = a + np.searchsorted(cell_key[a:b], cx * ny + y0)
                last = cx * ny + y1
                while m < b and cell_key[m] <= last:
                    j = cell_order[m]
                    dx = qx - ref_points[j, 0]
                    dy = qy - ref_points[j, 1]
                    if dx * dx + dy * dy < gate2:
                        found = True
                        break
                    m += 1
                if found:
                    break
            out[k, i] = found
    return out


@njit(cache=True, nogil=True)
def finite_points_within(
    points: np.ndarray, poses: np.ndarray, ref_points: np.ndarray, gate_m: float
) -> np.ndarray:
    """:func:`points_explained` against finite ``ref_points`` gridded by :func:`sorted_cells`
    in cells of ``gate_m``, in one call: the same two kernels, without the grid's round trip
    through Python.

    Args:
        points: ``(P, 2)`` float64 points in their own frame, metres.
        poses: ``(K, 3)`` float64 poses of that frame in the reference frame.
        ref_points: ``(R, 2)`` float64 finite reference points, reference frame, ``R >= 1``.
        gate_m: Distance gate and cell side, metres (> 0).

    Returns:
        ``(K, P)`` bool: whether a reference point lies closer than ``gate_m``.
    """
    origin, n_cells, key, order = sorted_cells(ref_points, gate_m)
    return points_explained(points, poses, ref_points, key, order, origin, n_cells, gate_m)


@njit(cache=True, nogil=True)
def blocks_explained_counts(
    points: np.ndarray,
    pose: np.ndarray,
    prediction: np.ndarray,
    block_poses: np.ndarray,
    block_counts: np.ndarray,
    block_points: np.ndarray,
    gate_m: float,
) -> tuple[bool, int, int, int, int]:
    """The counts of ``slam.points_prefer_prediction``'s sign test against points given in
    blocks, in one compiled call: the blocks moved into the reference frame
    (:func:`~iceg.landmark_frames.move_point_blocks`), then :func:`finite_points_within` at
    the match and at the prediction; the same kernels on the same arrays as those calls one
    by one, so the same counts.

    Args:
        points: ``(P, 2)`` float64 the new scan's points, its frame, metres.
        pose: ``(3,)`` float64 the matched pose of that frame in the reference frame.
        prediction: ``(3,)`` float64 the predicted pose, same frame.
        block_poses: ``(n, 3)`` float64 the pose of each block's frame in the reference frame.
        block_counts: ``(n,)`` int64 points in each block, summing to ``R >= 1``.
        block_points: ``(R, 2)`` float64 the blocks' points, one after the other, metres.
        gate_m: Distance within which a reference point explains a point, metres (> 0).

    Returns:
        ``(finite, at_pose, at_prediction, only_pose, only_prediction)``: whether every
        moved reference point is finite (where not, the counts are 0 and not computed), then
        the points explained at the match, at the prediction, at the match only and at the
        prediction only.
    """
    ref = move_point_blocks(block_poses, block_counts, block_points)
    if not all_finite(ref):
        return False, 0, 0, 0, 0
    poses = np.empty((2, 3))
    poses[0] = pose
    poses[1] = prediction
    within = finite_points_within(points, poses, ref, gate_m)
    at_pose = at_prediction = only_pose = only_prediction = 0
    for i in range(points.shape[0]):
        a, b = within[0, i], within[1, i]
        if a:
            at_pose += 1
        if b:
            at_prediction += 1
        if a and not b:
            only_pose += 1
        if b and not a:
            only_prediction += 1
    return True, at_pose, at_prediction, only_pose, only_prediction


@njit(cache=True, nogil=True)
def _aligned_translation(
    theta: float, new_xy: np.ndarray, ref_xy: np.ndarray, a: int, b: int
) -> tuple[float, float]:
    """``ref_xy[b] - R(theta) new_xy[a]`` (the arithmetic of ``rot`` and the einsum it
    replaces, bit for bit)."""
    c, s = np.cos(theta), np.sin(theta)
    nx, ny = new_xy[a, 0], new_xy[a, 1]
    return ref_xy[b, 0] - (c * nx + (-s) * ny), ref_xy[b, 1] - (s * nx + c * ny)


@njit(cache=True, nogil=True)
def directed_poses(
    i: np.ndarray,
    j: np.ndarray,
    codes: np.ndarray,
    new_heading: np.ndarray,
    new_edge: np.ndarray,
    new_xy: np.ndarray,
    ref_heading: np.ndarray,
    ref_edge: np.ndarray,
    ref_xy: np.ndarray,
    same_code: int,
    corner_eow_code: int,
    eow_corner_code: int,
) -> np.ndarray:
    """One SE(2) hypothesis per directed pair (:func:`iceg.matching.hypotheses.
    directed_hypotheses`): the pairs of ``same_code`` (heading against heading), then for
    each of the two edges ``k`` those of ``corner_eow_code`` (reference edge 0 against new
    edge ``k``) and of ``eow_corner_code`` (reference edge ``k`` against new edge 0), each
    group in pair order; rotations wrapped to ``[-pi, pi)``, non-finite ones dropped.

    Args:
        i, j: ``(Q,)`` int64 new and reference feature index of each pair.
        codes: ``(K_new, K_ref)`` int64 pair codes (``hypotheses.pair_codes``).
        new_heading, ref_heading: ``(K,)`` float64 feature headings, radians (NaN: none).
        new_edge, ref_edge: ``(K, 2)`` float64 edge direction angles, radians (NaN: none).
        new_xy, ref_xy: ``(K, 2)`` float64 feature positions, metres, each scan's frame.
        same_code, corner_eow_code, eow_corner_code: The three directed pair codes.

    Returns:
        ``(N, 3)`` float64 poses ``[x_m, y_m, theta_rad]`` of the new scan in the reference
        frame.
    """
    m = i.shape[0]
    code = np.empty(m, dtype=np.int64)
    for p in range(m):
        code[p] = codes[i[p], j[p]]
    out = np.empty((3 * m, 3))
    n = 0
    for group in range(5):  # same; (corner-eow, eow-corner) for edge 0, then edge 1
        want = same_code if group == 0 else corner_eow_code if group % 2 == 1 else eow_corner_code
        k = 0 if group < 3 else 1
        for p in range(m):
            if code[p] != want:
                continue
            a, b = i[p], j[p]
            if group == 0:
                raw = ref_heading[b] - new_heading[a]
            elif group % 2 == 1:
                raw = ref_edge[b, 0] - new_edge[a, k]
            else:
                raw = ref_edge[b, k] - new_edge[a, 0]
            theta = _wrap(raw)
            if not np.isfinite(theta):
                continue
            tx, ty = _aligned_translation(theta, new_xy, ref_xy, a, b)
            out[n, 0], out[n, 1], out[n, 2] = tx, ty, theta
            n += 1
    return out[:n].copy()


@njit(cache=True, nogil=True)
def intersection_pair_poses(
    i: np.ndarray,
    j: np.ndarray,
    new_xy: np.ndarray,
    ref_xy: np.ndarray,
    tolerance_m: float,
    min_baseline_m: float,
) -> np.ndarray:
    """Hypotheses from two Intersection pairs each (:func:`iceg.matching.hypotheses.
    intersection_hypotheses`): pairs ``p < q`` in row-major order with distinct features on
    both sides whose baselines have equal lengths (within ``tolerance_m``) of at least
    ``min_baseline_m``; the rotation aligns the baselines, the translation is the mean of
    the two pairs'.

    Args:
        i, j: ``(Q,)`` int64 new and reference Intersection index of each pair.
        new_xy, ref_xy: ``(K, 2)`` float64 feature positions, metres, each scan's frame.
        tolerance_m: Largest difference of the two baselines' lengths, metres.
        min_baseline_m: Shortest baseline, metres.

    Returns:
        ``(N, 3)`` float64 poses ``[x_m, y_m, theta_rad]`` of the new scan in the reference
        frame.
    """
    m = i.shape[0]
    out = np.empty((max(0, m * (m - 1) // 2), 3))
    n = 0
    for p in range(m):
        for q in range(p + 1, m):
            if i[p] == i[q] or j[p] == j[q]:
                continue
            vnx = new_xy[i[q], 0] - new_xy[i[p], 0]
            vny = new_xy[i[q], 1] - new_xy[i[p], 1]
            vrx = ref_xy[j[q], 0] - ref_xy[j[p], 0]
            vry = ref_xy[j[q], 1] - ref_xy[j[p], 1]
            dn = np.hypot(vnx, vny)
            dr = np.hypot(vrx, vry)
            if not (dn >= min_baseline_m and abs(dn - dr) <= tolerance_m):
                continue
            theta = _wrap(np.arctan2(vry, vrx) - np.arctan2(vny, vnx))
            t1x, t1y = _aligned_translation(theta, new_xy, ref_xy, i[p], j[p])
            t2x, t2y = _aligned_translation(theta, new_xy, ref_xy, i[q], j[q])
            out[n, 0], out[n, 1], out[n, 2] = 0.5 * (t1x + t2x), 0.5 * (t1y + t2y), theta
            n += 1
    return out[:n].copy()


@njit(cache=True, nogil=True)
def sorted_cells(
    points: np.ndarray, cell_m: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """A uniform grid over finite points (:func:`iceg.matching.refine.grid_points`): the
    same arithmetic as its numpy expressions, and its stable sort by cell key as a
    least-significant-digit radix sort (stable, so the same order), in O(R) instead of
    O(R log R).

    Args:
        points: ``(R, 2)`` float64 finite points, metres, ``R >= 1``.
        cell_m: Cell side, metres.

    Returns:
        ``origin`` ``(2,)`` float64, ``n_cells`` ``(2,)`` int64, the sorted keys ``(R,)``
        int64 and the point of each ``(R,)`` int64.
    """
    n = points.shape[0]
    lo_x, lo_y = points[0, 0], points[0, 1]
    for r in range(1, n):
        lo_x = min(lo_x, points[r, 0])
        lo_y = min(lo_y, points[r, 1])
    origin = np.array([lo_x, lo_y]) - cell_m
    cx = np.empty(n, dtype=np.int64)
    cy = np.empty(n, dtype=np.int64)
    for r in range(n):
        cx[r] = np.int64(np.floor((points[r, 0] - origin[0]) / cell_m))
        cy[r] = np.int64(np.floor((points[r, 1] - origin[1]) / cell_m))
    n_cells = np.array([cx.max() + 2, cy.max() + 2], dtype=np.int64)
    key = cx * n_cells[1] + cy
    top = key.max()
    order = np.arange(n, dtype=np.int64)
    spare = np.empty(n, dtype=np.int64)
    count = np.empty(257, dtype=np.int64)
    shift = 0
    while (top >> shift) > 0:
        count[:] = 0
        for r in range(n):
            count[((key[order[r]] >> shift) & 255) + 1] += 1
        for b in range(256):
            count[b + 1] += count[b]
        for r in range(n):
            digit = (key[order[r]] >> shift) & 255
            spare[count[digit]] = order[r]
            count[digit] += 1
        order, spare = spare, order
        shift += 8
    return origin, n_cells, key[order], order
