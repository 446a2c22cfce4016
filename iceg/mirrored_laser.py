"""A laser whose beams are mirrored against the odometry, told by the robot's turns.

A laser mounted upside down sees the world mirrored: a bearing ``a`` in its own frame is
``-a`` in the robot's. A ROS bag says so in its tf (the reader mirrors it back); a CARMEN log,
or a log converted by hand, has no such record, and a converter that writes the beams
clockwise does the same. Against wheel odometry such scans turn the wrong way: when the
robot turns by ``dθ``, the directions of the walls in the scan turn by ``+dθ`` instead of
``-dθ``. Every match then fights the odometry (MIT CSAIL with its beams reversed: 961
scan-match factors of 1813, 6.0 m against its relations, exit code 0 and a map of rays).

Wall directions do not depend on where the robot is, only on its heading, so the test needs
no scan matching: for a pair of scans between which the odometry turned by ``dθ``
(:func:`iceg.robot_body.turn_pairs`: 30-90° within 1 m of travel), the segment directions of
the second scan are compared with the first's turned by ``dθ`` (as the beams say) and by
``-dθ`` (as mirrored beams would say): a kernel correlation over every segment pair, lines
undirected (modulo π), weighted by the shorter segment, each pair's kernel the sum of the two
segments' direction variances and the odometry's heading variance over the turn
(:func:`graph.odometry_covariance`). A one-sided sign test (binomial) over the turns whose two
correlations differ says whether the mirrored reading wins more often than chance allows, at
the conventional 1 % (:data:`SIGNIFICANCE_LEVEL`). The odometry need not be accurate, only
turn the right way.

What it cannot tell: whether the laser is mirrored or the odometry is left-handed (``y`` and
``θ`` negated); the relative motions agree once either is mirrored, and the map of the other
reading is the mirror image. A mirrored laser is by far the commoner (an upside-down mount),
so the beams are the ones mirrored. A log without odometry, or without turns, is not tested.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray
from scipy.stats import binomtest

from graph import odometry_covariance
from iceg.features.extract import extract
from iceg.robot_body import turn_pairs
from iceg.scan_store import ScanStore
from iceg_common import se2

if TYPE_CHECKING:
    from collections.abc import Sequence

    from frontends import LaserScan
    from iceg.config import IcegConfig
    from iceg.types import ScanFeatures

FloatArray = NDArray[np.float64]

#: Level of the sign test: the mirrored reading is taken when chance would explain its wins
#: less often than this.
SIGNIFICANCE_LEVEL = 0.01
#: Most turns compared, evenly spread over the log: MIT CSAIL with its beams reversed wins
#: mirrored in 49 of 64 (p ~ 1e-5); a log as read is decided in 7-27 turns (6-21 ms, two
#: feature extractions per turn).
MAX_TURNS = 64


@dataclass(frozen=True)
class MirrorTest:
    """The sign test of a log's turns (module docstring).

    Attributes:
        turns: Turns of the odometry compared (pairs of scans; fewer than found where the
            beams as read won early).
        as_read: Turns whose wall directions follow the odometry as the beams are.
        mirrored: Turns whose wall directions follow it with the beams mirrored.
        p_value: One-sided binomial probability of ``mirrored`` or more wins of
            ``as_read + mirrored`` by chance (1.0 without a deciding turn).
    """

    turns: int
    as_read: int
    mirrored: int
    p_value: float

    @property
    def beams_mirrored(self) -> bool:
        """Whether the mirrored reading wins at :data:`SIGNIFICANCE_LEVEL`."""
        return self.p_value < SIGNIFICANCE_LEVEL

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return {**asdict(self), "beams_mirrored": self.beams_mirrored}


def mirror_test(scans: ScanStore | Sequence[LaserScan], config: IcegConfig) -> MirrorTest | None:
    """Whether ``scans``' beams turn against their odometry (module docstring).

    Args:
        scans: A log's scans in time order, with their odometry (``odom_pose``; scans without
            one never pair).
        config: Its run's configuration: the features' settings (segments) and the odometry
            noise (heading variance of a turn).

    Returns:
        The test, or None where the odometry turns nowhere (no odometry, or no turn of
        30-90° within 1 m of travel). The turns are compared in order until the beams as
        read win at :data:`SIGNIFICANCE_LEVEL` (seven turns of seven where every one
        decides), else all of them: stopping early can only keep a log as read, so the
        mirrored reading's level is the sign test's.
    """
    if isinstance(scans, ScanStore):
        odometry = scans.odometry[1]
    else:
        nan = np.full(3, np.nan)
        odometry = np.array([nan if s.odom_pose is None else s.odom_pose for s in scans])
    pairs = turn_pairs(odometry.reshape(-1, 3))
    if pairs.shape[0] == 0:
        return None
    if pairs.shape[0] > MAX_TURNS:
        pairs = pairs[np.linspace(0, pairs.shape[0] - 1, MAX_TURNS).round().astype(np.int64)]
    features: dict[int, ScanFeatures] = {}

    def features_of(k: int) -> ScanFeatures:
        if k not in features:
            features[k] = extract(scans[k], config.features)
        return features[k]

    as_read = mirrored = turns = 0
    for first, second in pairs.tolist():
        turns += 1
        delta = se2.between(odometry[first], odometry[second])
        heading_var = float(odometry_covariance(delta, config.odometry_noise)[2, 2])
        dtheta = float(delta[2])
        before = _correlation(features_of(first), features_of(second), dtheta, heading_var)
        mirror = _correlation(features_of(first), features_of(second), -dtheta, heading_var)
        as_read += before > mirror
        mirrored += mirror > before
        if _wins(as_read, mirrored) < SIGNIFICANCE_LEVEL:
            break  # the beams as read win: no later turn is needed (stops only this way)
    return MirrorTest(turns, as_read, mirrored, _wins(mirrored, as_read))


def _wins(wins: int, losses: int) -> float:
    """One-sided binomial probability of ``wins`` or more of ``wins + losses`` by chance
    (1.0 with none decided)."""
    n = wins + losses
    return float(binomtest(wins, n, 0.5, alternative="greater").pvalue) if n else 1.0


def _correlation(
    first: ScanFeatures, second: ScanFeatures, turn_rad: float, heading_var: float
) -> float:
    """Kernel correlation of ``second``'s segment directions turned by ``turn_rad`` with
    ``first``'s (lines undirected: differences modulo π), each segment pair weighted by the
    shorter segment (metres), its Gaussian kernel's variance the two directions' variances
    plus ``heading_var`` (rad²)."""
    if first.seg_lines.shape[0] == 0 or second.seg_lines.shape[0] == 0:
        return 0.0
    length_1 = np.linalg.norm(first.seg_endpoints[:, 1] - first.seg_endpoints[:, 0], axis=1)
    length_2 = np.linalg.norm(second.seg_endpoints[:, 1] - second.seg_endpoints[:, 0], axis=1)
    weight = np.minimum(length_1[:, None], length_2[None, :])
    var = first.seg_cov[:, None, 0, 0] + second.seg_cov[None, :, 0, 0] + heading_var
    diff = second.seg_lines[None, :, 0] + turn_rad - first.seg_lines[:, None, 0]
    diff = (diff + math.pi / 2) % math.pi - math.pi / 2
    return float(np.sum(weight * np.exp(-0.5 * diff * diff / var)))
