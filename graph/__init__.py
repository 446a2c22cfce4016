"""GTSAM pose-graph back-end: a small facade over iSAM2, batch Levenberg–Marquardt, marginals
and g2o files. A leaf package: it imports only ``iceg_common``, and gtsam objects never leave it.
"""

from graph.config import GraphConfig, OdometryNoiseConfig
from graph.g2o import G2oGraph, G2oPrior, load_g2o
from graph.noise import odometry_covariance
from graph.pose_graph import BatchStats, FactorKind, FactorRecord, PoseGraph, UpdateStats
from graph.tangent import local_coordinates

__all__ = [
    "BatchStats",
    "FactorKind",
    "FactorRecord",
    "G2oGraph",
    "G2oPrior",
    "GraphConfig",
    "OdometryNoiseConfig",
    "PoseGraph",
    "UpdateStats",
    "load_g2o",
    "local_coordinates",
    "odometry_covariance",
]
