"""A real log's scans degraded as a lesser scanner would measure them (generality probes)."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from frontends.scan import LaserScan
from frontends.simulate import ScannerDegradation, degrade_scans
from frontends.simulate.raycast import dropped_beams


def _scan(ranges: list[float] | np.ndarray, stamp_s: float = 0.0) -> LaserScan:
    r = np.asarray(ranges, dtype=np.float64)
    return LaserScan(
        stamp_s=stamp_s,
        ranges_m=r,
        angles_rad=np.linspace(-math.pi / 2, math.pi / 2, r.shape[0]),
        range_min_m=0.0,
        range_max_m=81.91,
        odom_pose=np.array([stamp_s, 0.0, 0.0]),
        laser_offset=np.array([0.1, 0.0, 0.0]),
        source=f"log:{int(stamp_s)}",
    )


def test_no_degradation_keeps_every_scan_as_it_is() -> None:
    scans = [_scan(np.full(361, 3.0), t) for t in range(4)]
    kept, out = degrade_scans(scans, ScannerDegradation())
    assert kept.tolist() == [0, 1, 2, 3]
    for a, b in zip(scans, out, strict=True):
        assert np.array_equal(a.ranges_m, b.ranges_m)
        assert np.array_equal(a.angles_rad, b.angles_rad)
        assert (a.stamp_s, a.range_max_m, a.source) == (b.stamp_s, b.range_max_m, b.source)


def test_every_nth_scan_is_kept_with_its_stamp_and_odometry() -> None:
    scans = [_scan(np.full(10, 3.0), t) for t in range(10)]
    kept, out = degrade_scans(scans, ScannerDegradation(every_nth=3))
    assert kept.tolist() == [0, 3, 6, 9]
    assert [s.stamp_s for s in out] == [0.0, 3.0, 6.0, 9.0]
    assert [float(s.odom_pose[0]) for s in out] == [0.0, 3.0, 6.0, 9.0]  # type: ignore[index]


def test_returns_beyond_the_reach_become_no_returns() -> None:
    scan = _scan([1.0, 7.99, 8.0, 9.0, 81.91, math.inf])
    _, (out,) = degrade_scans([scan], ScannerDegradation(reach_m=8.0))
    assert out.ranges_m.tolist() == [1.0, 7.99, math.inf, math.inf, 81.91, math.inf]
    assert out.valid_mask().tolist() == [True, True, False, False, False, False]
    assert out.range_max_m == 81.91  # the declared maximum stays unless asked
    _, (declared,) = degrade_scans([scan], ScannerDegradation(reach_m=8.0, declare_reach=True))
    assert declared.range_max_m == 8.0
    assert declared.valid_mask().tolist() == [True, True, False, False, False, False]


def test_a_narrower_field_of_view_keeps_the_beams_within_it() -> None:
    ranges = np.arange(361, dtype=np.float64) / 100.0 + 1.0  # 0.5° apart over 180°
    _, (out,) = degrade_scans([_scan(ranges)], ScannerDegradation(fov_deg=120.0))
    # beams -60° .. +60°: indices 60 .. 300 of the 0.5° grid starting at -90°
    assert out.n_beams == 241
    assert np.array_equal(out.ranges_m, ranges[60:301])
    assert math.degrees(out.angles_rad[0]) == pytest.approx(-60.0)
    assert math.degrees(out.angles_rad[-1]) == pytest.approx(60.0)


def test_range_noise_has_the_asked_spread_and_leaves_no_returns_alone() -> None:
    n = 20_000
    ranges = np.full(n, 5.0)
    ranges[::10] = 81.91  # no returns
    scans = [_scan(ranges)]
    _, (out,) = degrade_scans(scans, ScannerDegradation(range_sigma_m=0.02), seed=3)
    returns = ranges < 81.91
    err = out.ranges_m[returns] - 5.0
    assert abs(err.mean()) < 4 * 0.02 / math.sqrt(err.size)
    assert err.std() == pytest.approx(0.02, rel=0.03)
    assert np.array_equal(out.ranges_m[~returns], ranges[~returns])
    _, (again,) = degrade_scans(scans, ScannerDegradation(range_sigma_m=0.02), seed=3)
    _, (other,) = degrade_scans(scans, ScannerDegradation(range_sigma_m=0.02), seed=4)
    assert np.array_equal(out.ranges_m, again.ranges_m)
    assert not np.array_equal(out.ranges_m, other.ranges_m)


def test_dropouts_lose_the_expected_fraction_in_runs() -> None:
    n, fraction, run = 200_000, 0.05, 3
    _, (out,) = degrade_scans(
        [_scan(np.full(n, 4.0))],
        ScannerDegradation(dropout_fraction=fraction, dropout_run_beams=run),
        seed=1,
    )
    lost = ~out.valid_mask()
    # a beam is lost when a run starts at it or at one of the run - 1 beams before it
    expected = 1.0 - (1.0 - fraction / run) ** run
    assert lost.mean() == pytest.approx(expected, abs=4 * math.sqrt(expected / n))
    edges = np.diff(np.concatenate([[0], lost.astype(np.int64), [0]]))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    inside = ends < n  # a run at the scan's end may be cut short
    assert (ends - starts)[inside].min() == run  # runs of three beams (overlapping ones merge)


def test_the_simulator_and_the_degradation_draw_dropouts_alike() -> None:
    a = dropped_beams(500, 0.1, 2, np.random.default_rng(9))
    b = dropped_beams(500, 0.1, 2, np.random.default_rng(9))
    assert np.array_equal(a, b) and 0 < a.sum() < 500


def test_a_degradation_refuses_settings_without_meaning() -> None:
    with pytest.raises(ValidationError):
        ScannerDegradation(every_nth=0)
    with pytest.raises(ValidationError):
        ScannerDegradation(fov_deg=400.0)
    with pytest.raises(ValidationError):
        ScannerDegradation(dropout_fraction=1.0)
