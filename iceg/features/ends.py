"""End-of-wall features: a segment endpoint beyond which the beams see past the wall's
extension (paper §III-B, Fig. 1; docs/design.md step 4)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from iceg.features.config import FeatureConfig
from iceg.features.geometry import meet, norm, sandwich, unit
from iceg.features.points import BeamPoints
from iceg.features.segments import Segments

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

# Variance of a uniform distribution over an interval of length g is g² / UNIFORM_VAR_DIVISOR.
UNIFORM_VAR_DIVISOR = 12.0


class EndsOfWall(NamedTuple):
    """E end-of-wall features, robot frame."""

    seg: IntArray  # (E,) int64 segment of each EOW
    end: IntArray  # (E,) int64 which endpoint (0 first, 1 last)
    xy: FloatArray  # (E, 2) float64 position, metres
    cov: FloatArray  # (E, 2, 2) float64 its covariance, m²
    dirs: FloatArray  # (E, 2, 2) float64 [0]: unit vector into the wall; [1]: NaN
    beyond: IntArray  # (E,) int64 the first beam beyond the endpoint


def beams_beyond(segs: Segments, n_beams: int, check_beams: int) -> tuple[IntArray, BoolArray]:
    """The ``check_beams`` beams just beyond each endpoint, in beam order (outward).

    Returns:
        ``nb`` ``(M, 2, K)`` int64 beam indices clipped into the scan, and ``inside``
        ``(M, 2, K)`` bool: the unclipped index lies in the scan.
    """
    outward = np.array([-1, 1], dtype=np.int64)
    k_steps = np.arange(1, check_beams + 1, dtype=np.int64)
    nb = segs.end_beam[:, :, None] + outward[None, :, None] * k_steps[None, None, :]
    inside = (nb >= 0) & (nb < n_beams)
    return np.clip(nb, 0, n_beams - 1), inside


def sees_past(beams: BeamPoints, segs: Segments, nb: IntArray, cfg: FeatureConfig) -> BoolArray:
    """Which beams ``nb`` ``(M, 2, K)`` see past their segment's infinite line.

    The range ``r_pred`` at which a beam meets the line (from the laser origin) must be
    positive, below ``range_max - eow_range_margin_m`` and at an incidence of at most
    ``eow_max_incidence_deg`` from the normal; the beam then returns farther than
    ``r_pred + eow_range_margin_m``, or nothing.

    Returns:
        ``(M, 2, K)`` bool (``inside`` of :func:`beams_beyond` not yet applied).
    """
    cos_max_inc = math.cos(math.radians(cfg.eow_max_incidence_deg))
    n_dot_u = np.einsum("mj,mekj->mek", segs.normals, beams.dirs[nb])
    dist_to_line = segs.lines[:, 1] - segs.normals @ beams.origin  # (M,) laser -> line
    with np.errstate(divide="ignore", invalid="ignore"):
        r_pred = dist_to_line[:, None, None] / n_dot_u
    predicted = (
        np.isfinite(r_pred)
        & (r_pred > 0.0)
        & (np.abs(n_dot_u) >= cos_max_inc)
        & (r_pred < beams.range_max - cfg.eow_range_margin_m)
    )
    with np.errstate(invalid="ignore"):
        farther = beams.valid[nb] & (beams.ranges[nb] > r_pred + cfg.eow_range_margin_m)
    out: BoolArray = predicted & (farther | beams.no_return[nb])
    return out


def junctions(segs: Segments, cfg: FeatureConfig) -> BoolArray:
    """Endpoints where another segment starts right there: within ``eow_check_beams + 1``
    beams and ``corner_gap_m`` plus both endpoints' beam spacing (a corner, or walls
    meeting at a shallow angle; not an end of wall).

    Endpoint beams strictly increase (first, last, first, ... of segments in point order),
    so only the next ``eow_check_beams + 1`` endpoints can be that close in beams: ``O(M)``
    work instead of all endpoint pairs (issue 12).

    Returns:
        ``(M, 2)`` bool.
    """
    ends = segs.endpoints.reshape(-1, 2)
    sp = segs.spacing.reshape(-1)
    beam = segs.end_beam.reshape(-1)
    n = ends.shape[0]
    window = cfg.eow_check_beams + 1
    a = np.repeat(np.arange(n), window)
    b = a + np.tile(np.arange(1, window + 1), n)
    a, b = a[b < n], b[b < n]
    close = (np.abs(beam[a] - beam[b]) <= window) & (a // 2 != b // 2)
    d = norm(ends[a] - ends[b])
    hit = np.zeros(n, dtype=bool)
    hit[a[close & (d <= cfg.corner_gap_m + sp[a] + sp[b])]] = True
    hit[b[close & (d <= cfg.corner_gap_m + sp[b] + sp[a])]] = True
    return hit.reshape(-1, 2)


def wall_end_geometry(
    beams: BeamPoints, segs: Segments, seg: IntArray, end: IntArray, beyond: IntArray
) -> tuple[FloatArray, FloatArray, FloatArray]:
    """Position, covariance and direction of EOWs (paper §III-B).

    The wall ends between the ray of the endpoint's beam and the ray of the first beam
    beyond; both meet the wall's line and the EOW is the middle of the two meeting points.
    Covariance: that midpoint's Jacobian applied to the line covariance, plus ``gap² / 12``
    along the wall (uniform over the gap).

    Returns:
        ``xy`` ``(E, 2)`` metres, ``cov`` ``(E, 2, 2)`` m², ``wall_dir`` ``(E, 2)`` unit
        vectors from the EOW into its wall.
    """
    n_e = seg.shape[0]
    end_xy = segs.endpoints[seg, end]
    wall_dir = unit(segs.endpoints[seg, 1 - end] - end_xy)
    ray_beams = np.concatenate([segs.end_beam[seg, end], beyond])
    rays = np.empty((2 * n_e, 2))
    rays[:, 0] = beams.bearing_robot[ray_beams] + 0.5 * np.pi  # normal of the beam's ray
    rays[:, 1] = np.cos(rays[:, 0]) * beams.origin[0] + np.sin(rays[:, 0]) * beams.origin[1]
    hits, j_wall, _ = meet(np.concatenate([segs.lines[seg], segs.lines[seg]]), rays)
    hit_end, hit_next = hits[:n_e], hits[n_e:]
    xy = 0.5 * (hit_end + hit_next)
    gap_len = norm(hit_next - hit_end)
    along = (gap_len**2 / UNIFORM_VAR_DIVISOR)[:, None, None] * np.einsum(
        "ki,kj->kij", wall_dir, wall_dir
    )
    cov = sandwich(0.5 * (j_wall[:n_e] + j_wall[n_e:]), segs.cov[seg]) + along
    return xy, cov, wall_dir


def find_ends_of_wall(
    beams: BeamPoints, segs: Segments, in_corner: BoolArray, cfg: FeatureConfig
) -> EndsOfWall:
    """Ends of wall: endpoints in no corner and no junction whose next ``eow_check_beams``
    beams (in beam order) all see past the wall's extension (paper §III-B, Fig. 1).

    Not an EOW: an endpoint next to nearer returns (occlusion), at the scan's angular limit,
    or where the wall's extension would lie beyond the usable range or at grazing incidence.

    Args:
        beams: The scan's beams.
        segs: Its segments.
        in_corner: ``(M, 2)`` bool endpoints taken by a corner.
        cfg: ``eow_check_beams``, ``eow_range_margin_m``, ``eow_max_incidence_deg``,
            ``corner_gap_m``.

    Returns:
        :class:`EndsOfWall`, by segment then endpoint.
    """
    nb, inside = beams_beyond(segs, beams.ranges.shape[0], cfg.eow_check_beams)
    past = inside & sees_past(beams, segs, nb, cfg)
    is_eow = np.all(past, axis=2) & ~in_corner & ~junctions(segs, cfg)
    seg, end = np.nonzero(is_eow)
    beyond = nb[seg, end, 0]
    if seg.size == 0:
        no = np.zeros(0, dtype=np.int64)
        return EndsOfWall(no, no, np.zeros((0, 2)), np.zeros((0, 2, 2)), np.zeros((0, 2, 2)), no)
    xy, cov, wall_dir = wall_end_geometry(beams, segs, seg, end, beyond)
    dirs = np.stack([wall_dir, np.full((seg.size, 2), np.nan)], axis=1)
    return EndsOfWall(seg.astype(np.int64), end.astype(np.int64), xy, cov, dirs, beyond)
