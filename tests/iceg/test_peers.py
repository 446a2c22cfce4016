"""Other matchers behind the :class:`~iceg.matching.Matcher` protocol (``matching.method``)."""

from __future__ import annotations

import importlib
import math

import numpy as np
import pytest

from frontends.simulate import office_world, simulate, simulate_pair
from iceg.config import config_from_dict
from iceg.evaluation import position_errors
from iceg.features import extract
from iceg.matching import IceMatcher, MatchBounds, Matcher, MatchingConfig
from iceg.matching.peers import (
    METHODS,
    available_methods,
    hessian_covariance,
    make_matcher,
    matrix_to_pose,
    pose_to_matrix,
)
from iceg.matching.plicp import INLIER_DISTANCE_M, PlIcpMatcher, overlap, reference_points
from iceg.slam import Slam
from iceg.types import ScanFeatures
from iceg_common import se2
from iceg_common.errors import ConfigError

#: Largest position error (m) of each method on the office pair, from a prediction 0.25 m
#: and 4.6 deg off (point-to-point peers sample walls differently in the two scans).
TOLERANCE_M = {
    "ice": 0.02,
    "plicp": 0.03,
    "small_gicp": 0.15,
    "kiss_icp": 0.1,
    "open3d_point": 0.15,
    "open3d_plane": 0.08,
}


@pytest.fixture(scope="module")
def pair() -> tuple[ScanFeatures, ScanFeatures, np.ndarray]:
    """Features of two office scans 0.6 m / 10 deg apart and their true relative pose."""
    a, b = simulate_pair(office_world(), [2.0, 2.0, 0.1], [2.5, 2.3, 0.27], seed=5)
    assert a.odom_pose is not None and b.odom_pose is not None
    return extract(a), extract(b), se2.between(a.odom_pose, b.odom_pose)


def test_every_method_is_a_config_value_and_ice_is_the_default() -> None:
    assert MatchingConfig().method == "ice"
    assert set(METHODS) == {
        "ice",
        "plicp",
        "small_gicp",
        "kiss_icp",
        "open3d_point",
        "open3d_plane",
    }
    for m in METHODS:
        assert MatchingConfig(method=m).method == m
    assert isinstance(make_matcher(MatchingConfig()), IceMatcher)
    assert isinstance(make_matcher(MatchingConfig(method="plicp")), PlIcpMatcher)
    assert isinstance(make_matcher(), Matcher)
    with pytest.raises(ConfigError, match=r"matching\.method"):
        config_from_dict({"matching": {"method": "icp"}})


@pytest.mark.parametrize("method", METHODS)
def test_method_recovers_the_relative_pose(
    method: str, pair: tuple[ScanFeatures, ScanFeatures, np.ndarray]
) -> None:
    if method not in available_methods():
        pytest.skip(f"{method}: library not installed (extra 'peers')")
    fa, fb, truth = pair
    pred = truth + np.array([0.2, -0.15, 0.08])
    res = make_matcher(MatchingConfig(method=method)).match(
        fb, fa, pred, MatchBounds.local(0.5, 15.0)
    )
    assert res.success, res.reason
    err = se2.between(truth, res.pose)
    assert math.hypot(err[0], err[1]) < TOLERANCE_M[method]
    assert abs(math.degrees(err[2])) < 1.0
    cov = res.cov
    assert np.allclose(cov, cov.T)
    evals = np.linalg.eigvalsh(cov)
    assert np.all(evals > 0) and math.sqrt(evals[-1]) < 0.1  # positive definite, informative
    assert 0.35 <= res.correlation <= 1.0  # the overlap for point matchers


def test_point_matcher_fails_far_from_the_truth(
    pair: tuple[ScanFeatures, ScanFeatures, np.ndarray],
) -> None:
    """Bounds hold: a prediction 2 m off with 0.3 m bounds cannot give a trusted match."""
    fa, fb, truth = pair
    res = PlIcpMatcher().match(
        fb, fa, truth + np.array([2.0, 0.0, 0.0]), MatchBounds.local(0.3, 5.0)
    )
    assert not res.success
    assert np.all(np.isnan(res.cov))
    assert res.reason


def test_reference_without_points_is_sampled_along_its_segments() -> None:
    ref = ScanFeatures.empty()
    ref = ScanFeatures(
        **{
            **ref.__dict__,
            "seg_endpoints": np.array([[[0.0, 0.0], [1.0, 0.0]]]),
            "seg_lines": np.array([[math.pi / 2, 0.0]]),
            "seg_cov": np.zeros((1, 2, 2)),
            "seg_point_range": np.array([[-1, -1]]),
        }
    )
    pts = reference_points(ref)
    assert pts.shape == (21, 2)  # every 5 cm, both ends
    assert np.allclose(pts[:, 1], 0.0)
    assert np.allclose(np.diff(pts[:, 0]), 0.05)


def test_hessian_covariance_takes_the_planar_block() -> None:
    h = np.diag([1.0, 2.0, 4.0, 100.0, 400.0, 9.0])  # (rx, ry, rz, tx, ty, tz)
    cov = hessian_covariance(h, error=5.0, n_inliers=13)  # reduced chi-square 2*5/10 = 1
    assert np.allclose(cov, np.diag([0.01, 0.0025, 0.25]))
    assert np.all(np.isinf(hessian_covariance(np.zeros((6, 6)), 1.0, 10)))


def test_pose_matrix_round_trip() -> None:
    p = np.array([1.5, -2.0, 2.9])
    assert np.allclose(matrix_to_pose(pose_to_matrix(p)), p)


def test_missing_library_is_a_config_error(monkeypatch: pytest.MonkeyPatch) -> None:
    real = importlib.import_module

    def no_gicp(name: str, *args: object) -> object:
        if name == "small_gicp":
            raise ImportError("No module named 'small_gicp'")
        return real(name, *args)

    monkeypatch.setattr(importlib, "import_module", no_gicp)
    with pytest.raises(ConfigError, match=r"iceg\[peers\]"):
        make_matcher(MatchingConfig(method="small_gicp"))
    assert "small_gicp" not in available_methods()


def test_plicp_drives_the_whole_pipeline() -> None:
    """The same graph back-end with PL-ICP: the first 150 office scans within 5 cm."""
    run = simulate(office_world(), seed=2)
    slam = Slam(config_from_dict({"matching": {"method": "plicp"}}))
    assert isinstance(slam.matcher, PlIcpMatcher)
    for scan in run.scans[:150]:
        slam.process(scan)
    result = slam.finish()
    assert position_errors(result.poses, run.true_poses[:150]).rmse_m < 0.05
    assert sum(result.match_failures.values()) <= 2


def test_point_overlap_counts_the_points_closer_than_the_inlier_distance() -> None:
    # Points 0.5 m apart on a line, moved by a pose; the reference holds every point at its
    # moved place, each one offset across the line by 0.0, 0.1, 0.2 or 0.3 m in turn: the
    # first two offsets are within INLIER_DISTANCE_M (0.15 m), the others not (the nearest
    # other reference point is farther), so half the points count.
    assert INLIER_DISTANCE_M == 0.15
    pose = np.array([1.0, -2.0, 0.7])
    pts = np.column_stack([np.arange(40) * 0.5, np.zeros(40)])
    offsets = np.tile([0.0, 0.1, 0.2, 0.3], 10)
    ref = se2.transform_points(pose, pts + np.column_stack([np.zeros(40), offsets]))
    assert overlap(pts, ref, pose) == 0.5
    assert overlap(pts, ref[:0], pose) == 0.0
