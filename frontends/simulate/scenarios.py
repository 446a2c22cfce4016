"""Named simulated runs: a world, its route, a speed and an odometry model.

A scenario fixes everything but the seed, so a benchmark row (``benchmarks/bench_accuracy.py``)
or a test names a run by a short name. The issue-11 scenarios reproduce the four ways the
pipeline failed on unseen logs: ``long_corridor`` (a 200 m corridor with door recesses,
accurate odometry), ``office_biased`` (the office loop with 1.5 % scale error and
0.4 deg/m heading drift), ``two_loop`` (odometry drift > 20 m at the return to the start,
in a building), ``open_loops`` (the same over open ground, where the laser cannot correct
the drift) and ``outdoor`` (trees and posts, few walls). ``office_people`` is the office
loop with people walking its corridors (moving legs in every scan, as in a real building).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from frontends.simulate.odometry import ACCURATE_ODOMETRY, OdometryModel
from frontends.simulate.raycast import LaserModel
from frontends.simulate.run import SimulatedRun, simulate
from frontends.simulate.trajectory import DEFAULT_SPEED_MPS, default_trajectory
from frontends.simulate.worlds import (
    World,
    corridor_world,
    long_corridor_world,
    office_world,
    open_loops_world,
    outdoor_world,
    two_loop_world,
    with_pedestrians,
)
from iceg_common.errors import ConfigError


@dataclass(frozen=True)
class Scenario:
    """A named simulated run.

    Attributes:
        name: Short name (the key in :data:`SCENARIOS`).
        world: Builds the world; its default route is driven.
        odometry: The wheel-odometry model.
        speed_mps: Forward speed along the route, m/s.
        description: What the scenario tests.
    """

    name: str
    world: Callable[[], World]
    odometry: OdometryModel
    speed_mps: float = DEFAULT_SPEED_MPS
    description: str = ""

    def simulate(self, seed: int = 0, laser: LaserModel | None = None) -> SimulatedRun:
        """Drive the world's default route at 5 Hz with this odometry and ``laser`` (default:
        the SICK LMS200 of :class:`LaserModel`)."""
        world = self.world()
        trajectory = default_trajectory(world, speed_mps=self.speed_mps)
        return simulate(world, trajectory, laser=laser, odometry=self.odometry, seed=seed)


#: People walking the office loop in the ``office_people`` scenario (one per 6 m of its 58 m
#: route: each pair of legs is a moving landmark the static-world matcher can latch on).
OFFICE_PEOPLE = 10

#: Scenarios by name.
SCENARIOS: dict[str, Scenario] = {
    s.name: s
    for s in (
        Scenario("office", office_world, OdometryModel(), description="office loop, default noise"),
        Scenario("corridor", corridor_world, OdometryModel(), description="40 m bare corridor"),
        Scenario(
            "office_biased",
            office_world,
            OdometryModel.biased(scale_error=0.015, heading_drift_deg_per_m=0.4),
            description="office loop, 1.5 % scale error and 0.4 deg/m heading drift",
        ),
        Scenario(
            "long_corridor",
            long_corridor_world,
            ACCURATE_ODOMETRY,
            description="200 m corridor with door recesses, accurate odometry",
        ),
        Scenario(
            "two_loop",
            two_loop_world,
            OdometryModel.biased(scale_error=0.01, heading_drift_deg_per_m=0.3),
            description="two loops (256 m), 1 % scale error, 0.3 deg/m: drift > 20 m at return",
        ),
        Scenario(
            "open_loops",
            open_loops_world,
            OdometryModel.biased(scale_error=0.01, heading_drift_deg_per_m=0.3),
            speed_mps=1.0,
            description="two 160 m loops over open ground, 1 %, 0.3 deg/m: odometry > 20 m off",
        ),
        Scenario(
            "outdoor",
            outdoor_world,
            OdometryModel(),
            description="trees and posts, two long walls, 100 m loop",
        ),
        Scenario(
            "office_people",
            lambda: with_pedestrians(office_world(), OFFICE_PEOPLE, seed=1),
            OdometryModel(),
            description=f"office loop with {OFFICE_PEOPLE} people walking its corridors",
        ),
    )
}


def simulate_scenario(name: str, seed: int = 0, laser: LaserModel | None = None) -> SimulatedRun:
    """Simulate the scenario ``name`` (a key of :data:`SCENARIOS`) with ``seed`` and ``laser``
    (default: the SICK LMS200 of :class:`LaserModel`).

    Raises:
        ConfigError: unknown name.
    """
    try:
        scenario = SCENARIOS[name]
    except KeyError:
        raise ConfigError(
            f"unknown scenario {name!r}; choose one of {', '.join(sorted(SCENARIOS))}"
        ) from None
    return scenario.simulate(seed, laser)
