"""Odometry read at the scan stamp plus an offset (frontends.odometry_shift)."""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator

import numpy as np
import pytest

from frontends.odometry_shift import shift_odometry
from frontends.scan import LaserScan
from iceg_common.errors import ConfigError


def _scan(t: float, pose: list[float] | None, odom_break: bool = False) -> LaserScan:
    return LaserScan(
        stamp_s=t,
        ranges_m=np.ones(3),
        angles_rad=np.array([-0.1, 0.0, 0.1]),
        range_min_m=0.1,
        range_max_m=10.0,
        odom_pose=None if pose is None else np.array(pose, dtype=np.float64),
        odom_break=odom_break,
    )


def _linear(t: float) -> list[float]:
    """A pose linear in time (SE(2) interpolation of two samples is then exact)."""
    return [1.0 * t, -0.2 * t, 0.3 * t]


STAMPS = [0.1 * k for k in range(10)]


@pytest.mark.parametrize("offset_s", [-0.25, -0.05, 0.05, 0.25])
def test_odometry_is_read_at_the_shifted_stamp(offset_s: float) -> None:
    scans = [_scan(t, _linear(t)) for t in STAMPS]
    out = list(shift_odometry(scans, offset_s))
    assert [s.stamp_s for s in out] == STAMPS  # order and stamps kept
    for s in out:
        t = min(max(s.stamp_s + offset_s, STAMPS[0]), STAMPS[-1])  # held at the ends
        assert s.odom_pose is not None
        np.testing.assert_allclose(s.odom_pose, _linear(t), atol=1e-12)


def test_heading_is_interpolated_along_the_shorter_arc() -> None:
    scans = [_scan(0.0, [0.0, 0.0, 3.1]), _scan(1.0, [1.0, 0.0, -3.1])]
    first = next(shift_odometry(scans, 0.5))
    assert first.odom_pose is not None
    # halfway from 3.1 to -3.1 through pi, not through 0
    assert abs(abs(first.odom_pose[2]) - math.pi) < 1e-12
    assert first.odom_pose[0] == pytest.approx(0.5)


def test_no_interpolation_across_an_odometry_break_or_a_scan_without_odometry() -> None:
    scans = [
        _scan(0.0, [0.0, 0.0, 0.0]),
        _scan(0.1, [0.1, 0.0, 0.0]),
        _scan(0.2, [50.0, 7.0, 1.0], odom_break=True),  # a new odometry frame
        _scan(0.3, [50.1, 7.0, 1.0]),
        _scan(0.4, None),
        _scan(0.5, [9.0, 9.0, 0.0]),
    ]
    expected: dict[float, list[list[float] | None]] = {
        -0.05: [[0, 0, 0], [0.05, 0, 0], [50, 7, 1], [50.05, 7, 1], None, [9, 9, 0]],
        0.05: [[0.05, 0, 0], [0.1, 0, 0], [50.05, 7, 1], [50.1, 7, 1], None, [9, 9, 0]],
    }
    for offset_s, want in expected.items():
        ahead = list(shift_odometry(scans, offset_s))
        for got, pose in zip(ahead, want, strict=True):
            if pose is None:
                assert got.odom_pose is None
            else:
                assert got.odom_pose is not None
                np.testing.assert_allclose(got.odom_pose, pose, atol=1e-12)
    assert [s.odom_break for s in ahead] == [s.odom_break for s in scans]


def test_zero_offset_passes_the_scans_through_and_a_non_finite_one_is_refused() -> None:
    scans = [_scan(t, _linear(t)) for t in STAMPS]
    assert all(a is b for a, b in zip(shift_odometry(scans, 0.0), scans, strict=True))
    with pytest.raises(ConfigError, match="finite"):
        next(shift_odometry(scans, math.nan))


def test_streams_an_endless_log() -> None:
    def endless() -> Iterator[LaserScan]:
        for k in itertools.count():
            yield _scan(0.1 * k, _linear(0.1 * k))

    out = list(itertools.islice(shift_odometry(endless(), 0.25), 5))
    assert out[4].odom_pose is not None
    np.testing.assert_allclose(out[4].odom_pose, _linear(0.65), atol=1e-12)
