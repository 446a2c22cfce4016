"""Odometry that holds one pose while the scans move: a stalled odometry.

A wheel odometry that stops reporting (a driver that hangs, a topic that stops, encoders
that drop out) leaves a log's scans with the last pose it gave, bit for bit, while the robot
drives on. A run then sees no motion: no keyframe until ``slam.keyframe_max_interval_s``,
whose prediction misses every metre driven meanwhile, and a jump, or a lasting offset, where
the odometry comes back. MIT CSAIL with its odometry held over scans 800-999 (43 s) gave
0.97 m / 5.5° against its relations where it comes back at the robot's pose, 1.27 m / 6.4°
where it comes back offset by the motion it missed (0.0298 m / 0.417° as recorded).

A robot that stands still holds its odometry too (MIT CSAIL stands for 7 s at its start and
6 s at its end), so a held pose alone says nothing: the scans tell the two apart. In each run
of consecutive scans whose odometry is one pose (:func:`held_runs`), scans are compared at
the held pose: each is ICE-matched against the scan before it (identity prediction, the
local match's bounds) and, where that match cannot tell its step from standing, against the
scan :data:`LONGER_STEP` before it. It moved where a match places it beyond the chi-square
quantile of :data:`~iceg.slam.CONSISTENCY_PROBABILITY` under the match's own covariance and
moves its points by more than their range noise (:data:`NOISE_SIGMAS`), stood where neither
match does both, and tells nothing where both fail. The ranges beam by beam cannot
tell it: a scanner driven along a corridor measures its side walls at the same ranges (the
office world's robot moving 10 cm a scan: median difference under 3 cm), where the match
finds the motion from the corners and ends (9.8 cm, standard deviation 2.8 mm along the
corridor).

The odometry stalled over the run where moved scans outnumber stood ones beyond chance: a
one-sided sign test at :data:`~iceg.odometry_check.SIGNIFICANCE_LEVEL` over at most
:data:`MAX_PAIRS` scans evenly spread over the run, of the runs that last
:data:`MIN_UPDATES` of the odometry's usual intervals between updates. A run of fewer than 8
scans cannot pass it (7 of 7 is the least significant win): MIT CSAIL holds its odometry
over 4-5 scans three times while the robot drives 10-22 cm a scan, and its odometry catches
up after each. Where a run does not pass as a whole but some of its scans moved, the span
around the most of them in a row is tested alone (a robot that stood, then drove on, or
drove, then stopped): the odometry is wrong from where that motion began.

The scans of a stalled run from there (but its first) are read without odometry
(:func:`frontends.open_log`'s ``odometry_stalls_s``): each is a node tracked by the laser
alone, predicted by constant velocity, and the scan after the run starts the odometry
again as after a break.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from iceg.features.extract import extract
from iceg.matching.config import MatchBounds
from iceg.matching.matcher import IceMatcher
from iceg.odometry_check import SIGNIFICANCE_LEVEL, sign_test_p
from iceg.scan_store import ScanStore, odometry_of
from iceg.slam import chi2_3dof
from iceg_common import se2

if TYPE_CHECKING:
    from collections.abc import Sequence

    from frontends import LaserScan
    from iceg.config import IcegConfig
    from iceg.types import ScanFeatures

FloatArray = NDArray[np.float64]

#: Most pairs compared in one held run, evenly spread over it: a stall wins nearly all of
#: them (MIT CSAIL held over 200 scans: 22 of the 22 that match; the simulated two-loop
#: world: 20 of 24), a robot standing still is decided in six.
MAX_PAIRS = 24
#: A held run is tested only where it lasts this many of the odometry's usual intervals
#: between updates (:func:`_update_interval`): an odometry that updates once every ten
#: scans (2 Hz beside a 20 Hz laser) holds for ten scans at a time while the robot drives,
#: and catches up each time; each such run alone passes the sign test (9 of 9 pairs).
MIN_UPDATES = 8
#: Scans back to the second match of a pair whose step the first could not tell from
#: standing: the simulated two-loop world's robot moves 10 cm a scan where the walls fix
#: the motion along them to 3-6 cm (two of seven steps beyond the quantile), 30 cm there.
LONGER_STEP = 3
#: A scan moved where its match, besides being beyond the chi-square quantile, moves its
#: points (the median) by more than this many range standard deviations
#: (``features.sigma_range_m``): the TurtleBot 4 standing still gives matches 2-4 mm off,
#: beyond the quantile of its covariances (0.6-0.7 mm across the beams), in 9 of 15 pairs.
NOISE_SIGMAS = 3.0

_ORIGIN = np.zeros(3)


@dataclass(frozen=True)
class OdometryStall:
    """A run of scans whose odometry holds one pose while they move (module docstring).

    Attributes:
        first, stop: Scans ``[first, stop)`` read without odometry: the held run but its
            first scan, whose pose the odometry holds, or from the stood scan before the
            span whose moves decided (:func:`_moving_span`) to the run's end.
        start_s, end_s: Stamps of scans ``first`` and ``stop - 1``, seconds.
        held_s: From scan ``first - 1`` (the last at the held pose) to scan ``stop - 1``,
            seconds: how long it held wrong.
        moved, stood: Compared scans of the run (or span) that decided that moved, and
            stood.
        p: One-sided binomial probability of ``moved`` or more of ``moved + stood`` by
            chance.
    """

    first: int
    stop: int
    start_s: float
    end_s: float
    held_s: float
    moved: int
    stood: int
    p: float

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return asdict(self)


def held_runs(odometry: FloatArray, breaks: NDArray[np.bool_]) -> list[tuple[int, int]]:
    """The runs ``[lo, hi)`` of two or more consecutive scans whose odometry is one finite
    pose, bit for bit, with no odometry break within them.

    Args:
        odometry: ``(N, 3)`` float64 odometry poses in scan order (NaN rows: none).
        breaks: ``(N,)`` bool, an odometry break just before each scan.
    """
    poses = np.asarray(odometry, dtype=np.float64).reshape(-1, 3)
    finite = np.all(np.isfinite(poses[1:]), axis=1)
    repeated = np.all(poses[1:] == poses[:-1], axis=1)
    same = repeated & finite & ~np.asarray(breaks, dtype=bool).reshape(-1)[1:]
    edges = np.diff(np.concatenate(([0], same.astype(np.int8), [0])))
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    return [(int(lo), int(hi) + 1) for lo, hi in zip(starts, ends, strict=True)]


def odometry_stalls(
    scans: ScanStore | Sequence[LaserScan], config: IcegConfig
) -> list[OdometryStall]:
    """The runs of ``scans`` whose odometry stalled (module docstring), in scan order.

    Args:
        scans: A log's scans in time order, with their odometry (``odom_pose``, ``odom_break``).
        config: Its run's configuration: the features' and the matcher's settings, the local
            match's bounds.
    """
    stamps, odometry, breaks = odometry_of(scans)
    held = held_runs(odometry, breaks)
    longest = MIN_UPDATES * _update_interval(held, int(np.isfinite(odometry).all(axis=1).sum()))
    runs = [(lo, hi) for lo, hi in held if hi - lo >= longest and _may_pass(hi - lo - 1)]
    if not runs:
        return []
    compare = _PairComparison(scans, config)
    stalls = []
    for lo, hi in runs:
        stall = _stall(compare, lo, hi)
        if stall is not None:
            first, moved, stood, p = stall
            start_s, end_s = float(stamps[first]), float(stamps[hi - 1])
            held_s = end_s - float(stamps[first - 1])
            stalls.append(OdometryStall(first, hi, start_s, end_s, held_s, moved, stood, p))
    return stalls


def _stall(compare: _PairComparison, lo: int, hi: int) -> tuple[int, int, int, float] | None:
    """Whether held run ``[lo, hi)`` stalled, and where: ``(first, moved, stood, p)`` with
    ``first`` the first scan of it read without odometry, or None. Where the run as a whole
    does not pass the sign test but some scans of it moved, the span of the most of them in
    a row is tested alone (:func:`_moving_span`: a robot that stood, then drove on while the
    odometry held, or drove, then stopped), and so on within it while the span shrinks: the
    odometry is wrong from where that motion began to the end of the run. Under a robot
    standing still, a scan's false move is rare and a span around it passes the test no more
    often than a run does."""
    start, end = lo, hi
    while True:
        moved, stood, verdicts = compare.run(start, end)
        p = sign_test_p(moved, stood)
        if p < SIGNIFICANCE_LEVEL:
            return start + 1, moved, stood, p
        span = _moving_span(verdicts, start, end)
        if span is None:
            return None
        start, end = span


def _update_interval(held: list[tuple[int, int]], n_with_odometry: int) -> float:
    """The odometry's usual interval between updates, in scans: the median length of its
    runs of one pose (the held runs, and one scan for each scan between them)."""
    lengths = [hi - lo for lo, hi in held]
    single = max(n_with_odometry - sum(lengths), 0)
    if not lengths and not single:
        return 1.0
    return float(np.median(np.concatenate([np.ones(single), lengths])))


def _beyond_noise(pose: FloatArray, points_xy: FloatArray, noise_m: float) -> bool:
    """Whether ``pose`` ``(3,)`` ``[x_m, y_m, theta_rad]`` moves the median of ``points_xy``
    ``(P, 2)`` (metres, the scan's frame) by more than ``noise_m``."""
    if points_xy.shape[0] == 0:
        return False
    moved = se2.transform_points(pose, points_xy) - points_xy
    return float(np.median(np.hypot(moved[:, 0], moved[:, 1]))) > noise_m


def _moving_span(verdicts: dict[int, bool | None], lo: int, hi: int) -> tuple[int, int] | None:
    """The span ``[start, end)`` of run ``[lo, hi)`` around its compared scans that moved
    with no stood one between them, the most of them (the latest of equals): from the stood
    scan before them (else ``lo``) to the stood scan after them (else ``hi``); None where no
    scan moved, the span is the run, or it is too short for the sign test."""
    best: list[int] = []
    current: list[int] = []
    start = current_start = last_stood = lo
    for k in sorted(verdicts):
        if verdicts[k] is True:
            if not current:
                current_start = last_stood
            current.append(k)
            if len(current) >= len(best):
                best, start = list(current), current_start
        elif verdicts[k] is False:
            current, last_stood = [], k
    if not best:
        return None
    end = min((k for k, v in verdicts.items() if v is False and k > best[-1]), default=hi)
    if (start, end) == (lo, hi) or not _may_pass(end - start - 1):
        return None
    return start, end


def _coarse_to_fine(n: int) -> list[int]:
    """``0 .. n - 1`` in the order of halving: both ends, the middle, the quarters, ..."""
    order: list[int] = []
    parts = 1
    while len(order) < n:
        for j in range(parts + 1):
            i = round(j * (n - 1) / parts)
            if i not in order:
                order.append(i)
        parts *= 2
    return order


def _may_pass(n_pairs: int) -> bool:
    """Whether a run of ``n_pairs`` consecutive pairs can pass the sign test at all."""
    return sign_test_p(min(n_pairs, MAX_PAIRS), 0) < SIGNIFICANCE_LEVEL


class _PairComparison:
    """Consecutive scans compared at one pose (module docstring), each scan's features
    extracted once."""

    def __init__(self, scans: ScanStore | Sequence[LaserScan], config: IcegConfig) -> None:
        self.scans, self.config = scans, config
        self.features: dict[int, ScanFeatures] = {}
        self.matcher = IceMatcher(config.matching)
        self.bounds = MatchBounds.local(
            config.slam.match_max_translation_m, config.slam.match_max_rotation_deg
        )

    def run(self, lo: int, hi: int) -> tuple[int, int, dict[int, bool | None]]:
        """The scans that moved and that stood of up to :data:`MAX_PAIRS` of run
        ``[lo, hi)``, evenly spread and compared coarse to fine (both ends, the middle, the
        quarters, ...) until the stood ones leave the sign test no chance (which stops only
        in favour of the odometry, so the test keeps its level); and each compared scan's
        verdict (None: no match)."""
        n_pairs = hi - lo - 1
        n = min(n_pairs, MAX_PAIRS)
        later = (lo + 1 + np.linspace(0, n_pairs - 1, n).round()).astype(np.int64).tolist()
        moved = stood = 0
        verdicts: dict[int, bool | None] = {}
        for done, i in enumerate(_coarse_to_fine(n), start=1):
            k = later[i]
            verdicts[k] = verdict = self._moved(k, lo)
            moved += verdict is True
            stood += verdict is False
            if sign_test_p(moved + n - done, stood) >= SIGNIFICANCE_LEVEL:
                break
        return moved, stood, verdicts

    def _moved(self, k: int, lo: int) -> bool | None:
        """Whether scan ``k`` moved from the scan before it, or failing that from the scan
        :data:`LONGER_STEP` before it (or the run's first, ``lo``, where nearer): True where a
        match places it beyond the chi-square quantile and moves its points by more than their
        range noise (:func:`_beyond_noise`), False where a match does not do both and none
        does, None where both fail."""
        verdict = None
        noise_m = NOISE_SIGMAS * self.config.features.sigma_range_m
        for back in sorted({1, min(LONGER_STEP, k - lo)}):
            new, reference = self._features(k), self._features(k - back)
            result = self.matcher.match(new, reference, _ORIGIN, self.bounds)
            if result.success:
                pose = np.asarray(result.pose, dtype=np.float64)
                significant = pose @ np.linalg.solve(result.cov, pose) > chi2_3dof()
                if significant and _beyond_noise(pose, new.points_xy, noise_m):
                    return True
                verdict = False
        return verdict

    def _features(self, k: int) -> ScanFeatures:
        if k not in self.features:
            self.features[k] = extract(self.scans[k], self.config.features)
        return self.features[k]
