"""Step 1 of feature extraction: a scan's beams to robot-frame points (docs/design.md step 1)."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np
from numpy.typing import NDArray

from frontends.scan import LaserScan
from iceg_common.errors import ScanError

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
    angles = scan.angles_rad
    if angles.shape[0] > 1 and np.any(np.diff(angles) <= 0.0):
        raise ScanError(
            f"{scan.source}: beam bearings must increase strictly (got a non-increasing step); "
            "fix the reader's angle convention"
        )


def beam_points(scan: LaserScan, range_max_m: float) -> BeamPoints:
    """Valid beams to robot-frame points, and every beam's direction (docs/design.md step 1).

    A beam is valid when ``range_min < r < range_max_m`` and is a "no return" when its range is
    ``+inf`` or at least ``range_max_m`` (NaN is neither). Points are
    ``offset_xy + r (cos(b + offset_yaw), sin(b + offset_yaw))`` for bearing ``b``.

    Args:
        scan: One laser scan with increasing bearings (see :func:`check_bearings`).
        range_max_m: Usable maximum range, metres: ``min(config, scan.range_max_m)``.

    Returns:
        :class:`BeamPoints` (shapes and units listed there).
    """
    # Own writable copies (a reader may hand out read-only arrays): the compiled stages
    # then see one array type whatever the reader.
    ranges = np.array(scan.ranges_m, dtype=np.float64)
    with np.errstate(invalid="ignore"):
        no_return = np.isposinf(ranges) | (np.isfinite(ranges) & (ranges >= range_max_m))
        valid = np.isfinite(ranges) & (ranges > scan.range_min_m) & (ranges < range_max_m)
    bearing_robot = scan.angles_rad + scan.laser_offset[2]
    return BeamPoints(
        ranges=ranges,
        angles=np.array(scan.angles_rad, dtype=np.float64),
        valid=valid,
        no_return=no_return,
        beam_index=np.flatnonzero(valid).astype(np.int64),
        points=scan.points_xy(valid),
        point_ranges=ranges[valid],
        dirs=np.stack([np.cos(bearing_robot), np.sin(bearing_robot)], axis=1),
        bearing_robot=bearing_robot,
        origin=np.array(scan.laser_offset[:2], dtype=np.float64),
        range_max=range_max_m,
    )
