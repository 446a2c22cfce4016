"""ICEG: ICE feature scan matching over a GTSAM iSAM2 pose graph, with occupancy grids.

Public entry points are re-exported lazily where they are heavy; see the submodules:
``iceg.features``, ``iceg.matching``, ``iceg.feature_map``, ``iceg.grid``, ``iceg.slam``,
``iceg.evaluation``, ``iceg.plot``, ``iceg.cli``.
"""

from iceg_common.errors import (
    ConfigError,
    EvaluationError,
    GraphError,
    IcegError,
    LogFormatError,
    MatchingError,
)

__version__ = "0.1.0"

__all__ = [
    "ConfigError",
    "EvaluationError",
    "GraphError",
    "IcegError",
    "LogFormatError",
    "MatchingError",
    "__version__",
]
