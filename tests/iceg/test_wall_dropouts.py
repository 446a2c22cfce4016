"""Returns a scanner loses on walls: patches found by hand, random losses told from dark
surfaces on the simulated office, and a run that reads random losses as dropouts and holds
its map where the default reading bends it."""

from __future__ import annotations

import logging
import math
from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from frontends import LaserScan
from frontends.simulate import LaserModel, simulate_scenario
from iceg.config import IcegConfig
from iceg.evaluation import position_errors
from iceg.features.config import FeatureConfig
from iceg.features.extract import extract_beams
from iceg.pipeline import measure_scanner, run_log
from iceg.scan_store import ScanStore
from iceg.wall_dropouts import (
    PATCH_MAX_GAP_M,
    lost_again,
    patch_middles,
    wall_dropouts,
    with_measured_dropouts,
)
from iceg_common import se2
from tests.conftest import shared_file

#: 181 beams over 180°, a straight wall 2 m ahead (x = 2).
ANGLES = np.radians(np.linspace(-90.0, 90.0, 181))


def _wall_scan(lost: list[int], wall_m: float = 2.0) -> LaserScan:
    """Beams that meet a wall ``wall_m`` ahead (the line x = wall_m, robot frame) within 6 m
    return it; ``lost`` beams return nothing."""
    ranges = np.full(ANGLES.shape[0], np.inf)
    ahead = np.abs(ANGLES) < math.acos(wall_m / 6.0)
    ranges[ahead] = wall_m / np.cos(ANGLES[ahead])
    ranges[lost] = np.inf
    return LaserScan(0.0, ranges, ANGLES, 0.0, 20.0, np.zeros(3))


def test_patches_by_hand() -> None:
    cfg = FeatureConfig()
    # beams 90-92 (bearings 0°, 1°, 2°) lose the wall: a patch between the returns of beams
    # 89 and 93, 0.14 m apart on the wall; its middle is their midpoint
    middles = patch_middles(extract_beams(_wall_scan([90, 91, 92]), cfg), cfg)
    y = 2.0 * np.tan(np.radians([-1.0, 3.0]))
    np.testing.assert_allclose(middles, [[2.0, y.mean()]], atol=1e-12)
    # one lost beam is no patch (the segmentation merges across it)
    assert patch_middles(extract_beams(_wall_scan([90]), cfg), cfg).shape == (0, 2)
    # a run whose returns lie wider apart than a doorway's least width is an opening: beams
    # 80-95 (15° at 2 m: 0.57 m between the returns of beams 79 and 96)
    wide = list(range(80, 96))
    assert 2.0 * (np.tan(np.radians(6.0)) + np.tan(np.radians(11.0))) > PATCH_MAX_GAP_M
    assert patch_middles(extract_beams(_wall_scan(wide), cfg), cfg).shape == (0, 2)
    # beyond the usable range (less the end-of-wall test's margin) nothing is lost
    near_limit = FeatureConfig(range_max_m=2.1)
    assert patch_middles(extract_beams(_wall_scan([90, 91, 92]), near_limit), near_limit).shape == (
        0,
        2,
    )


def test_a_patch_is_followed_into_the_next_scan_by_hand() -> None:
    cfg = FeatureConfig()
    first = _wall_scan([90, 91, 92])
    middles = patch_middles(extract_beams(first, cfg), cfg)
    # the robot moved 0.5 m toward the wall: the patch's middle lies 1.5 m ahead, at the
    # bearing of beam 91 (1°) seen from 2 m, now arctan(0.0349 / 1.5) = 1.33° (beam 91)
    step = np.array([0.5, 0.0, 0.0])
    moved = se2.transform_points(se2.inverse(step), middles)
    dark = _wall_scan([88, 89, 90, 91, 92], wall_m=1.5)  # the surface is dark
    seen, lost = lost_again(extract_beams(dark, cfg), moved, cfg)
    assert seen.tolist() == [True] and lost.tolist() == [True]
    clear = _wall_scan([10, 11], wall_m=1.5)  # the wall returns there now
    seen, lost = lost_again(extract_beams(clear, cfg), moved, cfg)
    assert seen.tolist() == [True] and lost.tolist() == [False]
    # behind the robot: not in the 180° field of view
    seen, lost = lost_again(extract_beams(clear, cfg), np.array([[-1.0, 0.0]]), cfg)
    assert seen.tolist() == [False] and lost.tolist() == [False]


def _dark_patches(scans: list[LaserScan], truth: np.ndarray, spots: np.ndarray) -> list[LaserScan]:
    """The scans with every return within 0.12 m of one of the world points ``spots``
    ``(S, 2)`` lost: dark patches on the walls, lost whenever they are seen."""
    out = []
    for scan, pose in zip(scans, truth, strict=True):
        laser = se2.compose(pose, scan.laser_offset)
        r = scan.ranges_m
        finite = np.isfinite(r) & (r < scan.range_max_m)
        local = np.c_[r * np.cos(scan.angles_rad), r * np.sin(scan.angles_rad)]
        world = se2.transform_points(laser, np.where(finite[:, None], local, 0.0))
        near = np.min(np.hypot(*(world[:, None, :] - spots[None]).transpose(2, 0, 1)), axis=1)
        dark = finite & (near < 0.12)
        out.append(replace(scan, ranges_m=np.where(dark, np.inf, r)))
    return out


def test_random_losses_are_told_from_dark_surfaces() -> None:
    cfg = FeatureConfig()
    clean = simulate_scenario("office", seed=0)
    assert not wall_dropouts(clean.scans, cfg).rule_on
    # 5 % of the beams lost at random, in runs of three: often, and gone in the next scan
    noisy = simulate_scenario(
        "office", seed=0, laser=LaserModel(dropout_fraction=0.05, dropout_run_beams=3)
    )
    random = wall_dropouts(noisy.scans, cfg)
    assert random.rule_on and random.patches_per_1000 > 5.0
    assert random.recurring < 0.1 * random.followed
    # dark spots on the walls every 1.5 m along the office's walls: as often, but where the
    # scanner looks again they are lost again, so their edges are landmarks like any other
    spots = np.concatenate(
        [
            a + np.outer(np.arange(0.75, np.hypot(*(b - a)), 1.5), (b - a) / np.hypot(*(b - a)))
            for a, b in clean.world.walls_at(None)
        ]
    )
    dark = wall_dropouts(_dark_patches(clean.scans, np.asarray(clean.true_poses), spots), cfg)
    assert dark.patches_per_1000 > 2.5 and dark.recurring > 0.5 * dark.followed
    assert not dark.rule_on


def test_a_log_without_odometry_is_not_judged() -> None:
    noisy = simulate_scenario(
        "office", seed=0, laser=LaserModel(dropout_fraction=0.05, dropout_run_beams=3)
    )
    blind = [replace(s, odom_pose=None) for s in noisy.scans]
    measured = wall_dropouts(blind, FeatureConfig())
    assert measured.patches_per_1000 > 5.0 and measured.followed == 0 and not measured.rule_on


def test_a_rule_set_by_hand_or_a_measurement_switched_off_is_left_alone() -> None:
    noisy = simulate_scenario(
        "office", seed=0, laser=LaserModel(dropout_fraction=0.05, dropout_run_beams=3)
    )
    by_hand = IcegConfig.model_validate({"features": {"eow_dropout_max_gap_m": 0.3}})
    assert with_measured_dropouts(by_hand, noisy.scans) == (by_hand, None)
    off = IcegConfig.model_validate({"features": {"measure_wall_dropouts": False}})
    assert with_measured_dropouts(off, noisy.scans) == (off, None)
    config, measured = with_measured_dropouts(IcegConfig(), noisy.scans)
    assert measured is not None and measured.rule_on
    assert config.features.eow_dropout_max_gap_m == PATCH_MAX_GAP_M


def test_a_run_reads_random_losses_as_dropouts(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    # The office loop seen by a scanner that loses 5 % of its returns at random in runs of
    # three: read as views past walls' ends they bend the map (0.178 m, tests/iceg/test_slam.py);
    # the run measures them, reads them as dropouts and says so.
    noisy = simulate_scenario(
        "office", seed=0, laser=LaserModel(dropout_fraction=0.05, dropout_run_beams=3)
    )
    noisy.write_carmen(tmp_path / "office.clf")
    config = IcegConfig.model_validate({"slam": {"workers": 1}})
    with caplog.at_level(logging.WARNING, logger="iceg.pipeline"):
        result = run_log(tmp_path / "office.clf", config)
    assert result.metrics["wall_dropouts"]["rule_on"]
    assert "loses its return on walls" in caplog.text
    truth = np.asarray(noisy.true_poses)
    assert position_errors(result.poses, truth).rmse_m <= 0.02
    assert result.config.features.eow_dropout_max_gap_m == PATCH_MAX_GAP_M


@pytest.mark.parametrize(
    ("log", "options"),
    [("mit-csail/mit-csail.clf", {}), ("rosbag/turtlebot4-ros2", {})],
)
def test_real_scanners_keep_their_ends_of_wall(log: str, options: dict[str, str]) -> None:
    # MIT CSAIL's SICK loses few returns (1.4 patches per 1000); the TurtleBot 4's RPLIDAR
    # loses many (7.0), but on dark surfaces that it loses again where it looks again
    # (73 %): neither run changes.
    from frontends import open_log

    store = ScanStore(open_log(shared_file(log), **options))
    config = IcegConfig()
    measured = measure_scanner(config, store)
    assert measured.dropouts is not None and not measured.dropouts.rule_on
    assert measured.config.features.eow_dropout_max_gap_m == 0.0
