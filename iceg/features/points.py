"""Step 1 of feature extraction: a scan's beams to robot-frame points (docs/design.md step 1)."""

from __future__ import annotations

import math
from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from frontends.scan import LaserScan
from iceg_common.errors import ScanError
from iceg_common.numba_loading import njit
from iceg_common.se2 import wrap_angle

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]


class BeamPoints(NamedTuple):
    """A scan's beams and its valid beams' points, robot frame (N beams, P valid ones)."""

    ranges: FloatArray  # (N,) float64 all ranges, metres (as read: NaN/inf possible)
    angles: FloatArray  # (N,) float64 bearings in the laser frame, radians, increasing
    valid: BoolArray  # (N,) bool range_min < r < range_max: a point
    no_return: BoolArray  # (N,) bool +inf or r >= range_max: nothing within usable range
    beam_index: IntArray  # (P,) int64 index in the scan of each point's beam
    points: FloatArray  # (P, 2) float64 points, metres, robot frame (laser offset applied)
    point_ranges: FloatArray  # (P,) float64 ranges of the points, metres
    dirs: FloatArray  # (N, 2) float64 unit beam directions, robot frame
    bearing_robot: FloatArray  # (N,) float64 beam bearings in the robot frame, radians
    origin: FloatArray  # (2,) float64 laser position in the robot frame, metres
    range_max: float  # usable maximum range, metres


def check_bearings(scan: LaserScan) -> None:
    """Refuse a scan whose bearings do not increase strictly.

    Raises:
        ScanError: two consecutive beams' bearings do not increase (the reader's angle
            convention is wrong; every later step assumes beam order is bearing order).
    """
    if not _increasing(np.array(scan.angles_rad, dtype=np.float64)):  # own copy: one type
        raise ScanError(
            f"{scan.source}: beam bearings must increase strictly (got a non-increasing step); "
            "fix the reader's angle convention"
        )


def beam_points(
    scan: LaserScan,
    range_max_m: float,
    range_min_m: float | None = None,
    dark_body_rad: FloatArray | None = None,
) -> BeamPoints:
    """Valid beams to robot-frame points, and every beam's direction (docs/design.md step 1).

    A beam is valid when ``range_min_m < r < range_max_m`` and is a "no return" when its range
    is ``+inf`` or at least ``range_max_m`` (NaN is neither; nor is a return at or within
    ``range_min_m``, which occludes what lies behind it). Points are
    ``offset_xy + r (cos(b + offset_yaw), sin(b + offset_yaw))`` for bearing ``b``.

    Args:
        scan: One laser scan with increasing bearings (see :func:`check_bearings`).
        range_max_m: Usable maximum range, metres: ``min(config, scan.range_max_m)``.
        range_min_m: Usable minimum range, metres (``None``: ``scan.range_min_m``; the
            robot's own body may reach farther, ``FeatureConfig.robot_body_range_m``).
        dark_body_rad: ``(K, 2)`` float64 robot-frame bearing intervals ``[from, to]``
            (radians, in ``[-pi, pi)``) where the robot's body hides the view
            (``FeatureConfig.robot_body_dark_deg``): a beam without a return there
            (``+inf``, or at least ``range_max_m``) is read as ``-inf``, a return too close to
            measure (ROS REP 117), which occludes.

    Returns:
        :class:`BeamPoints` (shapes and units listed there).
    """
    # Own writable copies (a reader may hand out read-only arrays): the compiled stages
    # then see one array type whatever the reader.
    ranges = np.array(scan.ranges_m, dtype=np.float64)
    angles = np.array(scan.angles_rad, dtype=np.float64)
    origin = np.array(scan.laser_offset, dtype=np.float64)
    if dark_body_rad is not None:
        bearing = wrap_angle(angles + origin[2])  # robot frame, in [-pi, pi)
        lo, hi = dark_body_rad[:, 0], dark_body_rad[:, 1]
        inside = ((bearing[:, None] >= lo) & (bearing[:, None] <= hi)).any(axis=1)
        ranges[inside & (ranges >= range_max_m)] = -np.inf  # no return: +inf or beyond
    valid, no_return, beam_index, points, dirs, bearing_robot = _beams(
        ranges,
        angles,
        origin,
        float(scan.range_min_m if range_min_m is None else range_min_m),
        float(range_max_m),
    )
    return BeamPoints(
        ranges=ranges,
        angles=angles,
        valid=valid,
        no_return=no_return,
        beam_index=beam_index,
        points=points,
        point_ranges=ranges[beam_index],
        dirs=dirs,
        bearing_robot=bearing_robot,
        origin=origin[:2].copy(),
        range_max=range_max_m,
    )


@njit(cache=True, nogil=True)
def _increasing(angles: FloatArray) -> bool:
    """Whether no step of ``angles`` ``(N,)`` is ``<= 0`` (a NaN step is not, as in the
    numpy test this replaced; a LaserScan's bearings are finite)."""
    for i in range(1, angles.shape[0]):  # noqa: SIM110 (all(> 0) would refuse a NaN step)
        if angles[i] - angles[i - 1] <= 0.0:
            return False
    return True


@njit(cache=True, nogil=True)
def _beams(
    ranges: FloatArray,
    angles: FloatArray,
    offset: FloatArray,
    range_min_m: float,
    range_max_m: float,
) -> tuple[BoolArray, BoolArray, IntArray, FloatArray, FloatArray, FloatArray]:
    """:func:`beam_points`' arrays in one pass: ``valid`` and ``no_return`` ``(N,)``, the
    valid beams' indices ``(P,)``, their points ``(P, 2)`` as
    :meth:`~frontends.scan.LaserScan.points_xy` gives them (``r (cos a, sin a) + offset_xy``
    with ``a`` the robot-frame bearing), every beam's unit direction ``(N, 2)`` and
    robot-frame bearing ``(N,)``."""
    n = ranges.shape[0]
    valid = np.empty(n, dtype=np.bool_)
    no_return = np.empty(n, dtype=np.bool_)
    bearing = np.empty(n)
    dirs = np.empty((n, 2))
    n_valid = 0
    for i in range(n):
        r = ranges[i]
        finite = math.isfinite(r)
        valid[i] = finite and range_min_m < r < range_max_m
        no_return[i] = (r == np.inf) or (finite and r >= range_max_m)
        n_valid += valid[i]
        bearing[i] = angles[i] + offset[2]
        dirs[i, 0], dirs[i, 1] = math.cos(bearing[i]), math.sin(bearing[i])
    beam_index = np.empty(n_valid, dtype=np.int64)
    points = np.empty((n_valid, 2))
    k = 0
    for i in range(n):
        if valid[i]:
            beam_index[k] = i
            points[k, 0] = ranges[i] * dirs[i, 0] + offset[0]
            points[k, 1] = ranges[i] * dirs[i, 1] + offset[1]
            k += 1
    return valid, no_return, beam_index, points, dirs, bearing
