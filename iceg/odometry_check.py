"""Whether a log's walls turn and move as its odometry says.

Wall directions in a scan depend on the robot's heading only; their offsets (the ``rho`` of
a line) on its position too. When the odometry turns by ``dθ`` between two scans, the walls
of the second, turned by ``dθ``, line up with the first's; when it moves, the walls moved
by its translation line up. Three ways a log breaks that, each silent before (exit code 0, a
map of rays):

- *Mirrored beams.* A laser mounted upside down sees the world mirrored (a bearing ``a`` in
  its frame is ``-a`` in the robot's); a ROS bag says so in its tf (the reader mirrors it
  back), a CARMEN log or a log converted by hand does not, and a converter that writes the
  beams clockwise does the same. The walls then turn by ``-dθ``. MIT CSAIL with its beams
  reversed: 961 scan-match factors of 1813, 6.0 m against its relations.
- *A heading that is not the robot's.* The odometry's heading in degrees (a turn of 1° read
  as 57°), or another column read as the heading. The walls then hardly turn where the
  odometry turns by 30-90°. MIT CSAIL with its heading in degrees: 136 scan-match factors of
  1853, 2.7 m and 81° against its relations.
- *A translation that is not the robot's.* The odometry's x and y in centimetres or
  millimetres (the robot's 1 cm read as 1 m). The walls then hardly move where the odometry
  moves by half a metre or more. MIT CSAIL with them in centimetres: 745 scan-match factors
  of 1846, 43.5 m against its relations.

No scan is matched. For turns of the odometry (:func:`iceg.robot_body.turn_pairs`: 30-90°
within 1 m of travel) the segment directions of the later scan are compared with the earlier
one's turned by ``dθ`` (as read), by ``-dθ`` (mirrored) and by 0 (unturned): a kernel
correlation over every segment pair, lines undirected (modulo π), weighted by the shorter
segment, each pair's kernel variance the two directions' variances plus the odometry's
heading variance (:func:`graph.odometry_covariance`). For moves of the odometry
(:func:`move_pairs`: each scan and the first later one half a metre or more along its path)
the later scan's lines, turned by ``dθ``, are placed by the odometry's translation (moved)
or by none (unmoved) and compared with the earlier one's in direction and offset, over the
lines that the translation shifts by more than :data:`INFORMATIVE_SIGMAS` of their offsets'
standard deviation (the offsets' variances plus the odometry's translation variance): a
wall along the motion, which both readings place alike, tells nothing and counts in
neither. One-sided sign tests (binomial) over the pairs whose correlations differ, each
other reading against the one as read, at the conventional 1 % (:data:`SIGNIFICANCE_LEVEL`).
The odometry need not be accurate, only turn and move as the robot did.

What it cannot tell: whether the laser is mirrored or the odometry is left-handed (``y`` and
``θ`` negated); the relative motions agree once either is mirrored, and the map of the other
reading is the mirror image. A mirrored laser is by far the commoner (an upside-down mount),
so the beams are the ones mirrored. Where scans lie so far apart that they see few of the
same walls (MIT CSAIL or ACES thinned to one scan in 7-8 m), the moves win either reading
by chance and decide nothing; a log without odometry has nothing to test.
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from graph import odometry_covariance
from iceg.features.extract import extract
from iceg.robot_body import MAX_PATH_M, path_travelled, turn_pairs, without_breaks
from iceg.scan_store import ScanStore, odometry_of
from iceg_common import se2

if TYPE_CHECKING:
    from collections.abc import Callable, Sequence

    from frontends import LaserScan
    from iceg.config import IcegConfig
    from iceg.types import ScanFeatures

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Level of each sign test: another reading is taken when chance would explain its wins
#: over the reading as read less often than this.
SIGNIFICANCE_LEVEL = 0.01
#: Most turns, and most moves, compared, evenly spread over the log: MIT CSAIL with its beams
#: reversed wins mirrored in 49 of 64 turns (p ~ 1e-5), with its heading in degrees
#: unturned in 55 of 64, with its x and y in centimetres unmoved in 64 of 64 moves; a log as
#: read is decided in 7-27 pairs of each (two feature extractions per pair).
MAX_PAIRS = 64
#: Shortest move of the odometry compared, metres: half of the turns' largest travel
#: (:data:`~iceg.robot_body.MAX_PATH_M`), enough to shift the walls across the motion by
#: many times a line's offset noise.
MIN_MOVE_M = MAX_PATH_M / 2
#: A line's offset tells moved from unmoved where the odometry's translation shifts it by
#: more than this many standard deviations (the conventional three).
INFORMATIVE_SIGMAS = 3.0


@dataclass(frozen=True)
class OdometryCheck:
    """The sign tests of a log's turns and moves (module docstring); each count is of pairs
    whose two correlations differ.

    Attributes:
        turns: Turns of the odometry compared (pairs of scans; fewer than found where the
            reading as read won early).
        as_read, mirrored: Turns whose walls line up better turned by ``dθ`` / by ``-dθ``.
        p_mirrored: One-sided binomial probability of ``mirrored`` or more wins of
            ``as_read + mirrored`` by chance (1.0 without a deciding turn).
        turned, unturned: Turns whose walls line up better turned by ``dθ`` / not turned.
        p_unturned: The same of ``unturned`` of ``turned + unturned``.
        moves: Moves of the odometry compared.
        moved, unmoved: Moves whose walls line up better moved by the odometry / not moved.
        p_unmoved: The same of ``unmoved`` of ``moved + unmoved``.
    """

    turns: int
    as_read: int
    mirrored: int
    p_mirrored: float
    turned: int
    unturned: int
    p_unturned: float
    moves: int
    moved: int
    unmoved: int
    p_unmoved: float

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

    @property
    def translation_unusable(self) -> bool:
        """Whether the walls stay unmoved where the odometry moves, at
        :data:`SIGNIFICANCE_LEVEL`: its translation is not the robot's."""
        return self.p_unmoved < SIGNIFICANCE_LEVEL

    def finding(self) -> tuple[str, str] | None:
        """The reader option the check calls for (:func:`frontends.open_log`: ``laser_only``
        where the heading is not the robot's, else ``mirror_beams`` where the beams are
        mirrored, else ``laser_only`` where the translation is not the robot's) and what it
        found, in words; None where the log reads as it is."""
        if self.heading_unusable:
            return "laser_only", (
                f"the walls do not turn where the odometry turns (in {self.unturned} of "
                f"{self.turned + self.unturned} turns of 30-90 deg they line up better "
                f"unturned, p = {self.p_unturned:.1g}): its heading is not the robot's (in "
                "degrees instead of radians? another column?)"
            )
        if self.beams_mirrored:
            return "mirror_beams", (
                f"the walls turn against the odometry (in {self.mirrored} of "
                f"{self.as_read + self.mirrored} turns they follow it only with the beams "
                f"mirrored, p = {self.p_mirrored:.1g})"
            )
        if self.translation_unusable:
            return "laser_only", (
                f"the walls do not move where the odometry moves (in {self.unmoved} of "
                f"{self.moved + self.unmoved} moves of 0.5 m or more they line up better unmoved, "
                f"p = {self.p_unmoved:.1g}): its translation is not the robot's (in "
                "centimetres or millimetres instead of metres?)"
            )
        return None

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return {
            **asdict(self),
            "beams_mirrored": self.beams_mirrored,
            "heading_unusable": self.heading_unusable,
            "translation_unusable": self.translation_unusable,
        }


def odometry_check(
    scans: ScanStore | Sequence[LaserScan], config: IcegConfig
) -> OdometryCheck | None:
    """Whether ``scans``' walls turn and move as their odometry says (module docstring).

    Args:
        scans: A log's scans in time order, with their odometry (``odom_pose``; scans without
            one never pair, nor two with an odometry break, ``odom_break``, between them).
        config: Its run's configuration: the features' settings (segments) and the odometry
            noise (heading and translation variance of a pair).

    Returns:
        The check, or None where the odometry neither turns nor moves (no odometry, one that
        never moves, no turn of 30-90° within 1 m and no move of 0.5 m or more). The pairs are
        compared in order until the reading as read wins at :data:`SIGNIFICANCE_LEVEL`
        (seven of seven where every pair decides), else all of them: stopping early can
        only keep a log as read, so the other readings keep the sign tests' level.
    """
    _, odometry, breaks = odometry_of(scans)
    turns = _spread(turn_pairs(odometry, breaks))
    moves = _spread(move_pairs(odometry, breaks))
    if turns.shape[0] == 0 and moves.shape[0] == 0:
        return None
    features: dict[int, ScanFeatures] = {}

    def features_of(k: int) -> ScanFeatures:
        if k not in features:
            features[k] = extract(scans[k], config.features)
        return features[k]

    def turning(first: int, second: int, delta: FloatArray, cov: FloatArray) -> tuple[int, ...]:
        a, b, dtheta = features_of(first), features_of(second), float(delta[2])
        read, mirror, still = (
            _direction_correlation(a, b, t, float(cov[2, 2])) for t in (dtheta, -dtheta, 0.0)
        )
        return (read > mirror, mirror > read, read > still, still > read)

    def moving(first: int, second: int, delta: FloatArray, cov: FloatArray) -> tuple[int, ...]:
        a, b = features_of(first), features_of(second)
        moved, still = (_offset_correlation(a, b, delta, cov, shift) for shift in (1.0, 0.0))
        return (moved > still, still > moved)

    n_turns, (as_read, mirrored, turned, unturned) = _compare(turns, odometry, config, turning, 2)
    n_moves, (moved, unmoved) = _compare(moves, odometry, config, moving, 1)
    return OdometryCheck(
        n_turns,
        as_read,
        mirrored,
        sign_test_p(mirrored, as_read),
        turned,
        unturned,
        sign_test_p(unturned, turned),
        n_moves,
        moved,
        unmoved,
        sign_test_p(unmoved, moved),
    )


def move_pairs(poses: FloatArray, breaks: NDArray[np.bool_] | None = None) -> IntArray:
    """``(M, 2)`` int64 index pairs ``(k, l)``, ``l > k``: for each scan ``k`` the first later
    scan at least :data:`MIN_MOVE_M` along the path of ``poses``, however far (the nearest
    view the log has that the odometry moved; a log whose scans lie metres apart pairs each
    scan with the next), where no odometry break and no scan without a pose lie between them.

    Args:
        poses: ``(N, 3)`` float64 robot poses ``[x_m, y_m, theta_rad]``, one per scan, in
            scan order (any frame; NaN rows never pair, nor do pairs across them).
        breaks: ``(N,)`` bool, an odometry break just before each scan; None: none.
    """
    poses = np.asarray(poses, dtype=np.float64).reshape(-1, 3)
    path = path_travelled(poses)
    first = np.arange(path.shape[0])
    second = np.searchsorted(path, path + MIN_MOVE_M, side="left")
    ok = second < path.shape[0]
    first, second = first[ok], second[ok]
    # NaN rows up to each scan: none from the pair's first scan to its second
    unposed = np.concatenate([[0], np.cumsum(~np.isfinite(poses).all(axis=1))])
    ok = unposed[second + 1] == unposed[first]
    return without_breaks(np.stack([first[ok], second[ok]], axis=1).astype(np.int64), breaks)


def _spread(pairs: IntArray) -> IntArray:
    """At most :data:`MAX_PAIRS` of ``pairs``, evenly spread."""
    if pairs.shape[0] <= MAX_PAIRS:
        return pairs
    return pairs[np.linspace(0, pairs.shape[0] - 1, MAX_PAIRS).round().astype(np.int64)]


def _compare(
    pairs: IntArray,
    odometry: FloatArray,
    config: IcegConfig,
    readings: Callable[[int, int, FloatArray, FloatArray], tuple[int, ...]],
    tests: int,
) -> tuple[int, list[int]]:
    """The pairs compared and the wins of each reading: ``readings`` gives, per pair, the
    wins of as read and of another reading against it for each of ``tests`` tests, in
    order until as read wins every test at :data:`SIGNIFICANCE_LEVEL`."""
    wins = np.zeros(2 * tests, dtype=np.int64)
    compared = 0
    for first, second in pairs.tolist():
        compared += 1
        delta = se2.between(odometry[first], odometry[second])
        cov = odometry_covariance(delta, config.odometry_noise)
        wins += np.asarray(readings(first, second, delta, cov), dtype=np.int64)
        if max(sign_test_p(int(a), int(b)) for a, b in wins.reshape(-1, 2)) < SIGNIFICANCE_LEVEL:
            break  # as read wins every test: no later pair is needed (stops only this way)
    return compared, wins.tolist()


def sign_test_p(wins: int, losses: int) -> float:
    """One-sided sign test: the binomial probability of ``wins`` or more of ``wins + losses``
    by chance, ``sum_{i >= wins} C(n, i) / 2^n`` (1.0 with none decided). Exact integer sums
    (``scipy.stats.binomtest`` gives the same values; importing ``scipy.stats`` would add
    0.77 s to every run's start)."""
    n = int(wins + losses)
    if n == 0:
        return 1.0
    return sum(math.comb(n, i) for i in range(int(wins), n + 1)) / 2**n


def _direction_correlation(
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


def _offset_correlation(
    first: ScanFeatures, second: ScanFeatures, delta: FloatArray, cov: FloatArray, shift: float
) -> float:
    """Kernel correlation of ``second``'s lines, turned by ``delta``'s rotation and moved by
    ``shift`` times its translation, with ``first``'s lines, in direction and offset, over
    the line pairs whose ``second`` line the full translation shifts by more than
    :data:`INFORMATIVE_SIGMAS` of the offsets' standard deviation; weights the shorter
    segment (metres), kernel variances the lines' own plus ``cov``'s heading and translation
    variances (``(3, 3)``, rad² and m²)."""
    if first.seg_lines.shape[0] == 0 or second.seg_lines.shape[0] == 0:
        return 0.0
    alpha = second.seg_lines[:, 0] + delta[2]
    normal_shift = delta[0] * np.cos(alpha) + delta[1] * np.sin(alpha)
    rho = second.seg_lines[:, 1] + shift * normal_shift
    diff_a = (alpha[None, :] - first.seg_lines[:, None, 0] + math.pi) % (2 * math.pi) - math.pi
    opposite = np.abs(diff_a) > math.pi / 2  # the same line, its normal the other way
    diff_a = np.where(opposite, diff_a - math.pi * np.sign(diff_a), diff_a)
    diff_r = np.where(opposite, -rho[None, :], rho[None, :]) - first.seg_lines[:, None, 1]
    var_a = first.seg_cov[:, None, 0, 0] + second.seg_cov[None, :, 0, 0] + cov[2, 2]
    var_r = first.seg_cov[:, None, 1, 1] + second.seg_cov[None, :, 1, 1] + cov[0, 0]
    informative = np.abs(normal_shift)[None, :] > INFORMATIVE_SIGMAS * np.sqrt(var_r)
    length_1 = np.linalg.norm(first.seg_endpoints[:, 1] - first.seg_endpoints[:, 0], axis=1)
    length_2 = np.linalg.norm(second.seg_endpoints[:, 1] - second.seg_endpoints[:, 0], axis=1)
    weight = np.minimum(length_1[:, None], length_2[None, :]) * informative
    return float(np.sum(weight * np.exp(-0.5 * (diff_a**2 / var_a + diff_r**2 / var_r))))
