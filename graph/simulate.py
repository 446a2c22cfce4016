"""Simulated Manhattan-world pose graphs with known ground truth (for tests and benchmarks).

The robot moves on a square grid of 1-step cells, one cell per node, turning left or right by
90 degrees at random (the construction of the Manhattan M3500 graph of Olson, Leonard & Teller,
ICRA 2006). Odometry is the true relative pose perturbed with noise drawn from
:func:`graph.odometry_covariance`; a loop closure joins a node to an earlier node in the same
cell, its relative pose perturbed with a fixed covariance. A chosen fraction of loop closures
can be replaced by wrong ones (perceptual aliasing: "this is the place of node m'", for a node
m' several metres away).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from numpy.typing import NDArray

from graph.config import OdometryNoiseConfig
from graph.noise import odometry_covariance
from iceg_common.errors import ConfigError
from iceg_common.se2 import between, compose, wrap_angle

FloatArray = NDArray[np.float64]


def se2_exp(xi: FloatArray) -> FloatArray:
    """Exponential map of SE(2): tangent ``(..., 3)`` ``[vx, vy, omega]`` to pose ``(..., 3)``.

    ``Exp(xi) = (V(omega) [vx, vy], omega)`` with
    ``V = [[sin w / w, -(1 - cos w) / w], [(1 - cos w) / w, sin w / w]]`` (Barfoot, *State
    Estimation for Robotics*, 2017, §7.1 for SE(2)); matches gtsam ``Pose2.Expmap``.
    """
    xi = np.asarray(xi, dtype=np.float64)
    w = xi[..., 2]
    small = np.abs(w) < 1e-9
    w_safe = np.where(small, 1.0, w)
    a = np.where(small, 1.0 - w**2 / 6.0, np.sin(w_safe) / w_safe)
    b = np.where(small, w / 2.0, (1.0 - np.cos(w_safe)) / w_safe)
    x = a * xi[..., 0] - b * xi[..., 1]
    y = b * xi[..., 0] + a * xi[..., 1]
    return np.stack([x, y, wrap_angle(w)], axis=-1)


@dataclass(frozen=True)
class SimulatedPoseGraph:
    """A simulated pose graph and its ground truth.

    Attributes:
        true_poses: ``(N, 3)`` ``[x_m, y_m, theta_rad]`` world frame; node ``k`` is row ``k``.
        odometry_measured: ``(N-1, 3)`` measured ``pose_k^-1 ∘ pose_k+1``.
        odometry_cov: ``(N-1, 3, 3)`` covariance the odometry noise was drawn from (tangent
            space of the measurement).
        loop_ij: ``(L, 2)`` int64 ``(earlier node, later node)`` of each loop closure.
        loop_measured: ``(L, 3)`` measured ``pose_i^-1 ∘ pose_j``.
        loop_cov: ``(3, 3)`` covariance of every loop closure.
        loop_is_outlier: ``(L,)`` bool, True for a wrong loop closure.
    """

    true_poses: FloatArray
    odometry_measured: FloatArray
    odometry_cov: FloatArray
    loop_ij: NDArray[np.int64]
    loop_measured: FloatArray
    loop_cov: FloatArray
    loop_is_outlier: NDArray[np.bool_]


def _noisy(true_rel: FloatArray, cov: FloatArray, rng: np.random.Generator) -> FloatArray:
    """``true_rel ∘ Exp(e)``, ``e ~ N(0, cov)``: noise in the tangent space of the measurement."""
    e = rng.multivariate_normal(np.zeros(3), cov)
    return compose(true_rel, se2_exp(e))


def simulate_manhattan(
    n_nodes: int,
    *,
    seed: int,
    grid_cells: int = 10,
    step_m: float = 1.0,
    turn_probability: float = 0.3,
    odometry: OdometryNoiseConfig | None = None,
    loop_sigma_xy_m: float = 0.02,
    loop_sigma_theta_deg: float = 0.5,
    loop_probability: float = 0.5,
    loop_min_gap: int = 10,
    outlier_fraction: float = 0.0,
    outlier_min_distance_m: float = 3.0,
) -> SimulatedPoseGraph:
    """Simulate a Manhattan-world pose graph (see the module docstring).

    Args:
        n_nodes: number of poses (>= 2).
        seed: seed of the numpy random generator (the result is deterministic).
        grid_cells: the robot stays in a ``grid_cells x grid_cells`` square of cells.
        step_m: cell size, the distance travelled per node (m).
        turn_probability: probability of a 90 degree turn (left or right) before a step.
        odometry: odometry noise parameters (default ``OdometryNoiseConfig()``).
        loop_sigma_xy_m: loop-closure translation standard deviation (m).
        loop_sigma_theta_deg: loop-closure heading standard deviation (deg).
        loop_probability: probability that a node revisiting a cell gets a loop closure.
        loop_min_gap: a loop closure joins nodes at least this many steps apart.
        outlier_fraction: fraction of loop closures replaced by wrong ones.
        outlier_min_distance_m: a wrong loop closure claims a node at least this far away.

    Returns:
        The measurements and the ground truth (:class:`SimulatedPoseGraph`).
    """
    if n_nodes < 2:
        raise ConfigError(f"simulate_manhattan: n_nodes must be >= 2, got {n_nodes}")
    rng = np.random.default_rng(seed)
    cfg = odometry if odometry is not None else OdometryNoiseConfig()
    cells, headings = _manhattan_walk(n_nodes, rng, grid_cells, turn_probability)
    true_poses = np.column_stack([cells * step_m, wrap_angle(headings * (math.pi / 2.0))]).astype(
        np.float64
    )

    true_rel = between(true_poses[:-1], true_poses[1:])
    odo_cov = np.stack([odometry_covariance(d, cfg) for d in true_rel])
    odo = np.stack([_noisy(d, c, rng) for d, c in zip(true_rel, odo_cov, strict=True)])

    sigma_theta_rad = math.radians(loop_sigma_theta_deg)
    loop_cov = np.diag([loop_sigma_xy_m**2, loop_sigma_xy_m**2, sigma_theta_rad**2])
    loop_ij = _revisits(cells, rng, loop_probability, loop_min_gap)
    loop_measured = np.zeros((len(loop_ij), 3))
    for n, (m, k) in enumerate(loop_ij):
        loop_measured[n] = _noisy(between(true_poses[m], true_poses[k]), loop_cov, rng)
    outlier = _inject_outliers(
        true_poses,
        loop_ij,
        loop_measured,
        loop_cov,
        rng,
        n_out=round(outlier_fraction * len(loop_ij)),
        min_gap=loop_min_gap,
        min_distance_m=outlier_min_distance_m,
    )
    return SimulatedPoseGraph(
        true_poses=true_poses,
        odometry_measured=odo,
        odometry_cov=odo_cov,
        loop_ij=loop_ij,
        loop_measured=loop_measured,
        loop_cov=loop_cov,
        loop_is_outlier=outlier,
    )


def _manhattan_walk(
    n_nodes: int, rng: np.random.Generator, grid_cells: int, turn_probability: float
) -> tuple[NDArray[np.int64], NDArray[np.int64]]:
    """Grid cells ``(N, 2)`` and headings ``(N,)`` (quarter turns) of a random walk that turns
    left or right with ``turn_probability`` and otherwise goes straight, staying inside the
    ``grid_cells`` square (it tries the other directions, then turns back, at a border)."""
    moves = np.array([[1, 0], [0, 1], [-1, 0], [0, -1]])
    cell = np.array([0, 0])
    heading = 0
    cells = np.zeros((n_nodes, 2), dtype=np.int64)
    headings = np.zeros(n_nodes, dtype=np.int64)
    for k in range(1, n_nodes):
        r = rng.random()
        turn = 0 if r >= turn_probability else (1 if r < turn_probability / 2 else -1)
        for candidate in (turn, -turn if turn else 1, -1 if turn == 0 else 0, 2):
            h = (heading + candidate) % 4
            nxt = cell + moves[h]
            if np.all((nxt >= 0) & (nxt < grid_cells)):
                heading, cell = h, nxt
                break
        cells[k], headings[k] = cell, heading
    return cells, headings


def _revisits(
    cells: NDArray[np.int64], rng: np.random.Generator, probability: float, min_gap: int
) -> NDArray[np.int64]:
    """``(L, 2)`` node pairs ``(earlier, k)``: node ``k`` in a cell visited at least ``min_gap``
    nodes before gets a loop closure with ``probability`` to a random earlier visit."""
    visits: dict[tuple[int, int], list[int]] = {}
    loops: list[tuple[int, int]] = []
    for k in range(len(cells)):
        key = (int(cells[k, 0]), int(cells[k, 1]))
        earlier = [m for m in visits.get(key, []) if k - m >= min_gap]
        if earlier and rng.random() < probability:
            loops.append((int(rng.choice(earlier)), k))
        visits.setdefault(key, []).append(k)
    return np.array(loops, dtype=np.int64).reshape(-1, 2)


def _inject_outliers(
    true_poses: FloatArray,
    loop_ij: NDArray[np.int64],
    loop_measured: FloatArray,
    loop_cov: FloatArray,
    rng: np.random.Generator,
    *,
    n_out: int,
    min_gap: int,
    min_distance_m: float,
) -> NDArray[np.bool_]:
    """Replace ``n_out`` loop closures, in place, by wrong ones: the earlier node becomes one at
    least ``min_distance_m`` away and the measurement claims the same place, turned by a random
    multiple of 90 degrees. Returns the ``(L,)`` outlier mask."""
    outlier = np.zeros(len(loop_ij), dtype=bool)
    for n in rng.permutation(len(loop_ij)):
        if outlier.sum() >= n_out:
            break
        k = int(loop_ij[n, 1])
        dist = np.linalg.norm(true_poses[: k - min_gap + 1, :2] - true_poses[k, :2], axis=1)
        far = np.flatnonzero(dist >= min_distance_m)
        if far.size == 0:
            continue
        loop_ij[n, 0] = int(rng.choice(far))
        claimed = np.array([0.0, 0.0, rng.integers(0, 4) * (math.pi / 2.0)])
        loop_measured[n] = _noisy(claimed, loop_cov, rng)
        outlier[n] = True
    return outlier
