"""Laser model and vectorized ray casting (beams x walls), plus ground-truth visibility.

Each beam is a ray ``o + t d`` (``t > 0``) from the laser origin; each wall a segment
``p + s e`` (``0 <= s <= 1``). Solving ``o + t d = p + s e`` with 2D cross products gives
``t = (w x e) / (d x e)`` and ``s = (w x d) / (d x e)`` with ``w = p - o``, for all beams and
walls at once; the range of a beam is its smallest valid ``t``.
"""

from __future__ import annotations

import math
from enum import IntEnum

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from frontends.simulate.worlds import CORNER_MAX_DEG, CORNER_MIN_DEG, World
from iceg_common.se2 import compose, inverse, transform_points, wrap_angle

FloatArray = NDArray[np.float64]
BoolArray = NDArray[np.bool_]

_PARALLEL_EPS = 1e-12
_SEGMENT_EPS = 1e-12


class LaserModel(BaseModel):
    """A planar laser range finder; defaults are the paper's SICK LMS200 (§IV: 181 range
    measurements at 5 Hz, 20 m maximum range, one-degree resolution).

    Beam ``i`` has bearing ``-fov/2 + i * fov / (n_beams - 1)`` in the laser frame
    (endpoint-inclusive, the CARMEN FLASER convention for 181 beams: ``-pi/2 + i pi/180``).
    """

    model_config = ConfigDict(extra="forbid", frozen=True)

    n_beams: int = Field(
        default=181, ge=2, description="Number of beams (paper §IV: SICK LMS200, 181 measurements)."
    )
    fov_deg: float = Field(
        default=180.0,
        gt=0.0,
        le=360.0,
        description="Field of view in degrees (paper §IV: 180 deg).",
    )
    range_min_m: float = Field(
        default=0.0,
        ge=0.0,
        description="Minimum valid range in metres (a beam is valid if r > this).",
    )
    range_max_m: float = Field(
        default=20.0,
        gt=0.0,
        description="Maximum range in metres (paper §IV: 20 m); a beam with no return reads "
        "exactly this value, which LaserScan treats as invalid (r < range_max_m).",
    )
    range_sigma_m: float = Field(
        default=0.01,
        ge=0.0,
        description="Standard deviation of the Gaussian range noise per beam, metres "
        "(SICK LMS200 datasheet: about 1 cm).",
    )
    laser_offset: tuple[float, float, float] = Field(
        default=(0.0, 0.0, 0.0),
        description="Laser pose in the robot frame [x_m, y_m, theta_rad].",
    )
    dropout_fraction: float = Field(
        default=0.0,
        ge=0.0,
        lt=1.0,
        description="Fraction of the beams that return nothing although they hit a wall (dark "
        "or glossy patches, weak echoes), in runs of dropout_run_beams beams placed at random "
        "in each scan.",
    )
    dropout_run_beams: int = Field(
        default=1,
        ge=1,
        description="Length of each run of dropped beams (1: single-beam dropouts).",
    )
    body_posts_deg: tuple[float, ...] = Field(
        default=(),
        description="Bearings (laser frame, degrees) of posts on the robot around the laser "
        "(a lidar under a plate on standoffs): each a flat face body_post_range_m from the "
        "laser, facing it, 2 body_post_half_width_m wide, that moves with the robot.",
    )
    body_post_range_m: float = Field(
        default=0.18, gt=0.0, description="Distance of each post's face from the laser, metres."
    )
    body_post_half_width_m: float = Field(
        default=0.03, gt=0.0, description="Half the width of each post's face, metres."
    )

    def angles_rad(self) -> FloatArray:
        """``(n_beams,)`` float64 beam bearings in the laser frame, radians, CCW from ahead."""
        fov = self.fov_deg / 180.0 * math.pi
        step = fov / (self.n_beams - 1)
        return np.asarray(-fov / 2.0 + np.arange(self.n_beams) * step, dtype=np.float64)

    def offset(self) -> FloatArray:
        """``(3,)`` float64 laser pose in the robot frame."""
        return np.asarray(self.laser_offset, dtype=np.float64)

    def body_walls(self, laser_pose: FloatArray) -> FloatArray:
        """``(P, 2, 2)`` float64 the faces of :attr:`body_posts_deg` in the world frame for a
        laser at ``laser_pose`` ``(3,)`` (world frame), metres."""
        b = laser_pose[2] + np.radians(np.asarray(self.body_posts_deg, dtype=np.float64))
        centre = laser_pose[:2] + self.body_post_range_m * np.stack([np.cos(b), np.sin(b)], 1)
        across = self.body_post_half_width_m * np.stack([-np.sin(b), np.cos(b)], 1)
        return np.stack([centre - across, centre + across], axis=1)


def ray_ranges(origin_xy: ArrayLike, directions_rad: ArrayLike, walls: FloatArray) -> FloatArray:
    """Exact distance from ``origin_xy`` along each direction to the first wall.

    Args:
        origin_xy: ``(2,)`` ray origin, metres, world frame.
        directions_rad: ``(B,)`` ray directions in the world frame, radians.
        walls: ``(W, 2, 2)`` wall segments, metres, world frame.

    Returns:
        ``(B,)`` float64 ranges in metres; ``inf`` where a ray hits no wall.
    """
    o = np.asarray(origin_xy, dtype=np.float64)
    phi = np.asarray(directions_rad, dtype=np.float64)
    if walls.shape[0] == 0:
        return np.full(phi.shape, np.inf)
    dx, dy = np.cos(phi)[:, None], np.sin(phi)[:, None]  # (B, 1)
    p = walls[:, 0]
    e = walls[:, 1] - p
    ex, ey = e[None, :, 0], e[None, :, 1]  # (1, W)
    wx, wy = (p[:, 0] - o[0])[None], (p[:, 1] - o[1])[None]
    denom = dx * ey - dy * ex  # (B, W)
    ok = np.abs(denom) > _PARALLEL_EPS
    safe = np.where(ok, denom, 1.0)
    t = (wx * ey - wy * ex) / safe
    s = (wx * dy - wy * dx) / safe
    ok &= (t > 0.0) & (s >= -_SEGMENT_EPS) & (s <= 1.0 + _SEGMENT_EPS)
    return np.where(ok, t, np.inf).min(axis=1)


#: Walls farther than ``range_max_m`` plus this margin (metres) are not cast against: a
#: hit there reads ``range_max_m`` whatever the range noise (the margin is 100 sigma of it).
_CULL_MARGIN_M = 1.0
#: A wall counts as behind the laser only if it is this far (metres) behind: the beams at
#: exactly +-90 deg point a rounding error (1e-16 rad) into ``x < 0``.
_BEHIND_TOL_M = 1e-6


def _reachable_walls(walls: FloatArray, laser_pose: FloatArray, model: LaserModel) -> FloatArray:
    """The walls a beam of ``model`` at ``laser_pose`` can hit within range: a speed-up only,
    the ranges of :func:`cast_rays` are unchanged.

    A wall is dropped if its closest point is more than ``range_max_m + _CULL_MARGIN_M``
    away, or, for a field of view of at most 180°, if it lies entirely behind the laser
    (every beam then points into ``x >= 0`` of the laser frame).
    """
    if walls.shape[0] == 0:
        return walls
    a = walls[:, 0] - laser_pose[:2]
    e = walls[:, 1] - walls[:, 0]
    s = np.clip(-np.einsum("ij,ij->i", a, e) / np.einsum("ij,ij->i", e, e), 0.0, 1.0)
    near = np.hypot(*(a + s[:, None] * e).T) <= model.range_max_m + _CULL_MARGIN_M
    if model.fov_deg <= 180.0:
        c, sn = math.cos(laser_pose[2]), math.sin(laser_pose[2])
        fwd0 = a[:, 0] * c + a[:, 1] * sn
        fwd1 = (a[:, 0] + e[:, 0]) * c + (a[:, 1] + e[:, 1]) * sn
        near &= (fwd0 >= -_BEHIND_TOL_M) | (fwd1 >= -_BEHIND_TOL_M)
    return walls[near]


def cast_rays(
    world: World,
    pose: ArrayLike,
    model: LaserModel | None = None,
    rng: np.random.Generator | None = None,
    stamp_s: float | None = None,
) -> FloatArray:
    """Simulate one scan: the ranges the laser on a robot at ``pose`` measures.

    Args:
        world: The world; its dynamic walls present at ``stamp_s`` are included, and the
            robot's own posts (``model.body_posts_deg``).
        pose: ``(3,)`` true robot pose ``[x_m, y_m, theta_rad]``, world frame. The laser sits
            at ``pose ∘ model.laser_offset``.
        model: Laser model (default: SICK LMS200, see :class:`LaserModel`).
        rng: Source of the Gaussian range noise; ``None`` gives exact ranges.
        stamp_s: Scan time in seconds for dynamic walls; ``None``: static walls only.

    Returns:
        ``(n_beams,)`` float64 ranges in metres, beam order of ``model.angles_rad()``. A beam
        that hits nothing within ``range_max_m`` (or whose noisy range reaches it), or that
        drops out (``model.dropout_fraction``, drawn from ``rng`` after the noise), reads
        exactly ``range_max_m`` (invalid under ``LaserScan``'s strict ``r < range_max_m``).
    """
    model = LaserModel() if model is None else model
    laser_pose = compose(np.asarray(pose, dtype=np.float64), model.offset())
    walls = _reachable_walls(world.walls_at(stamp_s), laser_pose, model)
    if model.body_posts_deg:
        walls = np.concatenate([walls, model.body_walls(laser_pose)])
    ranges = ray_ranges(laser_pose[:2], laser_pose[2] + model.angles_rad(), walls)
    if rng is not None and model.range_sigma_m > 0.0:
        noise = rng.normal(0.0, model.range_sigma_m, size=ranges.shape)
        ranges = np.maximum(ranges + noise, 0.0)  # inf stays inf
    if rng is not None and model.dropout_fraction > 0.0:
        dropped = dropped_beams(
            ranges.shape[0], model.dropout_fraction, model.dropout_run_beams, rng
        )
        ranges = np.where(dropped, np.inf, ranges)
    return np.where(ranges < model.range_max_m, ranges, model.range_max_m)


def dropped_beams(
    n_beams: int, fraction: float, run_beams: int, rng: np.random.Generator
) -> BoolArray:
    """The beams of one scan that drop out: ``(n_beams,)`` bool, in runs of ``run_beams``
    beams starting at beams drawn with probability ``fraction / run_beams`` (runs may
    overlap or be cut by the scan's end, so slightly fewer than ``fraction`` drop).

    Args:
        n_beams: Beams in the scan.
        fraction: Target fraction of dropped beams, in ``[0, 1)``.
        run_beams: Length of each run (1: single-beam dropouts).
        rng: Source of the run starts (one uniform draw per beam).
    """
    starts = np.flatnonzero(rng.uniform(size=n_beams) < fraction / run_beams)
    dropped = np.zeros(n_beams, dtype=bool)
    for k in range(run_beams):
        dropped[np.minimum(starts + k, n_beams - 1)] = True
    return dropped


def visible_mask(
    world: World,
    pose: ArrayLike,
    points_world: ArrayLike,
    model: LaserModel | None = None,
    stamp_s: float | None = None,
    clearance_m: float = 1e-6,
) -> BoolArray:
    """Which world points the laser can see: inside the field of view, nearer than
    ``range_max_m``, and with a clear line of sight (no wall crosses the segment from the
    laser to the point, except walls ending at the point itself).

    Args:
        world: The world (walls present at ``stamp_s``).
        pose: ``(3,)`` true robot pose, world frame.
        points_world: ``(P, 2)`` float64 metres, world frame.
        model: Laser model (field of view, range, offset).
        stamp_s: Time for dynamic walls; ``None``: static walls only.
        clearance_m: A wall hit closer than ``distance - clearance_m`` occludes the point.

    Returns:
        ``(P,)`` bool.
    """
    model = LaserModel() if model is None else model
    pts = np.asarray(points_world, dtype=np.float64).reshape(-1, 2)
    if pts.shape[0] == 0:
        return np.zeros(0, dtype=bool)
    laser_pose = compose(np.asarray(pose, dtype=np.float64), model.offset())
    rel = pts - laser_pose[:2]
    dist = np.hypot(rel[:, 0], rel[:, 1])
    direction = np.arctan2(rel[:, 1], rel[:, 0])
    bearing = wrap_angle(direction - laser_pose[2])
    angles = model.angles_rad()
    half_step = 1e-9
    in_fov = (bearing >= angles[0] - half_step) & (bearing <= angles[-1] + half_step)
    if model.fov_deg >= 360.0:
        in_fov[:] = True
    in_range = (dist < model.range_max_m) & (dist > model.range_min_m)
    hit = ray_ranges(laser_pose[:2], direction, world.walls_at(stamp_s))
    clear = hit >= dist - clearance_m
    return in_fov & in_range & clear


class JunctionClass(IntEnum):
    """What the laser sees at a wall endpoint (returned by :func:`classify_junctions`).

    ``CORNER`` and ``WALL_END`` have the values of ``iceg.types.FeatureKind.CORNER`` (0) and
    ``FeatureKind.EOW`` (1), so a ground-truth class compares directly with an extracted
    feature's kind (``frontends`` may not import ``iceg``; ``tests/frontends/test_simulate.py``
    checks that the values agree). The other classes have no feature kind and use values
    no feature kind uses.
    """

    CORNER = 0
    WALL_END = 1
    HIDDEN = 3
    APPARENT_END = 4
    NOTHING = 5


HIDDEN = JunctionClass.HIDDEN
CORNER = JunctionClass.CORNER
WALL_END = JunctionClass.WALL_END
APPARENT_END = JunctionClass.APPARENT_END
NOTHING = JunctionClass.NOTHING


def classify_junctions(
    world: World,
    pose: ArrayLike,
    model: LaserModel | None = None,
    stamp_s: float | None = None,
) -> tuple[NDArray[np.int64], FloatArray]:
    """What the laser at ``pose`` sees at each wall endpoint of the world.

    A point must first be visible (:func:`visible_mask`). The walls leaving it split the
    plane around it into sectors; the laser sits in one, bounded by two walls. A face of a
    bounding wall is seen if the laser is on that face's side (less than 180° from the wall
    inside the sector). Then the point is:

    - ``CORNER``: both bounding walls are seen and meet at 30°–150° (paper §III-B);
    - ``WALL_END``: a free wall end (one wall);
    - ``APPARENT_END``: a convex corner seen from a side where only one of its walls shows:
      to the laser it is the end of that wall (the beams beyond it reach farther; docs/design.md
      EOW definition);
    - ``NOTHING``: e.g. a T-junction seen from its straight side;
    - ``HIDDEN``: out of the field of view, out of range, or occluded.

    Args:
        world: The world (walls present at ``stamp_s``).
        pose: ``(3,)`` true robot pose, world frame.
        model: Laser model (field of view, range, offset).
        stamp_s: Time for dynamic walls; ``None``: static walls only.

    Returns:
        ``(P,)`` int64 :class:`JunctionClass` values aligned with
        ``world.junctions(stamp_s).points``, and those
        points ``(P, 2)`` float64 in metres, world frame.
    """
    model = LaserModel() if model is None else model
    j = world.junctions(stamp_s)
    out = np.full(j.points.shape[0], HIDDEN, dtype=np.int64)
    if j.points.shape[0] == 0:
        return out, j.points
    seen = visible_mask(world, pose, j.points, model, stamp_s)
    laser_xy = compose(np.asarray(pose, dtype=np.float64), model.offset())[:2]
    rel = laser_xy - j.points
    psi = np.arctan2(rel[:, 1], rel[:, 0])[:, None]  # direction from the point to the laser
    two_pi = 2.0 * np.pi
    with np.errstate(invalid="ignore"):
        d_ccw = np.mod(j.ray_angles_rad - psi, two_pi)  # from psi ccw to each wall
        d_cw = np.mod(psi - j.ray_angles_rad, two_pi)  # from each wall ccw to psi
    d_ccw = np.where(np.isnan(d_ccw) | (d_ccw == 0.0), two_pi, d_ccw)
    d_cw = np.where(np.isnan(d_cw) | (d_cw == 0.0), two_pi, d_cw)
    a, b = d_ccw.min(axis=1), d_cw.min(axis=1)
    sector = a + b
    opening = np.minimum(sector, two_pi - sector)
    lo, hi = math.radians(CORNER_MIN_DEG), math.radians(CORNER_MAX_DEG)
    both = (a < np.pi) & (b < np.pi)
    one = (a < np.pi) ^ (b < np.pi)
    multi = j.n_rays >= 2
    out[seen] = NOTHING
    out[seen & j.is_end] = WALL_END
    out[seen & multi & one] = APPARENT_END
    out[seen & multi & both & (opening >= lo - 1e-12) & (opening <= hi + 1e-12)] = CORNER
    return out, j.points


def visible_corners(
    world: World,
    pose: ArrayLike,
    model: LaserModel | None = None,
    stamp_s: float | None = None,
) -> FloatArray:
    """Ground-truth corners the laser at ``pose`` sees as corners: visible
    (:func:`visible_mask`) and with both walls seen (see :func:`classify_junctions`).

    Returns:
        ``(K, 2)`` float64 corner positions in metres in the **robot** frame.
    """
    cls, pts = classify_junctions(world, pose, model, stamp_s)
    return transform_points(inverse(np.asarray(pose, dtype=np.float64)), pts[cls == CORNER])


def visible_wall_ends(
    world: World,
    pose: ArrayLike,
    model: LaserModel | None = None,
    stamp_s: float | None = None,
    include_apparent: bool = True,
) -> FloatArray:
    """Ground-truth wall ends the laser at ``pose`` sees: visible free wall ends and, with
    ``include_apparent``, convex corners of which only one wall shows (they look like the
    end of that wall; see :func:`classify_junctions`).

    Returns:
        ``(K, 2)`` float64 wall-end positions in metres in the **robot** frame.
    """
    cls, pts = classify_junctions(world, pose, model, stamp_s)
    keep = (cls == WALL_END) | ((cls == APPARENT_END) & include_apparent)
    return transform_points(inverse(np.asarray(pose, dtype=np.float64)), pts[keep])
