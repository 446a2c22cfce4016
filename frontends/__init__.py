"""Sensor data in: laser scans, log readers (CARMEN), benchmark relations, and a simulator.

A leaf package: it never imports ``iceg`` or ``graph``.
"""

from frontends.carmen import CarmenReader, write_carmen
from frontends.registry import LogReader, available_formats, open_log, register_reader
from frontends.relations import Relations, match_stamps, read_relations, write_relations
from frontends.scan import LaserScan

__all__ = ["LaserScan", "LogReader", "available_formats", "open_log", "register_reader"]

# The simulator's types (the package frontends.simulate holds worlds and simulate()).
from frontends.simulate import LaserModel, OdometryModel, SimulatedRun, World

__all__ += ["LaserModel", "OdometryModel", "SimulatedRun", "World"]
__all__ += ["CarmenReader", "write_carmen"]
__all__ += ["Relations", "match_stamps", "read_relations", "write_relations"]
