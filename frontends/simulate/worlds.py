"""Polygon worlds for the simulator, with ground-truth ICE geometry derived from the walls.

A world is a set of wall segments in metres in the **world** frame. Corners and free wall
ends (door frames) are computed from the wall list, never typed by hand, so the ground truth
a test scores against is the geometry the laser actually sees.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
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


@dataclass(frozen=True, eq=False)
class World:
    """A 2D polygon world.

    Attributes:
        name: Short name, used in scan sources ``"sim:<name>:<index>"``.
        walls: ``(W, 2, 2)`` float64 static wall segments in metres, world frame;
            ``walls[w, 0]`` and ``walls[w, 1]`` are the endpoints.
        dynamic_walls: Walls that exist only during a time window (see :class:`DynamicWalls`).
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
    route_xy: FloatArray | None = None
    start_heading_rad: float | None = None
    description: str = field(default="", compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "walls", _as_walls(self.walls, f"World {self.name!r}"))
        object.__setattr__(self, "dynamic_walls", tuple(self.dynamic_walls))
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
            stamp_s: Time in seconds; ``None`` returns the static walls only.
        """
        if stamp_s is None or not self.dynamic_walls:
            return self.walls
        active = [d.walls for d in self.dynamic_walls if d.present_at(stamp_s)]
        if not active:
            return self.walls
        return np.concatenate([self.walls, *active], axis=0)

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
            stamp_s: Include the dynamic walls present at this time; ``None``: static only.
        """
        if stamp_s is None or not self.dynamic_walls:
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
            stamp_s: Include the dynamic walls present at this time; ``None``: static only.
        """
        j = self.junctions(stamp_s)
        return j.points[j.is_corner]

    def wall_ends(self, stamp_s: float | None = None) -> FloatArray:
        """Ground-truth free wall ends (door frames, stubs): ``(E, 2)`` float64 metres, world
        frame. An end is a wall endpoint that touches no other wall (paper §III-B: End of Wall).

        Args:
            stamp_s: Include the dynamic walls present at this time; ``None``: static only.
        """
        j = self.junctions(stamp_s)
        return j.points[j.is_end]

    def __repr__(self) -> str:
        return (
            f"World({self.name!r}, walls={self.walls.shape[0]}, "
            f"dynamic={sum(d.walls.shape[0] for d in self.dynamic_walls)}, "
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
    is degenerate along the corridor axis (DESIGN.md: a large variance along the corridor).
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


#: Built-in worlds by name.
WORLDS: dict[str, Callable[[], World]] = {
    "office": office_world,
    "corridor": corridor_world,
    "pillar": pillar_world,
    "box": box_world,
}


def world_by_name(name: str) -> World:
    """A built-in world by name (``office``, ``corridor``, ``pillar``, ``box``).

    Raises:
        ConfigError: unknown name.
    """
    try:
        return WORLDS[name]()
    except KeyError:
        raise ConfigError(
            f"unknown simulated world {name!r}; choose one of {', '.join(sorted(WORLDS))}"
        ) from None
