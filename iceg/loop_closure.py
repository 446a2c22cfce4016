"""Loop closure: candidate search among older nodes, chi-square gate, pairwise agreement.

Every ``every_n_nodes`` nodes the current node's scan is matched (ICE, paper §III-C2) against
the landmarks of older places near its estimate (DESIGN "Loop closure"). A closure is accepted
when its innovation passes a chi-square gate under the node's marginal covariance plus the
match covariance, or when two closures that failed the gate imply the same correction
(pairwise consistency after Olson 2009, "Recognizing places using spectrally clustered local
matches", reduced to pairs). :class:`LoopCloser` only decides; the pipeline
(:mod:`iceg.slam`) adds the accepted closures to the pose graph as factors.
"""

from __future__ import annotations

import logging
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field

from graph import PoseGraph
from iceg.feature_map import FeatureMap
from iceg.matching import MatchBounds, Matcher
from iceg.types import MatchResult, ScanFeatures
from iceg_common import se2

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Decimals of the innovation in debug log lines.
_LOG_DECIMALS = 3


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
    min_correlation: float = Field(
        default=0.5, ge=0, le=1, description="Minimum ICE correlation (eq. 1) of a loop closure."
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
    robust_kernel: Literal["huber", "cauchy"] = Field(
        default="cauchy", description="M-estimator wrapped around loop-closure factors."
    )
    robust_k: float = Field(
        default=1.0, gt=0, description="Kernel width in whitened units (sigmas)."
    )


@dataclass
class LoopClosureStats:
    """Loop-closure bookkeeping: searches run, matches tried, accepted and rejected."""

    searches: int = 0
    attempts: int = 0
    accepted: int = 0
    rejected_match: int = 0
    rejected_consistency: int = 0

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
    """

    node_from: int
    node_to: int
    measured: FloatArray
    cov: FloatArray
    correlation: float
    implied: FloatArray


@dataclass(frozen=True, eq=False)
class AcceptedClosures:
    """Closures to add to the pose graph as factors.

    Attributes:
        closures: The accepted closures, oldest first.
        robust_kernel: M-estimator of their factors (``None``: Gaussian; closures accepted by
            pairwise agreement are their own outlier test).
    """

    closures: tuple[LoopClosure, ...]
    robust_kernel: Literal["huber", "cauchy"] | None


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


@dataclass(frozen=True, eq=False)
class _Search:
    """Inputs shared by the steps of one search (estimates at the search's start)."""

    node_id: int
    ids: IntArray
    poses: FloatArray  # (N, 3) map frame, row = node id
    older: IntArray  # candidate pool: old in node count and along the path
    marginal: FloatArray  # (3, 3) current node
    radius_m: float


@dataclass(frozen=True, eq=False)
class _Best:
    candidate: int
    prediction: FloatArray
    result: MatchResult


class LoopCloser:
    """Searches loop closures for new nodes and decides which to accept.

    Example::

        closer = LoopCloser(config.loop_closure, matcher, feature_map)
        if closer.due(node_id):
            accepted = closer.search(node_id, features, graph, path_m)

    Args:
        config: Loop-closure settings.
        matcher: The ICE matcher used for loop-closure matches.
        feature_map: The map whose landmarks form each place's reference.
    """

    def __init__(
        self, config: LoopClosureConfig, matcher: Matcher, feature_map: FeatureMap
    ) -> None:
        self.config = config
        self.matcher = matcher
        self.feature_map = feature_map
        self.stats = LoopClosureStats()
        self.pending: list[LoopClosure] = []

    def due(self, node_id: int) -> bool:
        """Whether a search runs for this new node (enabled, every ``every_n_nodes``)."""
        return self.config.enabled and node_id % self.config.every_n_nodes == 0

    def search(
        self,
        node_id: int,
        features: ScanFeatures,
        graph: PoseGraph,
        path_m: Sequence[float],
    ) -> AcceptedClosures | None:
        """Search older nodes near the current estimate for a loop closure of ``node_id``.

        Candidates are nodes at least ``min_node_gap`` nodes and ``min_path_m`` metres of path
        back, within ``radius = base + n_sigma * sqrt(lambda_max(cov_xy))`` of the current
        estimate (``cov_xy`` from the current node's marginal, capped at
        ``max_search_radius_m``); up to ``max_candidates`` of the nearest, from distinct
        places, are matched against the landmarks of the ``reference_nodes`` old nodes
        nearest each candidate, and the best-correlated match is kept. It is accepted (robust
        kernel) when it passes the chi-square gate (:func:`innovation_chi2`), or together with
        held closures it agrees with (:func:`closures_agree`, no kernel); otherwise it is held.

        Args:
            node_id: The current node (already through ``graph.update()``).
            features: Its scan's ICE features, robot frame.
            graph: The pose graph (estimates and marginals are read, nothing is added).
            path_m: Odometry path length at each node, metres, indexed by node id.

        Returns:
            The closures to add as factors, or ``None``.

        Raises:
            GraphError: the graph cannot give the current node's marginal covariance.
        """
        ids, poses = graph.estimates()
        older = self._older_nodes(node_id, ids, np.asarray(path_m))
        if older.size == 0:
            return None
        self.stats.searches += 1
        marginal = graph.marginal_covariance(node_id)
        search = _Search(node_id, ids, poses, older, marginal, self._radius(marginal))
        best = self._best_match(search, features)
        if best is None:
            return None
        return self._decide(search, best, graph, path_m)

    # ------------------------------------------------------------------ steps

    def _older_nodes(self, node_id: int, ids: IntArray, path: FloatArray) -> IntArray:
        """Old in node count and far along the path: a node reached again after a detour,
        not the corridor just driven."""
        lc = self.config
        return ids[
            (ids <= node_id - lc.min_node_gap) & (path[node_id] - path[ids] >= lc.min_path_m)
        ]

    def _radius(self, marginal: FloatArray) -> float:
        lc = self.config
        sigma_xy = float(np.sqrt(max(np.linalg.eigvalsh(marginal[:2, :2]).max(), 0.0)))
        return min(lc.search_radius_m + lc.search_n_sigma * sigma_xy, lc.max_search_radius_m)

    def _candidates(self, s: _Search) -> list[int]:
        """Up to ``max_candidates`` nearest old nodes within the radius, from distinct places
        (more than ``reference_nodes`` nodes apart)."""
        lc = self.config
        dist = np.hypot(*(s.poses[s.older, :2] - s.poses[s.node_id, :2]).T)
        order = np.argsort(dist, kind="stable")
        candidates: list[int] = []
        for k in order[dist[order] <= s.radius_m]:
            if all(abs(int(s.older[k]) - c) > lc.reference_nodes for c in candidates):
                candidates.append(int(s.older[k]))
            if len(candidates) == lc.max_candidates:
                break
        return candidates

    def _bounds(self, s: _Search) -> MatchBounds:
        rotation_sigma = float(np.sqrt(max(s.marginal[2, 2], 0.0)))
        return MatchBounds(
            max_translation_m=s.radius_m,
            max_rotation_rad=np.radians(self.config.max_rotation_deg)
            + self.config.search_n_sigma * rotation_sigma,
        )

    def _best_match(self, s: _Search, features: ScanFeatures) -> _Best | None:
        """Match each candidate place; keep the best-correlated acceptable match."""
        lc = self.config
        bounds = self._bounds(s)
        best: _Best | None = None
        for candidate in self._candidates(s):
            # The place's reference: the old nodes nearest the candidate (any pass through it).
            near_cand = np.hypot(*(s.poses[s.older, :2] - s.poses[candidate, :2]).T)
            window = s.older[np.argsort(near_cand, kind="stable")[: lc.reference_nodes]]
            reference = self.feature_map.reference((s.ids, s.poses), window, s.poses[candidate])
            prediction = se2.between(s.poses[candidate], s.poses[s.node_id])
            self.stats.attempts += 1
            result = self.matcher.match(features, reference.features, prediction, bounds)
            if not result.success or result.correlation < lc.min_correlation:
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

    def _decide(
        self, s: _Search, best: _Best, graph: PoseGraph, path_m: Sequence[float]
    ) -> AcceptedClosures | None:
        """Chi-square gate, else pairwise agreement with a held closure, else hold it."""
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
        rounded = np.round(innovation, _LOG_DECIMALS)
        if d2 <= lc.consistency_chi2:
            logger.debug(
                "loop closure %d->%d accepted: innovation %s, chi2 %.1f, correlation %.2f",
                *(best.candidate, s.node_id, rounded, d2, result.correlation),
            )
            return self._accept([closure], lc.robust_kernel)
        agreeing = [c for c in self.pending if self._agree(c, closure, graph.estimate, path_m)]
        if agreeing:
            # Two independent places agree: the pair is its own outlier test, and a robust
            # kernel would all but ignore the large residual the drift gives it.
            self.pending = [c for c in self.pending if c not in agreeing]
            logger.debug(
                "loop closures %s->%d accepted by pairwise agreement (chi2 %.1f vs estimate)",
                *([c.node_from for c in agreeing], s.node_id, d2),
            )
            return self._accept([*agreeing, closure], None)
        self.stats.rejected_consistency += 1
        self.pending = [
            c for c in self.pending if s.node_id - c.node_to <= lc.agreement_window_nodes
        ] + [closure]
        logger.debug(
            "loop closure %d->%d held back: innovation %s, chi2 %.1f",
            *(best.candidate, s.node_id, rounded, d2),
        )
        return None

    def _agree(
        self,
        a: LoopClosure,
        b: LoopClosure,
        estimate: Callable[[int], FloatArray],
        path_m: Sequence[float],
    ) -> bool:
        if b.node_to - a.node_to > self.config.agreement_window_nodes:
            return False
        carry = se2.between(estimate(a.node_to), estimate(b.node_to))
        return closures_agree(a, b, carry, path_m, self.config)

    def _accept(
        self, closures: list[LoopClosure], kernel: Literal["huber", "cauchy"] | None
    ) -> AcceptedClosures:
        self.stats.accepted += len(closures)
        return AcceptedClosures(tuple(closures), kernel)


__all__ = [
    "AcceptedClosures",
    "LoopCloser",
    "LoopClosure",
    "LoopClosureConfig",
    "LoopClosureStats",
    "closures_agree",
    "innovation_chi2",
]
