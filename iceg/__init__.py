"""ICEG: ICE feature scan matching over a GTSAM iSAM2 pose graph, with occupancy grids.

The package itself exports only the error hierarchy and the version; importing it loads no
heavy module. The entry points live in the submodules: ``iceg.features``, ``iceg.matching``,
``iceg.feature_map``, ``iceg.loop_closure``, ``iceg.grid``, ``iceg.slam``, ``iceg.evaluation``,
``iceg.plot``, ``iceg.cli``.
"""

from iceg_common.errors import (
    ConfigError,
    EvaluationError,
    FeatureMapError,
    GraphError,
    GridError,
    IcegError,
    LogFormatError,
    MatchingError,
    OutputError,
    ScanError,
)

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "EvaluationError",
    "FeatureMapError",
    "GraphError",
    "GridError",
    "IcegError",
    "LogFormatError",
    "MatchingError",
    "OutputError",
    "ScanError",
    "__version__",
]
