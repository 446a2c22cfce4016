"""Odometry read at a scan's stamp plus a time offset (laser-odometry latency).

A scan is often stamped when it arrives, not when its beams were measured: a SICK LMS200
sends its 361 ranges over a serial line for about 0.2 s, and a rotating lidar's driver may
stamp the end of its sweep. The odometry read at the stamp is then the robot's pose a
little after the scan was taken, which while turning is off by the turn rate times the
delay. :func:`shift_odometry` reads each scan's odometry at ``stamp + offset`` instead,
interpolated in SE(2) between the log's own odometry samples (the scans' ``odom_pose``);
:func:`iceg.odometry_timing.estimate_odometry_time_offset` measures the offset from a run.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Iterable, Iterator
from dataclasses import replace

import numpy as np

from frontends.scan import LaserScan
from iceg_common.errors import ConfigError
from iceg_common.se2 import wrap_angle


def shift_odometry(scans: Iterable[LaserScan], offset_s: float) -> Iterator[LaserScan]:
    """The scans with their odometry read at ``stamp_s + offset_s``.

    Each scan's ``odom_pose`` becomes the SE(2) interpolation (position linear, heading along
    the shorter arc) of the two odometry samples around ``stamp_s + offset_s``, taken from the
    scans of the same odometry segment (a scan without odometry or with ``odom_break`` starts
    a new one). A time beyond a segment's first or last sample takes that sample's pose.
    Streaming: scans come out in input order, at most ``offset_s`` of log time after they go
    in; a scan without odometry comes out unchanged.

    Args:
        scans: Scans in non-decreasing stamp order (as :func:`frontends.open_log` yields them).
        offset_s: Seconds added to each stamp to read the odometry; negative when the scans
            were measured before their stamps. 0 passes the scans through.

    Raises:
        ConfigError: ``offset_s`` is not finite.
    """
    if not math.isfinite(offset_s):
        raise ConfigError(
            f"odometry time offset must be a finite number of seconds, not {offset_s}"
        )
    if offset_s == 0.0:
        yield from scans
        return
    samples: deque[LaserScan] = deque()  # the current segment's odometry, oldest needed first
    pending: deque[LaserScan] = deque()  # scans of the segment not yet yielded
    for scan in scans:
        if scan.odom_pose is None or scan.odom_break:
            while pending:
                yield _shifted(pending.popleft(), samples, offset_s)
            samples.clear()
            if scan.odom_pose is None:
                yield scan
                continue
        samples.append(scan)
        pending.append(scan)
        while pending and pending[0].stamp_s + offset_s <= scan.stamp_s:
            yield _shifted(pending.popleft(), samples, offset_s)
        oldest_needed = (pending[0] if pending else scan).stamp_s + min(offset_s, 0.0)
        while len(samples) >= 2 and samples[1].stamp_s <= oldest_needed:
            samples.popleft()
    while pending:
        yield _shifted(pending.popleft(), samples, offset_s)


def _shifted(scan: LaserScan, samples: deque[LaserScan], offset_s: float) -> LaserScan:
    """``scan`` with the odometry of ``samples`` (same segment, stamps ascending) at its stamp
    plus ``offset_s``."""
    t = scan.stamp_s + offset_s
    after = next((k for k, s in enumerate(samples) if s.stamp_s >= t), None)
    if after is None:
        return replace(scan, odom_pose=np.array(samples[-1].odom_pose, dtype=np.float64))
    b = samples[after]
    if after == 0 or b.stamp_s == t:
        return replace(scan, odom_pose=np.array(b.odom_pose, dtype=np.float64))
    a = samples[after - 1]
    pa = np.asarray(a.odom_pose, dtype=np.float64)
    pb = np.asarray(b.odom_pose, dtype=np.float64)
    f = (t - a.stamp_s) / (b.stamp_s - a.stamp_s)
    heading = wrap_angle(pa[2] + f * wrap_angle(pb[2] - pa[2]))
    pose = np.array([pa[0] + f * (pb[0] - pa[0]), pa[1] + f * (pb[1] - pa[1]), heading])
    return replace(scan, odom_pose=pose)
