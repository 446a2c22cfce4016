"""Covariance consistency of a run against ground truth: the normalized estimation error
squared (NEES) of its factors and of its node estimates.

A covariance is honest when the errors it describes are as large as it says. For a Gaussian
error ``e`` of ``d`` degrees of freedom with covariance ``P``, ``NEES = eᵀ P⁻¹ e`` follows a
chi-square distribution with ``d`` degrees of freedom (mean ``d``): a mean far above 3 for a
planar pose is an overconfident covariance (the graph trusts that measurement or estimate
more than its errors deserve), far below a conservative one (Bar-Shalom, Li and
Kirubarajan, *Estimation with Applications to Tracking and Navigation*, Wiley 2001, §5.4.2).

Errors are taken in gtsam's convention, so a factor's NEES is twice its Gaussian error at the
true poses: for a between-factor ``z`` with covariance ``Σ`` and true relative pose ``T``,
``e = Log(z⁻¹ ∘ T)`` (:func:`graph.local_coordinates`); for a node estimate ``x`` with
marginal ``P`` (``pose = x ∘ Exp(ξ)``, ``PoseGraph.marginal_covariance``) and true pose
``t``, ``e = Log(x⁻¹ ∘ t)``. Robust kernels are left out: the NEES is that of the factor's
Gaussian noise model, which the kernel only reweights.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import numpy as np
from numpy.typing import ArrayLike, NDArray

from frontends.relations import Relations, match_stamps
from graph import FactorRecord, local_coordinates
from iceg_common import se2
from iceg_common.errors import EvaluationError

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Degrees of freedom of a planar pose error ``[x, y, theta]``.
POSE_DOF = 3

#: The summaries' default confidence.
NEES_CONFIDENCE = 0.95

#: ``scipy.special.chdtri(3, 1 - NEES_CONFIDENCE)``, the chi-square (3 dof) quantile, bit for
#: bit (``test_the_default_bound_is_scipy_s_quantile``), written out: a run scored against
#: relations then imports no ``scipy.special`` (43-86 ms at the run's end).
_BOUND_3DOF = 7.814727903251179


@dataclass(frozen=True)
class NeesSummary:
    """The NEES of a set of 3-dof errors against its chi-square distribution.

    Attributes:
        count: Errors summarized.
        mean: Mean NEES (3 for an honest covariance).
        median: Median NEES (2.37 for an honest covariance).
        p90: 90th percentile (6.25 for an honest covariance).
        bound: The chi-square (3 dof) quantile at ``confidence``.
        beyond_bound: Fraction of the errors whose NEES exceeds ``bound`` (``1 - confidence``
            for an honest covariance).
        scale: ``mean / 3``: the factor by which the covariances would have to grow for a
            mean NEES of 3.
    """

    count: int
    mean: float
    median: float
    p90: float
    bound: float
    beyond_bound: float
    scale: float


def summarize_nees(nees: ArrayLike, confidence: float = NEES_CONFIDENCE) -> NeesSummary:
    """:class:`NeesSummary` of 3-dof NEES values (NaN values are left out).

    Args:
        nees: ``(k,)`` float64 NEES values.
        confidence: Probability of the chi-square bound, in ``(0, 1)``.

    Raises:
        EvaluationError: no finite value, or ``confidence`` outside ``(0, 1)``.
    """
    if not 0.0 < confidence < 1.0:
        raise EvaluationError(f"confidence must lie in (0, 1), not {confidence}")
    values = np.asarray(nees, dtype=np.float64).ravel()
    values = values[np.isfinite(values)]
    if values.size == 0:
        raise EvaluationError("no finite NEES value to summarize")
    bound = _BOUND_3DOF if confidence == NEES_CONFIDENCE else _chi2_quantile(confidence)
    mean = float(values.mean())
    return NeesSummary(
        count=int(values.size),
        mean=mean,
        median=float(np.median(values)),
        p90=float(np.quantile(values, 0.9)),
        bound=bound,
        beyond_bound=float(np.mean(values > bound)),
        scale=mean / POSE_DOF,
    )


def _chi2_quantile(confidence: float) -> float:
    """The chi-square quantile of 3 degrees of freedom at ``confidence``."""
    from scipy.special import chdtri  # lazy; scipy.stats would take 0.6 s to import

    return float(chdtri(POSE_DOF, 1.0 - confidence))


@dataclass(frozen=True)
class FactorNees:
    """The NEES of a run's between-factors against true relative poses.

    Attributes:
        kind: ``(k,)`` str factor kinds (``graph.FactorKind`` values: ``"odometry"``,
            ``"scan_match"``, ``"loop_closure"``).
        i: ``(k,)`` int64 first node of each factor.
        j: ``(k,)`` int64 second node.
        error: ``(k, 3)`` float64 ``Log(z⁻¹ ∘ T)`` ``[x_m, y_m, theta_rad]``: the tangent vector
            at the measurement ``z`` that reaches the true relative pose ``T`` (the factor's
            frame, gtsam's error convention).
        nees: ``(k,)`` float64 ``errorᵀ Σ⁻¹ error`` under the factor's covariance ``Σ``.
    """

    kind: NDArray[np.str_]
    i: IntArray
    j: IntArray
    error: FloatArray
    nees: FloatArray

    def summary(self, confidence: float = NEES_CONFIDENCE) -> dict[str, NeesSummary]:
        """:func:`summarize_nees` per factor kind present, in order of first appearance."""
        kinds = dict.fromkeys(self.kind.tolist())
        return {k: summarize_nees(self.nees[self.kind == k], confidence) for k in kinds}


def factor_nees(factors: Iterable[FactorRecord], node_truth: ArrayLike) -> FactorNees:
    """The NEES of every between-factor whose two nodes have a true pose.

    Args:
        factors: The run's factors (``SlamResult.factors``); priors are skipped.
        node_truth: ``(N, 3)`` float64 true pose ``[x_m, y_m, theta_rad]`` of node ``n`` in row
            ``n``, any fixed world frame; a row of NaN (or a node past the last row) marks a
            node without truth, whose factors are skipped. A simulated run gives it as
            ``true_poses[result.node_scan_index]`` over ``result.node_ids``
            (:func:`per_node`).

    Returns:
        :class:`FactorNees`, factors in the given order.

    Raises:
        EvaluationError: ``node_truth`` is not ``(N, 3)``, or a factor's covariance is not
            positive definite.
    """
    truth = np.asarray(node_truth, dtype=np.float64)
    if truth.ndim != 2 or truth.shape[1] != 3:
        raise EvaluationError(f"node_truth must be (N, 3) poses, got {truth.shape}")
    known = np.all(np.isfinite(truth), axis=1)

    def true_relative(f: FactorRecord) -> FloatArray | None:
        assert f.j is not None
        if max(f.i, f.j) >= truth.shape[0] or not (known[f.i] and known[f.j]):
            return None
        return se2.between(truth[f.i], truth[f.j])

    return _nees_of(factors, true_relative)


def relation_factor_nees(
    factors: Iterable[FactorRecord],
    node_stamps_s: ArrayLike,
    relations: Relations,
    tolerance_s: float = 1e-3,
) -> FactorNees:
    """The NEES of the between-factors whose two nodes are the two scans of a benchmark
    relation (Kümmerle et al. 2009): on a real log, the relations are the truth. MIT CSAIL's
    relations join consecutive scans, so its sequential factors are scored (not its loop
    closures).

    Args:
        factors: The run's factors (``SlamResult.factors``).
        node_stamps_s: ``(N,)`` float64 stamp of node ``n``'s scan in row ``n``, seconds
            (:func:`per_node` of ``result.stamps_s``); NaN for an id that is no node.
        relations: The log's relations (``frontends.relations.read_relations``).
        tolerance_s: Stamp matching tolerance, as :func:`iceg.evaluation.relation_errors`.

    Returns:
        :class:`FactorNees` of the factors a relation spans (in either direction).

    Raises:
        EvaluationError: no factor joins the two scans of a relation, or a factor's
            covariance is not positive definite.
    """
    stamps = np.asarray(node_stamps_s, dtype=np.float64).ravel()
    n1, ok1 = match_stamps(relations.stamps_s[:, 0], stamps, tolerance_s)
    n2, ok2 = match_stamps(relations.stamps_s[:, 1], stamps, tolerance_s)
    ok = ok1 & ok2
    spans: dict[tuple[int, int], FloatArray] = {}
    for a, b, delta in zip(n1[ok].tolist(), n2[ok].tolist(), relations.deltas[ok], strict=True):
        spans.setdefault((a, b), delta)
        spans.setdefault((b, a), se2.inverse(delta))

    def true_relative(f: FactorRecord) -> FloatArray | None:
        assert f.j is not None
        return spans.get((f.i, f.j))

    out = _nees_of(factors, true_relative)
    if out.nees.size == 0:
        raise EvaluationError(
            f"no factor joins the two scans of any of the {len(relations.deltas)} relations "
            f"({int(ok.sum())} matched two node stamps within {tolerance_s} s)"
        )
    return out


def pose_nees(
    node_poses: ArrayLike, node_covariances: ArrayLike, true_poses: ArrayLike
) -> FloatArray:
    """The NEES of node estimates under their marginal covariances.

    The truth is first moved onto the estimate's first pose (``x_0 ∘ t_0⁻¹ ∘ t_n``): a pose
    graph's frame is fixed by a prior on its first node, so its marginals describe the
    uncertainty relative to that node, and so must the errors.

    Args:
        node_poses: ``(N, 3)`` float64 estimates ``x_n`` ``[x_m, y_m, theta_rad]``, first row
            the node the graph's prior holds.
        node_covariances: ``(N, 3, 3)`` float64 marginals ``P_n`` in each pose's tangent
            space (``PoseGraph.marginal_covariance``).
        true_poses: ``(N, 3)`` float64 true poses ``t_n``, any fixed world frame.

    Returns:
        ``(N,)`` float64 ``eᵀ P⁻¹ e`` with ``e = Log(x_n⁻¹ ∘ x_0 ∘ t_0⁻¹ ∘ t_n)``
        (``nan`` for the first node, which the prior fixes).

    Raises:
        EvaluationError: shapes differ, or a covariance is not positive definite.
    """
    x = np.asarray(node_poses, dtype=np.float64)
    cov = np.asarray(node_covariances, dtype=np.float64)
    t = np.asarray(true_poses, dtype=np.float64)
    if x.ndim != 2 or x.shape[1] != 3 or t.shape != x.shape or cov.shape != (len(x), 3, 3):
        raise EvaluationError(
            f"node_poses {x.shape} and true_poses {t.shape} must be (N, 3) and "
            f"node_covariances {cov.shape} (N, 3, 3)"
        )
    aligned = se2.compose(se2.compose(x[0], se2.inverse(t[0])), t)
    error = local_coordinates(x, aligned)
    out = _mahalanobis2(error, cov, "node marginal")
    if out.size:
        out[0] = np.nan
    return out


def per_node(node_ids: ArrayLike, node_scan_index: ArrayLike, per_scan: ArrayLike) -> FloatArray:
    """A per-scan array as a table by node id: the ``node_truth`` of :func:`factor_nees` from
    a simulated run's true poses, or the ``node_stamps_s`` of :func:`relation_factor_nees`
    from the scans' stamps.

    Args:
        node_ids: ``(M,)`` int node ids (``SlamResult.node_ids``).
        node_scan_index: ``(M,)`` int index of each node's scan (``SlamResult.node_scan_index``).
        per_scan: ``(S,)`` or ``(S, k)`` float64, one row per scan (poses ``(S, 3)``
            ``[x_m, y_m, theta_rad]``, stamps ``(S,)`` seconds).

    Returns:
        ``(max(node_ids) + 1,)`` or ``(max(node_ids) + 1, k)`` float64, row ``n`` the row of
        node ``n``'s scan (NaN for an id that is not a node).
    """
    ids = np.asarray(node_ids, dtype=np.int64).ravel()
    scans = np.asarray(node_scan_index, dtype=np.int64).ravel()
    rows = np.asarray(per_scan, dtype=np.float64)
    out = np.full((int(ids.max()) + 1 if ids.size else 0, *rows.shape[1:]), np.nan)
    out[ids] = rows[scans]
    return out


def _nees_of(
    factors: Iterable[FactorRecord], true_relative: Callable[[FactorRecord], FloatArray | None]
) -> FactorNees:
    """The rows of :class:`FactorNees` for the between-factors ``true_relative(f)`` gives a
    true relative pose for (``None``: skipped)."""
    scored = [(f, t) for f in factors if f.j is not None and (t := true_relative(f)) is not None]
    measured = np.array([f.measured for f, _ in scored], dtype=np.float64).reshape(-1, 3)
    truths = np.array([t for _, t in scored], dtype=np.float64).reshape(-1, 3)
    error = local_coordinates(measured, truths)
    ij = np.array([(f.i, f.j) for f, _ in scored], dtype=np.int64).reshape(-1, 2)
    covs = [f.cov for f, _ in scored]
    kinds = [f.kind.value for f, _ in scored]
    return FactorNees(
        kind=np.array(kinds, dtype=np.str_),
        i=ij[:, 0].copy(),
        j=ij[:, 1].copy(),
        error=error,
        nees=_mahalanobis2(error, np.array(covs).reshape(-1, 3, 3), "factor"),
    )


def _mahalanobis2(error: FloatArray, cov: FloatArray, what: str) -> FloatArray:
    """``(k,)`` ``e_kᵀ C_k⁻¹ e_k`` through each covariance's Cholesky factor."""
    if error.shape[0] == 0:
        return np.zeros(0)
    try:
        chol = np.linalg.cholesky(cov)
    except np.linalg.LinAlgError:
        raise EvaluationError(f"a {what} covariance is not positive definite") from None
    white = np.linalg.solve(chol, error[..., None])[..., 0]
    return np.einsum("ij,ij->i", white, white)
