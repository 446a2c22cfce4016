"""Ground-truth trajectories: a differential-drive robot driving through waypoints.

The robot turns in place toward the next waypoint at a constant turn rate, then drives
straight to it at a constant speed; the continuous motion is sampled at the scan rate.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg_common.errors import ConfigError
from iceg_common.se2 import wrap_angle

if TYPE_CHECKING:
    from frontends.simulate.worlds import World

FloatArray = NDArray[np.float64]

#: Defaults: a P2AT-like robot at walking pace, and the SICK LMS200 rate of the paper (§IV:
#: "181 range measurements at 5Hz").
DEFAULT_SPEED_MPS = 0.5
DEFAULT_RATE_HZ = 5.0
DEFAULT_TURN_RATE_DPS = 45.0


def _primitives(
    waypoints_xy: ArrayLike,
    speed_mps: float,
    turn_rate_dps: float,
    start_heading_rad: float | None,
) -> tuple[FloatArray, FloatArray, FloatArray, FloatArray]:
    """Motion primitives: start poses (M, 3), kind (M,) 0 turn / 1 drive, signed amount
    (rad or m) (M,), durations (M,) s."""
    wp = np.asarray(waypoints_xy, dtype=np.float64)
    if wp.ndim != 2 or wp.shape[1] != 2 or wp.shape[0] < 2:
        raise ConfigError(f"waypoints_xy must have shape (K >= 2, 2), got {wp.shape}")
    if not np.all(np.isfinite(wp)):
        raise ConfigError("waypoints_xy contains NaN or infinite values")
    if speed_mps <= 0 or turn_rate_dps <= 0:
        raise ConfigError(
            f"speed_mps ({speed_mps}) and turn_rate_dps ({turn_rate_dps}) must be > 0"
        )
    steps = np.diff(wp, axis=0)
    lengths = np.hypot(steps[:, 0], steps[:, 1])
    keep = lengths > 1e-9
    steps, lengths = steps[keep], lengths[keep]
    starts_xy = wp[:-1][keep]
    if lengths.size == 0:
        raise ConfigError("waypoints_xy: all waypoints coincide; the robot would not move")
    headings = np.arctan2(steps[:, 1], steps[:, 0])
    h0 = headings[0] if start_heading_rad is None else float(start_heading_rad)
    prev = np.concatenate([[h0], headings[:-1]])
    turns = wrap_angle(headings - prev)
    omega = math.radians(turn_rate_dps)
    n = lengths.size
    start = np.empty((2 * n, 3))
    start[0::2, :2] = starts_xy
    start[0::2, 2] = prev
    start[1::2, :2] = starts_xy
    start[1::2, 2] = headings
    kind = np.tile([0.0, 1.0], n)
    amount = np.empty(2 * n)
    amount[0::2] = turns
    amount[1::2] = lengths
    duration = np.empty(2 * n)
    duration[0::2] = np.abs(turns) / omega
    duration[1::2] = lengths / speed_mps
    return start, kind, amount, duration


def trajectory_from_waypoints(
    waypoints_xy: ArrayLike,
    speed_mps: float = DEFAULT_SPEED_MPS,
    rate_hz: float = DEFAULT_RATE_HZ,
    turn_rate_dps: float = DEFAULT_TURN_RATE_DPS,
    start_heading_rad: float | None = None,
) -> FloatArray:
    """True robot poses driving through waypoints, sampled at ``rate_hz``.

    At each waypoint the robot turns in place (shortest way, constant ``turn_rate_dps``)
    toward the next one, then drives straight at ``speed_mps``. Sample ``k`` is the pose at
    time ``k / rate_hz`` from the start; the last sample is the final waypoint (the robot
    waits there for the rest of the last period).

    Args:
        waypoints_xy: ``(K >= 2, 2)`` float64 metres, world frame.
        speed_mps: Forward speed, m/s.
        rate_hz: Scan rate, Hz.
        turn_rate_dps: Turn rate in place, degrees per second.
        start_heading_rad: Heading at the first waypoint; ``None`` faces the second one.

    Returns:
        ``(T, 3)`` float64 poses ``[x_m, y_m, theta_rad]`` in the world frame, ``theta``
        wrapped to ``[-pi, pi)``.

    Raises:
        ConfigError: malformed waypoints or non-positive speeds/rate.
    """
    if rate_hz <= 0:
        raise ConfigError(f"rate_hz must be > 0, got {rate_hz}")
    start, kind, amount, duration = _primitives(
        waypoints_xy, speed_mps, turn_rate_dps, start_heading_rad
    )
    t_end = np.cumsum(duration)
    total = float(t_end[-1])
    n_samples = math.ceil(total * rate_hz - 1e-9) + 1
    t = np.minimum(np.arange(n_samples) / rate_hz, total)
    idx = np.minimum(np.searchsorted(t_end, t, side="right"), duration.size - 1)
    tau = t - (t_end[idx] - duration[idx])
    dur = duration[idx]
    frac = np.where(dur > 0, np.clip(tau / np.where(dur > 0, dur, 1.0), 0.0, 1.0), 1.0)
    poses = start[idx].copy()
    turning = kind[idx] == 0.0
    poses[:, 2] += np.where(turning, frac * amount[idx], 0.0)
    dist = np.where(turning, 0.0, frac * amount[idx])
    poses[:, 0] += dist * np.cos(start[idx, 2])
    poses[:, 1] += dist * np.sin(start[idx, 2])
    poses[:, 2] = wrap_angle(poses[:, 2])
    return poses


def default_trajectory_duration_s(
    route_xy: ArrayLike,
    speed_mps: float = DEFAULT_SPEED_MPS,
    turn_rate_dps: float = DEFAULT_TURN_RATE_DPS,
    start_heading_rad: float | None = None,
) -> float:
    """Duration in seconds of driving ``route_xy`` as :func:`trajectory_from_waypoints` does."""
    *_, duration = _primitives(route_xy, speed_mps, turn_rate_dps, start_heading_rad)
    return float(duration.sum())


def default_trajectory(
    world: World,
    speed_mps: float = DEFAULT_SPEED_MPS,
    rate_hz: float = DEFAULT_RATE_HZ,
    turn_rate_dps: float = DEFAULT_TURN_RATE_DPS,
) -> FloatArray:
    """The world's default route (``world.route_xy``) as ``(T, 3)`` true poses.

    Raises:
        ConfigError: the world has no default route.
    """
    if world.route_xy is None:
        raise ConfigError(f"world {world.name!r} has no default route; pass a trajectory")
    return trajectory_from_waypoints(
        world.route_xy, speed_mps, rate_hz, turn_rate_dps, world.start_heading_rad
    )
