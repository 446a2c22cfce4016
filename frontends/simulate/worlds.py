"""Polygon worlds for the simulator, with ground-truth ICE geometry derived from the walls.

A world is a set of wall segments in metres in the **world** frame. Corners and free wall
ends (door frames) are computed from the wall list, never typed by hand, so the ground truth
a test scores against is the geometry the laser actually sees.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field, replace
from functools import cached_property

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg_common.errors import ConfigError

FloatArray = NDArray[np.float64]

#: Two wall endpoints closer than this (metres) are the same point.
JOIN_TOL_M = 1e-6
#: Corner opening angle limits (paper §III-B: lines meeting at 30°–150°).
CORNER_MIN_DEG = 30.0
CORNER_MAX_DEG = 150.0


def _as_walls(walls: ArrayLike, what: str) -> FloatArray:
    arr = np.array(walls, dtype=np.float64)
    if arr.size == 0:
        arr = np.zeros((0, 2, 2))
    if arr.ndim != 3 or arr.shape[1:] != (2, 2):
        raise ConfigError(f"{what}: walls must have shape (W, 2, 2), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ConfigError(f"{what}: walls contain NaN or infinite coordinates")
    lengths = np.linalg.norm(arr[:, 1] - arr[:, 0], axis=1)
    if np.any(lengths <= JOIN_TOL_M):
        bad = int(np.argmax(lengths <= JOIN_TOL_M))
        raise ConfigError(f"{what}: wall {bad} has zero length ({arr[bad].tolist()})")
    arr.setflags(write=False)
    return arr


@dataclass(frozen=True, eq=False)
class DynamicWalls:
    """Walls present only during a time window ``present_from_s <= stamp_s < present_until_s``.

    Used for an obstacle that is removed part way through a run (a box taken away), which
    tests feature-map time-validity pruning (paper §III-C3, last paragraph).

    Attributes:
        walls: ``(K, 2, 2)`` float64 segments in metres, world frame.
        present_from_s: First timestamp (s) at which the walls exist.
        present_until_s: Timestamp (s) from which the walls are gone.
    """

    walls: FloatArray
    present_from_s: float = -math.inf
    present_until_s: float = math.inf

    def __post_init__(self) -> None:
        object.__setattr__(self, "walls", _as_walls(self.walls, "DynamicWalls"))
        if not self.present_from_s < self.present_until_s:
            raise ConfigError(
                f"DynamicWalls: present_from_s ({self.present_from_s}) must be before "
                f"present_until_s ({self.present_until_s})"
            )

    def present_at(self, stamp_s: float) -> bool:
        """Whether the walls exist at ``stamp_s`` (seconds)."""
        return self.present_from_s <= stamp_s < self.present_until_s


#: Leg of a simulated pedestrian: a circle of this radius at laser height, metres.
LEG_RADIUS_M = 0.06
#: Lateral distance between a pedestrian's two legs, metres.
LEG_SPACING_M = 0.26


@dataclass(frozen=True, eq=False)
class Pedestrian:
    """A person walking a polyline back and forth at constant speed, seen at laser height as
    two legs (circles of :data:`LEG_RADIUS_M`, :data:`LEG_SPACING_M` apart across the walking
    direction) that swing ``±stride_m / 2`` along it in antiphase at ``step_hz``.

    The walk reflects at both ends of the path, so the person stays on it for any time.
    Legs are drawn as 16-gons like tree trunks (no ground-truth corners). A pedestrian walks
    through walls and the robot alike: the path is the caller's to choose.

    Attributes:
        path_xy: ``(P, 2)`` float64 waypoints in metres, world frame, ``P >= 2``.
        speed_mps: Walking speed along the path, m/s (> 0).
        start_m: Distance along the path at ``stamp_s = 0``, metres (any real: it wraps).
        stride_m: Peak-to-peak swing of each leg along the walking direction, metres.
        step_hz: Gait frequency (one swing back and forth per period), Hz.

    Raises:
        ConfigError: a path of the wrong shape, non-finite or with two consecutive waypoints
            the same, or a speed that is not positive.
    """

    path_xy: FloatArray
    speed_mps: float = 1.2
    start_m: float = 0.0
    stride_m: float = 0.4
    step_hz: float = 0.9

    def __post_init__(self) -> None:
        path = np.array(self.path_xy, dtype=np.float64)
        if path.ndim != 2 or path.shape[1] != 2 or path.shape[0] < 2:
            raise ConfigError(f"Pedestrian: path_xy must have shape (P >= 2, 2), got {path.shape}")
        if not np.isfinite(path).all() or not (np.hypot(*np.diff(path, axis=0).T) > 0.0).all():
            raise ConfigError("Pedestrian: path_xy must be finite, consecutive waypoints distinct")
        if not self.speed_mps > 0.0:
            raise ConfigError(f"Pedestrian: speed_mps must be > 0, got {self.speed_mps}")
        path.setflags(write=False)
        object.__setattr__(self, "path_xy", path)

    @cached_property
    def _along(self) -> FloatArray:
        """``(P,)`` float64 distance along the path at each waypoint, metres."""
        return np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(self.path_xy, axis=0).T))])

    def pose_at(self, stamp_s: float) -> tuple[FloatArray, FloatArray]:
        """Where the person is at ``stamp_s`` (seconds): ``(2,)`` float64 position (metres)
        and ``(2,)`` float64 unit walking direction, world frame."""
        along = self._along
        total = float(along[-1])
        s = (self.start_m + self.speed_mps * stamp_s) % (2.0 * total)
        backwards = s > total
        if backwards:
            s = 2.0 * total - s
        k = min(int(np.searchsorted(along, s, side="right")) - 1, along.shape[0] - 2)
        a, b = self.path_xy[k], self.path_xy[k + 1]
        u = (b - a) / (along[k + 1] - along[k])
        return a + u * (s - along[k]), -u if backwards else u

    def legs_at(self, stamp_s: float) -> FloatArray:
        """``(2 * TREE_SIDES, 2, 2)`` float64 walls of the two legs at ``stamp_s``, metres."""
        p, u = self.pose_at(stamp_s)
        across = np.array([-u[1], u[0]])
        swing = 0.5 * self.stride_m * math.sin(2.0 * math.pi * self.step_hz * stamp_s)
        legs = [
            [*(p + side * (0.5 * LEG_SPACING_M * across + swing * u)), LEG_RADIUS_M]
            for side in (1.0, -1.0)
        ]
        return tree_walls(np.array(legs))


@dataclass(frozen=True, eq=False)
class World:
    """A 2D polygon world.

    Attributes:
        name: Short name, used in scan sources ``"sim:<name>:<index>"``.
        walls: ``(W, 2, 2)`` float64 static wall segments in metres, world frame;
            ``walls[w, 0]`` and ``walls[w, 1]`` are the endpoints.
        dynamic_walls: Walls that exist only during a time window (see :class:`DynamicWalls`).
        pedestrians: People walking through the world (see :class:`Pedestrian`); their legs
            are walls at any given time.
        route_xy: ``(R, 2)`` float64 waypoints in metres (world frame) of the world's default
            route, or ``None``; see :func:`frontends.simulate.default_trajectory`.
        start_heading_rad: Heading at the first waypoint of the route (``None``: face the
            second waypoint).
        description: Human-readable layout (the world function's docstring).

    Raises:
        ConfigError: walls of the wrong shape, non-finite or of zero length.
    """

    name: str
    walls: FloatArray
    dynamic_walls: tuple[DynamicWalls, ...] = ()
    pedestrians: tuple[Pedestrian, ...] = ()
    route_xy: FloatArray | None = None
    start_heading_rad: float | None = None
    description: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "walls", _as_walls(self.walls, f"World {self.name!r}"))
        object.__setattr__(self, "dynamic_walls", tuple(self.dynamic_walls))
        object.__setattr__(self, "pedestrians", tuple(self.pedestrians))
        if self.route_xy is not None:
            route = np.array(self.route_xy, dtype=np.float64)
            if route.ndim != 2 or route.shape[1] != 2 or route.shape[0] < 2:
                raise ConfigError(
                    f"World {self.name!r}: route_xy must have shape (R >= 2, 2), got {route.shape}"
                )
            route.setflags(write=False)
            object.__setattr__(self, "route_xy", route)

    def walls_at(self, stamp_s: float | None = None) -> FloatArray:
        """Walls present at ``stamp_s``: ``(W', 2, 2)`` float64 metres, world frame.

        Args:
            stamp_s: Time in seconds (the dynamic walls present then and the pedestrians'
                legs are included); ``None`` returns the static walls only.
        """
        if stamp_s is None or not self.is_dynamic:
            return self.walls
        active = [d.walls for d in self.dynamic_walls if d.present_at(stamp_s)]
        active += [p.legs_at(stamp_s) for p in self.pedestrians]
        if not active:
            return self.walls
        return np.concatenate([self.walls, *active], axis=0)

    @property
    def is_dynamic(self) -> bool:
        """Whether anything in the world changes with time (dynamic walls, pedestrians)."""
        return bool(self.dynamic_walls or self.pedestrians)

    def bounds(self) -> FloatArray:
        """``(2, 2)`` float64 ``[[x_min, y_min], [x_max, y_max]]`` of all walls, metres."""
        pts = np.concatenate(
            [self.walls.reshape(-1, 2)] + [d.walls.reshape(-1, 2) for d in self.dynamic_walls]
        )
        return np.stack([pts.min(axis=0), pts.max(axis=0)])

    @cached_property
    def _static_junctions(self) -> Junctions:
        return _junctions(self.walls)

    def junctions(self, stamp_s: float | None = None) -> Junctions:
        """All wall endpoints with the walls leaving them (see :class:`Junctions`).

        Args:
            stamp_s: Include the dynamic walls and pedestrians' legs at this time;
                ``None``: static only.
        """
        if stamp_s is None or not self.is_dynamic:
            return self._static_junctions
        return _junctions(self.walls_at(stamp_s))

    def corners(self, stamp_s: float | None = None) -> FloatArray:
        """Ground-truth corners: ``(C, 2)`` float64 metres, world frame.

        A corner is a wall endpoint where two walls meet (shared endpoint, or an endpoint on
        another wall's interior: a T-junction) with an angle between them in 30°–150°
        (paper §III-B, Fig. 1). Whether a corner *looks* like one depends on the side it is
        seen from (a T-junction seen from its straight side does not): see
        :func:`frontends.simulate.visible_corners`.

        Args:
            stamp_s: Include the dynamic walls and pedestrians' legs at this time;
                ``None``: static only.
        """
        j = self.junctions(stamp_s)
        return j.points[j.is_corner]

    def wall_ends(self, stamp_s: float | None = None) -> FloatArray:
        """Ground-truth free wall ends (door frames, stubs): ``(E, 2)`` float64 metres, world
        frame. An end is a wall endpoint that touches no other wall (paper §III-B: End of Wall).

        Args:
            stamp_s: Include the dynamic walls and pedestrians' legs at this time;
                ``None``: static only.
        """
        j = self.junctions(stamp_s)
        return j.points[j.is_end]

    def __repr__(self) -> str:
        return (
            f"World({self.name!r}, walls={self.walls.shape[0]}, "
            f"dynamic={sum(d.walls.shape[0] for d in self.dynamic_walls)}, "
            f"pedestrians={len(self.pedestrians)}, "
            f"corners={self.corners().shape[0]}, wall_ends={self.wall_ends().shape[0]})"
        )


@dataclass(frozen=True, eq=False)
class Junctions:
    """Wall endpoints of a world and the walls leaving them (ground-truth ICE geometry).

    Attributes:
        points: ``(P, 2)`` float64 every distinct wall endpoint, metres, world frame.
        ray_angles_rad: ``(P, R)`` float64 directions (world frame, radians, sorted
            ascending in ``[-pi, pi]``) of the walls leaving each point; NaN-padded. A wall
            through a point (a T-junction) gives two directions.
        n_rays: ``(P,)`` int64 number of valid entries per row of ``ray_angles_rad``.
        is_corner: ``(P,)`` bool: some pair of walls meets at 30°–150° (paper §III-B).
        is_end: ``(P,)`` bool: a free wall end (one wall, touching no other).
    """

    points: FloatArray
    ray_angles_rad: FloatArray
    n_rays: NDArray[np.int64]
    is_corner: NDArray[np.bool_]
    is_end: NDArray[np.bool_]


def _junctions(walls: FloatArray) -> Junctions:
    """Corners and free ends of a wall set; see :meth:`World.corners`."""
    if walls.shape[0] == 0:
        return Junctions(
            np.zeros((0, 2)),
            np.zeros((0, 0)),
            np.zeros(0, dtype=np.int64),
            np.zeros(0, dtype=bool),
            np.zeros(0, dtype=bool),
        )
    # Unique endpoints (rounded to the join tolerance), in first-seen order.
    ends = walls.reshape(-1, 2)
    keys = np.round(ends / JOIN_TOL_M).astype(np.int64)
    _, first = np.unique(keys, axis=0, return_index=True)
    points = ends[np.sort(first)]  # (P, 2)
    a, b = walls[:, 0], walls[:, 1]  # (W, 2)
    e = b - a
    length2 = np.einsum("ij,ij->i", e, e)
    # Distance of every point to every wall (P, W), vectorized.
    rel = points[:, None, :] - a[None, :, :]
    s = np.clip(np.einsum("pwk,wk->pw", rel, e) / length2, 0.0, 1.0)
    closest = a[None] + s[..., None] * e[None]
    touch = np.linalg.norm(points[:, None, :] - closest, axis=2) <= JOIN_TOL_M
    at_a = np.linalg.norm(points[:, None, :] - a[None], axis=2) <= JOIN_TOL_M
    at_b = np.linalg.norm(points[:, None, :] - b[None], axis=2) <= JOIN_TOL_M
    # Rays leaving each point along each touching wall: toward b unless at b, toward a unless
    # at a (an interior contact gives both).
    fwd = np.arctan2(e[:, 1], e[:, 0])
    back = np.arctan2(-e[:, 1], -e[:, 0])
    angles = np.concatenate(
        [np.broadcast_to(fwd, touch.shape), np.broadcast_to(back, touch.shape)], axis=1
    )  # (P, 2W)
    ok = np.concatenate([touch & ~at_b, touch & ~at_a], axis=1)  # (P, 2W)
    n_rays = ok.sum(axis=1).astype(np.int64)
    ray_angles = np.sort(np.where(ok, angles, np.nan), axis=1)[:, : max(int(n_rays.max()), 1)]
    # Corner: some pair of rays at an unsigned angle in [30, 150] deg.
    diff = np.abs(ray_angles[:, :, None] - ray_angles[:, None, :])  # (P, R, R), NaN-padded
    unsigned = np.minimum(diff, 2.0 * np.pi - diff)
    lo, hi = math.radians(CORNER_MIN_DEG), math.radians(CORNER_MAX_DEG)
    with np.errstate(invalid="ignore"):
        is_corner = np.any((unsigned >= lo - 1e-12) & (unsigned <= hi + 1e-12), axis=(1, 2))
    is_end = n_rays == 1
    for arr in (points, ray_angles, n_rays, is_corner, is_end):
        arr.setflags(write=False)
    return Junctions(points, ray_angles, n_rays, is_corner, is_end)


# ----------------------------------------------------------------------------------------
# Construction helpers
# ----------------------------------------------------------------------------------------


def wall_with_doors(
    p: Sequence[float], q: Sequence[float], doors: Sequence[tuple[float, float]] = ()
) -> list[list[list[float]]]:
    """Straight wall from ``p`` to ``q`` (metres) with door gaps.

    Args:
        p, q: Wall endpoints ``(x, y)`` in metres.
        doors: ``(centre_m, width_m)`` pairs; ``centre_m`` is the distance from ``p`` along
            the wall. Each gap leaves two free wall ends (door frames).

    Returns:
        The wall pieces as ``[[x0, y0], [x1, y1]]`` lists.

    Raises:
        ConfigError: a door extends past the wall or overlaps another door.
    """
    p_arr, q_arr = np.asarray(p, float), np.asarray(q, float)
    length = float(np.linalg.norm(q_arr - p_arr))
    u = (q_arr - p_arr) / length
    cuts = [0.0]
    for centre, width in sorted(doors):
        lo, hi = centre - width / 2.0, centre + width / 2.0
        if lo <= cuts[-1] + JOIN_TOL_M or hi >= length - JOIN_TOL_M:
            raise ConfigError(f"door at {centre} m (width {width} m) does not fit in the wall")
        cuts += [lo, hi]
    cuts.append(length)
    pieces = []
    for s0, s1 in zip(cuts[0::2], cuts[1::2], strict=True):
        pieces.append([(p_arr + s0 * u).tolist(), (p_arr + s1 * u).tolist()])
    return pieces


def rectangle(x0: float, y0: float, x1: float, y1: float) -> list[list[list[float]]]:
    """Four walls of the axis-aligned rectangle ``[x0, x1] x [y0, y1]`` (metres), CCW."""
    c = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    return [[c[i], c[(i + 1) % 4]] for i in range(4)]


# ----------------------------------------------------------------------------------------
# Worlds
# ----------------------------------------------------------------------------------------


def office_world() -> World:
    """An office floor of 20 m x 15 m: rooms with doors around a corridor loop.

    Layout (metres): four rooms along the south side (``y`` 0–4, partitions at ``x`` = 5,
    10, 15), three along the north side (``y`` 11–15, partitions at ``x`` = 6, 13), a central
    block (``x`` 2–18, ``y`` 6–9) split into two rooms at ``x`` = 10, and a 2 m corridor ring
    around the block. Every room has a 0.9 m door (two free wall ends each); the central
    rooms have one door each. The default route leaves the south corridor, visits a south
    room and a north room, goes round the ring and returns to its start (a loop closure).
    """
    door = 0.9
    walls: list[list[list[float]]] = []
    # Outer boundary.
    walls += rectangle(0.0, 0.0, 20.0, 15.0)
    # South rooms: partitions and their corridor wall with a door per room.
    for x in (5.0, 10.0, 15.0):
        walls.append([[x, 0.0], [x, 4.0]])
    for x0, x1 in ((0.0, 5.0), (5.0, 10.0), (10.0, 15.0), (15.0, 20.0)):
        walls += wall_with_doors([x0, 4.0], [x1, 4.0], [((x1 - x0) / 2.0, door)])
    # North rooms.
    for x in (6.0, 13.0):
        walls.append([[x, 11.0], [x, 15.0]])
    for x0, x1 in ((0.0, 6.0), (6.0, 13.0), (13.0, 20.0)):
        walls += wall_with_doors([x0, 11.0], [x1, 11.0], [((x1 - x0) / 2.0, door)])
    # Central block with two rooms: west room door on the south side, east on the north.
    walls += wall_with_doors([2.0, 6.0], [10.0, 6.0], [(4.0, door)])
    walls.append([[10.0, 6.0], [18.0, 6.0]])
    walls.append([[2.0, 9.0], [10.0, 9.0]])
    walls += wall_with_doors([10.0, 9.0], [18.0, 9.0], [(4.0, door)])
    walls.append([[2.0, 6.0], [2.0, 9.0]])
    walls.append([[18.0, 6.0], [18.0, 9.0]])
    walls.append([[10.0, 6.0], [10.0, 9.0]])
    route = [
        [3.0, 5.0],
        [7.5, 5.0],
        [7.5, 2.0],  # into the second south room through its door
        [7.5, 5.0],
        [19.0, 5.0],
        [19.0, 10.0],
        [9.5, 10.0],
        [9.5, 13.0],  # into the middle north room
        [9.5, 10.0],
        [1.0, 10.0],
        [1.0, 5.0],
        [3.0, 5.0],  # back at the start: loop closure
    ]
    return World(
        "office",
        np.array(walls),
        route_xy=np.array(route),
        start_heading_rad=0.0,
        description=office_world.__doc__ or "",
    )


def corridor_world(length_m: float = 40.0, width_m: float = 2.0) -> World:
    """A long featureless corridor ``[0, length_m] x [0, width_m]`` (metres), walls only.

    Its only corners are at the far ends; the default route runs along the middle half, so
    from the middle of the route the ends are beyond the 20 m sensor range. Scan matching
    is degenerate along the corridor axis (docs/design.md: a large variance along the corridor).
    """
    if length_m <= 0 or width_m <= 0:
        raise ConfigError(
            f"corridor_world: length_m and width_m must be > 0, got {length_m}, {width_m}"
        )
    y = width_m / 2.0
    return World(
        "corridor",
        np.array(rectangle(0.0, 0.0, length_m, width_m)),
        route_xy=np.array([[length_m * 0.25, y], [length_m * 0.75, y]]),
        start_heading_rad=0.0,
        description=corridor_world.__doc__ or "",
    )


def pillar_world() -> World:
    """A 10 m x 8 m room with a free-standing 1 m x 1 m pillar at ``x`` 5–6, ``y`` 5.5–6.5.

    The pillar stands 1.5 m in front of the north wall (``y`` = 8) and hides part of it from
    a robot south of it. The default route drives east along ``y`` = 2, past the pillar,
    then back along ``y`` = 3.5.
    """
    walls = rectangle(0.0, 0.0, 10.0, 8.0) + rectangle(5.0, 5.5, 6.0, 6.5)
    route = [[1.5, 2.0], [8.5, 2.0], [8.5, 3.5], [1.5, 3.5]]
    return World(
        "pillar",
        np.array(walls),
        route_xy=np.array(route),
        start_heading_rad=0.0,
        description=pillar_world.__doc__ or "",
    )


def box_world(removed_at_s: float | None = None) -> World:
    """A 12 m x 8 m room with a 1 m x 1 m box at ``x`` 5.5–6.5, ``y`` 3.5–4.5 that is removed
    at ``removed_at_s`` (present for scans with ``stamp_s < removed_at_s``).

    The default route circles the box twice; by default the box is removed halfway through
    it (at the default speed, turn rate and rate). Tests feature-map time-validity pruning
    (paper §III-C3): the box's corners must disappear from the map after it goes.

    Args:
        removed_at_s: Removal time in seconds; ``None``: half the default route's duration.
    """
    from frontends.simulate.trajectory import default_trajectory_duration_s

    lap = [[2.0, 2.0], [10.0, 2.0], [10.0, 6.0], [2.0, 6.0]]
    route = np.array([*lap, *lap, lap[0]], dtype=np.float64)
    box = np.array(rectangle(5.5, 3.5, 6.5, 4.5))
    room = np.array(rectangle(0.0, 0.0, 12.0, 8.0))
    if removed_at_s is None:
        removed_at_s = 0.5 * default_trajectory_duration_s(route, start_heading_rad=0.0)
    return World(
        "box",
        room,
        dynamic_walls=(DynamicWalls(box, present_until_s=float(removed_at_s)),),
        route_xy=route,
        start_heading_rad=0.0,
        description=box_world.__doc__ or "",
    )


# ----------------------------------------------------------------------------------------
# Worlds for issue 11 (accuracy on unseen logs): long corridor, two loops, outdoor
# ----------------------------------------------------------------------------------------

#: Door recess geometry of :func:`long_corridor_world` (metres).
RECESS_WIDTH_M = 0.9
RECESS_DEPTH_RANGE_M = (0.2, 0.3)
RECESS_SPACING_RANGE_M = (3.0, 8.0)


def corridor_recesses(length_m: float = 200.0, seed: int = 11) -> FloatArray:
    """Door recesses of :func:`long_corridor_world`: ``(R, 3)`` float64 rows
    ``[side, centre_m, depth_m]``.

    ``side`` is 0 for the south wall (``y = 0``, recess toward ``-y``) and 1 for the north
    wall. On each side the gaps between recess centres are uniform in
    :data:`RECESS_SPACING_RANGE_M` (irregular, so no two stretches of corridor look alike),
    the first centre 2–5 m from the west end, none within 2 m of the east end; depths are
    uniform in :data:`RECESS_DEPTH_RANGE_M`. Deterministic under ``seed``.
    """
    rng = np.random.default_rng(seed)
    rows: list[tuple[float, float, float]] = []
    for side in (0, 1):
        centre = float(rng.uniform(2.0, 5.0))
        while centre <= length_m - 2.0:
            rows.append((float(side), centre, float(rng.uniform(*RECESS_DEPTH_RANGE_M))))
            centre += float(rng.uniform(*RECESS_SPACING_RANGE_M))
    return np.array(rows, dtype=np.float64).reshape(-1, 3)


def _recess_walls(y: float, outward: float, centre: float, depth: float) -> list[list[list[float]]]:
    """The three walls of a recess behind the gap ``centre ± RECESS_WIDTH_M / 2`` of the
    corridor wall at ``y``; ``outward`` is -1 (south wall) or +1 (north wall)."""
    x0, x1 = centre - RECESS_WIDTH_M / 2.0, centre + RECESS_WIDTH_M / 2.0
    yb = y + outward * depth
    return [[[x0, y], [x0, yb]], [[x0, yb], [x1, yb]], [[x1, yb], [x1, y]]]


def long_corridor_world(length_m: float = 200.0, width_m: float = 2.0, seed: int = 11) -> World:
    """A 200 m x 2 m corridor (``[0, length_m] x [0, width_m]``) with door recesses on both
    sides, driven end to end along its centre line (``x`` 1 → ``length_m - 1``).

    Recesses (:func:`corridor_recesses`) are 0.9 m wide and 0.2–0.3 m deep, every 3–8 m on
    each side at irregular spacing. Each recess adds four 90° corners (two at the corridor
    wall, two at its back), so the world has ``4 R + 4`` corners. The along-corridor
    position is observable only through the recesses (issue 11, failure 1: corridors come
    out 1.2–1.3 % short).

    Raises:
        ConfigError: ``length_m < 10`` or ``width_m <= 0``.
    """
    if length_m < 10.0 or width_m <= 0.0:
        raise ConfigError(
            f"long_corridor_world: need length_m >= 10 and width_m > 0, got {length_m}, {width_m}"
        )
    recesses = corridor_recesses(length_m, seed)
    walls: list[list[list[float]]] = [
        [[0.0, 0.0], [0.0, width_m]],
        [[length_m, 0.0], [length_m, width_m]],
    ]
    for side, y, outward in ((0, 0.0, -1.0), (1, width_m, 1.0)):
        mine = recesses[recesses[:, 0] == side]
        doors = [(float(c), RECESS_WIDTH_M) for c in mine[:, 1]]
        walls += wall_with_doors([0.0, y], [length_m, y], doors)
        for _, centre, depth in mine:
            walls += _recess_walls(y, outward, float(centre), float(depth))
    y_mid = width_m / 2.0
    return World(
        "long_corridor",
        np.array(walls),
        route_xy=np.array([[1.0, y_mid], [length_m - 1.0, y_mid]]),
        start_heading_rad=0.0,
        description=long_corridor_world.__doc__ or "",
    )


def _block_with_doors(
    x0: float, y0: float, x1: float, y1: float, rng: np.random.Generator
) -> list[list[list[float]]]:
    """A rectangular block of rooms whose four walls have 0.9 m doors every 5–9 m."""
    c = [[x0, y0], [x1, y0], [x1, y1], [x0, y1]]
    walls: list[list[list[float]]] = []
    for k in range(4):
        p, q = c[k], c[(k + 1) % 4]
        length = math.hypot(q[0] - p[0], q[1] - p[1])
        doors, centre = [], float(rng.uniform(2.0, 4.0))
        while centre <= length - 2.0:
            doors.append((centre, 0.9))
            centre += float(rng.uniform(5.0, 9.0))
        walls += wall_with_doors(p, q, doors)
    return walls


def two_loop_world() -> World:
    """A 50 m x 30 m building with two 22 m x 26 m blocks of rooms (``x`` 2–24 and 26–48,
    ``y`` 2–28) inside a ring of 2 m corridors, joined by a middle corridor at ``x`` 24–26.
    Block walls have 0.9 m doors every 5–9 m (irregular, fixed seed).

    The default route (256 m) starts in the south-west corner ``(1, 1)`` facing east, drives
    round the west block (loop 1, back at the start after 104 m), then round the whole
    building (loop 2, 152 m) and ends at the start again. With a biased odometry
    (:meth:`OdometryModel.biased`) the odometry drift at the return exceeds 20 m (issue 11,
    failure 3: a loop-closure search within 10 m of the estimate never finds the start).
    """
    rng = np.random.default_rng(7)
    walls = rectangle(0.0, 0.0, 50.0, 30.0)
    walls += _block_with_doors(2.0, 2.0, 24.0, 28.0, rng)
    walls += _block_with_doors(26.0, 2.0, 48.0, 28.0, rng)
    route = [
        [1.0, 1.0],
        [25.0, 1.0],
        [25.0, 29.0],
        [1.0, 29.0],
        [1.0, 1.0],  # end of loop 1
        [49.0, 1.0],
        [49.0, 29.0],
        [1.0, 29.0],
        [1.0, 1.0],  # end of loop 2
    ]
    return World(
        "two_loop",
        np.array(walls),
        route_xy=np.array(route),
        start_heading_rad=0.0,
        description=two_loop_world.__doc__ or "",
    )


def open_loops_world() -> World:
    """Two loops round a 40 m x 40 m square of open ground that leave and return to a small
    feature-rich start area: a 30 m wall along ``y`` = 0 (``x`` -10 to 20) with two 0.9 m
    doors and end stubs, and two 1 m boxes 2.5 m from the route. Away from the start the
    20 m laser sees nothing (about 80 % of the scans have no return), so the estimate can only
    follow the odometry there.

    The default route (320 m) starts at ``(5, 5)`` facing east and drives twice round the
    square ``x`` 5–45, ``y`` 5–45 (back at the start after 160 m and 320 m). With 1 % scale
    error and 0.3 deg/m heading drift the odometry is about 20 m off at the first return
    and about 40 m at the second, beyond a 10 m loop-closure search (issue 11, failure 3),
    while the start area offers a closure to a search wide enough.
    """
    walls = wall_with_doors([-10.0, 0.0], [20.0, 0.0], [(6.0, 0.9), (21.0, 0.9)])
    walls += [[[-10.0, 0.0], [-10.0, 3.0]], [[20.0, 0.0], [20.0, 3.0]]]
    walls += rectangle(12.0, 1.5, 13.0, 2.5) + rectangle(-3.0, 1.5, -2.0, 2.5)
    lap = [[45.0, 5.0], [45.0, 45.0], [5.0, 45.0], [5.0, 5.0]]
    return World(
        "open_loops",
        np.array(walls),
        route_xy=np.array([[5.0, 5.0], *lap, *lap]),
        start_heading_rad=0.0,
        description=open_loops_world.__doc__ or "",
    )


#: Outdoor layout of :func:`outdoor_world` (metres).
TREE_RADIUS_RANGE_M = (0.1, 0.4)
POST_HALF_SIDE_M = 0.075
#: Sides of the polygon approximating a tree trunk (16: neighbouring edges meet at 157.5°,
#: outside the 30°–150° corner range, so trunks hold no ground-truth corners).
TREE_SIDES = 16
_OUTDOOR_ROUTE = np.array(
    [[5.0, 5.0], [35.0, 5.0], [35.0, 25.0], [5.0, 25.0], [5.0, 5.0]], dtype=np.float64
)


@dataclass(frozen=True, eq=False)
class OutdoorLayout:
    """Objects of :func:`outdoor_world`, metres, world frame.

    Attributes:
        trees: ``(T, 3)`` float64 ``[x, y, radius]`` of the trunks.
        posts: ``(P, 2)`` float64 centres of the square posts (half side
            :data:`POST_HALF_SIDE_M`).
        walls: ``(L, 2, 2)`` float64 the few long walls.
    """

    trees: FloatArray
    posts: FloatArray
    walls: FloatArray


def _distance_to_route(points: FloatArray, route: FloatArray) -> FloatArray:
    """``(N,)`` distance of each point to the route polyline, metres."""
    a, b = route[:-1], route[1:]
    e = b - a
    s = np.clip(np.einsum("pwk,wk->pw", points[:, None] - a[None], e) / (e * e).sum(1), 0.0, 1.0)
    closest = a[None] + s[..., None] * e[None]
    return np.linalg.norm(points[:, None] - closest, axis=2).min(axis=1)


def outdoor_layout(n_trees: int = 70, n_posts: int = 20, seed: int = 3) -> OutdoorLayout:
    """Trees and posts scattered over ``[0, 40] x [0, 30]`` m, none within 1.2 m of the
    route of :func:`outdoor_world`, and two long walls (a building front along ``y`` = 31,
    ``x`` 0–22, and a fence along ``x`` = 41, ``y`` 8–22). Deterministic under ``seed``.
    """
    rng = np.random.default_rng(seed)

    def scatter(n: int, clearance: float) -> FloatArray:
        pts = np.zeros((0, 2))
        while pts.shape[0] < n:
            cand = rng.uniform([0.0, 0.0], [40.0, 30.0], size=(4 * n, 2))
            cand = cand[_distance_to_route(cand, _OUTDOOR_ROUTE) > clearance]
            pts = np.concatenate([pts, cand])
        return pts[:n]

    centres = scatter(n_trees, 1.2)
    radii = rng.uniform(*TREE_RADIUS_RANGE_M, size=n_trees)
    walls = np.array([[[0.0, 31.0], [22.0, 31.0]], [[41.0, 8.0], [41.0, 22.0]]])
    return OutdoorLayout(np.column_stack([centres, radii]), scatter(n_posts, 1.2), walls)


def tree_walls(trees: FloatArray) -> FloatArray:
    """``(T * TREE_SIDES, 2, 2)`` float64 edges of the polygons inscribed in the trunk
    circles ``[x, y, radius]`` (metres)."""
    phi = np.linspace(0.0, 2.0 * np.pi, TREE_SIDES + 1)
    ring = np.stack([np.cos(phi), np.sin(phi)], axis=1)  # (S + 1, 2)
    pts = trees[:, None, :2] + trees[:, None, 2:3] * ring[None]  # (T, S + 1, 2)
    return np.stack([pts[:, :-1], pts[:, 1:]], axis=2).reshape(-1, 2, 2)


def with_pedestrians(
    world: World,
    n_people: int,
    seed: int = 0,
    speed_range_mps: tuple[float, float] = (0.9, 1.4),
    max_offset_m: float = 0.6,
) -> World:
    """``world`` with ``n_people`` people walking its default route back and forth: each on
    the route moved by a random offset of at most ``max_offset_m`` in x and in y (so they
    share the robot's corridors and pass it on either side), from a random point in a random
    direction, at a speed drawn from ``speed_range_mps``. Deterministic under ``seed``.

    Raises:
        ConfigError: the world has no default route, ``n_people < 0``, or a speed range that
            is not positive and ascending.
    """
    if world.route_xy is None:
        raise ConfigError(f"world {world.name!r} has no default route for pedestrians")
    lo, hi = speed_range_mps
    if n_people < 0 or not 0.0 < lo <= hi:
        raise ConfigError(
            f"with_pedestrians: need n_people >= 0 and 0 < speed_range_mps[0] <= [1], got "
            f"{n_people}, {speed_range_mps}"
        )
    rng = np.random.default_rng(seed)
    route = world.route_xy
    keep = np.concatenate([[True], np.hypot(*np.diff(route, axis=0).T) > 0.0])
    length = float(np.hypot(*np.diff(route[keep], axis=0).T).sum())
    people = tuple(
        Pedestrian(
            route[keep] + rng.uniform(-max_offset_m, max_offset_m, size=2),
            speed_mps=float(rng.uniform(lo, hi)),
            start_m=float(rng.uniform(0.0, 2.0 * length)),
        )
        for _ in range(n_people)
    )
    return replace(world, pedestrians=world.pedestrians + people)


def outdoor_world(seed: int = 3) -> World:
    """A feature-poor outdoor scene: 70 tree trunks (circles of 0.1–0.4 m radius, as
    16-gons), 20 square posts of 0.15 m and only two long walls, over 40 m x 30 m with no
    enclosing boundary (beams into the open return nothing). The default route is a 100 m
    loop ``(5, 5) → (35, 5) → (35, 25) → (5, 25) → (5, 5)`` with at least 1.2 m of clearance
    from every object (:func:`outdoor_layout`). Most beam returns come from trees and posts
    (issue 11, failure 4: feature-poor outdoor scans lose scan-match factors).
    """
    layout = outdoor_layout(seed=seed)
    posts = [
        rectangle(
            x - POST_HALF_SIDE_M, y - POST_HALF_SIDE_M, x + POST_HALF_SIDE_M, y + POST_HALF_SIDE_M
        )
        for x, y in layout.posts
    ]
    walls = np.concatenate(
        [layout.walls, tree_walls(layout.trees), np.array(posts).reshape(-1, 2, 2)]
    )
    return World(
        "outdoor",
        walls,
        route_xy=_OUTDOOR_ROUTE.copy(),
        start_heading_rad=0.0,
        description=outdoor_world.__doc__ or "",
    )


#: Built-in worlds by name.
WORLDS: dict[str, Callable[[], World]] = {
    "office": office_world,
    "corridor": corridor_world,
    "pillar": pillar_world,
    "box": box_world,
    "long_corridor": long_corridor_world,
    "two_loop": two_loop_world,
    "open_loops": open_loops_world,
    "outdoor": outdoor_world,
}


def world_by_name(name: str) -> World:
    """A built-in world by name (``office``, ``corridor``, ``pillar``, ``box``,
    ``long_corridor``, ``two_loop``, ``open_loops``, ``outdoor``).

    Raises:
        ConfigError: unknown name.
    """
    try:
        return WORLDS[name]()
    except KeyError:
        raise ConfigError(
            f"unknown simulated world {name!r}; choose one of {', '.join(sorted(WORLDS))}"
        ) from None
