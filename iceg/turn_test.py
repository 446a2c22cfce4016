"""Whether a log's walls turn as its odometry says: as read, mirrored, or not at all.

Wall directions in a scan depend on the robot's heading only, not on where it is. When the
odometry turns by ``dθ`` between two scans, the walls of the second scan, turned by ``dθ``,
line up with the first's. Two ways a log breaks that, both silent before (exit code 0, a map
of rays):

- *Mirrored beams.* A laser mounted upside down sees the world mirrored (a bearing ``a`` in
  its frame is ``-a`` in the robot's); a ROS bag says so in its tf (the reader mirrors it
  back), a CARMEN log or a log converted by hand does not, and a converter that writes the
  beams clockwise does the same. The walls then turn by ``-dθ``. MIT CSAIL with its beams
  reversed: 961 scan-match factors of 1813, 6.0 m against its relations.
- *A heading that is not the robot's.* The odometry's heading in degrees (a turn of 1° read
  as 57°), or another column read as the heading. The walls then hardly turn where the
  odometry turns by 30-90°. MIT CSAIL with its heading in degrees: 136 scan-match factors of
  1853, 2.7 m and 81° against its relations.

The test needs no scan matching: for turns of the odometry (:func:`iceg.robot_body.
turn_pairs`: 30-90° within 1 m of travel, at most :data:`MAX_TURNS`, evenly spread), the
segment directions of the later scan are compared with the earlier one's turned by ``dθ``
(as read), by ``-dθ`` (mirrored) and by 0 (unturned): a kernel correlation over every segment
pair, lines undirected (modulo π), weighted by the shorter segment, each pair's kernel the
sum of the two segments' direction variances and the odometry's heading variance over the
turn (:func:`graph.odometry_covariance`). Two one-sided sign tests (binomial) over the turns
whose correlations differ, each of the other readings against the one as read, at the
conventional 1 % (:data:`SIGNIFICANCE_LEVEL`; at most 2 % for the two together). The odometry
need not be accurate, only turn as the robot turned.

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

#: Level of each sign test: another reading is taken when chance would explain its wins
#: over the reading as read less often than this.
SIGNIFICANCE_LEVEL = 0.01
#: Most turns compared, evenly spread over the log: MIT CSAIL with its beams reversed wins
#: mirrored in 49 of 64 (p ~ 1e-5), with its heading in degrees unturned in 55 of 64; a log
#: as read is decided in 7-27 turns (6-21 ms, two feature extractions per turn).
MAX_TURNS = 64


@dataclass(frozen=True)
class TurnTest:
    """The sign tests of a log's turns (module docstring); each count is of turns whose two
    correlations differ.

    Attributes:
        turns: Turns of the odometry compared (pairs of scans; fewer than found where the
            reading as read won early).
        as_read, mirrored: Turns whose walls line up better turned by ``dθ`` / by ``-dθ``.
        p_mirrored: One-sided binomial probability of ``mirrored`` or more wins of
            ``as_read + mirrored`` by chance (1.0 without a deciding turn).
        turned, unturned: Turns whose walls line up better turned by ``dθ`` / not turned.
        p_unturned: The same of ``unturned`` of ``turned + unturned``.
    """

    turns: int
    as_read: int
    mirrored: int
    p_mirrored: float
    turned: int
    unturned: int
    p_unturned: float

    @property
    def heading_unusable(self) -> bool:
        """Whether the walls stay unturned where the odometry turns, at
        :data:`SIGNIFICANCE_LEVEL`: its heading is not the robot's."""
        return self.p_unturned < SIGNIFICANCE_LEVEL

    @property
    def beams_mirrored(self) -> bool:
        """Whether the walls turn against the odometry, at :data:`SIGNIFICANCE_LEVEL` (and
        its heading is the robot's)."""
        return self.p_mirrored < SIGNIFICANCE_LEVEL and not self.heading_unusable

    def finding(self) -> tuple[str, str] | None:
        """The reader option the test calls for (:func:`frontends.open_log`: ``laser_only``
        where the heading is not the robot's, else ``mirror_beams`` where the beams are
        mirrored) and what it found, in words; None where the log reads as it is."""
        if self.heading_unusable:
            return "laser_only", (
                f"the walls do not turn where the odometry turns (in {self.unturned} of "
                f"{self.turned + self.unturned} turns of 30-90 deg they line up better "
                f"unturned, p = {self.p_unturned:.1g})"
            )
        if self.beams_mirrored:
            return "mirror_beams", (
                f"the walls turn against the odometry (in {self.mirrored} of "
                f"{self.as_read + self.mirrored} turns they follow it only with the beams "
                f"mirrored, p = {self.p_mirrored:.1g})"
            )
        return None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return {
            **asdict(self),
            "beams_mirrored": self.beams_mirrored,
            "heading_unusable": self.heading_unusable,
        }


def turn_test(scans: ScanStore | Sequence[LaserScan], config: IcegConfig) -> TurnTest | None:
    """Whether ``scans``' walls turn as their odometry says (module docstring).

    Args:
        scans: A log's scans in time order, with their odometry (``odom_pose``; scans without
            one never pair, nor two with an odometry break, ``odom_break``, between them).
        config: Its run's configuration: the features' settings (segments) and the odometry
            noise (heading variance of a turn).

    Returns:
        The test, or None where the odometry turns nowhere (no odometry, or no turn of
        30-90° within 1 m of travel). The turns are compared in order until the reading as
        read wins both tests at :data:`SIGNIFICANCE_LEVEL` (seven turns of seven where every
        one decides), else all of them: stopping early can only keep a log as read, so the
        other readings keep the sign tests' level.
    """
    if isinstance(scans, ScanStore):
        _, odometry, breaks = scans.odometry
    else:
        nan = np.full(3, np.nan)
        odometry = np.array([nan if s.odom_pose is None else s.odom_pose for s in scans])
        breaks = np.array([s.odom_break for s in scans], dtype=bool)
    pairs = turn_pairs(odometry.reshape(-1, 3), breaks)
    if pairs.shape[0] == 0:
        return None
    if pairs.shape[0] > MAX_TURNS:
        pairs = pairs[np.linspace(0, pairs.shape[0] - 1, MAX_TURNS).round().astype(np.int64)]
    features: dict[int, ScanFeatures] = {}

    def features_of(k: int) -> ScanFeatures:
        if k not in features:
            features[k] = extract(scans[k], config.features)
        return features[k]

    wins = np.zeros(4, dtype=np.int64)  # as read, mirrored, turned, unturned
    turns = 0
    for first, second in pairs.tolist():
        turns += 1
        delta = se2.between(odometry[first], odometry[second])
        heading_var = float(odometry_covariance(delta, config.odometry_noise)[2, 2])
        a, b = features_of(first), features_of(second)
        dtheta = float(delta[2])
        read, mirror, still = (_correlation(a, b, t, heading_var) for t in (dtheta, -dtheta, 0))
        wins += (read > mirror, mirror > read, read > still, still > read)
        if max(sign_test_p(wins[0], wins[1]), sign_test_p(wins[2], wins[3])) < SIGNIFICANCE_LEVEL:
            break  # as read wins both: no later turn is needed (stops only this way)
    as_read, mirrored, turned, unturned = wins.tolist()
    return TurnTest(
        turns,
        as_read,
        mirrored,
        sign_test_p(mirrored, as_read),
        turned,
        unturned,
        sign_test_p(unturned, turned),
    )


def sign_test_p(wins: int, losses: int) -> float:
    """One-sided sign test: the binomial probability of ``wins`` or more of ``wins + losses``
    by chance, ``sum_{i >= wins} C(n, i) / 2^n`` (1.0 with none decided). Exact integer sums
    (``scipy.stats.binomtest`` gives the same values; importing ``scipy.stats`` would add
    0.77 s to every run's start)."""
    n = int(wins + losses)
    if n == 0:
        return 1.0
    return sum(math.comb(n, i) for i in range(int(wins), n + 1)) / 2**n


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
