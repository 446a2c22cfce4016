"""Simulated runs: laser scans with odometry along a trajectory through a world, with exact
ground truth, deterministic under a seed, exportable to CARMEN and TUM files."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends.scan import LaserScan
from frontends.simulate.odometry import OdometryModel
from frontends.simulate.raycast import LaserModel, cast_rays
from frontends.simulate.trajectory import DEFAULT_RATE_HZ, default_trajectory
from frontends.simulate.worlds import World
from frontends.tum import write_tum
from iceg_common.errors import ConfigError

FloatArray = NDArray[np.float64]


@dataclass(frozen=True, eq=False)
class SimulatedRun:
    """A simulated run and its ground truth.

    Attributes:
        world: The world simulated.
        scans: One :class:`~frontends.scan.LaserScan` per true pose: ``stamp_s``, noisy
            ``ranges_m``, ``angles_rad``, ``odom_pose`` (noisy wheel odometry, odometry frame),
            ``laser_offset`` and ``source == "sim:<world>:<index>"``.
        true_poses: ``(N, 3)`` float64 true robot poses ``[x_m, y_m, theta_rad]``, world frame.
        odom_poses: ``(N, 3)`` float64 odometry poses (the scans' ``odom_pose``).
        stamps_s: ``(N,)`` float64 scan timestamps, seconds.
        laser: The laser model used.
        odometry: The odometry model used.
        seed: The seed of the run.
    """

    world: World
    scans: list[LaserScan]
    true_poses: FloatArray
    odom_poses: FloatArray
    stamps_s: FloatArray
    laser: LaserModel
    odometry: OdometryModel
    seed: int

    def __len__(self) -> int:
        return len(self.scans)

    def __repr__(self) -> str:
        path = np.hypot(*np.diff(self.true_poses[:, :2], axis=0).T).sum()
        end_err = float(np.hypot(*(self.odom_poses[-1, :2] - self.true_poses[-1, :2])))
        if self.odometry.start == "zero":
            end_err = float("nan")
        return (
            f"SimulatedRun(world={self.world.name!r}, scans={len(self.scans)}, "
            f"duration={self.stamps_s[-1] - self.stamps_s[0]:.1f} s, path={path:.1f} m, "
            f"odometry end error={end_err:.3f} m, seed={self.seed})"
        )

    def write_carmen(
        self, path: str | Path, laser_record: Literal["FLASER", "ROBOTLASER1"] = "FLASER"
    ) -> int:
        """Write the scans as a CARMEN log (see ``frontends.carmen.write_carmen``).

        Returns:
            The number of laser records written.
        """
        from frontends.carmen import write_carmen

        return write_carmen(path, self.scans, laser_record=laser_record)

    def write_tum(self, path: str | Path) -> int:
        """Write the true poses as a TUM trajectory (:func:`frontends.tum.write_tum`).

        Returns:
            The number of poses written.
        """
        return write_tum(path, self.stamps_s, self.true_poses)


def simulate(
    world: World,
    trajectory: ArrayLike | None = None,
    laser: LaserModel | None = None,
    odometry: OdometryModel | None = None,
    seed: int = 0,
    rate_hz: float = DEFAULT_RATE_HZ,
    start_stamp_s: float = 0.0,
) -> SimulatedRun:
    """Simulate a run: one laser scan with wheel odometry per true pose.

    Scan ``k`` has ``stamp_s = start_stamp_s + k / rate_hz``. The laser and odometry noise
    come from two independent streams spawned from ``numpy.random.SeedSequence(seed)``, so the
    same seed gives bit-identical runs and changing one model does not change the other's
    noise.

    Args:
        world: The world.
        trajectory: ``(N, 3)`` float64 true robot poses, world frame, one per scan; ``None``
            drives the world's default route (:func:`default_trajectory`) at ``rate_hz``.
        laser: Laser model (default: SICK LMS200, :class:`LaserModel`).
        odometry: Odometry model (default: :class:`OdometryModel`).
        seed: Seed of the noise.
        rate_hz: Scan rate, Hz.
        start_stamp_s: Timestamp of the first scan, seconds.

    Returns:
        A :class:`SimulatedRun`.

    Raises:
        ConfigError: a malformed trajectory, a non-positive rate, or no trajectory for a world
            without a default route.
    """
    laser = LaserModel() if laser is None else laser
    odometry = OdometryModel() if odometry is None else odometry
    if rate_hz <= 0:
        raise ConfigError(f"rate_hz must be > 0, got {rate_hz}")
    if trajectory is None:
        true_poses = default_trajectory(world, rate_hz=rate_hz)
    else:
        true_poses = np.array(trajectory, dtype=np.float64)
        if true_poses.ndim != 2 or true_poses.shape[1] != 3 or true_poses.shape[0] < 1:
            raise ConfigError(f"trajectory must have shape (N >= 1, 3), got {true_poses.shape}")
        if not np.all(np.isfinite(true_poses)):
            raise ConfigError("trajectory contains NaN or infinite values")
    laser_seq, odom_seq = np.random.SeedSequence(seed).spawn(2)
    laser_rng = np.random.default_rng(laser_seq)
    odom_poses = odometry.simulate(true_poses, np.random.default_rng(odom_seq))
    n = true_poses.shape[0]
    stamps = start_stamp_s + np.arange(n) / rate_hz
    angles = laser.angles_rad()
    offset = laser.offset()
    scans = [
        LaserScan(
            stamp_s=float(stamps[k]),
            ranges_m=cast_rays(world, true_poses[k], laser, laser_rng, float(stamps[k])),
            angles_rad=angles,
            range_min_m=laser.range_min_m,
            range_max_m=laser.range_max_m,
            odom_pose=odom_poses[k],
            laser_offset=offset,
            source=f"sim:{world.name}:{k}",
        )
        for k in range(n)
    ]
    for a in (true_poses, odom_poses, stamps):
        a.setflags(write=False)
    return SimulatedRun(world, scans, true_poses, odom_poses, stamps, laser, odometry, seed)


def simulate_pair(
    world: World,
    pose_a: ArrayLike,
    pose_b: ArrayLike,
    seed: int = 0,
    laser: LaserModel | None = None,
    stamps_s: tuple[float, float] = (0.0, 0.2),
) -> tuple[LaserScan, LaserScan]:
    """Two noisy scans from true poses ``pose_a`` and ``pose_b`` (``(3,)`` world frame), for
    matcher tests. Their ``odom_pose`` is the exact true pose, so the true relative pose is
    ``between(scan_a.odom_pose, scan_b.odom_pose)``.

    Returns:
        ``(scan_a, scan_b)`` with sources ``"sim:<world>:pair-a"`` / ``"...:pair-b"``.
    """
    laser = LaserModel() if laser is None else laser
    rng = np.random.default_rng(np.random.SeedSequence(seed).spawn(2)[0])
    out = []
    for tag, pose, stamp in (("a", pose_a, stamps_s[0]), ("b", pose_b, stamps_s[1])):
        p = np.array(pose, dtype=np.float64)
        out.append(
            LaserScan(
                stamp_s=float(stamp),
                ranges_m=cast_rays(world, p, laser, rng, float(stamp)),
                angles_rad=laser.angles_rad(),
                range_min_m=laser.range_min_m,
                range_max_m=laser.range_max_m,
                odom_pose=p,
                laser_offset=laser.offset(),
                source=f"sim:{world.name}:pair-{tag}",
            )
        )
    return out[0], out[1]
