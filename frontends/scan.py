"""The laser scan record every front-end produces."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
from numpy.typing import NDArray

from iceg_common.errors import ScanError

FloatArray = NDArray[np.float64]


def _pose3(value: object, what: str, scan: LaserScan) -> FloatArray:
    try:
        pose = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ScanError(f"{scan.source}: {what} is not numeric: {value!r}") from None
    if pose.shape != (3,) or not np.isfinite(pose).all():
        raise ScanError(
            f"{scan.source}: {what} must be a finite (3,) pose [x_m, y_m, theta_rad], got "
            f"{pose.tolist()}"
        )
    return pose


@dataclass(frozen=True, eq=False)
class LaserScan:
    """One 2D laser scan with the robot's wheel-odometry pose at its timestamp.

    Attributes:
        stamp_s: Timestamp in seconds (CARMEN: the ipc timestamp, first trailing field).
        ranges_m: ``(N,)`` float64 beam ranges in metres; a no-return beam holds a value
            ``>= range_max_m`` (CARMEN writes 81.91 or the sensor's max range).
        angles_rad: ``(N,)`` float64 beam bearings in the **laser** frame, radians,
            increasing counter-clockwise, 0 straight ahead.
        range_min_m: A beam is valid only if ``range_min_m < r``.
        range_max_m: A beam is valid only if ``r < range_max_m``.
        odom_pose: ``(3,)`` float64 robot pose from wheel odometry ``[x_m, y_m, theta_rad]``
            in the odometry frame, or ``None`` when the log has none.
        laser_offset: ``(3,)`` float64 laser pose in the robot frame ``[x_m, y_m, theta_rad]``.
        source: Where the record came from, ``"path:line"``, for error messages.
        odom_break: True when the reader found the odometry discontinuous just before this
            scan (a jump, or a record in a second odometry frame): the odometry delta from
            the previous scan is meaningless, and no odometry factor may span it.

    Raises:
        ScanError: ranges and bearings are not 1-D arrays of one length, a bearing is not
            finite, or ``laser_offset`` / ``odom_pose`` is not a finite ``(3,)`` pose.
    """

    stamp_s: float
    ranges_m: FloatArray
    angles_rad: FloatArray
    range_min_m: float
    range_max_m: float
    odom_pose: FloatArray | None
    laser_offset: FloatArray = field(default_factory=lambda: np.zeros(3))
    source: str = "<memory>"
    odom_break: bool = False

    def __post_init__(self) -> None:
        ranges = np.asarray(self.ranges_m, dtype=np.float64)
        angles = np.asarray(self.angles_rad, dtype=np.float64)
        if ranges.ndim != 1 or ranges.shape != angles.shape:
            raise ScanError(
                f"{self.source}: ranges_m {ranges.shape} and angles_rad {angles.shape} "
                "must be 1-D arrays of the same length"
            )
        if not np.isfinite(angles).all():
            raise ScanError(
                f"{self.source}: bearing {int(np.argmin(np.isfinite(angles)))} of "
                f"{angles.shape[0]} is not finite; every beam needs a finite bearing"
            )
        object.__setattr__(self, "ranges_m", ranges)
        object.__setattr__(self, "angles_rad", angles)
        object.__setattr__(self, "laser_offset", _pose3(self.laser_offset, "laser_offset", self))
        if self.odom_pose is not None:
            object.__setattr__(self, "odom_pose", _pose3(self.odom_pose, "odom_pose", self))

    @property
    def n_beams(self) -> int:
        """Number of beams ``N``."""
        return int(self.ranges_m.shape[0])

    def valid_mask(self) -> NDArray[np.bool_]:
        """``(N,)`` bool: finite beams with ``range_min_m < r < range_max_m``."""
        r = self.ranges_m
        with np.errstate(invalid="ignore"):
            return np.isfinite(r) & (r > self.range_min_m) & (r < self.range_max_m)

    def points_xy(self, mask: NDArray[np.bool_] | None = None) -> FloatArray:
        """Valid beam endpoints as ``(K, 2)`` float64 metres in the **robot** frame.

        Args:
            mask: ``(N,)`` bool selecting beams; defaults to :meth:`valid_mask`.

        The laser offset is applied: ``p_robot = R(off_theta) p_laser + off_xy``.
        """
        m = self.valid_mask() if mask is None else mask
        r = self.ranges_m[m]
        a = self.angles_rad[m] + self.laser_offset[2]
        out = np.empty((r.shape[0], 2))
        out[:, 0] = r * np.cos(a) + self.laser_offset[0]
        out[:, 1] = r * np.sin(a) + self.laser_offset[1]
        return out
