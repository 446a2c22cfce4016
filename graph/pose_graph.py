"""A small facade over gtsam for 2D pose graphs: iSAM2, batch Levenberg–Marquardt, marginals, g2o.

Conventions (those of gtsam ``Pose2`` / ``BetweenFactorPose2``):

- a pose is ``(3,)`` float64 ``[x_m, y_m, theta_rad]`` in the world frame;
- a between-factor measures ``pose_i^-1 ∘ pose_j`` (``pose_j`` in the frame of ``pose_i``);
  its error is ``Log(measured^-1 ∘ pose_i^-1 ∘ pose_j)``, so its covariance lives in the
  tangent space of the measurement (the frame of ``pose_j`` as predicted from ``pose_i``),
  ``(x, y, theta)`` order;
- a marginal covariance ``P`` of a node means ``pose = estimate ∘ Exp(xi)``, ``xi ~ N(0, P)``:
  the tangent space of the pose, i.e. its body frame, ``(x, y, theta)`` order.

Node ids are the gtsam keys (non-negative integers), so a graph written to g2o keeps its ids.
gtsam objects never leave this module: everything public takes and returns numpy arrays.

State. Factors and nodes are buffered until :meth:`PoseGraph.update`, which hands iSAM2 (Kaess
et al., IJRR 2012) only the new ones and clears the buffer; nothing is ever added twice.
:meth:`PoseGraph.optimize_batch` runs Levenberg–Marquardt over every factor from the current
estimate, then re-seeds iSAM2 with all factors linearized at the batch result, so that marginals
and later incremental updates continue from the batch optimum. Until the next ``update()`` the
estimates are the batch values themselves.
"""

from __future__ import annotations

import logging
import math
import operator
import os
import re
from collections import Counter
from collections.abc import Iterable
from dataclasses import dataclass
from enum import Enum
from typing import Literal

import gtsam
import numpy as np
from numpy.typing import ArrayLike, NDArray

from graph.config import GraphConfig
from graph.g2o import load_g2o, write_g2o_file
from iceg_common import se2
from iceg_common.errors import GraphError
from iceg_common.ids import sorted_unique

logger = logging.getLogger(__name__)

#: Largest node id: gtsam keys are 64-bit, and ids are returned as int64 arrays.
_MAX_NODE_ID = 2**63 - 1

FloatArray = NDArray[np.float64]

#: Default kernel widths on the whitened residual norm (standard deviations): 95 % asymptotic
#: efficiency on Gaussian noise (Huber 1981; Zhang 1997, "Parameter estimation techniques",
#: Table 1). Used when ``add_between`` gets a kernel but no ``robust_k``.
HUBER_K_95 = 1.345
CAUCHY_K_95 = 2.3849
RobustKernel = Literal["huber", "cauchy"]

# What gtsam's C++ exceptions become through pybind11.
_GTSAM_ERRORS = (RuntimeError, ValueError, IndexError, OverflowError)
_NEAR_VARIABLE = re.compile(r"near variable\s+(\d+)")
_MISSING_KEY = re.compile(r"key\s+\"?(\d+)\"?.*does not exist")


#: Codes of :attr:`PoseGraph.steps`.
STEP_UPDATE, STEP_DELTA, STEP_BATCH, STEP_BATCH_GAUSSIAN_LOOPS = 0, 1, 2, 3
STEP_BATCH_CORRECTION = 4


class FactorKind(str, Enum):
    """Label of a factor, kept for statistics and export (not used by the optimizer)."""

    PRIOR = "prior"
    ODOMETRY = "odometry"
    SCAN_MATCH = "scan_match"
    LOOP_CLOSURE = "loop_closure"


@dataclass(frozen=True)
class FactorRecord:
    """Python-side record of one factor (read-only arrays).

    Attributes:
        index: position of the factor in the graph, which is also its iSAM2 factor slot.
        kind: the factor's label.
        i: first node (the only node of a prior).
        j: second node; ``None`` for a prior.
        measured: ``(3,)`` ``pose_i^-1 ∘ pose_j`` for a between-factor, the prior pose
            (world frame) for a prior; ``[x_m, y_m, theta_rad]``.
        cov: ``(3, 3)`` covariance in the tangent space of the measurement, (x, y, theta).
        robust: ``None``, ``"huber"`` or ``"cauchy"``.
        robust_k: kernel parameter in standard deviations of the whitened residual, or None.
    """

    index: int
    kind: FactorKind
    i: int
    j: int | None
    measured: FloatArray
    cov: FloatArray
    robust: str | None
    robust_k: float | None


@dataclass(frozen=True)
class UpdateStats:
    """What one :meth:`PoseGraph.update` did.

    Attributes:
        new_nodes: nodes handed to iSAM2.
        new_factors: factors handed to iSAM2.
        relinearized: variables iSAM2 relinearized.
        reeliminated: variables iSAM2 re-eliminated.
        reseeded: iSAM2 was rebuilt from every factor (after a failed update).
    """

    new_nodes: int
    new_factors: int
    relinearized: int
    reeliminated: int
    reseeded: bool


@dataclass(frozen=True)
class BatchStats:
    """Outcome of :meth:`PoseGraph.optimize_batch`.

    Attributes:
        iterations: Levenberg–Marquardt iterations run.
        error_before: gtsam graph error (0.5 · sum of squared whitened residuals, robust loss
            for robust factors) at the starting estimate.
        error_after: the same at the result.
        converged: stopped on the error tolerance rather than on ``max_iterations``.
    """

    iterations: int
    error_before: float
    error_after: float
    converged: bool


def _readonly(a: FloatArray) -> FloatArray:
    out = np.array(a, dtype=np.float64, copy=True)
    out.setflags(write=False)
    return out


def _pose2(p: FloatArray) -> gtsam.Pose2:
    return gtsam.Pose2(float(p[0]), float(p[1]), float(p[2]))


def _xyt(pose: gtsam.Pose2) -> tuple[float, float, float]:
    return pose.x(), pose.y(), pose.theta()


class PoseGraph:
    """2D pose graph over gtsam: incremental iSAM2, batch refinement, marginals, g2o.

    Args:
        config: settings; defaults to ``GraphConfig()``.
        auto_prior: put a prior (``config.prior_sigma_*``) on the first node added, at its
            initial pose, to fix the gauge. ``read_g2o`` turns it off for files that carry
            their own priors.

    Example:
        >>> g = PoseGraph()
        >>> g.add_node(0, [0.0, 0.0, 0.0])
        >>> g.add_node(1, [1.0, 0.0, 0.0])
        >>> _ = g.add_between(0, 1, [1.0, 0.0, 0.0], np.diag([1e-4, 1e-4, 1e-5]))
        >>> _ = g.update()
        >>> ids, poses = g.estimates()
    """

    def __init__(self, config: GraphConfig | None = None, *, auto_prior: bool = True) -> None:
        self.config = config if config is not None else GraphConfig()
        self._auto_prior = auto_prior
        self._records: list[FactorRecord] = []
        self._gfactors: list[gtsam.NonlinearFactor] = []
        self._factors_of: dict[int, list[int]] = {}
        self._initial: dict[int, FloatArray] = {}
        self._pending_nodes: list[int] = []
        self._pending_factors: list[int] = []
        self._in_isam: set[int] = set()
        self._qr = self.config.factorization == "qr"
        self._isam: gtsam.ISAM2 | None = self._new_isam()
        self._seed: gtsam.Values | None = None  # linearization point kept after a failure
        self._served: gtsam.Values | None = None  # batch values, until the next update()
        # Solver call log (see :attr:`steps`): what rebuilds iSAM2 bit for bit on replay.
        self._steps: list[tuple[int, int, int]] = []
        self._delta_read = True  # iSAM2's lazy delta was read since the last update()
        # estimates() of the current state (ids, poses); dropped by every change of state.
        self._estimates: tuple[NDArray[np.int64], FloatArray] | None = None
        # Estimates of single nodes read since the solver last changed them (update, batch,
        # rebuild); a new node changes no other node's estimate, so add_node keeps them.
        self._pose_cache: dict[int, tuple[float, float, float]] = {}
        # The solver's own rows of the last full read (ids, poses; every node but the
        # buffered ones), kept until the solver changes them: add_node and solve_pending
        # change only buffered nodes, so the next full read takes these rows again.
        self._solver_rows: tuple[NDArray[np.int64], FloatArray] | None = None
        self._ids: NDArray[np.int64] | None = None  # sorted node ids; dropped by add_node

    # ------------------------------------------------------------------ building the graph

    def add_node(self, node_id: int, initial_pose: ArrayLike) -> None:
        """Add a pose node with its initial value (buffered until :meth:`update`).

        Args:
            node_id: non-negative integer, unique in the graph.
            initial_pose: ``(3,)`` ``[x_m, y_m, theta_rad]``, world frame.

        Raises:
            GraphError: the id is invalid or already used, or the pose is not finite ``(3,)``.
        """
        n = self._node_id(node_id, f"add_node({node_id!r})")
        if n in self._initial:
            raise GraphError(f"add_node: node {n} already exists; node ids must be unique")
        pose = self._vector3(initial_pose, "initial_pose", f"add_node({n})")
        first = not self._initial
        self._estimates = None
        self._ids = None
        self._initial[n] = pose
        self._factors_of[n] = []
        self._pending_nodes.append(n)
        if first and self._auto_prior:
            sxy, sth = self.config.prior_sigma_xy_m, self.config.prior_sigma_theta_rad
            self.add_prior(n, pose, np.diag([sxy**2, sxy**2, sth**2]))

    def add_prior(self, node_id: int, pose: ArrayLike, cov: ArrayLike) -> FactorRecord:
        """Add a prior on a node (``gtsam.PriorFactorPose2``).

        Args:
            node_id: an existing node.
            pose: ``(3,)`` prior mean ``[x_m, y_m, theta_rad]``, world frame.
            cov: ``(3, 3)`` symmetric positive definite covariance in the tangent space of the
                pose (body frame), ``(x, y, theta)`` order, m² / rad².

        Returns:
            The factor's record.

        Raises:
            GraphError: unknown node, or an invalid pose or covariance.
        """
        ctx = f"prior on node {node_id!r}"
        n = self._existing(node_id, ctx)
        mean = self._vector3(pose, "pose", ctx)
        c = self._covariance(cov, ctx)
        model = self._gaussian(c, ctx)
        factor = gtsam.PriorFactorPose2(n, _pose2(mean), model)
        return self._record(factor, FactorKind.PRIOR, n, None, mean, c, None, None)

    def add_between(
        self,
        i: int,
        j: int,
        measured: ArrayLike,
        cov: ArrayLike,
        kind: FactorKind | str = FactorKind.ODOMETRY,
        robust: RobustKernel | None = None,
        robust_k: float | None = None,
    ) -> FactorRecord:
        """Add a between-factor (``gtsam.BetweenFactorPose2``) with a full covariance.

        Args:
            i: first node (must exist).
            j: second node (must exist, ``j != i``).
            measured: ``(3,)`` ``pose_i^-1 ∘ pose_j`` = ``[dx_m, dy_m, dtheta_rad]``, ``pose_j``
                in the frame of ``pose_i``.
            cov: ``(3, 3)`` symmetric positive definite covariance in the tangent space of the
                measurement (gtsam convention: error ``Log(measured^-1 ∘ pose_i^-1 ∘ pose_j)``),
                ``(x, y, theta)`` order, m² / rad².
            kind: ``"odometry"``, ``"scan_match"`` or ``"loop_closure"`` (statistics, export).
            robust: ``None`` for a Gaussian factor, ``"huber"`` or ``"cauchy"`` for an
                M-estimator on the Mahalanobis distance (``noiseModel.Robust``).
            robust_k: kernel parameter in standard deviations; defaults to the 95 %-efficiency
                value of the kernel (:data:`HUBER_K_95`, :data:`CAUCHY_K_95`).

        Returns:
            The factor's record.

        Raises:
            GraphError: naming the factor (kind, i, j): unknown node, bad kind or kernel,
                non-finite measurement, or a covariance that is not ``(3, 3)`` symmetric
                positive definite.
        """
        try:
            k_kind = FactorKind(kind)
        except ValueError:
            k_kind = None
        if k_kind is None or k_kind is FactorKind.PRIOR:
            valid = [k.value for k in FactorKind if k is not FactorKind.PRIOR]
            raise GraphError(f"factor between {i} and {j}: kind {kind!r} is not one of {valid}")
        ctx = f"{k_kind.value} factor between {i} and {j}"
        a = self._existing(i, ctx)
        b = self._existing(j, ctx)
        if a == b:
            raise GraphError(f"{ctx}: a between-factor needs two different nodes")
        z = self._vector3(measured, "measured", ctx)
        c = self._covariance(cov, ctx)
        model = self._gaussian(c, ctx)
        k: float | None = None
        if robust is not None:
            if robust not in ("huber", "cauchy"):
                raise GraphError(f"{ctx}: robust must be None, 'huber' or 'cauchy', not {robust!r}")
            default = HUBER_K_95 if robust == "huber" else CAUCHY_K_95
            k = float(default if robust_k is None else robust_k)
            if not (np.isfinite(k) and k > 0.0):
                raise GraphError(f"{ctx}: robust_k must be a positive number, got {robust_k!r}")
            model = gtsam.noiseModel.Robust.Create(_m_estimator(robust, k), model)
        factor = gtsam.BetweenFactorPose2(a, b, _pose2(z), model)
        return self._record(factor, k_kind, a, b, z, c, robust, k)

    # ------------------------------------------------------------------ solving

    def update(self) -> UpdateStats:
        """One iSAM2 update with the buffered new nodes and factors; the buffer is cleared.

        With an empty buffer this is one more iSAM2 iteration: a Gauss–Newton step, and every
        ``config.relinearize_skip``-th call a relinearization of the nodes whose update exceeds
        ``config.relinearize_threshold``. Nodes added in the last updates have had few steps:
        to converge them (e.g. at the end of a run), call ``update()`` a few multiples of
        ``relinearize_skip`` times, or :meth:`optimize_batch`.

        Returns:
            Counts of what was done (:class:`UpdateStats`).

        Raises:
            GraphError: a new node has no factor, or gtsam failed; the message names the node
                (e.g. "indeterminant linear system near node 12") and its factors. After a
                gtsam failure the next ``update()`` rebuilds iSAM2 from every factor.
        """
        self._check_connected(self._pending_nodes)
        self._drop_estimates()
        self._steps.append((STEP_UPDATE, len(self._initial), len(self._records)))
        self._delta_read = False
        if self._isam is None:
            return self._reseed(self._seed_values())
        new_graph = gtsam.NonlinearFactorGraph()
        for idx in self._pending_factors:
            new_graph.add(self._gfactors[idx])
        new_values = gtsam.Values()
        for n in self._pending_nodes:
            new_values.insert(n, _pose2(self._initial[n]))
        try:
            result = self._isam.update(new_graph, new_values)
        except _GTSAM_ERRORS as exc:
            self._mark_broken()
            if self._switch_to_qr(exc):
                return self._reseed(self._seed_values())
            raise self._wrap(exc, "iSAM2 update") from exc
        slots = list(result.getNewFactorsIndices())
        if slots != self._pending_factors:  # FactorRecord.index must be the iSAM2 slot
            self._mark_broken()
            raise GraphError(
                f"iSAM2 update: gtsam put the new factors in slots {slots[:5]}... instead of "
                f"{self._pending_factors[:5]}...; the graph will be rebuilt at the next update()"
            )
        stats = UpdateStats(
            new_nodes=len(self._pending_nodes),
            new_factors=len(self._pending_factors),
            relinearized=int(result.getVariablesRelinearized()),
            reeliminated=int(result.getVariablesReeliminated()),
            reseeded=False,
        )
        self._in_isam.update(self._pending_nodes)
        self._pending_nodes.clear()
        self._pending_factors.clear()
        self._served = None
        return stats

    def solve_pending(self) -> None:
        """Estimate the buffered nodes without an iSAM2 update: their MAP estimate given every
        node already in iSAM2, held at its current estimate.

        Gauss–Newton (gtsam, to convergence) on the buffered factors alone, with each older node
        they name fixed by a prior of 1e-6 m / rad; the result becomes the buffered nodes'
        initial values, which :meth:`estimate` returns for them and :meth:`update` inserts into
        iSAM2. For nodes appended to a chain (a keyframe and its odometry and scan-match
        factors) this is the estimate an iSAM2 update would give them, less the corrections the
        update would also bring to older nodes (one more Gauss–Newton step). It costs what the
        buffer holds, where an iSAM2 update in gtsam 4.3 costs O(N) (docs/design.md, "Long
        logs"), so a long run calls it between updates (``SlamConfig.isam2_defer_from_nodes``).
        :meth:`marginal_covariance` and :meth:`relative_covariance` then answer for buffered
        nodes too.

        Does nothing with an empty buffer, before the first update or after a failed one. A
        gtsam failure on the small problem leaves the initial values as they were (logged at
        debug level): the next :meth:`update` meets and reports the same problem.
        """
        if not self._pending_nodes or self._isam is None or not self._in_isam:
            return
        graph, values, _ = self._buffered_problem()
        params = gtsam.GaussNewtonParams()
        params.setMaxIterations(10)
        params.setRelativeErrorTol(1e-10)
        params.setLinearSolverType("MULTIFRONTAL_QR" if self._qr else "MULTIFRONTAL_CHOLESKY")
        try:
            result = gtsam.GaussNewtonOptimizer(graph, values, params).optimize()
        except _GTSAM_ERRORS as exc:
            logger.debug("solve_pending: %s; the buffered nodes keep their initial values", exc)
            return
        self._estimates = None
        for n in self._pending_nodes:
            self._initial[n] = np.array(_xyt(result.atPose2(n)), dtype=np.float64)
            self._pose_cache.pop(n, None)

    def _buffered_problem(self) -> tuple[gtsam.NonlinearFactorGraph, gtsam.Values, list[int]]:
        """The buffered factors, each older node they name held at its estimate (a prior of
        1e-6 m / rad), and the values: ``(graph, values, held node ids)``."""
        pending = set(self._pending_nodes)
        graph = gtsam.NonlinearFactorGraph()
        values = gtsam.Values()
        held: set[int] = set()
        for idx in self._pending_factors:
            record = self._records[idx]
            graph.add(self._gfactors[idx])
            held.update(k for k in (record.i, record.j) if k is not None and k not in pending)
        hold = gtsam.noiseModel.Isotropic.Sigma(3, 1e-6)
        for n in sorted(held):
            pose = _pose2(self.estimate(n))
            values.insert(n, pose)
            graph.add(gtsam.PriorFactorPose2(n, pose, hold))
        for n in self._pending_nodes:
            values.insert(n, _pose2(self._initial[n]))
        return graph, values, sorted(held)

    def _given_anchor(self, node: int, ctx: str) -> tuple[int, gtsam.Marginals]:
        """For buffered nodes hanging from one node in iSAM2 (the anchor): the anchor and the
        marginals of the buffered problem, i.e. their covariances given the anchor.

        Raises:
            GraphError: the buffered factors name no node in iSAM2 or more than one.
        """
        graph, values, held = self._buffered_problem()
        if len(held) != 1:
            raise GraphError(
                f"{ctx}: node {node} has not been through update() yet and the buffered "
                f"factors hang from {len(held)} nodes in iSAM2, not one; call update()"
            )
        try:
            return held[0], gtsam.Marginals(graph, values)
        except _GTSAM_ERRORS as exc:
            raise self._wrap(exc, ctx) from exc

    def optimize_batch(
        self,
        max_iterations: int = 100,
        *,
        loop_closure_kernels: bool = True,
        correction: bool = False,
    ) -> BatchStats:
        """Levenberg–Marquardt over every factor ever added, from the current estimate.

        Buffered nodes and factors take part (buffered nodes start at their initial value)
        and leave the buffer. Afterwards :meth:`estimate` / :meth:`estimates` return the batch
        values until the next :meth:`update`, and iSAM2 is rebuilt with every factor linearized
        at the batch result: :meth:`marginal_covariance` gives the batch marginals, and nodes
        added later are solved incrementally from the batch optimum.

        Levenberg–Marquardt as in gtsam (Marquardt 1963 diagonal damping when
        ``config.batch_diagonal_damping``), linear solver per ``config.factorization`` (with
        'auto', a Cholesky failure switches the graph to QR and the run is repeated).

        Args:
            max_iterations: iteration cap; hitting it is logged as a warning.
            loop_closure_kernels: ``False``: loop-closure factors enter this solve with their
                Gaussian noise model, their robust kernel left out (every other factor, and
                iSAM2 rebuilt afterwards, keeps its kernel); then the closures the rest of the
                graph contradicts at that optimum (:meth:`_contradicted_loops`) get their
                kernel back and the solve goes on from it (the iterations add up, the errors
                are those of the first graph before and of the last after). A run's final
                refinement over the loop closures it accepted (``iceg.slam.Slam.finish``).
            correction: a mid-run solve after a large correction (``iceg.slam``): it stops at
                ``config.correction_relative_error_tol`` instead of
                ``config.batch_relative_error_tol`` (iSAM2 goes on from its result). Keeps
                the loop closures' kernels.

        Returns:
            Iterations and errors (:class:`BatchStats`).

        Raises:
            GraphError: empty graph, a node without factor, a gtsam failure (naming the node;
                the next :meth:`update` then rebuilds iSAM2 from every factor at the estimates
                before the solve), or ``correction`` without ``loop_closure_kernels`` (the
                solver log has no step for that pair, so a session could not replay it).
        """
        if correction and not loop_closure_kernels:
            raise GraphError("optimize_batch: a correction solve keeps the loop-closure kernels")
        if not self._initial:
            raise GraphError("optimize_batch: the graph has no node")
        self._check_connected(self._pending_nodes)
        values = self._current_values()
        # iSAM2 is rebuilt at the solve's result, never read before: free it now, so the
        # solve's own memory (as large again on a long log) does not come on top of it.
        self._release_isam(values)
        code, tol = self._batch_step(correction, loop_closure_kernels)
        self._steps.append((code, int(max_iterations), len(self._records)))
        graph = self._full_graph(gaussian_loops=not loop_closure_kernels)
        error_before = graph.error(values)
        result, iterations = self._levenberg_marquardt(graph, values, int(max_iterations), tol)
        converged = iterations < max_iterations
        rebuilt = False  # iSAM2 already rebuilt at ``result``
        if not loop_closure_kernels and self.config.final_closure_consistency_chi2 is not None:
            # the closures the rest of the Gaussian optimum contradicts keep their kernel
            # (iSAM2 rebuilt at that optimum gives their relative covariances)
            self._reseed(result)
            kept = self._contradicted_loops(result)
            rebuilt = not kept
            if kept:
                graph = self._full_graph(gaussian_loops=True, keep_kernels=kept)
                self._release_isam(result)
                result, again = self._levenberg_marquardt(graph, result, int(max_iterations), tol)
                converged = converged and again < max_iterations
                iterations += again
        stats = BatchStats(iterations, error_before, graph.error(result), converged)
        _warn_if_not_converged(stats, max_iterations)
        if not rebuilt:
            self._reseed(result)
        self._served = result
        self._drop_estimates()
        return stats

    def _batch_step(self, correction: bool, loop_closure_kernels: bool) -> tuple[int, float]:
        """The solver-log step code and the relative error tolerance of a batch solve."""
        cfg = self.config
        if correction:
            return STEP_BATCH_CORRECTION, cfg.correction_relative_error_tol
        if loop_closure_kernels:
            return STEP_BATCH, cfg.batch_relative_error_tol
        return STEP_BATCH_GAUSSIAN_LOOPS, cfg.batch_relative_error_tol

    def _levenberg_marquardt(
        self,
        graph: gtsam.NonlinearFactorGraph,
        values: gtsam.Values,
        max_iterations: int,
        relative_error_tol: float,
    ) -> tuple[gtsam.Values, int]:
        """gtsam's Levenberg–Marquardt from ``values``: ``(result, iterations)``. With the
        'auto' factorization a Cholesky failure switches the graph to QR and solves again.

        Raises:
            GraphError: a gtsam failure QR does not cure.
        """
        params = gtsam.LevenbergMarquardtParams()
        params.setMaxIterations(max_iterations)
        params.setRelativeErrorTol(relative_error_tol)
        params.setAbsoluteErrorTol(1e-12)  # error units; far below any meaningful change
        params.setDiagonalDamping(self.config.batch_diagonal_damping)
        while True:
            params.setLinearSolverType("MULTIFRONTAL_QR" if self._qr else "MULTIFRONTAL_CHOLESKY")
            try:
                optimizer = gtsam.LevenbergMarquardtOptimizer(graph, values, params)
                return optimizer.optimize(), int(optimizer.iterations())
            except _GTSAM_ERRORS as exc:
                if not self._switch_to_qr(exc):
                    raise self._wrap(exc, "batch Levenberg–Marquardt") from exc

    # ------------------------------------------------------------------ reading results

    def estimate(self, node_id: int) -> FloatArray:
        """Current estimate of one node.

        Returns:
            ``(3,)`` float64 ``[x_m, y_m, theta_rad]``, world frame: the batch value after
            :meth:`optimize_batch`, else the iSAM2 estimate, else (node not yet through
            :meth:`update`) its initial value.

        Raises:
            GraphError: unknown node.
        """
        n = self._existing(node_id, f"estimate({node_id!r})")
        pose = self._pose_cache.get(n)
        if pose is None:
            pose = self._pose_cache[n] = self._read_pose(n)
        return np.array(pose, dtype=np.float64)

    def _read_pose(self, n: int) -> tuple[float, float, float]:
        """``(x, y, theta)`` of :meth:`estimate` of an existing node, read from the solver."""
        if self._served is not None and self._served.exists(n):
            return _xyt(self._served.atPose2(n))
        if self._isam is not None and n in self._in_isam:
            self._note_delta_read()
            return _xyt(self._isam.calculateEstimatePose2(n))
        if self._isam is None and self._seed is not None and self._seed.exists(n):
            return _xyt(self._seed.atPose2(n))
        x, y, t = self._initial[n].tolist()
        return x, y, t

    def estimates(self) -> tuple[NDArray[np.int64], FloatArray]:
        """Current estimates of every node, sorted by id (same sources as :meth:`estimate`).

        The arrays are built once per state of the graph (after each :meth:`add_node`,
        :meth:`update`, :meth:`optimize_batch`) and cached; each call returns copies.

        Returns:
            ``ids`` ``(N,)`` int64 ascending, and ``poses`` ``(N, 3)`` float64
            ``[x_m, y_m, theta_rad]`` in the world frame.
        """
        if self._estimates is None:
            self._estimates = self._read_estimates()
        ids, poses = self._estimates
        return ids.copy(), poses.copy()

    def estimates_of(self, node_ids: ArrayLike) -> tuple[NDArray[np.int64], FloatArray]:
        """Current estimates of some nodes: the same values as the rows of :meth:`estimates`,
        the same bits as :meth:`estimate` of each node, read in one iSAM2 call for the nodes
        not yet read in this state of the graph (O(k), not O(N), when :meth:`estimates` is
        not cached).

        Args:
            node_ids: ``(k,)`` node ids (repeats allowed).

        Returns:
            ``ids`` ``(m,)`` int64, the sorted unique ``node_ids``, and ``poses`` ``(m, 3)``
            float64 ``[x_m, y_m, theta_rad]``, world frame.

        Raises:
            GraphError: an unknown node.
        """
        ids = sorted_unique(node_ids)
        if self._estimates is not None:
            all_ids, all_poses = self._estimates
            pos = np.searchsorted(all_ids, ids)
            ok = (pos < all_ids.shape[0]) & (all_ids[np.minimum(pos, all_ids.shape[0] - 1)] == ids)
            if bool(np.all(ok)):
                return ids, all_poses[pos].copy()
        out = np.empty((ids.shape[0], 3))
        todo: NDArray[np.bool_] | slice = slice(None)
        if self._solver_rows is not None:  # the solver's nodes, from its last full read
            solver_ids, solver_poses = self._solver_rows
            pos = np.minimum(np.searchsorted(solver_ids, ids), solver_ids.shape[0] - 1)
            held = solver_ids[pos] == ids
            out[held] = solver_poses[pos[held]]
            todo = ~held
            nodes = ids[todo].tolist()
        else:
            nodes = ids.tolist()
        cache = self._pose_cache
        # Ascending, as ``ids``; after a solver change the cache is empty.
        missing = [n for n in nodes if n not in cache] if cache else nodes
        if missing:
            # Straight from iSAM2 when it serves the estimates (the common case; its nodes
            # are all in ``initial``): one call for all of them, the same values as a call
            # per node, else as estimate() reads them.
            in_isam = self._in_isam if self._isam is not None and self._served is None else set()
            solver = (
                missing if in_isam.issuperset(missing) else [n for n in missing if n in in_isam]
            )
            if solver:
                self._note_delta_read()
                values = self._isam.calculateEstimate(solver)  # type: ignore[union-attr]
                read = gtsam.utilities.extractPose2(values)  # rows in ascending key order
                cache.update(zip(solver, map(tuple, read.tolist()), strict=True))
                if len(solver) == len(nodes):  # all of them from this read (after an update)
                    out[todo] = read
                    return ids, out
            for n in missing:
                if n not in cache:
                    if n not in self._initial:
                        self._existing(n, f"estimate({n!r})")  # raises
                    cache[n] = self._read_pose(n)
        out[todo] = np.array([cache[n] for n in nodes], dtype=np.float64).reshape(-1, 3)
        return ids, out

    def _drop_estimates(self) -> None:
        """Forget every cached estimate (the solver state changed)."""
        self._estimates = None
        self._pose_cache.clear()
        self._solver_rows = None

    def _sorted_ids(self) -> NDArray[np.int64]:
        """``(N,)`` int64 node ids, ascending (cached until the next :meth:`add_node`)."""
        if self._ids is None:
            ids = np.fromiter(self._initial, dtype=np.int64, count=len(self._initial))
            if ids.size > 1 and not bool(np.all(ids[1:] > ids[:-1])):
                ids.sort()
            self._ids = ids
        return self._ids

    def _read_estimates(self) -> tuple[NDArray[np.int64], FloatArray]:
        """Every node's estimate (:meth:`estimates`): the solver's rows (from its last full
        read while it has not changed them) and the buffered nodes' initial values as they
        are, the values :meth:`estimate` gives each node. (gtsam's rows of a buffered node
        would be its initial value through a ``Pose2``, whose heading can differ in the last
        bit: a run's results would then depend on whether it read one node or all.)"""
        ids = self._sorted_ids().copy()
        if ids.size == 0:
            return ids, np.zeros((0, 3))
        pending = sorted(self._pending_nodes)
        held = np.ones(ids.shape[0], dtype=bool)
        held[np.searchsorted(ids, pending)] = False
        if self._solver_rows is None:
            values = self._current_values()
            # Values hold exactly the nodes of _initial, in ascending key order.
            poses = np.asarray(gtsam.utilities.extractPose2(values), dtype=np.float64)
            poses = poses.reshape(-1, 3)
            solver_nodes = (
                self._served.size()
                if self._served is not None
                else len(self._in_isam)
                if self._isam is not None
                else 0
            )
            if solver_nodes and solver_nodes == int(held.sum()):
                self._solver_rows = ids[held], poses[held]
        else:
            poses = np.empty((ids.shape[0], 3))
            poses[held] = self._solver_rows[1]
        if pending:
            poses[~held] = [self._initial[n] for n in pending]
        return ids, poses

    def marginal_covariance(self, node_id: int) -> FloatArray:
        """Marginal covariance of a node from iSAM2's Bayes tree.

        After :meth:`optimize_batch` it is the batch marginal (iSAM2 is re-linearized at the
        batch result).

        A node buffered since the last update (:meth:`solve_pending`) whose buffered factors
        hang from one node ``c`` in iSAM2 (a chain of keyframes): ``A P_c Aᵀ + C``, with ``C``
        its covariance given ``c`` and ``A = Ad(d^-1)``, ``d`` the relative pose ``c -> node``
        (right perturbations): iSAM2's marginal once it is updated, to first order.

        Returns:
            ``(3, 3)`` float64 ``P`` with ``pose = estimate ∘ Exp(xi)``, ``xi ~ N(0, P)``: the
            tangent space of the pose (its body frame), ``(x, y, theta)`` order, m² / rad².

        Raises:
            GraphError: unknown node, a buffered node not hanging from one node in iSAM2, or
                the last update failed.
        """
        ctx = f"marginal_covariance({node_id!r})"
        n = self._existing(node_id, ctx)
        if self._isam is None:
            raise GraphError(f"{ctx}: the last update failed; fix the graph and call update()")
        if n not in self._in_isam:
            # X_n = X_c d Exp(e), e given the anchor c: P_n = A P_c Aᵀ + C_n, A = Ad(d^-1)
            anchor, given = self._given_anchor(n, ctx)
            adj = se2.adjoint(se2.between(self.estimate(n), self.estimate(anchor)))
            cov = adj @ self.marginal_covariance(anchor) @ adj.T + given.marginalCovariance(n)
            return 0.5 * (cov + cov.T)
        try:
            cov = np.asarray(self._isam.marginalCovariance(n), dtype=np.float64)
        except _GTSAM_ERRORS as exc:
            raise self._wrap(exc, ctx) from exc
        return 0.5 * (cov + cov.T)

    def relative_covariance(self, i: int, j: int) -> FloatArray:
        """Covariance of the relative pose ``estimate(i)^-1 ∘ estimate(j)`` from the joint
        marginal of the two nodes in iSAM2's Bayes tree (``jointMarginalCovariance``).

        With right perturbations ``X_i Exp(a)``, ``X_j Exp(b)`` the relative pose moves by
        ``b - A a``, ``A = Ad((X_i^-1 X_j)^-1)``, so ``C = Σ_jj + A Σ_ii Aᵀ - A Σ_ij - Σ_ji Aᵀ``.
        Unlike either node's marginal, it does not grow with the uncertainty the two nodes
        share (the first node's prior, the heading error of everything before them).

        Args:
            i: The first node's id (the frame of the relative pose).
            j: The second node's id.

        Returns:
            ``(3, 3)`` float64, tangent space of the relative pose, ``(x, y, theta)``, m² /
            rad².

        Raises:
            GraphError: unknown node, a buffered node not hanging from one node in iSAM2
                (:meth:`marginal_covariance` says how buffered nodes are answered), ``i == j``,
                or the last update failed.
        """
        ctx = f"relative_covariance({i!r}, {j!r})"
        a, b = self._existing(i, ctx), self._existing(j, ctx)
        if a == b:
            raise GraphError(f"{ctx}: the two nodes must differ")
        if self._isam is None:
            raise GraphError(f"{ctx}: the last update failed; fix the graph and call update()")
        if a not in self._in_isam or b not in self._in_isam:
            return self._relative_buffered(a, b, ctx)
        try:
            joint = self._isam.jointMarginalCovariance([a, b])
            # the joint caches shortcut marginals in the cliques it walked; left there they
            # made every later update slower (iSAM2 2.9 -> 4.6 s on 10k corridor scans)
            self._isam.deleteCachedShortcuts()
        except _GTSAM_ERRORS as exc:
            raise self._wrap(exc, ctx) from exc
        return self._relative_from_joint(a, b, joint)

    def _relative_from_joint(self, a: int, b: int, joint: gtsam.JointMarginal) -> FloatArray:
        """The covariance of :meth:`relative_covariance` from a joint marginal of the two."""
        s_ii, s_jj, s_ij = (np.asarray(joint.at(*k)) for k in ((a, a), (b, b), (a, b)))
        adj = se2.adjoint(se2.between(self.estimate(b), self.estimate(a)))
        cov = s_jj + adj @ s_ii @ adj.T - adj @ s_ij - s_ij.T @ adj.T
        return 0.5 * (cov + cov.T)

    def _relative_buffered(self, a: int, b: int, ctx: str) -> FloatArray:
        """:meth:`relative_covariance` with a buffered node (:meth:`solve_pending`), from the
        buffered nodes' covariances given their anchor ``c`` in iSAM2: ``X_b = X_c d Exp(e)``."""
        if b in self._in_isam:  # only a is buffered: the relative pose b -> a, inverted
            adj = se2.adjoint(se2.between(self.estimate(b), self.estimate(a)))
            cov = adj @ self._relative_buffered(b, a, ctx) @ adj.T
            return 0.5 * (cov + cov.T)
        anchor, given = self._given_anchor(b, ctx)
        if a not in self._in_isam:  # both buffered: the anchor's own error cancels
            try:
                joint = given.jointMarginalCovariance([a, b])
            except _GTSAM_ERRORS as exc:
                raise self._wrap(exc, ctx) from exc
            return self._relative_from_joint(a, b, joint)
        cov = given.marginalCovariance(b)
        if a != anchor:  # the relative pose a -> c, carried on through d
            adj = se2.adjoint(se2.between(self.estimate(b), self.estimate(anchor)))
            cov = cov + adj @ self.relative_covariance(a, anchor) @ adj.T
        return 0.5 * (cov + cov.T)

    def residual_errors(self) -> dict[str, float]:
        """Sum of the factor errors per kind at the current estimate.

        A factor's error is gtsam's objective term: ``0.5 · e^T Σ^-1 e`` for a Gaussian factor
        (half its chi²), the M-estimator loss of the Mahalanobis distance for a robust one. The
        values sum to the total error the optimizers minimize.

        Returns:
            ``{kind value: error}`` for every kind present (keys ``"prior"``, ``"odometry"``,
            ``"scan_match"``, ``"loop_closure"``).
        """
        values = self._current_values()
        sums: dict[str, float] = {}
        for record, factor in zip(self._records, self._gfactors, strict=True):
            key = record.kind.value
            sums[key] = sums.get(key, 0.0) + float(factor.error(values))
        return sums

    @property
    def factors(self) -> tuple[FactorRecord, ...]:
        """Every factor's record, in insertion order (read-only)."""
        return tuple(self._records)

    def factors_from(self, start: int) -> tuple[FactorRecord, ...]:
        """The records of the factors added from index ``start`` on (``factors[start:]``
        without building the whole tuple: O(new factors), for callers that follow the graph
        as it grows)."""
        return tuple(self._records[start:])

    @property
    def n_factors(self) -> int:
        """Number of factors, priors included."""
        return len(self._records)

    @property
    def n_nodes(self) -> int:
        """Number of nodes."""
        return len(self._initial)

    @property
    def isam2_factor_count(self) -> int:
        """Number of factors held by gtsam's iSAM2 (each factor exactly once after update())."""
        return 0 if self._isam is None else int(self._isam.getFactorsUnsafe().nrFactors())

    @property
    def factorization(self) -> str:
        """Factorization in use: ``"qr"`` or ``"cholesky"`` ('auto' may have moved to QR)."""
        return "qr" if self._qr else "cholesky"

    @property
    def n_pending(self) -> tuple[int, int]:
        """``(nodes, factors)`` buffered for the next :meth:`update`."""
        return len(self._pending_nodes), len(self._pending_factors)

    def __repr__(self) -> str:
        kinds = Counter(r.kind.value for r in self._records)
        pending_nodes, pending_factors = self.n_pending
        return (
            f"PoseGraph(nodes={self.n_nodes}, factors={self.n_factors} {dict(kinds)}, "
            f"pending={pending_nodes} nodes/{pending_factors} factors)"
        )

    # ------------------------------------------------------------------ g2o

    def write_g2o(self, path: str | os.PathLike[str]) -> None:
        """Write the graph to a 2D g2o file, atomically (see :func:`graph.g2o.write_g2o_file`).

        Vertices are the current estimates (:meth:`estimates`); edges carry the information
        matrix ``inv(cov)``; kinds, robust kernels and priors follow as ``# ICEG_*`` comment
        lines after the last record. Floats are written exactly (``repr``).

        Raises:
            GraphError: the file cannot be written.
        """
        ids, poses = self.estimates()
        write_g2o_file(path, ids, poses, self._records)

    @classmethod
    def read_g2o(cls, path: str | os.PathLike[str], config: GraphConfig | None = None) -> PoseGraph:
        """Build a graph from a 2D g2o file (read through ``gtsam.readG2o``, is3D=False).

        Nodes get the file's vertex poses as initial values; nothing is optimized yet (call
        :meth:`update` or :meth:`optimize_batch`). Priors come from ``# ICEG_PRIOR`` lines when
        the file has them, else the automatic prior is put on the smallest id. Kinds come from
        ``# ICEG_EDGE`` lines, else ``j == i + 1`` is odometry and any other edge a loop
        closure. The raw edge list is :func:`graph.load_g2o`.

        Raises:
            GraphError: the file is missing or malformed (see :func:`graph.load_g2o`).
        """
        data = load_g2o(path)
        graph = cls(config, auto_prior=not data.priors)
        for n, pose in zip(data.node_ids.tolist(), data.poses, strict=True):
            graph.add_node(n, pose)
        for what, idx in data.factor_order:
            if what == "prior":
                prior = data.priors[idx]
                graph.add_prior(prior.node, prior.pose, prior.cov)
                continue
            k = float(data.edge_robust_k[idx])
            graph.add_between(
                int(data.edge_ij[idx, 0]),
                int(data.edge_ij[idx, 1]),
                data.edge_measured[idx],
                data.edge_cov[idx],
                kind=data.edge_kind[idx],
                robust=data.edge_robust[idx],  # type: ignore[arg-type]
                robust_k=None if np.isnan(k) else k,
            )
        return graph

    # ------------------------------------------------------------------ replay log

    @property
    def steps(self) -> tuple[tuple[int, int, int], ...]:
        """Log of the solver calls, in order, for an exact rebuild (``iceg.session``).

        Each step is ``(code, a, b)``: ``(STEP_UPDATE, nodes, factors)`` an :meth:`update`
        when the graph held ``nodes`` nodes and ``factors`` factors; ``(STEP_DELTA, 0, 0)``
        the first read of an iSAM2 estimate after an update (gtsam solves its delta lazily,
        so when it is read changes later floating point); ``(STEP_BATCH, max_iterations,
        factors)`` an :meth:`optimize_batch` (``STEP_BATCH_GAUSSIAN_LOOPS`` one without the
        loop closures' kernels, ``STEP_BATCH_CORRECTION`` a ``correction`` solve). Replaying
        the same node and factor additions with these calls (``iceg.session.replay_graph``)
        gives the same iSAM2 state bit for bit.
        """
        return tuple(self._steps)

    def initial_pose(self, node_id: int) -> FloatArray:
        """Initial value ``(3,)`` ``[x_m, y_m, theta_rad]`` (world frame) a node was added with.

        Raises:
            GraphError: unknown node.
        """
        return self._initial[self._existing(node_id, f"initial_pose({node_id!r})")].copy()

    def read_delta(self) -> None:
        """Make iSAM2 solve its pending delta now, as a first estimate read does (replay)."""
        if self._isam is not None and self._in_isam:
            self._note_delta_read()
            self._isam.calculateEstimate()

    def _note_delta_read(self) -> None:
        if not self._delta_read:
            self._delta_read = True
            self._steps.append((STEP_DELTA, 0, 0))

    # ------------------------------------------------------------------ internals

    def _new_isam(self) -> gtsam.ISAM2:
        params = gtsam.ISAM2Params()
        cfg = self.config
        if cfg.relinearize_threshold_xy_m is None:
            params.setRelinearizeThreshold(cfg.relinearize_threshold)
        else:  # per component of the Pose2 tangent (x, y, theta), by the key's top byte
            thresholds = gtsam.ISAM2ThresholdMap()
            xy = cfg.relinearize_threshold_xy_m
            vector = np.array([xy, xy, cfg.relinearize_threshold])
            for top in range((_MAX_NODE_ID >> 56) + 1):  # every top byte of a node id
                thresholds.insert((chr(top), vector))
            params.setRelinearizeThreshold(thresholds)
        params.relinearizeSkip = cfg.relinearize_skip
        params.setFactorization("QR" if self._qr else "CHOLESKY")
        return gtsam.ISAM2(params)

    def _record(
        self,
        factor: gtsam.NonlinearFactor,
        kind: FactorKind,
        i: int,
        j: int | None,
        measured: FloatArray,
        cov: FloatArray,
        robust: str | None,
        robust_k: float | None,
    ) -> FactorRecord:
        index = len(self._records)
        record = FactorRecord(
            index, kind, i, j, _readonly(measured), _readonly(cov), robust, robust_k
        )
        self._records.append(record)
        self._gfactors.append(factor)
        self._pending_factors.append(index)
        self._factors_of[i].append(index)
        if j is not None:
            self._factors_of[j].append(index)
        return record

    def _full_graph(
        self, gaussian_loops: bool = False, keep_kernels: frozenset[int] = frozenset()
    ) -> gtsam.NonlinearFactorGraph:
        """Every factor; with ``gaussian_loops`` the robust loop closures as Gaussian ones,
        but those whose index is in ``keep_kernels``."""
        graph = gtsam.NonlinearFactorGraph()
        for record, factor in zip(self._records, self._gfactors, strict=True):
            j = record.j
            loop = record.kind is FactorKind.LOOP_CLOSURE and record.robust is not None
            if gaussian_loops and loop and j is not None and record.index not in keep_kernels:
                model = self._gaussian(np.asarray(record.cov), "loop closure")
                factor = gtsam.BetweenFactorPose2(record.i, j, _pose2(record.measured), model)
            graph.add(factor)
        return graph

    def _contradicted_loops(self, values: gtsam.Values) -> frozenset[int]:
        """Indices of the robust loop closures the rest of the graph contradicts at ``values``
        (the estimate iSAM2 was rebuilt at), which keep their kernel in a final refinement.

        A closure ``z`` between nodes ``i`` and ``j`` with residual ``e = z^-1 ∘ X_i^-1 X_j``
        is contradicted when ``eᵀ (C + Σ)⁻¹ e > config.final_closure_consistency_chi2``, with
        ``Σ`` its covariance and ``C`` the covariance of ``X_i^-1 X_j`` given every factor but
        it: the relative covariance of the joint marginal (:meth:`relative_covariance`, iSAM2)
        with the closure's own information taken out, ``C = (C_all⁻¹ - w Σ⁻¹)⁻¹`` (its factor
        is linear in the relative pose to first order; ``w`` its kernel's weight at the
        residual). A leave-one-out test of the closure against the rest of the graph,
        modelled on the chi-square test of pairwise consistency (Mangelson et al. 2018, PCM)
        with the whole graph as the other measurement. A closure within the gate under ``Σ`` alone,
        one that is all that constrains its relative pose (``C`` not positive definite) and
        one whose relative covariance cannot be read (no iSAM2, a node not in it) is not
        contradicted."""
        gate = self.config.final_closure_consistency_chi2
        if gate is None or self._isam is None:  # no test, or no marginals to test with
            return frozenset()
        kept: list[int] = []
        for r in self._records:
            if r.kind is not FactorKind.LOOP_CLOSURE or r.robust is None or r.j is None:
                continue
            rel = values.atPose2(r.i).between(values.atPose2(r.j))
            e = se2.between(r.measured, np.array([rel.x(), rel.y(), rel.theta()]))
            info = np.linalg.inv(r.cov)
            d2 = float(e @ info @ e)
            if d2 <= gate:
                continue
            try:
                info_all = np.linalg.inv(self.relative_covariance(r.i, r.j))
            except (GraphError, np.linalg.LinAlgError):
                continue
            # the kernel's weight at the residual (IRLS, gtsam's mEstimator::weight)
            weight = _m_estimator(r.robust, r.robust_k).weight(float(np.sqrt(d2)))
            info_rest = info_all - weight * info
            if np.linalg.eigvalsh(0.5 * (info_rest + info_rest.T))[0] <= 0.0:
                continue
            d2_rest = float(e @ np.linalg.solve(np.linalg.inv(info_rest) + r.cov, e))
            if d2_rest > gate:
                logger.debug(
                    "loop closure %d->%d keeps its kernel: chi2 %.1f against the rest of the graph",
                    r.i,
                    r.j,
                    d2_rest,
                )
                kept.append(r.index)
        if kept:
            logger.info(
                "final refinement: %d loop closures the rest of the graph contradicts keep "
                "their kernel",
                len(kept),
            )
        return frozenset(kept)

    def _current_values(self) -> gtsam.Values:
        """Estimate of every node as gtsam Values (served, iSAM2 or seed, then initial)."""
        # With iSAM2 (and the batch values it was rebuilt at) every node is in iSAM2 or
        # buffered: only the buffered ones can be missing (no O(N) loop per call).
        missing: Iterable[int] = self._pending_nodes
        if self._served is not None:
            values = gtsam.Values(self._served)
        elif self._isam is not None:
            if self._in_isam:
                self._note_delta_read()
            values = self._isam.calculateEstimate() if self._in_isam else gtsam.Values()
        else:
            values = gtsam.Values(self._seed) if self._seed is not None else gtsam.Values()
            missing = self._initial
        for n in missing:
            if not values.exists(n):
                values.insert(n, _pose2(self._initial[n]))
        return values

    def _seed_values(self) -> gtsam.Values:
        values = gtsam.Values(self._seed) if self._seed is not None else gtsam.Values()
        for n, pose in self._initial.items():
            if not values.exists(n):
                values.insert(n, _pose2(pose))
        return values

    def _mark_broken(self) -> None:
        """After a gtsam failure inside iSAM2: keep its linearization point, drop the object."""
        seed = gtsam.Values()
        if self._isam is not None:
            try:
                lin = self._isam.getLinearizationPoint()
                for n in self._in_isam:
                    if lin.exists(n):
                        seed.insert(n, lin.atPose2(n))
            except _GTSAM_ERRORS:
                logger.warning("iSAM2 linearization point unreadable after a failed update")
        self._release_isam(seed)

    def _release_isam(self, values: gtsam.Values) -> None:
        """Drop iSAM2 and its memory, keeping ``values`` (every node's current estimate) as
        the seed: until the next rebuild the estimates read the same, and after a failure
        the next :meth:`update` rebuilds iSAM2 from every factor at them."""
        self._seed = gtsam.Values(values)
        self._isam = None
        self._in_isam.clear()
        self._drop_estimates()

    def _reseed(self, values: gtsam.Values) -> UpdateStats:
        """Rebuild iSAM2 from every factor, linearized at ``values``; clears the buffer. The
        old iSAM2 is dropped first, so the two are never held at once."""
        self._isam = None
        while True:
            isam = self._new_isam()
            try:
                result = isam.update(self._full_graph(), values)
                break
            except _GTSAM_ERRORS as exc:
                if self._switch_to_qr(exc):
                    continue
                self._release_isam(values)
                raise self._wrap(exc, "iSAM2 rebuild") from exc
        self._isam = isam
        self._seed = None
        self._served = None
        self._drop_estimates()
        self._in_isam = set(self._initial)
        stats = UpdateStats(
            new_nodes=len(self._initial),
            new_factors=len(self._gfactors),
            relinearized=int(result.getVariablesRelinearized()),
            reeliminated=int(result.getVariablesReeliminated()),
            reseeded=True,
        )
        self._pending_nodes.clear()
        self._pending_factors.clear()
        return stats

    def _switch_to_qr(self, exc: BaseException) -> bool:
        """With factorization 'auto', move from Cholesky to QR after an indeterminant system."""
        if self._qr or self.config.factorization != "auto":
            return False
        if not _NEAR_VARIABLE.search(str(exc)):
            return False
        self._qr = True
        logger.warning(
            "Cholesky found an indeterminant system (%s); switching this graph to QR",
            str(exc).strip().splitlines()[0] if str(exc).strip() else "",
        )
        return True

    def _check_connected(self, nodes: list[int]) -> None:
        for n in nodes:
            if not self._factors_of[n]:
                raise GraphError(
                    f"node {n} has no factor: add a between-factor (or a prior) that links it "
                    "to the graph before update()"
                )

    def _describe(self, node: int) -> str:
        indices = self._factors_of.get(node, [])
        parts = []
        for idx in indices[:6]:
            r = self._records[idx]
            parts.append(f"{r.kind.value} {r.i}" if r.j is None else f"{r.kind.value} {r.i}-{r.j}")
        more = f", ... ({len(indices)} in all)" if len(indices) > 6 else ""
        return f"its factors: {', '.join(parts)}{more}" if parts else "it has no factor"

    def _wrap(self, exc: BaseException, action: str) -> GraphError:
        text = str(exc).strip()
        near = _NEAR_VARIABLE.search(text)
        if near:
            node = int(near.group(1))
            hint = "" if self._qr else " (try factorization='qr')"
            return GraphError(
                f"{action}: indeterminant linear system near node {node} ({self._describe(node)})"
                ": the node is under-constrained (no path of factors to a prior, or a covariance "
                "so large in some direction that it constrains nothing) or the system is too "
                f"ill-conditioned for the {self.factorization} factorization{hint}"
            )
        missing = _MISSING_KEY.search(text)
        if missing:
            return GraphError(f"{action}: node {missing.group(1)} has no initial value in gtsam")
        first = text.splitlines()[0] if text else ""
        return GraphError(f"{action}: gtsam raised {type(exc).__name__}: {first}")

    def _node_id(self, node_id: object, ctx: str) -> int:
        try:
            n = operator.index(node_id)  # type: ignore[arg-type]
        except TypeError:
            raise GraphError(f"{ctx}: node id must be an integer, got {node_id!r}") from None
        if n < 0 or n > _MAX_NODE_ID:
            raise GraphError(
                f"{ctx}: node id must be non-negative and below 2**63 (a gtsam key, stored as "
                f"int64), got {n}"
            )
        return int(n)

    def _existing(self, node_id: object, ctx: str) -> int:
        n = self._node_id(node_id, ctx)
        if n not in self._initial:
            raise GraphError(f"{ctx} references unknown node {n}: add_node({n}, pose) first")
        return n

    @staticmethod
    def _vector3(value: ArrayLike, what: str, ctx: str) -> FloatArray:
        try:
            v = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise GraphError(f"{ctx}: {what} is not numeric: {value!r}") from None
        if v.shape != (3,) or not all(math.isfinite(x) for x in v.tolist()):
            raise GraphError(
                f"{ctx}: {what} must be a finite (3,) [x_m, y_m, theta_rad], got shape "
                f"{v.shape} {v.tolist()}"
            )
        return v

    @staticmethod
    def _covariance(value: ArrayLike, ctx: str) -> FloatArray:
        try:
            c = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise GraphError(f"{ctx}: covariance is not numeric: {value!r}") from None
        # The checks on the nine numbers as floats (a factor per keyframe and more: numpy's
        # calls on a 3 x 3 cost five times as much); the returned matrix is numpy's.
        rows = c.tolist() if c.shape == (3, 3) else None
        if rows is None or not all(math.isfinite(x) for row in rows for x in row):
            raise GraphError(
                f"{ctx}: covariance must be a finite (3, 3) matrix in (x, y, theta) order, got "
                f"shape {c.shape}"
            )
        (a00, a01, a02), (a10, a11, a12), (a20, a21, a22) = rows
        scale = max(abs(x) for row in rows for x in row)
        if max(abs(a01 - a10), abs(a02 - a20), abs(a12 - a21)) > 1e-9 * scale:
            raise GraphError(f"{ctx}: covariance is not symmetric: {rows}")
        # 0.5 * (c + c.T), entry by entry (the same operations on the same floats)
        s01, s02, s12 = 0.5 * (a01 + a10), 0.5 * (a02 + a20), 0.5 * (a12 + a21)
        sym = [
            [0.5 * (a00 + a00), s01, s02],
            [s01, 0.5 * (a11 + a11), s12],
            [s02, s12, 0.5 * (a22 + a22)],
        ]
        c = np.array(sym)
        if not _clearly_positive_definite(sym):
            try:
                np.linalg.cholesky(c)
            except np.linalg.LinAlgError:
                eig = np.linalg.eigvalsh(c)
                raise GraphError(
                    f"{ctx}: covariance is not positive definite (eigenvalues {eig.tolist()}); "
                    "every direction needs a positive variance"
                ) from None
        return c

    @staticmethod
    def _gaussian(cov: FloatArray, ctx: str) -> gtsam.noiseModel.Base:
        try:
            return gtsam.noiseModel.Gaussian.Covariance(cov)
        except _GTSAM_ERRORS as exc:
            raise GraphError(f"{ctx}: gtsam rejected the covariance: {exc}") from exc


#: Least pivot of :func:`_clearly_positive_definite`, relative to its diagonal entry: far
#: above the rounding of the elimination, so that LAPACK's Cholesky succeeds wherever the
#: test does.
_PIVOT_MARGIN = 1e-9


def _clearly_positive_definite(c: list[list[float]]) -> bool:
    """Whether the symmetric ``(3, 3)`` ``c`` (rows of floats) is positive definite with
    every pivot of its ``L D L^T`` elimination above :data:`_PIVOT_MARGIN` of its diagonal
    entry, in floats (False: too close to call here; ``np.linalg.cholesky`` decides)."""
    (a00, a01, a02), (_, a11, a12), (_, _, a22) = c
    if not a00 > 0.0:
        return False
    l10, l20 = a01 / a00, a02 / a00
    d1 = a11 - l10 * a01
    if not d1 > _PIVOT_MARGIN * abs(a11):
        return False
    l21 = (a12 - l20 * a01) / d1
    d2 = a22 - l20 * a02 - l21 * l21 * d1
    return d2 > _PIVOT_MARGIN * abs(a22)


def _warn_if_not_converged(stats: BatchStats, max_iterations: int) -> None:
    """Log a warning when a batch solve stopped at its iteration cap."""
    if not stats.converged:
        logger.warning(
            "optimize_batch: no convergence in %d iterations (error %.6g -> %.6g)",
            max_iterations,
            stats.error_before,
            stats.error_after,
        )


def _m_estimator(
    robust: str, k: float | None
) -> gtsam.noiseModel.mEstimator.Huber | gtsam.noiseModel.mEstimator.Cauchy:
    """gtsam's M-estimator of a kernel name (``"huber"`` or ``"cauchy"``) and width ``k``
    (standard deviations; None: its 95 %-efficiency value, :data:`HUBER_K_95`,
    :data:`CAUCHY_K_95`)."""
    m_est = gtsam.noiseModel.mEstimator
    if robust == "huber":
        return m_est.Huber.Create(HUBER_K_95 if k is None else k)
    return m_est.Cauchy.Create(CAUCHY_K_95 if k is None else k)
