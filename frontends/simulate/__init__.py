"""A 2D laser simulator with exact ground truth: polygon worlds (with people walking through
them, :func:`with_pedestrians`), a trajectory through them, vectorized ray casting (beams x
walls) with the paper's SICK LMS200 model (or another scanner's range, field of view, noise
and dropouts), noisy wheel odometry, and export to CARMEN / TUM files; and a real log's scans
degraded as a lesser scanner would have measured them (:func:`degrade_scans`). Deterministic
under a seed.

Example::

    from frontends.simulate import office_world, simulate
    run = simulate(office_world(), seed=0)
    run.scans[0].points_xy(), run.true_poses[0], run.world.corners()
"""

from frontends.simulate.degraded_scans import ScannerDegradation, degrade_scans
from frontends.simulate.odometry import ACCURATE_ODOMETRY, OdometryModel
from frontends.simulate.raycast import (
    APPARENT_END,
    CORNER,
    HIDDEN,
    NOTHING,
    WALL_END,
    JunctionClass,
    LaserModel,
    cast_rays,
    classify_junctions,
    ray_ranges,
    visible_corners,
    visible_mask,
    visible_wall_ends,
)
from frontends.simulate.run import SimulatedRun, simulate, simulate_pair
from frontends.simulate.scenarios import SCENARIOS, Scenario, simulate_scenario
from frontends.simulate.synthetic_odometry import (
    SyntheticOdometry,
    synthetic_odometry,
    write_synthetic_log,
)
from frontends.simulate.trajectory import (
    default_trajectory,
    default_trajectory_duration_s,
    trajectory_from_waypoints,
)
from frontends.simulate.worlds import (
    WORLDS,
    DynamicWalls,
    Junctions,
    Pedestrian,
    World,
    box_world,
    corridor_recesses,
    corridor_world,
    long_corridor_world,
    office_world,
    open_loops_world,
    outdoor_layout,
    outdoor_world,
    pillar_world,
    rectangle,
    tree_walls,
    two_loop_world,
    wall_with_doors,
    with_pedestrians,
    world_by_name,
)

__all__ = [
    "ACCURATE_ODOMETRY",
    "APPARENT_END",
    "CORNER",
    "HIDDEN",
    "NOTHING",
    "SCENARIOS",
    "WALL_END",
    "WORLDS",
    "DynamicWalls",
    "JunctionClass",
    "Junctions",
    "LaserModel",
    "OdometryModel",
    "Pedestrian",
    "ScannerDegradation",
    "Scenario",
    "SimulatedRun",
    "SyntheticOdometry",
    "World",
    "box_world",
    "cast_rays",
    "classify_junctions",
    "corridor_recesses",
    "corridor_world",
    "default_trajectory",
    "default_trajectory_duration_s",
    "degrade_scans",
    "long_corridor_world",
    "office_world",
    "open_loops_world",
    "outdoor_layout",
    "outdoor_world",
    "pillar_world",
    "ray_ranges",
    "rectangle",
    "simulate",
    "simulate_pair",
    "simulate_scenario",
    "synthetic_odometry",
    "trajectory_from_waypoints",
    "tree_walls",
    "two_loop_world",
    "visible_corners",
    "visible_mask",
    "visible_wall_ends",
    "wall_with_doors",
    "with_pedestrians",
    "world_by_name",
    "write_synthetic_log",
]
