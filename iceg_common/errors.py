"""The ICEG exception hierarchy: one root, one subclass per concern.

Library code raises these; the CLI catches ``IcegError`` once, prints one line and exits
with code 1. Messages say what is wrong and what to fix, and for log files name
``file:line``.
"""

from __future__ import annotations


class IcegError(Exception):
    """Root of every error ICEG raises on purpose."""


class LogFormatError(IcegError):
    """A sensor log or relations file is missing, unreadable, or malformed."""


class ConfigError(IcegError):
    """A configuration value is invalid (out of range, wrong type, unknown key)."""


class GraphError(IcegError):
    """The pose-graph back-end failed (gtsam error, unknown node, singular system)."""


class EvaluationError(IcegError):
    """A trajectory cannot be scored (no relation matches a scan, empty trajectory)."""


class MatchingError(IcegError):
    """The scan matcher was called with inconsistent inputs (not a failed match: that is
    a ``MatchResult`` with ``success=False``)."""
