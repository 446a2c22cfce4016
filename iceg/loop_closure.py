"""Loop closure: local and global candidate search, chi-square gate, pairwise consistency.

Every ``every_n_nodes`` nodes the current node's scan is matched (ICE, paper §III-C2) against
the landmarks of older places near its estimate (docs/design.md "Loop closure"). A closure is
accepted when its innovation passes a chi-square gate under the node's marginal covariance plus the
match covariance, or when two closures that failed the gate imply the same correction
(pairwise consistency after Olson 2009, "Recognizing places using spectrally clustered local
matches", reduced to pairs). A closure that the odometry between its two nodes contradicts
(over a path short enough for a first-order test), or that contradicts a closure accepted
shortly before (its PCM cycle under both the fused and the odometry chains), is ruled out
first, whatever the marginal says, and a global closure is gated under the relative
covariance of its two nodes. :class:`LoopCloser` only decides; the pipeline (:mod:`iceg.slam`)
adds the accepted closures to the pose graph as factors.

Global search (issue 11): the local search cannot reach a place farther than
``max_search_radius_m`` from the estimate. Since the ICE matcher needs no prediction, every
``global_every_n_searches``-th search also takes the places most similar in appearance
(:mod:`iceg.place_index`, over all older keyframes, independent of the estimate) and verifies
each with a global ICE match (:meth:`MatchBounds.global_`, the matcher's strict evidence
thresholds). A global closure far from the estimate is accepted only with a second one it is
consistent with under the covariances of the cycle the two form (:func:`pcm_chi2`, pairwise
consistency maximisation after Mangelson et al. 2018, "Pairwise Consistent Measurement Set
Maximization for Robust Multi-robot Map Merging", with groups of two), and a query whose
verified places contradict each other (perceptual aliasing) is dropped (the uniqueness test of
Olson 2009).
"""

from __future__ import annotations

import bisect
import itertools
import logging
import math
from collections.abc import Iterator, Mapping, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from pydantic import BaseModel, ConfigDict, Field

from graph import FactorKind, OdometryNoiseConfig, PoseGraph
from iceg.feature_map import FeatureMap
from iceg.match_pool import MatchJob, MatchPool, SentMatches
from iceg.matching import MatchBounds, Matcher
from iceg.node_index import NodeGrid, nearest_within
from iceg.place_index import PlaceIndex, PlaceIndexConfig, place_descriptor
from iceg.types import MatchResult, ScanFeatures
from iceg_common import se2
from iceg_common.ids import sorted_unique

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Decimals of the innovation in debug log lines.
_LOG_DECIMALS = 3

#: Cell edge of the spatial index of nodes (m), about twice the base search radius.
_INDEX_CELL_M = 4.0

#: Staleness margin of the node index (m): queries reach this much farther on the indexed
#: positions, and the index is rebuilt from all estimates once the accepted corrections may
#: have moved a node by half of it (the other half absorbs iSAM2's small re-estimates).
_INDEX_MARGIN_M = 2.0

#: The odometry test of a loop closure (:meth:`LoopCloser._contradicts_odometry`) runs only
#: while the odometry chain's heading standard deviation is at most this (rad, about 11°):
#: the small-angle regime where a first-order covariance of the composed pose holds
#: (sin and cos within 0.7 % and 2 % of their linearisations).
_ODOMETRY_TEST_MAX_HEADING_SIGMA_RAD = 0.2

#: First radius (m) of the search for the old nodes nearest a candidate (doubled until the
#: ``reference_nodes`` nearest are certain).
_REFERENCE_RADIUS_M = 4.0

#: More new nodes than this to index at once: read every estimate (one gtsam call).
_INDEX_BULK = 512

#: First distance (m) out to which the local search reads the old nodes near the estimate,
#: doubled until it has its ``max_candidates`` places or reaches the search radius. A cost
#: setting only: the candidates are those of a read out to the radius (:class:`_Nearby`).
_FIRST_REACH_M = 0.5


class LoopClosureConfig(BaseModel):
    """Loop-closure search among older nodes near the current estimate."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    enabled: bool = True
    every_n_nodes: int = Field(
        default=3, ge=1, description="Search once every this many new nodes."
    )
    min_node_gap: int = Field(
        default=30,
        ge=1,
        description="Only nodes at least this many nodes older are loop candidates.",
    )
    min_path_m: float = Field(
        default=10.0,
        ge=0,
        description="Only nodes at least this far back along the odometry path are candidates.",
    )
    reference_nodes: int = Field(
        default=10,
        ge=1,
        description="The old nodes nearest a candidate whose landmarks form its reference.",
    )
    search_radius_m: float = Field(
        default=2.0, gt=0, description="Base search radius around the current estimate."
    )
    max_search_radius_m: float = Field(
        default=10.0,
        gt=0,
        description="Cap of the search radius (and of the match's translation bound).",
    )
    max_candidates: int = Field(
        default=3, ge=1, description="Candidate places (distinct node windows) matched per search."
    )
    search_n_sigma: float = Field(
        default=3.0, ge=0, description="Radius grows by this many marginal position sigmas."
    )
    max_rotation_deg: float = Field(
        default=30.0, gt=0, description="Base admissible rotation of a loop-closure match."
    )
    min_correlation: float | None = Field(
        default=None,
        ge=0,
        le=1,
        description="A floor on the ICE correlation (eq. 1) of a loop-closure match above the "
        "matcher's own: a loop-closure match has wider bounds than tracking, so the matcher "
        "already requires the global evidence (matching.validation.*_global: correlation, "
        "feature pairs, point overlap, free space, no rival). None: the matcher decides; the "
        "chi-square gate and the agreement of several closures guard against aliasing.",
    )
    consistency_chi2: float = Field(
        default=16.27,
        gt=0,
        description="Mahalanobis gate (chi-square, 3 dof, 99.9 %) on the innovation.",
    )
    agreement_window_nodes: int = Field(
        default=30,
        ge=1,
        description="A closure that fails the gate is held this many nodes; two held closures "
        "implying the same correction are accepted together (pairwise consistency).",
    )
    agreement_min_separation_m: float = Field(
        default=2.0,
        ge=0,
        description="Agreeing closures must reach old nodes this far apart along the path "
        "(matches to one place can share one aliasing error).",
    )
    agreement_translation_m: float = Field(
        default=0.3, gt=0, description="Largest translation between two agreeing corrections."
    )
    agreement_rotation_deg: float = Field(
        default=2.0, gt=0, description="Largest rotation between two agreeing corrections."
    )
    global_search: bool = Field(
        default=True,
        description="Also search places by appearance, independent of the estimate.",
    )
    global_every_n_searches: int = Field(
        default=5,
        ge=1,
        description="A global search runs every this many searches, whether or not the local "
        "radius is capped at max_search_radius_m (that radius comes from the current node's "
        "marginal, which grows with the whole log, not with the distance to any old place).",
    )
    global_candidates: int = Field(
        default=3, ge=1, description="Most similar places verified by a global ICE match."
    )
    global_window_nodes: int = Field(
        default=90,
        ge=1,
        description="A held global closure waits this many nodes for a consistent second one "
        "(the cycle covariance grows with the nodes between them).",
    )
    global_min_group: int = Field(
        default=3,
        ge=2,
        description="A global closure beyond the gate needs this many mutually consistent "
        "closures (itself included; a clique of the pairwise consistency graph).",
    )
    place_index: PlaceIndexConfig = Field(default_factory=PlaceIndexConfig)
    robust_kernel: Literal["huber", "cauchy"] = Field(
        default="cauchy", description="M-estimator wrapped around loop-closure factors."
    )
    robust_k: float = Field(
        default=1.0, gt=0, description="Kernel width in whitened units (sigmas)."
    )
    forbidden_closures: list[tuple[int, int]] = Field(
        default_factory=list,
        description="Loop closures [old, new] not to make again: a wrong closure found in a "
        "run's loop_closures.csv (columns node_i, node_j), for a new run of the same logs and "
        "configuration (deterministic: its nodes up to the newer one are the same). At node "
        "new, no candidate place whose reference shares a node with the old node's (the place "
        "the closure matched) is matched; the search takes the next candidates. For a closure "
        "that iceg optimize --remove-factor cannot undo (one a revisit hangs from).",
    )


@dataclass
class LoopClosureStats:
    """Loop-closure bookkeeping: searches run, matches tried, accepted and rejected.

    ``attempts`` counts local matches only; ``global_searches`` / ``global_attempts`` the
    appearance searches and their global matches, ``global_accepted`` the accepted closures
    they found and ``rejected_ambiguous`` verified global matches dropped as aliased;
    ``rejected_odometry`` matches that the odometry between their two nodes rules out
    (:meth:`LoopCloser._contradicts_odometry`), ``rejected_accepted`` those that contradict a
    closure accepted shortly before (:meth:`LoopCloser._contradicts_accepted`);
    ``confirmed_steps`` the disputed keyframe steps an accepted closure confirmed
    (:meth:`LoopCloser._confirmed_step`).
    """

    searches: int = 0
    attempts: int = 0
    accepted: int = 0
    rejected_match: int = 0
    rejected_consistency: int = 0
    global_searches: int = 0
    global_attempts: int = 0
    global_accepted: int = 0
    rejected_ambiguous: int = 0
    rejected_odometry: int = 0
    rejected_accepted: int = 0
    confirmed_steps: int = 0

    def as_dict(self) -> dict[str, int]:
        """Plain dict for JSON output."""
        return dict(self.__dict__)


@dataclass(frozen=True, eq=False)
class LoopClosure:
    """One loop-closure measurement between an old node and the current one.

    Attributes:
        node_from: The old node (its place's reference frame).
        node_to: The current node.
        measured: ``(3,)`` float64 pose of ``node_to`` in the frame of ``node_from``,
            ``[x_m, y_m, theta_rad]`` (the match pose).
        cov: ``(3, 3)`` float64 match covariance, tangent space at ``measured`` (m², rad²).
        correlation: ICE correlation of the match (paper eq. 1), in ``[0, 1]``.
        implied: ``(3,)`` float64 map-frame pose of ``node_to`` the closure implies
            (``estimate(node_from) ∘ measured``).
        is_global: Found by the appearance (global) search, verified by a global match.
    """

    node_from: int
    node_to: int
    measured: FloatArray
    cov: FloatArray
    correlation: float
    implied: FloatArray
    is_global: bool = False


@dataclass(frozen=True, eq=False)
class AcceptedClosures:
    """Closures to add to the pose graph as factors.

    Attributes:
        closures: The accepted closures, oldest first.
        robust_kernel: M-estimator of their factors (``None``: Gaussian; closures accepted by
            pairwise agreement are their own outlier test).
        large_correction: The closures move the estimate far beyond its covariance (a group
            with a global closure, or a global closure whose correction lies beyond its own
            covariance): the pipeline re-solves in batch rather than leaving the correction
            to iSAM2's incremental relinearisation.
        confirmed_steps: Nodes whose disputed step (:meth:`LoopCloser.finish_search`,
            ``disputed``) the closure confirmed: their unverified hypotheses enter as
            scan-match factors with it.
    """

    closures: tuple[LoopClosure, ...]
    robust_kernel: Literal["huber", "cauchy"] | None
    large_correction: bool = False
    confirmed_steps: tuple[int, ...] = ()


def innovation_chi2(
    prediction: FloatArray, measured: FloatArray, marginal: FloatArray, match_cov: FloatArray
) -> tuple[FloatArray, float]:
    """Innovation of a loop-closure match and its squared Mahalanobis distance.

    The innovation is ``prediction^-1 ∘ measured`` (both poses of the current node in the old
    node's frame, ``[x_m, y_m, theta_rad]``); its covariance is taken as
    ``marginal + match_cov`` (both ``(3, 3)``, tangent space of the current node).

    Returns:
        ``(innovation (3,), d2)`` with ``d2 = innovationᵀ (marginal + match_cov)⁻¹ innovation``,
        chi-square with 3 degrees of freedom under the hypothesis that the closure is right.

    Raises:
        numpy.linalg.LinAlgError: ``marginal + match_cov`` is singular.
    """
    innovation = se2.between(prediction, measured)
    d2 = float(innovation @ np.linalg.solve(marginal + match_cov, innovation))
    return innovation, d2


def usable_match(result: MatchResult, config: LoopClosureConfig) -> bool:
    """Whether a loop-closure match may be used: successful (the matcher's own validation)
    and at or above ``config.min_correlation`` when that floor is set."""
    floor = config.min_correlation
    return result.success and (floor is None or result.correlation >= floor)


def closures_agree(
    a: LoopClosure,
    b: LoopClosure,
    carry: FloatArray,
    path_m: Sequence[float] | FloatArray,
    config: LoopClosureConfig,
) -> bool:
    """Whether two closures (``b`` the later) imply the same correction.

    ``a``'s implied pose, carried to ``b``'s node by ``carry`` (``(3,)`` current estimate of
    ``node_to(a)^-1 ∘ node_to(b)``), must land on ``b``'s implied pose within
    ``agreement_translation_m`` / ``agreement_rotation_deg``. The two must be at most
    ``agreement_window_nodes`` apart and reach old nodes at least
    ``agreement_min_separation_m`` apart along the path (``path_m[node]``: odometry path length
    at each node, metres), so that they are independent evidence. Pairwise consistency after
    Olson 2009, "Recognizing places using spectrally clustered local matches", reduced to pairs.
    """
    if (
        b.node_to - a.node_to > config.agreement_window_nodes
        or abs(path_m[b.node_from] - path_m[a.node_from]) < config.agreement_min_separation_m
    ):
        return False
    diff = se2.between(se2.compose(a.implied, carry), b.implied)
    return bool(
        np.hypot(diff[0], diff[1]) <= config.agreement_translation_m
        and abs(diff[2]) <= np.radians(config.agreement_rotation_deg)
    )


def with_step_replaced(
    before: FloatArray, at: FloatArray, later: FloatArray, step: FloatArray
) -> FloatArray:
    """A later pose of a chain moved rigidly with one of its steps replaced:
    ``before ∘ step ∘ at^-1 ∘ later``.

    Args:
        before: ``(3,)`` float64 pose ``[x_m, y_m, theta_rad]`` of the step's first node.
        at: ``(3,)`` float64 pose of its second node, as the chain has it.
        later: ``(3,)`` float64 pose of a node after it.
        step: ``(3,)`` float64 the replacing step, the second node in the first's frame.

    Returns:
        ``(3,)`` float64 ``later`` with everything after ``at`` moved as ``at`` moves, same
        frame as the inputs.
    """
    return se2.compose(se2.compose(before, step), se2.between(at, later))


def pcm_chi2(
    a: LoopClosure,
    b: LoopClosure,
    old_chain: tuple[FloatArray, FloatArray],
    new_chain: tuple[FloatArray, FloatArray],
) -> float:
    """Squared Mahalanobis error of the cycle formed by two loop closures (PCM consistency).

    The pose of ``b.node_to`` in the frame of ``a.node_from`` is computed two ways: along the
    old path then ``b`` (``T_old ∘ z_b``), and by ``a`` then along the new path
    (``z_a ∘ T_new``). Their difference is zero when both closures are right. Covariances
    are moved to the tangent space at ``b.node_to`` to first order
    (``Ad(B⁻¹) Σ_A Ad(B⁻¹)ᵀ`` for ``A ∘ B``, :func:`iceg_common.se2.adjoint`) and summed
    (the four measurements are taken as independent). Pairwise consistency as in Mangelson
    et al. 2018, "Pairwise Consistent Measurement Set Maximization for Robust Multi-robot Map
    Merging" (ICRA), and Olson 2009.

    Args:
        a: One closure (``z_a``: pose of ``a.node_to`` in the frame of ``a.node_from``, with
            its ``cov``).
        b: The other closure.
        old_chain: ``(T (3,), C (3, 3))``: pose of ``b.node_from`` in the frame of
            ``a.node_from`` and its covariance (tangent space at ``b.node_from``; m², rad²).
        new_chain: ``(T, C)``: pose of ``b.node_to`` in the frame of ``a.node_to`` and its
            covariance (tangent space at ``b.node_to``).

    Returns:
        ``d2``, chi-square with 3 degrees of freedom when both closures are right.

    Raises:
        numpy.linalg.LinAlgError: the summed covariance is singular.
    """
    (t_old, c_old), (t_new, c_new) = old_chain, new_chain
    return float(_cycle_chi2(a.measured, a.cov, b, t_old, c_old, t_new, c_new))


def _cycle_chi2(
    z_a: FloatArray,
    cov_a: FloatArray,
    b: LoopClosure,
    t_old: FloatArray,
    c_old: FloatArray,
    t_new: FloatArray,
    c_new: FloatArray,
) -> FloatArray:
    """:func:`pcm_chi2` of closures ``a`` (measurements ``z_a`` ``(..., 3)``, covariances
    ``cov_a`` ``(..., 3, 3)``) with one closure ``b``, and their chains (``(..., 3)`` poses,
    ``(..., 3, 3)`` covariances): ``d2`` ``(...)``."""
    ad_b = se2.adjoint(se2.inverse(b.measured))
    ad_new = se2.adjoint(se2.inverse(t_new))
    cov = ad_b @ c_old @ ad_b.T + b.cov + ad_new @ cov_a @ np.swapaxes(ad_new, -1, -2) + c_new
    error = se2.between(se2.compose(z_a, t_new), se2.compose(t_old, b.measured))
    return np.einsum("...i,...i->...", error, np.linalg.solve(cov, error[..., None])[..., 0])


def chain_covariance(poses: FloatArray, step_covs: ArrayLike) -> FloatArray:
    """Covariance of the pose of the last of a chain of nodes in the frame of the first.

    Dead reckoning along the sequential factors: ``C_{k+1} = Ad(Δ⁻¹) C_k Ad(Δ⁻¹)ᵀ + Σ_k``
    with ``Δ`` the estimated step ``k -> k+1`` (tangent space at the later node). It ignores
    the loop closures between the nodes, so it over-estimates the relative uncertainty: the
    consistency test that uses it errs towards accepting a pair, which the chi-square gate,
    the uniqueness test and the separation of the old nodes keep in check.

    Evaluated in closed form, vectorized over the steps: the adjoint is a homomorphism, so the
    recursion unrolls to ``C = Σ_k Ad(M_k) Σ_k Ad(M_k)ᵀ`` with ``M_k = X_last⁻¹ ∘ X_{k+1}``
    (the later node of step ``k`` in the frame of the last node).

    Args:
        poses: ``(n, 3)`` estimates of the chain's nodes, in order, map frame.
        step_covs: ``(n - 1, 3, 3)`` covariances of the steps (tangent at the later node).

    Returns:
        ``(3, 3)`` covariance, m² and rad² (zeros for a single node).
    """
    covs = np.asarray(step_covs, dtype=np.float64).reshape(-1, 3, 3)
    if covs.shape[0] == 0:
        return np.zeros((3, 3))
    ad = _adjoints(poses[-1], poses[1:])
    return np.einsum("kij,kjl,kml->im", ad, covs, ad)


def odometry_bias_covariance(
    poses: FloatArray, scale_sigma: float, heading_drift_sigma_rad_per_m: float
) -> FloatArray:
    """Covariance that a systematic odometry error adds to a chain's relative pose.

    :func:`chain_covariance` treats every step's error as independent, so it grows with the
    square root of the path; an uncalibrated odometry errs the same way at every step (a
    wheel radius, a wheel base), which grows linearly with the path and bends it. Two such
    errors, zero-mean Gaussian and shared by every step of the chain: a scale error ``s``
    (each step's translation times ``1 + s``) and a heading drift ``d`` (each step's
    rotation plus ``d`` times its length). To first order the last node moves by
    ``J_s s + J_d d`` (tangent at the last node) with
    ``J_s = Σ_k Ad(M_k) [R_kᵀ t_k, 0]`` and ``J_d = Σ_k Ad(M_k) [0, 0, |t_k|]`` (step
    ``k = (R_k, t_k)``, ``M_k`` as in :func:`chain_covariance`). The odometry motion model of
    Thrun, Burgard & Fox, *Probabilistic Robotics* (2005), §5.4, read as a calibration error
    rather than noise.

    Args:
        poses: ``(n, 3)`` estimates of the chain's nodes, in order, map frame.
        scale_sigma: Standard deviation of ``s`` (m per m).
        heading_drift_sigma_rad_per_m: Standard deviation of ``d`` (rad per m).

    Returns:
        ``(3, 3)`` covariance ``σ_s² J_s J_sᵀ + σ_d² J_d J_dᵀ``, m² and rad² (zeros for a
        single node).
    """
    if poses.shape[0] < 2:
        return np.zeros((3, 3))
    ad = _adjoints(poses[-1], poses[1:])
    steps = se2.between(poses[:-1], poses[1:])
    c, s = np.cos(steps[:, 2]), np.sin(steps[:, 2])
    xi_scale = np.stack(
        [c * steps[:, 0] + s * steps[:, 1], -s * steps[:, 0] + c * steps[:, 1]], axis=1
    )
    j_scale = np.einsum("kij,kj->i", ad[:, :, :2], xi_scale)
    j_drift = ad[:, :, 2].T @ np.hypot(steps[:, 0], steps[:, 1])
    return scale_sigma**2 * np.outer(j_scale, j_scale) + heading_drift_sigma_rad_per_m**2 * (
        np.outer(j_drift, j_drift)
    )


def _adjoints(frame: FloatArray, poses: FloatArray) -> FloatArray:
    """``(n, 3, 3)`` adjoints of ``frame⁻¹ ∘ poses[i]`` (``frame`` ``(3,)``, ``poses``
    ``(n, 3)``): they carry a tangent vector at ``poses[i]`` to the tangent at ``frame``. With
    ``frame`` the last node of a chain and ``poses`` its nodes after the first, ``Ad(M_k)``,
    ``M_k = X_last⁻¹ ∘ X_{k+1}``, carries a perturbation of step ``k`` (tangent at its later
    node) to the tangent at the last node."""
    return se2.adjoint(se2.between(frame, poses))


class _Poses:
    """Current estimates of the nodes a search reads, fetched on first use
    (``PoseGraph.estimates_of``: the same values as the full table, bit for bit), or served
    from a full table when the search read one.

    ``poses[n]`` is node ``n``'s ``(3,)`` pose, ``poses[lo:hi]`` the ``(hi - lo, 3)`` poses of
    ``lo..hi-1``, map frame.
    """

    def __init__(self, graph: PoseGraph) -> None:
        self._graph = graph
        self._cache = np.zeros((graph.n_nodes, 3))  # row = node id, valid where _known
        self._known = np.zeros(graph.n_nodes, dtype=bool)
        self._full: FloatArray | None = None

    def use_full(self, poses: FloatArray) -> None:
        """Serve from ``poses`` ``(N, 3)``, row = node id (``PoseGraph.estimates()``)."""
        self._full = poses

    def rows(self, node_ids: IntArray) -> FloatArray:
        """``(k, 3)`` poses of ``node_ids`` ``(k,)``, in that order."""
        ids = np.asarray(node_ids, dtype=np.int64).reshape(-1)
        if self._full is not None:
            return self._full[ids]
        missing = ids[~self._known[ids]]
        if 8 * missing.shape[0] > self._known.shape[0]:
            # a long stretch (a chain between distant places): one read of the full table
            # costs less than reading so many nodes one by one (same values, bit for bit)
            self.use_full(self._graph.estimates()[1])
            return self.rows(ids)
        if missing.shape[0]:
            got, poses = self._graph.estimates_of(missing)
            self._cache[got] = poses
            self._known[got] = True
        return self._cache[ids]

    def table(self, node_ids: IntArray) -> tuple[IntArray, FloatArray]:
        """``(ids (k,), poses (k, 3))`` of the sorted unique ``node_ids`` (a pose table)."""
        ids = sorted_unique(node_ids)
        return ids, self.rows(ids)

    def __getitem__(self, key: int | np.integer | slice) -> FloatArray:
        if isinstance(key, slice):
            return self.rows(np.arange(key.start, key.stop, dtype=np.int64))
        n = int(key)
        if self._full is not None:
            return self._full[n].copy()
        if self._known[n]:
            return self._cache[n].copy()
        return self.rows(np.array([n]))[0]


class _Nearby:
    """Old nodes near a point by their distance on the current estimates, read as far as a
    question needs.

    The node index gives every old node (id below ``n_older``) whose indexed position lies
    within ``reach_m`` plus the staleness margin of ``center``, ordered by that indexed
    distance. The index's invariant (:meth:`LoopCloser._sync_index`) is that no estimate
    lies farther than the margin from its indexed position, so every node within ``d`` of
    the center is among those indexed within ``d`` plus the margin: only those are read.
    The answers are those of reading every node the index returns (``d <= reach_m``).

    Args:
        nodes: The node index.
        poses: The search's estimates.
        center: ``(2,)`` map-frame point (m).
        n_older: Only nodes ``0..n_older-1`` count.
        reach_m: The farthest distance a question may ask about (m).
    """

    def __init__(
        self, nodes: NodeGrid, poses: _Poses, center: FloatArray, n_older: int, reach_m: float
    ) -> None:
        self._ids, self._indexed = nodes.nearest_first(center, reach_m + _INDEX_MARGIN_M, n_older)
        self._dist = np.full(self._ids.shape[0], np.nan)  # exact distances, NaN: not read yet
        self._poses, self._center = poses, center

    def __len__(self) -> int:
        """Number of old nodes indexed within the reach plus the margin."""
        return int(self._ids.shape[0])

    def _distances(self, rows: slice | IntArray) -> FloatArray:
        """Exact distances of the nodes at ``rows`` (indexed order), reading the unread."""
        dist = self._dist[rows]
        unread = np.isnan(dist)
        if unread.any():
            ids = self._ids[rows][unread]
            dist[unread] = np.hypot(*(self._poses.rows(ids)[:, :2] - self._center).T)
            self._dist[rows] = dist
        return dist

    def within(self, d: float) -> tuple[IntArray, FloatArray]:
        """The nodes at most ``d`` (m, at most the reach) from the center, nearest first
        (ties by id), and their distances: ``(ids (k,) int64, dist (k,) m)``."""
        m = self._reads(d)
        self._distances(slice(0, m))
        return nearest_within(self._ids, self._dist, m, d)

    def read_all(self, d: float) -> bool:
        """Whether :meth:`within` ``d`` reads every node the index returned (a larger
        distance would read no more)."""
        return self._reads(d) == len(self)

    def _reads(self, d: float) -> int:
        """How many nodes (a prefix in indexed order) :meth:`within` ``d`` reads: those
        indexed within ``d`` plus the margin."""
        return int(np.searchsorted(self._indexed, d + _INDEX_MARGIN_M, side="right"))

    def members(self, d: float) -> IntArray:
        """The ids of the nodes at most ``d`` (m, at most the reach) from the center, in no
        particular order: those indexed within ``d`` less the margin without a read, the
        rest of the nodes indexed within ``d`` plus the margin by their exact distance."""
        near = self._indexed <= d - _INDEX_MARGIN_M
        band = np.flatnonzero(~near & (self._indexed <= d + _INDEX_MARGIN_M))
        return np.concatenate([self._ids[near], self._ids[band[self._distances(band) <= d]]])

    def nearest(self, k: int) -> tuple[IntArray, FloatArray]:
        """The ``k`` nodes nearest the center (ties by id; all of them when fewer) and their
        distances, as :meth:`within` orders them: right whenever the k-th lies within the
        reach, or the index returned every old node."""
        if len(self) == 0:
            return self._ids, self._dist
        # the first k read lie within d, so the k nearest do too
        d = float(np.max(self._distances(slice(0, min(k, len(self))))))
        ids, dist = self.within(d)
        return ids[:k], dist[:k]


@dataclass(frozen=True, eq=False)
class _Search:
    """Inputs shared by the steps of one search (estimates at the search's start)."""

    node_id: int
    poses: _Poses
    n_older: int  # candidate pool: nodes 0..n_older-1 (old in node count and along the path)
    marginal: FloatArray  # (3, 3) current node
    radius_m: float
    nearby: _Nearby  # old nodes near the current estimate, reaching radius_m


@dataclass(frozen=True, eq=False)
class _Best:
    candidate: int
    prediction: FloatArray
    result: MatchResult


@dataclass(frozen=True, eq=False)
class OpenSearch:
    """A search begun by :meth:`LoopCloser.start_search`, for
    :meth:`LoopCloser.finish_search`: its inputs, candidates and matches in flight.

    Attributes:
        search: The estimates and radius the search started from.
        places: The due global search's candidate places (``None``: not due).
        candidates: The local candidate places matched, in job order.
        predictions: Their ``(3,)`` predicted poses of the new node in each place's frame.
        sent: The matches: the global ones first, then one per local candidate.
    """

    search: _Search
    places: list[int] | None
    candidates: list[int]
    predictions: list[FloatArray]
    sent: SentMatches


class LoopCloser:
    """Searches loop closures for new nodes and decides which to accept.

    Example::

        closer = LoopCloser(config.loop_closure, matcher, feature_map)
        closer.observe(node_id, features)  # every node: its place descriptor
        if closer.due(node_id):
            begun = closer.start_search(node_id, features, graph, path_m)
            ...  # other work while the match helper runs the matches
            accepted = None if begun is None else closer.finish_search(begun, graph, path_m)

    Args:
        config: Loop-closure settings.
        matcher: The ICE matcher used for loop-closure matches.
        feature_map: The map whose landmarks form each place's reference.
        odometry_noise: The odometry noise model; its per-distance sigmas bound a systematic
            odometry error in the odometry test (:meth:`_contradicts_odometry`).
    """

    def __init__(
        self,
        config: LoopClosureConfig,
        matcher: Matcher,
        feature_map: FeatureMap,
        odometry_noise: OdometryNoiseConfig | None = None,
    ) -> None:
        self.config = config
        self.odometry_noise = (
            odometry_noise if odometry_noise is not None else OdometryNoiseConfig()
        )
        self.matcher = matcher
        #: Runs a search's matches beside a helper process when set (by the pipeline).
        self.match_pool: MatchPool | None = None
        self.feature_map = feature_map
        self.stats = LoopClosureStats()
        self.pending: list[LoopClosure] = []
        self._accepted: list[LoopClosure] = []  # accepted within global_window_nodes
        self.places = PlaceIndex(config.place_index)
        self._forbidden_pairs = {(int(i), int(j)) for i, j in config.forbidden_closures}
        # Row i: fused information of the sequential factors i -> i+1 (zero: none yet).
        self._step_info = np.zeros((0, 3, 3))
        # Row i: the odometry factor i -> i+1, measured step and covariance (NaN: none).
        self._odom_step = np.zeros((0, 3))
        self._odom_cov = np.zeros((0, 3, 3))
        self._factors_seen = 0
        self.nodes = NodeGrid(_INDEX_CELL_M)
        self._indexed_to = 0  # nodes 0.._indexed_to-1 are in self.nodes
        self._moved_m = 0.0  # bound on how far estimates moved since the index was built
        self._closures_seen = 0  # loop-closure factors in the graph, seen by _sync_steps
        self._closures_own = 0  # of those, the ones this closer accepted
        self.index_rebuilds = 0

    def due(self, node_id: int) -> bool:
        """Whether a search runs for this new node (enabled, every ``every_n_nodes``)."""
        return self.config.enabled and node_id % self.config.every_n_nodes == 0

    def observe(self, node_id: int, features: ScanFeatures) -> None:
        """Add a new node's place descriptor (:func:`iceg.place_index.place_descriptor` of its
        robot-frame ICE features) to the place index; call it for every node, in order."""
        if self.config.enabled and self.config.global_search:
            self.places.add(node_id, place_descriptor(features, self.config.place_index))

    def start_search(
        self,
        node_id: int,
        features: ScanFeatures,
        graph: PoseGraph,
        path_m: Sequence[float],
        log_start: int = 0,
    ) -> OpenSearch | None:
        """Begin a search of older nodes for a loop closure of ``node_id``, near its estimate
        and, when due, by appearance: its candidates, and their matches built and handed to
        :attr:`match_pool` (sent to its helper process, each as its reference is built).
        :meth:`finish_search` decides it; call it before the graph changes or another search
        starts (:mod:`iceg.slam` tracks the next keyframe in between, while the helper runs
        the matches).

        Local search: candidates are nodes at least ``min_node_gap`` nodes and
        ``min_path_m`` metres of path back, or of an earlier log (before ``log_start``),
        within ``radius = base + n_sigma * sqrt(lambda_max(cov_xy))`` of the current
        estimate (``cov_xy`` from the current node's marginal, capped at
        ``max_search_radius_m``); up to ``max_candidates`` of the nearest, from distinct
        places, are matched against the landmarks of the ``reference_nodes`` old nodes
        nearest each candidate, and the best-correlated match is kept. Unless the odometry
        rules it out (:meth:`_contradicts_odometry`), it is accepted (robust kernel) when it
        passes the chi-square gate (:func:`innovation_chi2`), or together with held closures
        it agrees with (no kernel; :meth:`_agreeing`: held local closures that agree, else a
        clique of ``global_min_group`` with held global ones); otherwise it is held.

        Global search (when nothing was accepted, every ``global_every_n_searches``-th
        search): see :meth:`_global`.

        Args:
            node_id: The current node (through ``graph.update()`` or ``graph.solve_pending()``,
                and observed).
            features: Its scan's ICE features, robot frame.
            graph: The pose graph (estimates, marginals and the sequential factors' covariances
                are read, nothing is added).
            path_m: Odometry path length at each node, metres, indexed by node id.
            log_start: The first node of the current log (:meth:`iceg.slam.Slam.start_segment`;
                0 for a single run): every node before it is a candidate, another log's
                path, which this one never drove.

        Returns:
            The search for :meth:`finish_search`, or ``None`` when the node has no older
            candidates.

        Raises:
            GraphError: the graph cannot give the current node's marginal covariance.
        """
        n_older = max(self._n_older(node_id, path_m), log_start)
        if n_older == 0:
            return None
        self.stats.searches += 1
        self._sync_steps(graph)
        marginal = graph.marginal_covariance(node_id)
        radius = self._radius(marginal)
        poses = _Poses(graph)
        self._sync_index(graph, poses)
        nearby = _Nearby(self.nodes, poses, poses[node_id][:2], n_older, radius)
        search = _Search(node_id, poses, n_older, marginal, radius, nearby)
        # A due global search's matches run in one batch with the local ones; their results
        # are read only where nothing local is accepted, as if matched after it.
        places = self._global_places(search, features) if self._global_due() else None
        candidates: list[int] = []
        predictions: list[FloatArray] = []
        jobs = itertools.chain(
            () if places is None else self._global_jobs(search, features, places),
            self._local_jobs(search, features, candidates, predictions),
        )
        # each match is sent as soon as its reference is built
        pool = self.match_pool
        sent = pool.submit(jobs) if pool is not None else SentMatches(list(jobs))
        self.stats.attempts += len(candidates)
        return OpenSearch(search, places, candidates, predictions, sent)

    def finish_search(
        self,
        begun: OpenSearch,
        graph: PoseGraph,
        path_m: Sequence[float],
        disputed: Mapping[int, FloatArray] | None = None,
    ) -> AcceptedClosures | None:
        """Decide a search begun by :meth:`start_search`: the matches' results (from
        :attr:`match_pool` when set, else run here), then the gates and agreement described
        there. ``disputed`` maps a node ``k`` whose tracking match failed for lack of
        evidence to its unverified hypothesis (``(3,)`` float64 pose of ``k`` in the frame of
        ``k - 1``); the caller keeps only those after the newest accepted closure. A local
        closure beyond the gate that passes it with one of them in place of the estimate's
        step confirms that step (:meth:`_confirmed_step`).

        Returns:
            The closures to add as factors, or ``None``.

        Raises:
            GraphError: the graph cannot give a global closure's relative covariance.
        """
        s, places = begun.search, begun.places
        pool = self.match_pool
        if pool is not None:
            every = pool.collect(begun.sent)
        else:
            every = [self.matcher.match(*job) for job in begun.sent.jobs]
        n_global = 0 if places is None else len(places)
        best = self._best(s, begun.candidates, begun.predictions, every[n_global:])
        steps = disputed or {}
        accepted = self._decide(s, best, graph, path_m, steps) if best is not None else None
        if accepted is None and places is not None:
            accepted = self._global(s, places, every[:n_global], graph, path_m)
        if accepted is not None:
            self._note_correction(accepted, s.poses)
        return accepted

    # ------------------------------------------------------------------ steps

    def _n_older(self, node_id: int, path_m: Sequence[float]) -> int:
        """Candidates are nodes ``0..n-1``: old in node count and far along the path (a node
        reached again after a detour, not the corridor just driven). The path length never
        decreases along the nodes, so ``path[node] - path[i] >= min_path_m`` holds for a
        prefix of the ids: found by bisection on that test, O(log N)."""
        lc = self.config
        by_count = max(0, node_id - lc.min_node_gap + 1)
        now = path_m[node_id]
        by_path = bisect.bisect_left(
            range(by_count), True, key=lambda i: not now - path_m[i] >= lc.min_path_m
        )
        return int(by_path)

    # ------------------------------------------------------------------ node index

    def _sync_index(self, graph: PoseGraph, poses: _Poses) -> None:
        """Bring the node index up to the graph: index the nodes added since the last search
        (their current estimates), or rebuild it from every estimate when the estimates may
        have moved more than half the margin (or the graph is not the one indexed)."""
        n = graph.n_nodes
        if (
            self._moved_m > 0.5 * _INDEX_MARGIN_M
            or n < self._indexed_to
            or n - self._indexed_to > _INDEX_BULK
        ):
            ids, all_poses = graph.estimates()
            poses.use_full(all_poses)
            self.nodes.clear()
            self.nodes.add(ids, all_poses[:, :2])
            self._indexed_to, self._moved_m = n, 0.0
            self.index_rebuilds += 1
            return
        new = np.arange(self._indexed_to, n, dtype=np.int64)
        self.nodes.add(new, poses.rows(new)[:, :2])
        self._indexed_to = n

    def _note_correction(self, accepted: AcceptedClosures, poses: _Poses) -> None:
        """Add what the accepted closures may move any estimate by to the staleness bound:
        each closure's correction of its new node, translation plus rotation times the
        extent of the map (a rotation about any node moves the others by at most that); a
        large correction (batch solve) moves everything: rebuild at the next search."""
        self._closures_own += len(accepted.closures)
        if accepted.large_correction:
            self._moved_m = np.inf
            return
        extent = self.nodes.extent_m
        for c in accepted.closures:
            d = se2.between(poses[c.node_to], c.implied)
            self._moved_m += float(np.hypot(d[0], d[1]) + abs(d[2]) * extent)

    def _radius(self, marginal: FloatArray) -> float:
        """The local search radius (m)."""
        lc = self.config
        sigma_xy = float(np.sqrt(max(np.linalg.eigvalsh(marginal[:2, :2]).max(), 0.0)))
        return min(lc.search_radius_m + lc.search_n_sigma * sigma_xy, lc.max_search_radius_m)

    def _global_due(self) -> bool:
        lc = self.config
        return lc.global_search and self.stats.searches % lc.global_every_n_searches == 0

    def _candidates(self, s: _Search, banned: frozenset[int] = frozenset()) -> list[int]:
        """Up to ``max_candidates`` nearest old nodes within the radius, from distinct places
        (more than ``reference_nodes`` nodes apart), none of the ``banned`` nodes. The nodes
        are read nearest first out to a distance doubled until the places are found or it
        reaches the radius: the greedy over those is the greedy over every node within the
        radius."""
        lc = self.config
        reach = min(_FIRST_REACH_M, s.radius_m)
        while True:
            candidates: list[int] = []
            for n in s.nearby.within(reach)[0].tolist():
                if n in banned:
                    continue
                if all(abs(n - c) > lc.reference_nodes for c in candidates):
                    candidates.append(n)
                    if len(candidates) == lc.max_candidates:
                        return candidates
            if reach >= s.radius_m:
                return candidates
            # nothing more to read: the rest of the radius costs one more pass
            reach = s.radius_m if s.nearby.read_all(reach) else min(2.0 * reach, s.radius_m)

    def _bounds(self, s: _Search) -> MatchBounds:
        rotation_sigma = float(np.sqrt(max(s.marginal[2, 2], 0.0)))
        return MatchBounds(
            max_translation_m=s.radius_m,
            max_rotation_rad=np.radians(self.config.max_rotation_deg)
            + self.config.search_n_sigma * rotation_sigma,
        )

    def _reference(
        self, s: _Search, candidate: int, window: IntArray | None = None
    ) -> ScanFeatures:
        """The landmarks of the old nodes nearest the candidate (any pass through the place;
        ``window``, when given, is :meth:`_window` of it), in the candidate's frame."""
        if window is None:
            window = self._window(s, candidate)
        table = s.poses.table(self.feature_map.reference_pose_nodes(window))
        return self.feature_map.reference(table, window, s.poses[candidate]).features

    def _window(self, s: _Search, candidate: int) -> IntArray:
        """The ``reference_nodes`` old nodes nearest the candidate (ties by id): from the node
        index, on a radius doubled until the k-th nearest lies within it."""
        k = self.config.reference_nodes
        center = s.poses[candidate][:2]
        reach = _REFERENCE_RADIUS_M
        while True:
            near = _Nearby(self.nodes, s.poses, center, s.n_older, reach)
            ids, dist = near.nearest(k)
            if len(near) == s.n_older or (ids.shape[0] == k and dist[-1] <= reach):
                return ids
            reach *= 2.0

    def _local_jobs(
        self,
        s: _Search,
        features: ScanFeatures,
        candidates: list[int],
        predictions: list[FloatArray],
    ) -> Iterator[MatchJob]:
        """The matches of the candidate places, each reference built when the match is
        asked for; each place and its prediction are appended to ``candidates`` and
        ``predictions`` as its match is. A candidate whose reference window is one already
        taken in this search is skipped (:func:`_same_place`)."""
        bounds = self._bounds(s)
        matched: list[IntArray] = []  # the windows of the places taken so far
        banned = self._forbidden_nodes(s)
        for candidate in self._candidates(s, banned):
            window = self._window(s, candidate)
            if banned.intersection(window.tolist()):
                continue
            if any(_same_place(window, other) for other in matched):
                continue
            matched.append(window)
            prediction = se2.between(s.poses[candidate], s.poses[s.node_id])
            candidates.append(candidate)
            predictions.append(prediction)
            yield self._job(s, features, candidate, window, prediction, bounds)

    def _best(
        self,
        s: _Search,
        candidates: Sequence[int],
        predictions: Sequence[FloatArray],
        results: Sequence[MatchResult],
    ) -> _Best | None:
        """The best-correlated acceptable match of the candidate places."""
        best: _Best | None = None
        for candidate, prediction, result in zip(candidates, predictions, results, strict=True):
            if not usable_match(result, self.config):
                self.stats.rejected_match += 1
                logger.debug(
                    "loop closure %d->%d (radius %.2f m) not matched: %s (correlation %.2f)",
                    candidate,
                    s.node_id,
                    s.radius_m,
                    result.reason,
                    result.correlation,
                )
            elif best is None or result.correlation > best.result.correlation:
                best = _Best(candidate, prediction, result)
        return best

    def _job(
        self,
        s: _Search,
        features: ScanFeatures,
        candidate: int,
        window: IntArray | None,
        prediction: FloatArray,
        bounds: MatchBounds,
    ) -> MatchJob:
        """The match of ``features`` against the candidate's place (its reference built
        now)."""
        return MatchJob(features, self._reference(s, candidate, window), prediction, bounds)

    def _decide(
        self,
        s: _Search,
        best: _Best,
        graph: PoseGraph,
        path_m: Sequence[float],
        disputed: Mapping[int, FloatArray],
    ) -> AcceptedClosures | None:
        """Chi-square gate, else pairwise agreement with a held closure, else a disputed step
        it confirms, else hold it."""
        lc = self.config
        result = best.result
        innovation, d2 = innovation_chi2(best.prediction, result.pose, s.marginal, result.cov)
        closure = LoopClosure(
            best.candidate,
            s.node_id,
            result.pose,
            result.cov,
            result.correlation,
            implied=se2.compose(s.poses[best.candidate], result.pose),
        )
        if self._contradicts_odometry(closure) or self._contradicts_accepted(closure, s.poses):
            return None
        rounded = np.round(innovation, _LOG_DECIMALS)
        if d2 <= lc.consistency_chi2:
            logger.debug(
                "loop closure %d->%d accepted: innovation %s, chi2 %.1f, correlation %.2f",
                *(best.candidate, s.node_id, rounded, d2, result.correlation),
            )
            return self._accept([closure], lc.robust_kernel)
        agreeing = self._agreeing(closure, s.poses, path_m)
        if agreeing:
            logger.debug(
                "loop closures %s->%d accepted by pairwise agreement (chi2 %.1f vs estimate)",
                *([c.node_from for c in agreeing], s.node_id, d2),
            )
            return self._accept_group(agreeing, closure)
        confirmed = self._confirmed_step(s, closure, disputed)
        if confirmed is not None:
            logger.debug(
                "loop closure %d->%d accepted with the disputed step into node %d",
                *(best.candidate, s.node_id, confirmed),
            )
            self.stats.confirmed_steps += 1
            return self._accept([closure], lc.robust_kernel, confirmed_steps=(confirmed,))
        self.stats.rejected_consistency += 1
        self._hold(closure)
        logger.debug(
            "loop closure %d->%d held back: innovation %s, chi2 %.1f",
            *(best.candidate, s.node_id, rounded, d2),
        )
        return None

    def _confirmed_step(
        self, s: _Search, closure: LoopClosure, disputed: Mapping[int, FloatArray]
    ) -> int | None:
        """The newest disputed step between the closure's old node and the current node with
        which the closure passes the gate: the current node's estimate moved rigidly with the
        step replaced by its hypothesis (``x_{k-1} ∘ h ∘ x_k^-1 ∘ x_now``, the chain after
        the newest accepted closure being open), under the same marginal and match
        covariance. The hypothesis's own checks (bounds, free space) and a match to another
        place then agree: two independent validations (docs/design.md, "A disputed step
        confirmed by a loop closure"). ``None`` where none does."""
        old, now = closure.node_from, s.node_id
        for k in sorted((k for k in disputed if old < k <= now), reverse=True):
            moved = with_step_replaced(s.poses[k - 1], s.poses[k], s.poses[now], disputed[k])
            prediction = se2.between(s.poses[old], moved)
            _, d2 = innovation_chi2(prediction, closure.measured, s.marginal, closure.cov)
            if d2 <= self.config.consistency_chi2:
                return k
        return None

    def _agreeing(
        self, closure: LoopClosure, poses: _Poses, path_m: Sequence[float]
    ) -> list[LoopClosure]:
        """The held closures that a local ``closure`` beyond the gate enters with, or none.

        Held local closures that agree with it (:func:`closures_agree`): two independent
        places are their own outlier test. Otherwise held global closures may vouch for it,
        but as for a global closure (:meth:`_global`) the group must be a clique of
        ``global_min_group`` mutually consistent closures: a pair with a global closure is
        only as strong as the chains' covariances between them, and a wrong match with a wide
        covariance is consistent with almost anything."""
        local = [
            c for c in self.pending if not c.is_global and self._agree(c, closure, poses, path_m)
        ]
        if local:
            return local
        clique = self._clique(closure, poses, path_m)
        return clique if len(clique) + 1 >= self.config.global_min_group else []

    # ------------------------------------------------------------------ global search

    def _global_places(self, s: _Search, features: ScanFeatures) -> list[int]:
        """The ``global_candidates`` older places beyond the local radius (the local search
        covers the rest) most similar to the current scan
        (:class:`~iceg.place_index.PlaceIndex`, one per ``reference_nodes`` stretch), none
        of them a place the user forbade this node to close with (:meth:`_forbidden_nodes`)."""
        lc = self.config
        banned = self._forbidden_nodes(s)

        def far(ids: IntArray) -> NDArray[np.bool_]:
            inside = s.nearby.members(s.radius_m)
            if banned:
                inside = np.concatenate([inside, np.fromiter(banned, np.int64, len(banned))])
            return (ids < s.n_older) & ~np.isin(ids, inside, kind="table")

        query = place_descriptor(features, lc.place_index)
        places = self.places.query(query, far, lc.global_candidates, lc.reference_nodes)
        if not banned:
            return places
        return [c for c in places if not banned.intersection(self._window(s, c).tolist())]

    def _forbidden_nodes(self, s: _Search) -> frozenset[int]:
        """The old nodes of the places the user forbade this node to close with
        (``config.forbidden_closures``): the reference window of each forbidden old node."""
        olds = [i for i, j in self._forbidden_pairs if j == s.node_id and 0 <= i < s.n_older]
        return frozenset(n for i in olds for n in self._window(s, i).tolist())

    def _global_jobs(
        self, s: _Search, features: ScanFeatures, places: Sequence[int]
    ) -> Iterator[MatchJob]:
        """The global ICE match (no prediction used) of the scan against each place, each
        reference built when the match is asked for."""
        bounds = MatchBounds.global_()
        for c in places:
            prediction = se2.between(s.poses[c], s.poses[s.node_id])
            yield self._job(s, features, c, None, prediction, bounds)

    def _global(
        self,
        s: _Search,
        places: Sequence[int],
        results: Sequence[MatchResult],
        graph: PoseGraph,
        path_m: Sequence[float],
    ) -> AcceptedClosures | None:
        """Appearance-based search, independent of the estimate.

        The places of :meth:`_global_places` are each verified by their global match
        (``results``, of :meth:`_global_jobs`). When two verified places
        contradict each other (:meth:`_unique`) the scene is aliased and all are dropped.
        Unless the odometry rules it out (:meth:`_contradicts_odometry`), the
        best-correlated survivor is accepted if it passes the chi-square gate against the
        estimate under the current node's marginal and under the exact relative covariance
        of its two nodes (:meth:`graph.PoseGraph.relative_covariance`; an appearance match
        has no spatial prior, and the marginal grows with everything before the old node: on
        a long log it admits look-alikes anywhere): with the robust kernel, or, where its
        correction is beyond its own covariance (the innovation's chi-square under the
        match covariance alone exceeds the gate), without kernel as a large correction, as
        a group enters (a kernel scaled by that covariance would leave the estimate where
        the drift put it until the final refinement); otherwise it needs
        ``global_min_group - 1`` held closures consistent with it and with each other under
        :func:`pcm_chi2` (old nodes ``agreement_min_separation_m`` apart along the path); the
        group enters without kernel as a large correction. Else it is held for
        ``global_window_nodes`` nodes.
        """
        lc = self.config
        self.stats.global_searches += 1
        verified = self._verify_global(s, places, results)
        if not verified:
            return None
        if not self._unique(verified, s.poses):
            self.stats.rejected_ambiguous += len(verified)
            logger.debug(
                "global loop closures %s->%d dropped: the places contradict each other",
                *([c.node_from for c in verified], s.node_id),
            )
            return None
        closure = max(verified, key=lambda c: c.correlation)
        if self._contradicts_odometry(closure) or self._contradicts_accepted(closure, s.poses):
            return None
        prediction = se2.between(s.poses[closure.node_from], s.poses[s.node_id])
        innovation, d2 = innovation_chi2(prediction, closure.measured, s.marginal, closure.cov)
        if d2 <= lc.consistency_chi2:
            # and under the two nodes' relative covariance (its joint marginal costs a walk
            # through the Bayes tree: only for a closure the marginal would let through)
            relative = graph.relative_covariance(closure.node_from, s.node_id)
            d2 = max(d2, innovation_chi2(prediction, closure.measured, relative, closure.cov)[1])
        if d2 <= lc.consistency_chi2:
            logger.debug("global loop closure %d->%d accepted: chi2 %.1f", *_ends(closure), d2)
            # the same innovation under the match covariance alone
            if innovation @ np.linalg.solve(closure.cov, innovation) > lc.consistency_chi2:
                # The drift the gate allowed for lies beyond the closure's own covariance: a
                # kernel scaled by it would all but ignore the closure until the final
                # refinement, and the next searches would look around where the drift left
                # the estimate. It enters as a group's large correction does.
                return self._accept([closure], None, large_correction=True)
            return self._accept([closure], lc.robust_kernel)
        agreeing = self._clique(closure, s.poses, path_m)
        if len(agreeing) + 1 >= lc.global_min_group:
            logger.debug(
                "global loop closures %s->%d accepted by pairwise consistency (chi2 %.1f)",
                *([c.node_from for c in agreeing], s.node_id, d2),
            )
            return self._accept_group(agreeing, closure)
        self.stats.rejected_consistency += 1
        self._hold(closure)
        logger.debug("global loop closure %d->%d held: chi2 %.1f", *_ends(closure), d2)
        return None

    def _clique(
        self, closure: LoopClosure, poses: _Poses, path_m: Sequence[float]
    ) -> list[LoopClosure]:
        """Held closures consistent with ``closure`` and with each other (greedy clique of
        the pairwise consistency graph, newest first, as PCM's maximum clique)."""
        clique: list[LoopClosure] = []
        for c in reversed(self.pending):
            if self._agree(c, closure, poses, path_m) and all(
                self._agree(c, m, poses, path_m)
                for m in clique  # c is the older
            ):
                clique.append(c)
        return clique[::-1]

    def _verify_global(
        self, s: _Search, candidates: Sequence[int], results: Sequence[MatchResult]
    ) -> list[LoopClosure]:
        """The closures of the candidate places whose global match (``results``) is usable,
        in candidate order."""
        self.stats.global_attempts += len(candidates)
        verified = []
        for candidate, result in zip(candidates, results, strict=True):
            if not usable_match(result, self.config):
                self.stats.rejected_match += 1
                continue
            implied = se2.compose(s.poses[candidate], result.pose)
            verified.append(
                LoopClosure(
                    candidate, s.node_id, result.pose, result.cov, result.correlation, implied, True
                )
            )
        return verified

    def _unique(self, verified: list[LoopClosure], poses: _Poses) -> bool:
        """Whether every two verified places put the current node at the same pose (the
        :func:`pcm_chi2` cycle through the old path between them, same new node)."""
        zero = (np.zeros(3), np.zeros((3, 3)))
        for k, a in enumerate(verified):
            for b in verified[k + 1 :]:
                old = self._relative(a.node_from, b.node_from, poses)
                if old is None or pcm_chi2(a, b, old, zero) > self.config.consistency_chi2:
                    return False
        return True

    # ------------------------------------------------------------------ consistency

    def _contradicts_odometry(self, closure: LoopClosure) -> bool:
        """Whether the distance the odometry measured between the closure's two nodes rules
        it out.

        The current node's marginal, which the chi-square gate uses, grows with the whole
        log: after kilometres of exploration it admits a place a few metres back that looks
        the same (a corridor's repeating doors). The wheels measured how far the robot went
        between the two nodes, independently of the scan matching. With ``t`` the odometry's
        displacement from the old node to the current one (the odometry factors composed,
        old node's frame) and ``u = t / |t|``, the closure is ruled out when the component
        along ``u`` of its own displacement differs from ``|t|`` by more than
        ``sqrt(consistency_chi2)`` standard deviations: ``uᵀ C u`` from the odometry chain's
        covariance (:func:`chain_covariance` of the odometry factors' covariances plus
        :func:`odometry_bias_covariance`, a systematic error of the size of the noise model's
        per-distance sigmas) and the match covariance. Ruled-out closures are not held for
        agreement.

        Only the distance along the way is tested in the pose: a heading from wheels is what
        slips (MIT CSAIL's odometry turns 19° off the model's 5 % per radian within 57 nodes),
        and a heading error moves the pose through the whole lever arm. And only where the
        first-order covariance holds: the chain's heading standard deviation (its steps'
        heading variances plus the systematic drift over its length) at most
        :data:`_ODOMETRY_TEST_MAX_HEADING_SIGMA_RAD`; over a longer or turning path the
        odometry's error is no longer Gaussian in the pose. Skipped too where a step has no
        odometry factor. The heading alone is tested over any path
        (:meth:`_turns_otherwise`).
        """
        if self._turns_otherwise(closure):
            return True
        lo, hi = closure.node_from, closure.node_to
        odometry = self._odometry_chain(lo, hi)
        if odometry is None:
            return False
        chain, cov = odometry
        distance_m = float(np.hypot(chain[-1, 0], chain[-1, 1]))
        if distance_m == 0.0:
            return False
        u_old = chain[-1, :2] / distance_m  # old node's frame
        # the chain's end and the match are perturbed in their own frames (tangent spaces)
        u_end = se2.rotation_matrix(chain[-1, 2]).T @ u_old
        u_match = se2.rotation_matrix(closure.measured[2]).T @ u_old
        var = u_end @ cov[:2, :2] @ u_end + u_match @ closure.cov[:2, :2] @ u_match
        error_m = float(u_old @ closure.measured[:2]) - distance_m
        return self._ruled_out_by_odometry(
            error_m,
            var,
            "loop closure %d->%d ruled out by the odometry between them: %.3f m along the "
            "odometry's %.3f m, sigma %.3f m",
            (lo, hi, error_m + distance_m, distance_m, np.sqrt(var)),
        )

    def _turns_otherwise(self, closure: LoopClosure) -> bool:
        """Whether the heading the odometry measured between the closure's two nodes rules it
        out.

        Headings add up along a chain in SE(2): the composed pose's heading is the sum of the
        steps' headings, whatever the path, so this test needs no small-angle regime (the
        distance test of :meth:`_contradicts_odometry` does). The closure is ruled out when
        its heading differs from the odometry's sum by more than ``sqrt(consistency_chi2)``
        standard deviations, the variance the steps' heading variances (the noise model's
        per-distance and per-radian terms), the systematic drift of the noise model's
        per-distance sigma over the path's length (as :func:`odometry_bias_covariance`) and
        the match's heading variance. A match of a symmetric room turned by half a turn
        (three global closures of the office world with a 3 cm scanner, 180° and 14-18 m
        off, 9.7 standard deviations from the odometry's heading) is ruled out; MIT CSAIL's
        true closures lie within 2.5. Skipped where a step has no odometry factor; a
        standard deviation so wide that no heading lies beyond it rules nothing out."""
        lo, hi = closure.node_from, closure.node_to
        turn = float(self._odom_step[lo:hi, 2].sum())
        var = self._odometry_heading_var(lo, hi) + closure.cov[2, 2]
        if not (math.isfinite(turn) and math.isfinite(var)):  # a step without odometry
            return False
        error = se2.wrap_float(float(closure.measured[2]) - turn)
        return self._ruled_out_by_odometry(
            error,
            var,
            "loop closure %d->%d ruled out by the odometry's heading between them: %.1f deg "
            "against the odometry's %.1f deg, sigma %.1f deg",
            (lo, hi, np.degrees(closure.measured[2]), np.degrees(turn), np.degrees(var**0.5)),
        )

    def _ruled_out_by_odometry(
        self, error: float, var: float, message: str, args: tuple[object, ...]
    ) -> bool:
        """Whether an ``error`` (its variance ``var``) of a closure against the odometry lies
        beyond ``sqrt(consistency_chi2)`` standard deviations; such a closure is counted
        (``stats.rejected_odometry``) and logged (``message % args``)."""
        if error**2 <= self.config.consistency_chi2 * var:
            return False
        self.stats.rejected_odometry += 1
        logger.debug(message, *args)
        return True

    def _odometry_heading_var(self, lo: int, hi: int) -> float:
        """Variance (rad²) of the odometry's heading from node ``lo`` to node ``hi > lo``: its
        steps' heading variances plus the noise model's systematic drift over the path's
        length; NaN where a step has no odometry factor."""
        steps = self._odom_step[lo:hi]
        path_m = float(np.hypot(steps[:, 0], steps[:, 1]).sum())
        rate = self.odometry_noise.sigma_theta_per_distance_rad_per_m
        return float(self._odom_cov[lo:hi, 2, 2].sum()) + (rate * path_m) ** 2

    def _odometry_chain(self, lo: int, hi: int) -> tuple[FloatArray, FloatArray] | None:
        """The odometry from node ``lo`` to node ``hi > lo``: ``(chain (n, 3), cov (3, 3))``,
        the poses of nodes ``lo..hi`` in the frame of ``lo`` (the odometry factors composed)
        and the covariance of the last (tangent space at ``hi``): :func:`chain_covariance` of
        the factors' covariances plus :func:`odometry_bias_covariance` (a systematic error of
        the size of the noise model's per-distance sigmas). ``None`` where a step has no
        odometry factor, or beyond the first-order regime: the chain's heading standard
        deviation (its steps' heading variances plus the systematic drift over its length)
        above :data:`_ODOMETRY_TEST_MAX_HEADING_SIGMA_RAD`."""
        noise = self.odometry_noise
        if not self._odometry_heading_var(lo, hi) <= _ODOMETRY_TEST_MAX_HEADING_SIGMA_RAD**2:
            return None  # also NaN: a gap
        steps = self._odom_step[lo:hi]
        covs = self._odom_cov[lo:hi]
        chain = se2.accumulate(steps)
        cov = chain_covariance(chain, covs) + odometry_bias_covariance(
            chain, noise.sigma_xy_per_distance_m_per_m, noise.sigma_theta_per_distance_rad_per_m
        )
        return chain, cov

    def _contradicts_accepted(self, closure: LoopClosure, poses: _Poses) -> bool:
        """Whether the closure contradicts a closure accepted shortly before it.

        An accepted local closure enters with a robust kernel: drawn from far beyond its own
        covariance, it barely moves the estimate until the final refinement, so the
        marginal stays as wide as before and a second, wrong match to the same place a few
        nodes later passes the gate just as well (ACES: two closures to node 192, 3 nodes
        apart, 0.9 m and 12° apart from each other). The accepted set must stay pairwise
        consistent (PCM, Mangelson et al. 2018): the closure is ruled out when its cycle with
        an accepted closure (:func:`pcm_chi2`; both new nodes and both old nodes within
        ``global_window_nodes``) exceeds ``consistency_chi2`` under both short chains that
        connect them: the fused sequential factors (estimates) and the odometry alone
        (:meth:`_odometry_chain`). Either sensor can be wrong over a few metres (a corridor
        match that slid, wheels that slipped in a turn), both at once rarely: a chain that
        is missing or beyond the first-order regime vetoes nothing. Ruled-out closures are
        not held for agreement.
        """
        lc = self.config
        near = [
            a
            for a in self._accepted
            if closure.node_to - a.node_to <= lc.global_window_nodes
            and abs(closure.node_from - a.node_from) <= lc.global_window_nodes
        ]
        if not near:
            return False
        ok_old, t_old, c_old = self._relatives_to(
            np.array([a.node_from for a in near]), closure.node_from, poses
        )
        ok_new, t_new, c_new = self._relatives_to(
            np.array([a.node_to for a in near]), closure.node_to, poses
        )
        # a step without a sequential factor: no chain, no veto
        ok = ok_old & ok_new
        d2 = np.zeros(len(near))
        d2[ok] = _cycle_chi2(
            np.array([a.measured for a in near])[ok],
            np.array([a.cov for a in near])[ok],
            closure,
            t_old[ok],
            c_old[ok],
            t_new[ok],
            c_new[ok],
        )
        for i in np.flatnonzero(d2 > lc.consistency_chi2).tolist():
            # the smaller cycle chi2 of the two chains decides: the odometry's is only
            # read when the estimates' is beyond the gate
            a = near[i]
            old = self._odometry_relative(a.node_from, closure.node_from)
            new = self._odometry_relative(a.node_to, closure.node_to)
            if old is None or new is None:
                continue
            chi2 = min(d2[i], pcm_chi2(a, closure, old, new))
            if chi2 > lc.consistency_chi2:
                self.stats.rejected_accepted += 1
                logger.debug(
                    "loop closure %d->%d ruled out by the accepted %d->%d: cycle chi2 %.1f",
                    *(*_ends(closure), *_ends(a), chi2),
                )
                return True
        return False

    def _odometry_relative(self, u: int, v: int) -> tuple[FloatArray, FloatArray] | None:
        """Pose of node ``v`` in the frame of node ``u`` by the odometry alone and its
        covariance, tangent at ``v`` (as :meth:`_relative`); ``None`` where
        :meth:`_odometry_chain` has none."""
        if u == v:
            return np.zeros(3), np.zeros((3, 3))
        odometry = self._odometry_chain(min(u, v), max(u, v))
        if odometry is None:
            return None
        chain, cov = odometry
        return _seen_from(chain[-1], cov, u < v)

    def _agree(
        self, a: LoopClosure, b: LoopClosure, poses: _Poses, path_m: Sequence[float]
    ) -> bool:
        """Local pairs: :func:`closures_agree`; a pair with a global closure: :func:`pcm_chi2`,
        both the new and the old nodes within ``global_window_nodes`` of each other (the
        dead-reckoning chain covariances of :func:`chain_covariance` stay tight only over
        short chains), old nodes ``agreement_min_separation_m`` apart along the path."""
        lc = self.config
        if not (a.is_global or b.is_global):
            if b.node_to - a.node_to > lc.agreement_window_nodes:
                return False
            carry = se2.between(poses[a.node_to], poses[b.node_to])
            return closures_agree(a, b, carry, path_m, lc)
        if (
            abs(b.node_to - a.node_to) > lc.global_window_nodes
            or abs(b.node_from - a.node_from) > lc.global_window_nodes  # short chains only
            or abs(path_m[b.node_from] - path_m[a.node_from]) < lc.agreement_min_separation_m
        ):
            return False
        old = self._relative(a.node_from, b.node_from, poses)
        new = self._relative(a.node_to, b.node_to, poses)
        return (
            old is not None and new is not None and pcm_chi2(a, b, old, new) <= lc.consistency_chi2
        )

    def _sync_steps(self, graph: PoseGraph) -> None:
        """Fuse the information of new sequential factors (``i -> i+1``: odometry, scan
        match) into the per-step information used by :func:`chain_covariance`, and keep each
        step's odometry factor for :meth:`_contradicts_odometry`."""
        new = graph.factors_from(self._factors_seen)
        n = graph.n_nodes
        if self._step_info.shape[0] < n:
            size = max(n, 2 * self._step_info.shape[0])
            self._step_info = _grown(self._step_info, size, 0.0)
            self._odom_step = _grown(self._odom_step, size, np.nan)
            self._odom_cov = _grown(self._odom_cov, size, np.nan)
        steps = []
        for f in new:
            if f.kind is FactorKind.LOOP_CLOSURE:
                self._closures_seen += 1
            elif f.j == f.i + 1:
                steps.append(f)
                if f.kind is FactorKind.ODOMETRY:
                    self._odom_step[f.i], self._odom_cov[f.i] = f.measured, f.cov
        if steps:
            # One stacked inverse (LAPACK per matrix, the bits of one call each).
            infos = np.linalg.inv(np.array([f.cov for f in steps]))
            for f, info in zip(steps, infos, strict=True):
                self._step_info[f.i] += info
        self._factors_seen = graph.n_factors
        if self._closures_seen > self._closures_own:  # closures added by someone else
            self._closures_own = self._closures_seen
            self._moved_m = np.inf

    def _relative(self, u: int, v: int, poses: _Poses) -> tuple[FloatArray, FloatArray] | None:
        """Pose of node ``v`` in the frame of node ``u`` (estimates) and its dead-reckoning
        covariance along the sequential factors, tangent at ``v``; ``None`` if a step has no
        sequential factor (:meth:`_relatives_to` of one node)."""
        ok, t, cov = self._relatives_to(np.array([u]), v, poses)
        return (t[0], cov[0]) if ok[0] else None

    def _relatives_to(
        self, us: IntArray, v: int, poses: _Poses
    ) -> tuple[NDArray[np.bool_], FloatArray, FloatArray]:
        """:meth:`_relative` from each of several nodes to one node, in one pass.

        :func:`chain_covariance` of the chain between ``u`` and ``v``, seen from ``v``
        (through :func:`_seen_from` when ``u > v``), is ``Σ_k Ad(X_v⁻¹ X_{k+1}) Σ_k
        Ad(X_v⁻¹ X_{k+1})ᵀ`` over the steps ``k -> k+1`` between them, on either side of
        ``v``: the terms are computed once, and each node's covariance is their cumulative
        sum outwards from ``v``.

        Args:
            us: ``(m,)`` node ids.
            v: The common node.
            poses: The search's estimates.

        Returns:
            ``ok`` ``(m,)`` bool: every step between ``us[i]`` and ``v`` has a sequential
            factor; ``t`` ``(m, 3)``: the pose of ``v`` in the frame of ``us[i]``; ``cov``
            ``(m, 3, 3)``: its covariance, tangent at ``v`` (m², rad²). Rows where ``ok``
            is False are undefined.
        """
        us = np.asarray(us, dtype=np.int64)
        lo, hi = min(int(us.min()), v), max(int(us.max()), v)
        x = poses[lo : hi + 1]
        info = np.zeros((hi - lo, 3, 3))
        known = max(0, min(hi, self._step_info.shape[0]) - lo)
        info[:known] = self._step_info[lo : lo + known]
        valid = np.asarray(info.any(axis=(1, 2)))
        gaps = np.asarray(~valid, dtype=np.int64)
        step_cov = np.zeros_like(info)
        step_cov[valid] = np.linalg.inv(info[valid])
        ad = _adjoints(x[v - lo], x[1:])
        terms = np.einsum("kij,kjl,kml->kim", ad, step_cov, ad)
        # row j of each side: the steps from v out to j + 1 steps away
        before = np.cumsum(terms[: v - lo][::-1], axis=0)
        after = np.cumsum(terms[v - lo :], axis=0)
        gaps_before = np.cumsum(gaps[: v - lo][::-1])
        gaps_after = np.cumsum(gaps[v - lo :])
        cov = np.zeros((us.shape[0], 3, 3))
        ok = np.ones(us.shape[0], dtype=bool)
        below, above = us < v, us > v
        cov[below], ok[below] = before[v - 1 - us[below]], gaps_before[v - 1 - us[below]] == 0
        cov[above], ok[above] = after[us[above] - 1 - v], gaps_after[us[above] - 1 - v] == 0
        return ok, se2.between(x[us - lo], x[v - lo]), cov

    # ------------------------------------------------------------------ bookkeeping

    def _hold(self, closure: LoopClosure) -> None:
        lc = self.config
        self.pending = [
            c
            for c in self.pending
            if closure.node_to - c.node_to
            <= (lc.global_window_nodes if c.is_global else lc.agreement_window_nodes)
        ] + [closure]

    def _accept_group(self, agreeing: list[LoopClosure], closure: LoopClosure) -> AcceptedClosures:
        # Independent places agree: the group is its own outlier test, and a robust kernel
        # would all but ignore the large residual the drift gives it.
        self.pending = [c for c in self.pending if c not in agreeing]
        group = [*agreeing, closure]
        large = any(c.is_global for c in group)
        return self._accept(group, None, large)

    def _accept(
        self,
        closures: list[LoopClosure],
        kernel: Literal["huber", "cauchy"] | None,
        large_correction: bool = False,
        confirmed_steps: tuple[int, ...] = (),
    ) -> AcceptedClosures:
        self.stats.accepted += len(closures)
        window = self.config.global_window_nodes
        newest = closures[-1].node_to
        self._accepted = [c for c in self._accepted if newest - c.node_to <= window]
        self._accepted += closures
        self.stats.global_accepted += sum(c.is_global for c in closures)
        return AcceptedClosures(tuple(closures), kernel, large_correction, confirmed_steps)


def _same_place(window: IntArray, other: IntArray) -> bool:
    """Whether two candidates' reference windows (:meth:`LoopCloser._window`, ``(k,)`` node
    ids, nearest first) are the same nodes: candidates from several passes through one place.
    Their references are then the same landmarks, and a second match would measure the scan
    against them again (the same map-frame pose, or the same failure)."""
    return bool(np.array_equal(np.sort(window), np.sort(other)))


def _grown(a: NDArray[np.float64], size: int, fill: float) -> NDArray[np.float64]:
    """``a`` with rows up to ``size``, the new rows set to ``fill``."""
    out = np.full((size, *a.shape[1:]), fill)
    out[: a.shape[0]] = a
    return out


def _seen_from(t: FloatArray, cov: FloatArray, forward: bool) -> tuple[FloatArray, FloatArray]:
    """A chain's relative pose ``t`` ``(3,)`` (later node in the earlier one's frame) with its
    covariance ``(3, 3)`` (tangent at the later node), as seen from the later node when not
    ``forward``: ``t⁻¹`` with covariance ``Ad(t) C Ad(t)ᵀ`` (tangent at the earlier node;
    ``X⁻¹`` of ``X Exp(xi)`` is ``X⁻¹ Exp(-Ad(X) xi)``)."""
    if forward:
        return t, cov
    ad = se2.adjoint(t)
    return se2.inverse(t), ad @ cov @ ad.T


def _ends(c: LoopClosure) -> tuple[int, int]:
    return c.node_from, c.node_to


__all__ = [
    "AcceptedClosures",
    "LoopCloser",
    "LoopClosure",
    "LoopClosureConfig",
    "LoopClosureStats",
    "chain_covariance",
    "closures_agree",
    "innovation_chi2",
    "pcm_chi2",
]
