"""The :class:`Matcher` protocol: what the pipeline needs from a scan matcher.

:class:`~iceg.matching.IceMatcher` is the reference implementation; the peers of
:mod:`iceg.matching.peers` (PL-ICP, GICP, KISS-ICP, Open3D ICP) offer the same call, so that
``matching.method`` swaps the matcher while the pose graph, the feature map and the loop
closure stay the same.
"""

from __future__ import annotations

from typing import Protocol, runtime_checkable

from numpy.typing import ArrayLike

from iceg.matching.config import MatchBounds
from iceg.types import MatchResult, ScanFeatures


@runtime_checkable
class Matcher(Protocol):
    """A scan matcher: the new scan against a reference, from a prediction, within bounds."""

    def match(
        self,
        features: ScanFeatures,
        reference: ScanFeatures,
        prediction: ArrayLike,
        bounds: MatchBounds | None = None,
    ) -> MatchResult:
        """Match a new scan against a reference.

        Args:
            features: The new scan (robot frame): its ``points_xy`` and, for feature
                matchers, its segments and ICE features.
            reference: The reference (reference frame): a scan or a feature-map reference;
                its ``points_xy`` may be empty (then point matchers sample its segments).
            prediction: ``(3,)`` predicted pose ``[x_m, y_m, theta_rad]`` of the new scan in
                the reference frame.
            bounds: Admissible motion around the prediction (``None``: global).

        Returns:
            A :class:`~iceg.types.MatchResult`: pose in the reference frame, covariance in
            the tangent space at the pose in the new scan's frame; or a failure and reason.
        """
        ...
