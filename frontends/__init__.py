"""Sensor data in: laser scans, log readers (CARMEN, ROS bags), benchmark relations, and a
simulator.

A leaf package: it never imports ``iceg`` or ``graph``. ``frontends.rosbag`` imports
``rosbags`` (the ``ros`` extra) only when a bag is opened or written, and the simulator's
types are imported on first use: a run of a log never loads the simulator.
"""

from typing import TYPE_CHECKING, Any

from frontends.carmen import CarmenReader, write_carmen
from frontends.registry import (
    AdjustedReader,
    LogReader,
    available_formats,
    describe_log,
    open_log,
    register_reader,
)
from frontends.relations import Relations, match_stamps, read_relations, write_relations
from frontends.rosbag import RosbagReader, write_rosbag
from frontends.scan import LaserScan

__all__ = ["AdjustedReader", "LaserScan", "LogReader", "available_formats", "open_log"]
__all__ += ["register_reader"]

# The simulator's types (the package frontends.simulate holds worlds and simulate()),
# imported on first use.
if TYPE_CHECKING:
    from frontends.simulate import LaserModel, OdometryModel, SimulatedRun, World

__all__ += ["LaserModel", "OdometryModel", "SimulatedRun", "World"]
__all__ += ["CarmenReader", "describe_log", "write_carmen"]
__all__ += ["RosbagReader", "write_rosbag"]
__all__ += ["Relations", "match_stamps", "read_relations", "write_relations"]


def __getattr__(name: str) -> Any:
    """The simulator's types, imported on first use (PEP 562)."""
    if name in ("LaserModel", "OdometryModel", "SimulatedRun", "World"):
        import frontends.simulate

        return getattr(frontends.simulate, name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
