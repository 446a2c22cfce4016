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


class ScanError(IcegError):
    """A laser scan is inconsistent (unsorted or non-finite bearings, a non-finite laser
    offset, shapes that disagree, an absurd beam count)."""


class FeatureMapError(IcegError):
    """The feature map was updated or queried inconsistently (a node added twice, a match
    that refers to no reference)."""


class GridError(IcegError):
    """Occupancy-grid inputs are inconsistent (pose count, shapes, non-finite poses), the grid
    would be too large, or an export cannot be written."""


class OutputError(IcegError):
    """A result cannot be written where asked (an existing file in the way, a read-only
    folder, no space)."""


class SessionError(IcegError):
    """A saved session cannot be read, continued or edited (missing or corrupt file, a format
    version this ICEG does not know, a log whose scans no longer match their hashes), or a log
    cannot be placed in its map."""
