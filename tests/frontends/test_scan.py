"""LaserScan validation and timestamp ordering (issue 12)."""

from __future__ import annotations

import math
import re
from typing import Any

import numpy as np
import pytest

from frontends.scan import LaserScan, StampReport, order_by_stamp
from iceg_common.errors import IcegError, LogFormatError, ScanError

ANGLES = np.linspace(-math.pi / 2, math.pi / 2, 5)


def _scan(stamp: float = 0.0, **kw: Any) -> LaserScan:
    args: dict[str, object] = {
        "stamp_s": stamp,
        "ranges_m": np.ones(5),
        "angles_rad": ANGLES,
        "range_min_m": 0.0,
        "range_max_m": 30.0,
        "odom_pose": np.zeros(3),
        "source": f"log.clf:{int(stamp)}",
    }
    args.update(kw)
    return LaserScan(**args)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("field", "value", "message"),
    [
        ("angles_rad", np.where(np.arange(5) == 2, np.nan, ANGLES), "bearing 2 of 5 is not finite"),
        ("laser_offset", [0.1, np.nan, 0.0], "laser_offset must be a finite (3,) pose"),
        ("odom_pose", [0.0, 0.0, np.inf], "odom_pose must be a finite (3,) pose"),
        ("laser_offset", [0.1, 0.0], "laser_offset must be a finite (3,) pose"),
        ("ranges_m", np.ones(4), "must be 1-D arrays of the same length"),
    ],
)
def test_inconsistent_scan_raises_scan_error(field: str, value: object, message: str) -> None:
    overrides: dict[str, Any] = {field: value}
    with pytest.raises(ScanError, match=re.escape(message)) as info:
        _scan(**overrides)
    assert isinstance(info.value, IcegError)
    assert str(info.value).startswith("log.clf:0: ")


def test_odom_break_defaults_to_false() -> None:
    assert _scan().odom_break is False
    assert _scan(odom_break=True).odom_break is True


def test_without_odometry_drops_the_pose_and_the_break_only() -> None:
    scan = _scan(3.0, odom_pose=[1.0, 2.0, 0.5], odom_break=True, laser_offset=[0.2, 0.0, 0.1])
    bare = scan.without_odometry()
    assert bare.odom_pose is None and bare.odom_break is False
    assert (bare.stamp_s, bare.source, bare.range_max_m) == (3.0, "log.clf:3", 30.0)
    np.testing.assert_array_equal(bare.ranges_m, scan.ranges_m)
    np.testing.assert_array_equal(bare.angles_rad, scan.angles_rad)
    np.testing.assert_array_equal(bare.laser_offset, [0.2, 0.0, 0.1])
    assert scan.odom_break is True and scan.odom_pose is not None  # the scan is unchanged


def _order(stamps: list[float], policy: str, window: int = 100) -> tuple[list[float], StampReport]:
    report = StampReport(policy=policy)  # type: ignore[arg-type]
    items = [(i, _scan(t)) for i, t in enumerate(stamps)]
    out = list(order_by_stamp(items, report, window))
    return [s.stamp_s for _, s in out], report


def test_sort_policy_reorders_stably_and_counts() -> None:
    stamps, report = _order([1.0, 3.0, 2.0, 3.0, 4.0, 0.5], "sort")
    assert stamps == [0.5, 1.0, 2.0, 3.0, 3.0, 4.0]
    assert (report.out_of_order, report.duplicates) == (2, 1)
    assert report.first == "log.clf:2"
    # equal stamps keep file order: the tags of the two 3.0 scans are 1 then 3
    report2 = StampReport()
    tags = [
        i for i, _ in order_by_stamp([(i, _scan(t)) for i, t in enumerate([3.0, 3.0])], report2, 10)
    ]
    assert tags == [0, 1]


def test_refuse_policy_names_the_scan() -> None:
    with pytest.raises(LogFormatError, match=r"log.clf:2: timestamp 2.0 is earlier than"):
        _order([1.0, 3.0, 2.0], "refuse")
    with pytest.raises(LogFormatError, match=r"log.clf:3: timestamp 3.0 is the same as"):
        _order([1.0, 2.0, 3.0, 3.0], "refuse")


def test_disorder_beyond_the_window_is_refused() -> None:
    with pytest.raises(LogFormatError, match="more than 2 scans out of order"):
        _order([5.0, 6.0, 7.0, 8.0, 1.0], "sort", window=2)
