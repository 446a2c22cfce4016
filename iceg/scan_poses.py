"""The pose of every scan of a run from its nodes' estimates: each scan between two nodes
follows its odometry from the node before it, bent to meet the node after it.

A scan that is not a graph node (the robot moved less than a keyframe spacing since the last
node) is recorded with its node and the odometry ``delta`` from that node's scan. Composed
with the node's estimate alone, it carries the whole error the odometry makes between the two
nodes, which the next node's match removes only from the next node: in a fast turn read from
lagging odometry, several degrees (MIT CSAIL, docs/design.md "Scans between two nodes").

Between nodes ``k`` and ``k + 1`` joined by an odometry step ``u`` (the graph's odometry
factor), the estimates disagree with the odometry by ``E = (x_k ∘ u)^-1 ∘ x_{k+1}``. With the
odometry's errors growing along its motion, as its noise model says (a random walk, whose
value given both ends is the Brownian bridge: linear in the accumulated variance), the scan
at odometry ``d`` from node ``k`` takes the fraction ``a`` of that disagreement,
``x_k ∘ d ∘ (a * E)`` (first order in ``E``, a fraction of a keyframe spacing), with ``a``
the fraction of the step's motion the scan has made: its distance for ``x, y``, and for
``theta`` its rotation and distance weighted as :func:`graph.odometry_covariance` weights
them (the time fraction where the step does not move). ``a = 0`` at node ``k``; a scan at
the step's end would land on ``x_{k+1}``.

Scans are left on their node's odometry where there is no next node, where the next node was
not reached by odometry (its step is the constant-velocity prior of a log without odometry or
across an odometry break: the scans' odometry does not lead to it), and where the scan's node
is not the one before it in time (a revisit's scans hang from an old node).
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph import OdometryNoiseConfig
from iceg_common import se2

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: A step shorter than this (metres) or turning less (radians, weighted) does not move: its
#: scans take the time fraction of the disagreement (a robot standing, a keyframe by time).
_STILL_M = 1e-6
_STILL_RAD = math.radians(1e-4)


def scan_poses(
    stamps_s: ArrayLike,
    scan_node: ArrayLike,
    scan_delta: ArrayLike,
    node_ids: ArrayLike,
    node_poses: ArrayLike,
    node_scan_index: ArrayLike,
    step_from: ArrayLike,
    steps: ArrayLike,
    noise: OdometryNoiseConfig,
) -> FloatArray:
    """Every scan's pose from the node estimates (see the module docstring).

    Args:
        stamps_s: ``(N,)`` float64 scan stamps, seconds, in input order.
        scan_node: ``(N,)`` int64 the node each scan is recorded against.
        scan_delta: ``(N, 3)`` float64 each scan's pose in its node's frame ``[x_m, y_m,
            theta_rad]`` (zero for a node's own scan).
        node_ids: ``(M,)`` int64 every node id, ascending.
        node_poses: ``(M, 3)`` float64 their estimates, map frame.
        node_scan_index: ``(M,)`` int64 the index of each one's own scan.
        step_from: ``(S,)`` int64 nodes ``k`` whose odometry step to ``k + 1`` is given.
        steps: ``(S, 3)`` float64 those steps, node ``k``'s frame (:func:`odometry_steps`).
        noise: The odometry noise model, for the rotation's weights.

    Returns:
        ``(N, 3)`` float64 scan poses, map frame. Raises nothing for a run's own records.
    """
    t = np.asarray(stamps_s, dtype=np.float64)
    node = np.asarray(scan_node, dtype=np.int64)
    delta = np.asarray(scan_delta, dtype=np.float64).reshape(-1, 3)
    ids = np.asarray(node_ids, dtype=np.int64)
    poses = np.asarray(node_poses, dtype=np.float64).reshape(-1, 3)
    nsi = np.asarray(node_scan_index, dtype=np.int64)
    row = np.searchsorted(ids, node)
    poses_out = se2.compose(poses[row], delta) if node.size else np.zeros((0, 3))
    # the step of each node row (-1: none), and the row of each scan's next node
    step_of = np.full(ids.shape[0], -1, dtype=np.int64)
    step_of[np.searchsorted(ids, step_from)] = np.arange(np.asarray(step_from).shape[0])
    nxt = np.minimum(row + 1, ids.shape[0] - 1)
    scan = np.arange(node.shape[0])
    bridged = (ids[nxt] == node + 1) & (step_of[row] >= 0) & (nsi[row] < scan) & (scan < nsi[nxt])
    if not np.any(bridged):
        return poses_out
    k, k1, s = row[bridged], nxt[bridged], scan[bridged]
    u = np.asarray(steps, dtype=np.float64).reshape(-1, 3)[step_of[k]]
    disagreement = se2.between(se2.compose(poses[k], u), poses[k1])
    d = delta[bridged]
    span_s = t[nsi[k1]] - t[nsi[k]]
    time = np.divide(t[s] - t[nsi[k]], span_s, out=np.zeros_like(span_s), where=span_s > 0.0)
    dist_s, dist = np.hypot(d[:, 0], d[:, 1]), np.hypot(u[:, 0], u[:, 1])
    w_rot = noise.sigma_theta_per_rotation_deg_per_deg
    w_dist = noise.sigma_theta_per_distance_rad_per_m
    turn_s = w_rot * np.abs(d[:, 2]) + w_dist * dist_s
    turn = w_rot * np.abs(se2.wrap_angle(u[:, 2])) + w_dist * dist
    moves, turns = dist > _STILL_M, turn > _STILL_RAD
    frac = np.empty((k.shape[0], 3))
    frac[:, 0] = np.where(moves, dist_s / np.where(moves, dist, 1.0), time)
    frac[:, 1] = frac[:, 0]
    frac[:, 2] = np.where(turns, turn_s / np.where(turns, turn, 1.0), time)
    poses_out[bridged] = se2.compose(poses_out[bridged], np.clip(frac, 0.0, 1.0) * disagreement)
    return poses_out


def odometry_steps(
    kinds: ArrayLike,
    ij: ArrayLike,
    measured: ArrayLike,
    cov: ArrayLike,
    no_odometry_cov: ArrayLike,
) -> tuple[IntArray, FloatArray]:
    """The odometry steps between consecutive nodes that come from odometry, from a graph's
    factors: ``(step_from (S,) int64, steps (S, 3) float64)`` for :func:`scan_poses`.

    Args:
        kinds: ``(F,)`` bool, True where the factor is an odometry factor.
        ij: ``(F, 2)`` int64 each factor's nodes.
        measured: ``(F, 3)`` float64 each factor's measurement, first node's frame.
        cov: ``(F, 3, 3)`` float64 each factor's covariance.
        no_odometry_cov: ``(3, 3)`` the constant-velocity prior's covariance
            (:meth:`iceg.config.SlamConfig.no_odometry_covariance`): a step with it was
            predicted, not read from odometry, and is left out.

    Raises nothing.
    """
    odometry = np.asarray(kinds, dtype=bool)
    pairs = np.asarray(ij, dtype=np.int64).reshape(-1, 2)
    covs = np.asarray(cov, dtype=np.float64).reshape(-1, 3, 3)
    predicted = np.all(covs == np.asarray(no_odometry_cov, dtype=np.float64), axis=(1, 2))
    keep = odometry & (pairs[:, 1] == pairs[:, 0] + 1) & ~predicted
    return pairs[keep, 0].copy(), np.asarray(measured, dtype=np.float64).reshape(-1, 3)[keep]
