"""The laser scan record every front-end produces."""

from __future__ import annotations

import heapq
import logging
import math
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field, replace
from typing import Literal, TypeVar

import numpy as np
from numpy.typing import NDArray

from iceg_common.errors import LogFormatError, ScanError

logger = logging.getLogger(__name__)

T = TypeVar("T")

FloatArray = NDArray[np.float64]


def _pose3(value: object, what: str, scan: LaserScan) -> FloatArray:
    try:
        pose = np.asarray(value, dtype=np.float64)
    except (TypeError, ValueError):
        raise ScanError(f"{scan.source}: {what} is not numeric: {value!r}") from None
    # The finiteness test on the three numbers as floats (two poses per scan read; numpy's
    # calls on a (3,) array cost several times as much), the same answer.
    if pose.shape != (3,) or not all(map(math.isfinite, pose.tolist())):
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

    def without_odometry(self) -> LaserScan:
        """This scan as a log without odometry would give it: ``odom_pose=None`` and no
        ``odom_break`` (a break has no meaning without odometry). Ranges, bearings, stamp,
        laser mounting and source are kept."""
        return replace(self, odom_pose=None, odom_break=False)

    def mirrored(self) -> LaserScan:
        """This scan with its beams mirrored in the laser frame (bearing ``a -> -a``, the
        beams reversed so that bearings increase): how a laser mounted upside down, or one
        whose beams were written clockwise, is read the right way round. Twice gives the
        scan back bit for bit. Stamp, odometry, laser mounting and source are kept."""
        return replace(self, ranges_m=self.ranges_m[::-1].copy(), angles_rad=-self.angles_rad[::-1])

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


#: Timestamp policies of the readers: reorder out-of-order scans, or refuse the log.
StampPolicy = Literal["sort", "refuse"]


@dataclass
class StampReport:
    """What a reader found in a log's timestamps (filled during iteration).

    Attributes:
        policy: ``"sort"`` or ``"refuse"``.
        out_of_order: Scans whose stamp is earlier than an earlier scan's (reordered).
        duplicates: Scans whose stamp equals the latest earlier stamp (kept, file order).
        first: ``source`` (``path:line``) of the first out-of-order or duplicate scan.
        odometry_breaks: ``(source, reason)`` of every scan with ``odom_break``.
    """

    policy: StampPolicy = "sort"
    out_of_order: int = 0
    duplicates: int = 0
    first: str | None = None
    odometry_breaks: list[tuple[str, str]] = field(default_factory=list)

    def as_dict(self) -> dict[str, object]:
        """JSON-ready summary (``odometry_breaks`` as a count plus the first few)."""
        return {
            "policy": self.policy,
            "out_of_order": self.out_of_order,
            "duplicates": self.duplicates,
            "first": self.first,
            "odometry_breaks": len(self.odometry_breaks),
            "first_odometry_breaks": [f"{s}: {r}" for s, r in self.odometry_breaks[:5]],
        }


def order_by_stamp(
    items: Iterable[tuple[T, LaserScan]], report: StampReport, window: int
) -> Iterator[tuple[T, LaserScan]]:
    """Yield ``(tag, scan)`` pairs in timestamp order (stable: equal stamps keep file order).

    Out-of-order and duplicate stamps are counted in ``report`` and the first is logged with
    its ``path:line``. Policy ``"refuse"`` raises at the first out-of-order or duplicate stamp;
    ``"sort"`` reorders through a buffer of ``window`` scans (streaming, bounded memory).

    Raises:
        LogFormatError: policy ``"refuse"`` and a stamp not after the previous one, or a scan
            more than ``window`` scans out of place.
    """
    heap: list[tuple[float, int, T, LaserScan]] = []
    latest = -math.inf
    emitted = -math.inf
    for seq, (tag, scan) in enumerate(items):
        t = scan.stamp_s
        if t <= latest:
            _note_disorder(report, scan, latest)
        latest = max(latest, t)
        heapq.heappush(heap, (t, seq, tag, scan))
        if len(heap) > window:
            t0, _, tag0, scan0 = heapq.heappop(heap)
            if t0 < emitted:
                raise LogFormatError(
                    f"{scan0.source}: timestamp {t0!r} is more than {window} scans out of "
                    "order; the log cannot be sorted while streaming (sort it first)"
                )
            emitted = t0
            yield tag0, scan0
    while heap:
        _, _, tag0, scan0 = heapq.heappop(heap)
        yield tag0, scan0


def _note_disorder(report: StampReport, scan: LaserScan, latest: float) -> None:
    what = "the same as" if scan.stamp_s == latest else "earlier than"
    if report.policy == "refuse":
        raise LogFormatError(
            f"{scan.source}: timestamp {scan.stamp_s!r} is {what} an earlier scan's "
            f"({latest!r}); scans must have increasing timestamps (policy 'refuse'; use "
            "stamps='sort', CLI --stamps sort, to reorder them)"
        )
    if scan.stamp_s == latest:
        report.duplicates += 1
    else:
        report.out_of_order += 1
    if report.first is None:
        report.first = scan.source
        logger.warning(
            "%s: timestamp %r is %s an earlier scan's (%r); scans are reordered by timestamp "
            "(policy 'sort'; equal stamps keep file order)",
            scan.source,
            scan.stamp_s,
            what,
            latest,
        )
