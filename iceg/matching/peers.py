"""Other scan matchers on the same graph back-end, and the factory of ``matching.method``.

The adapters register the new scan's points (2D, as 3D points with ``z = 0``) against the
reference's points (its segments sampled when it keeps none, see
:func:`~iceg.matching.plicp.reference_points`) from the prediction, with a well-kept
library, and give the same :class:`~iceg.types.MatchResult` as the ICE matcher:

- ``small_gicp`` (GICP, Koide et al. 2024): covariance from the library's Hessian ``H``
  (planar block ``(tx, ty, rz)``, scaled by the reduced chi-square of the final error).
  With all points at ``z = 0`` GICP's local covariances are degenerate and it behaves as
  point-to-point ICP (5.6 cm mean error on office pairs); each point is therefore also put
  at ``z = +-GICP_EXTRUDE_M`` (the wall it lies on), which makes the local covariances
  planar (0.6 cm);
- ``kiss_icp`` (KISS-ICP's point-to-point registration against its voxel map, Vizzo et al.
  2023) and ``open3d_point`` / ``open3d_plane`` (Open3D point-to-point / point-to-plane ICP;
  the plane normals are the reference's in-plane local-line normals): no Hessian, so the
  project's lattice covariance of the final pose
  (:func:`~iceg.matching.plicp.lattice_covariance`).

Each library is imported when its matcher is built (extra ``peers``); a missing one is a
:class:`~iceg_common.errors.ConfigError`. The final pose is checked as PL-ICP's is
(:func:`~iceg.matching.plicp.check_result`: bounds, overlap, covariance).
"""

from __future__ import annotations

import importlib
import importlib.metadata
import math
from typing import Any

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg.matching.config import MatchBounds, MatchingConfig
from iceg.matching.matcher import IceMatcher
from iceg.matching.plicp import (
    PlIcpMatcher,
    plicp_problem,
)
from iceg.matching.protocol import Matcher
from iceg_common.errors import ConfigError

FloatArray = NDArray[np.float64]

#: Largest point correspondence distance (metres) of the peer registrations.
MAX_CORRESPONDENCE_M = 0.5
#: Iteration cap of the peer registrations.
MAX_ITERATIONS = 50
#: Height (metres) of the copies of each point above and below z = 0 given to GICP.
GICP_EXTRUDE_M = 0.2
#: KISS-ICP voxel size (metres) and points kept per voxel.
KISS_VOXEL_M = 0.25
KISS_POINTS_PER_VOXEL = 20
#: KISS-ICP robust kernel scale (metres).
KISS_KERNEL_M = 0.05
#: Python module and distribution of each peer library.
PEER_MODULES: dict[str, tuple[str, str]] = {
    "small_gicp": ("small_gicp", "small_gicp"),
    "kiss_icp": ("kiss_icp", "kiss-icp"),
    "open3d_point": ("open3d", "open3d"),
    "open3d_plane": ("open3d", "open3d"),
}
#: Every value of ``matching.method``.
METHODS = ("ice", "plicp", *PEER_MODULES)


def to_3d(points: FloatArray) -> FloatArray:
    """``(P, 2)`` points as ``(P, 3)`` with ``z = 0``."""
    return np.column_stack([points, np.zeros(points.shape[0])]).astype(np.float64)


def extruded(points: FloatArray) -> FloatArray:
    """``(3P, 3)``: the points at ``z = 0`` and at ``z = +-GICP_EXTRUDE_M``."""
    p3 = to_3d(points)
    up, down = p3.copy(), p3.copy()
    up[:, 2] = GICP_EXTRUDE_M
    down[:, 2] = -GICP_EXTRUDE_M
    return np.vstack([down, p3, up])


def pose_to_matrix(pose: FloatArray) -> FloatArray:
    """``(3,)`` SE(2) pose as a ``(4, 4)`` homogeneous transform."""
    c, s = math.cos(pose[2]), math.sin(pose[2])
    t = np.eye(4)
    t[:2, :2] = [[c, -s], [s, c]]
    t[:2, 3] = pose[:2]
    return t


def matrix_to_pose(t: ArrayLike) -> FloatArray:
    """The SE(2) part ``[x, y, theta]`` of a ``(4, 4)`` transform."""
    m = np.asarray(t, dtype=np.float64)
    return np.array([m[0, 3], m[1, 3], math.atan2(m[1, 0], m[0, 0])])


def _import(method: str) -> Any:
    module, dist = PEER_MODULES[method]
    try:
        return importlib.import_module(module)
    except ImportError as exc:
        raise ConfigError(
            f"matching.method {method!r} needs the {dist} package "
            f"(pip install 'iceg[peers]'): {exc}"
        ) from None


def peer_version(method: str) -> str | None:
    """Installed version of the library behind ``method`` (None: not installed or ICE/PL-ICP)."""
    if method not in PEER_MODULES:
        return None
    try:
        return importlib.metadata.version(PEER_MODULES[method][1])
    except importlib.metadata.PackageNotFoundError:
        return None


def available_methods() -> list[str]:
    """The methods whose library imports here (``ice`` and ``plicp`` always)."""
    out = ["ice", "plicp"]
    for method in PEER_MODULES:
        try:
            _import(method)
        except ConfigError:
            continue
        out.append(method)
    return out


class _PointPeer(PlIcpMatcher):
    """Common part of the adapters: the point matcher of :class:`PlIcpMatcher` (points,
    checks, lattice covariance where the library gives none) with the library's registration."""

    method = ""

    def __init__(self, config: MatchingConfig | None = None) -> None:
        super().__init__(config)
        self.lib = _import(self.method)

    def __repr__(self) -> str:
        return f"{type(self).__name__}({self.method})"


class SmallGicpMatcher(_PointPeer):
    """GICP of ``small_gicp``; covariance from its Hessian."""

    method = "small_gicp"

    def _register(
        self, new: FloatArray, ref: FloatArray, pred: FloatArray, bounds: MatchBounds
    ) -> tuple[FloatArray, FloatArray | None]:
        res = self.lib.align(
            extruded(ref),
            extruded(new),
            init_T_target_source=pose_to_matrix(pred),
            registration_type="GICP",
            downsampling_resolution=0.02,
            max_correspondence_distance=MAX_CORRESPONDENCE_M,
            num_threads=1,
            max_iterations=MAX_ITERATIONS,
        )
        pose = matrix_to_pose(res.T_target_source)
        return pose, hessian_covariance(np.asarray(res.H), float(res.error), int(res.num_inliers))


def hessian_covariance(h: FloatArray, error: float, n_inliers: int) -> FloatArray:
    """Covariance ``(3, 3)`` of ``(x, y, theta)`` in the new scan's frame from a 6x6
    Hessian in ``(rx, ry, rz, tx, ty, tz)`` right-perturbation order (small_gicp): the
    inverse of the planar block, times the reduced chi-square ``2 error / (n - 3)``.
    Infinite when the block is singular."""
    idx = [3, 4, 2]
    block = h[np.ix_(idx, idx)]
    try:
        inv = np.linalg.inv(block)
    except np.linalg.LinAlgError:
        return np.full((3, 3), np.inf)
    scale = 2.0 * error / max(1, n_inliers - 3)
    out = inv * scale
    return np.asarray(0.5 * (out + out.T), dtype=np.float64)


class KissIcpMatcher(_PointPeer):
    """KISS-ICP's registration of the new points against a voxel map of the reference."""

    method = "kiss_icp"

    def _register(
        self, new: FloatArray, ref: FloatArray, pred: FloatArray, bounds: MatchBounds
    ) -> tuple[FloatArray, FloatArray | None]:
        from kiss_icp.mapping import VoxelHashMap
        from kiss_icp.registration import Registration

        voxels = VoxelHashMap(KISS_VOXEL_M, 1e3, KISS_POINTS_PER_VOXEL)
        voxels.add_points(to_3d(ref))
        reg = Registration(MAX_ITERATIONS, 1e-4, 1)
        t = reg.align_points_to_map(
            to_3d(new), voxels, pose_to_matrix(pred), MAX_CORRESPONDENCE_M, KISS_KERNEL_M
        )
        return matrix_to_pose(t), None


class Open3dMatcher(_PointPeer):
    """Open3D ICP, point-to-point (``open3d_point``) or point-to-plane (``open3d_plane``)."""

    def __init__(self, config: MatchingConfig | None = None, plane: bool = False) -> None:
        self.method = "open3d_plane" if plane else "open3d_point"
        super().__init__(config)

    def _register(
        self, new: FloatArray, ref: FloatArray, pred: FloatArray, bounds: MatchBounds
    ) -> tuple[FloatArray, FloatArray | None]:
        o3d = self.lib
        reg = o3d.pipelines.registration
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(to_3d(new)))
        tgt = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(to_3d(ref)))
        if self.method == "open3d_plane":
            cloud = plicp_problem(new, ref, pred, MatchBounds.global_(), self.config).cloud
            normals = np.nan_to_num(cloud.ref_normal, nan=0.0)
            tgt.normals = o3d.utility.Vector3dVector(to_3d(normals))
            estimation = reg.TransformationEstimationPointToPlane()
        else:
            estimation = reg.TransformationEstimationPointToPoint()
        res = reg.registration_icp(
            src,
            tgt,
            MAX_CORRESPONDENCE_M,
            pose_to_matrix(pred),
            estimation,
            reg.ICPConvergenceCriteria(max_iteration=MAX_ITERATIONS),
        )
        return matrix_to_pose(res.transformation), None


def make_matcher(config: MatchingConfig | None = None) -> Matcher:
    """The matcher named by ``config.method`` (see :data:`METHODS`).

    Raises:
        ConfigError: the method's library is not installed.
    """
    c = config or MatchingConfig()
    if c.method == "ice":
        return IceMatcher(c)
    if c.method == "plicp":
        return PlIcpMatcher(c)
    if c.method == "small_gicp":
        return SmallGicpMatcher(c)
    if c.method == "kiss_icp":
        return KissIcpMatcher(c)
    return Open3dMatcher(c, plane=c.method == "open3d_plane")
