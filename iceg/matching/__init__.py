"""ICE scan matching (paper §III-C2/C3; docs/design.md "ICE matching, step by step", steps 5-10).

Example::

    from iceg.matching import IceMatcher, MatchBounds, MatchingConfig
    matcher = IceMatcher(MatchingConfig())
    result = matcher.match(new_features, reference, prediction, MatchBounds.local(0.5, 15.0))
    if result.success:
        result.pose, result.cov  # new scan in the reference frame; Pose2 tangent covariance

Other matchers behind the same :class:`Matcher` protocol (``matching.method``):
:func:`iceg.matching.peers.make_matcher`.
"""

from iceg.matching.config import (
    CorrelationConfig,
    CovarianceConfig,
    FilterConfig,
    MatchBounds,
    MatchingConfig,
    RefinementConfig,
    ValidationConfig,
    VotingConfig,
)
from iceg.matching.geometry import transform_features, transform_lines
from iceg.matching.matcher import IceMatcher
from iceg.matching.protocol import Matcher

__all__ = [
    "CorrelationConfig",
    "CovarianceConfig",
    "FilterConfig",
    "IceMatcher",
    "MatchBounds",
    "Matcher",
    "MatchingConfig",
    "RefinementConfig",
    "ValidationConfig",
    "VotingConfig",
    "transform_features",
    "transform_lines",
]
