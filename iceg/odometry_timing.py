"""The time offset between a log's scans and its odometry, measured from a run.

A scan stamped on arrival was measured before its stamp (a serial SICK LMS200 takes about
0.2 s to send a scan; a rotating lidar's driver may stamp the end of its sweep), so the
odometry read at the stamp is the pose of a moment later. While the robot turns, the
odometry's heading change between two keyframes is then not the one the scans saw. The scan
matcher measures that change independently, so the offset is the shift of the odometry's
clock that makes the two agree: temporal calibration by matching rotations (Kelly and
Sukhatme 2010, "A general framework for temporal calibration of multiple proprioceptive and
exteroceptive sensors"; here a 1-D search over the shift, the rotation change between
consecutive keyframes of a run against the odometry's). The run's result carries the
estimate (``metrics["odometry_time_offset"]``); :func:`frontends.odometry_shift.shift_odometry`
(``iceg run --odometry-time-offset``) applies one. :func:`scan_pairs_time_offset` measures
the same before a run, from each scan matched against the one before it (``--odometry-time-offset
auto``).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from graph import FactorKind
from iceg.aside import compute_aside, while_caller_runs
from iceg.features.extract import extract
from iceg.matching.config import MatchBounds
from iceg.matching.matcher import IceMatcher
from iceg.scan_store import ScanStore
from iceg_common import se2
from iceg_common.se2 import wrap_angle

if TYPE_CHECKING:
    from collections.abc import Sequence

    from frontends import LaserScan
    from iceg.config import IcegConfig
    from iceg.results import SlamResult

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Offsets searched, seconds either side of 0, and their spacing.
MAX_OFFSET_S = 0.5
OFFSET_RESOLUTION_S = 0.01
#: Level of the test behind :attr:`TimeOffsetEstimate.significant`: the conventional 1 %, as
#: the estimate is a suggestion to the user, not a decision the run makes.
SIGNIFICANCE_LEVEL = 0.01


@dataclass(frozen=True)
class TimeOffsetEstimate:
    """The odometry clock's shift that best explains the matched rotations.

    Attributes:
        offset_s: Seconds to add to the scans' stamps to read the odometry (negative: the
            scans were measured before their stamps); a multiple of the search resolution.
        steps: Keyframe steps with a scan-match factor that were compared.
        heading_error_at_zero_deg: Mean absolute difference between matched and odometry
            rotation per step at offset 0, degrees.
        heading_error_at_offset_deg: The same at ``offset_s``, degrees.
        p_value: One-sided Wilcoxon signed-rank test (Wilcoxon 1945; normal approximation)
            of the per-step errors at ``-offset_s`` minus those at ``offset_s``: the
            probability of a rank sum this large if the sign of the offset did not matter.
            Not against 0: reading the odometry between two of its samples averages their
            noise, which lowers the errors at an offset of either sign (on simulated runs
            without delay, e.g. a corridor: -0.11 s, p 0.0006 against 0, 0.28 against
            +0.11 s).
        significant: ``p_value`` below :data:`SIGNIFICANCE_LEVEL` and ``offset_s`` more
            than one grid step from 0 (the search's own resolution).
    """

    offset_s: float
    steps: int
    heading_error_at_zero_deg: float
    heading_error_at_offset_deg: float
    p_value: float
    significant: bool

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return asdict(self)


def estimate_odometry_time_offset(
    stamps_s: FloatArray,
    odom_heading_rad: FloatArray,
    segment: IntArray,
    step_from: IntArray,
    step_to: IntArray,
    step_turn_rad: FloatArray,
    max_offset_s: float = MAX_OFFSET_S,
    resolution_s: float = OFFSET_RESOLUTION_S,
) -> TimeOffsetEstimate | None:
    """Search the odometry time offset that best matches the measured rotations.

    For each offset ``d`` on a grid of ``resolution_s`` over ``[-max_offset_s, max_offset_s]``
    the odometry heading is interpolated (per odometry segment, unwrapped) at
    ``stamps_s[step_from] + d`` and ``stamps_s[step_to] + d``; the cost is the summed
    absolute difference of its change and ``step_turn_rad`` (robust to a few wrong
    matches). The least cost wins, the offset nearest 0 among equal ones. Steps whose shifted
    times could leave their segment are not used.

    Args:
        stamps_s: ``(N,)`` float64 scan stamps, seconds, non-decreasing.
        odom_heading_rad: ``(N,)`` float64 odometry heading of each scan at its stamp,
            radians (odometry frame).
        segment: ``(N,)`` int64 odometry segment of each scan (a new one after a break); -1
            for a scan without odometry.
        step_from, step_to: ``(S,)`` int64 scan indices of each compared step's two
            keyframes.
        step_turn_rad: ``(S,)`` float64 the step's rotation measured by the scans, radians.
        max_offset_s: Largest offset searched, seconds.
        resolution_s: Grid spacing, seconds.

    Returns:
        The estimate, or None when no step can be compared.
    """
    stamps = np.asarray(stamps_s, dtype=np.float64)
    seg = np.asarray(segment, dtype=np.int64)
    a = np.asarray(step_from, dtype=np.int64)
    b = np.asarray(step_to, dtype=np.int64)
    turn = np.asarray(step_turn_rad, dtype=np.float64)
    keep = (seg[a] >= 0) & (seg[a] == seg[b])
    a, b, turn = a[keep], b[keep], turn[keep]
    offsets = resolution_s * np.arange(
        -round(max_offset_s / resolution_s), round(max_offset_s / resolution_s) + 1
    )
    errors = np.full((offsets.shape[0], a.shape[0]), np.nan)
    for s in np.unique(seg[a]).tolist():
        rows = np.flatnonzero(seg == s)
        t, heading = stamps[rows], np.unwrap(np.asarray(odom_heading_rad, dtype=np.float64)[rows])
        mine = np.flatnonzero(
            (seg[a] == s) & (stamps[a] - max_offset_s >= t[0]) & (stamps[b] + max_offset_s <= t[-1])
        )
        for k, d in enumerate(offsets.tolist()):
            change = np.interp(stamps[b[mine]] + d, t, heading) - np.interp(
                stamps[a[mine]] + d, t, heading
            )
            errors[k, mine] = np.abs(wrap_angle(turn[mine] - change))
    used = ~np.isnan(errors[0])
    if not used.any():
        return None
    errors = errors[:, used]
    cost = errors.sum(axis=1)
    nearest_zero_first = np.argsort(np.abs(offsets), kind="stable")
    best = int(nearest_zero_first[np.argmin(cost[nearest_zero_first])])
    zero = int(np.argmin(np.abs(offsets)))
    # Against the mirrored offset (see TimeOffsetEstimate.p_value): a delay lowers the
    # errors on its own side only.
    mirror = int(np.argmin(np.abs(offsets + offsets[best])))
    p_value = _signed_rank_p(errors[mirror] - errors[best])
    return TimeOffsetEstimate(
        offset_s=float(round(offsets[best], 6)),
        steps=int(errors.shape[1]),
        heading_error_at_zero_deg=math.degrees(float(errors[zero].mean())),
        heading_error_at_offset_deg=math.degrees(float(errors[best].mean())),
        p_value=p_value,
        significant=abs(best - zero) > 1 and p_value < SIGNIFICANCE_LEVEL,
    )


def _signed_rank_p(gain: FloatArray) -> float:
    """One-sided p-value of the Wilcoxon signed-rank test that ``gain`` ``(S,)`` is centred
    above 0 (normal approximation, zero gains dropped); 1 when none is non-zero. The
    normal tail is libm's ``erfc`` (scipy's ``ndtr`` to 6e-11 relative in the far tail): a
    run imports no ``scipy.special``, which cost 86 ms."""
    d = gain[gain != 0.0]
    n = d.shape[0]
    if n == 0:
        return 1.0
    ranks = np.empty(n)
    ranks[np.argsort(np.abs(d), kind="stable")] = np.arange(1, n + 1)
    w_plus = float(ranks[d > 0].sum())
    mean = n * (n + 1) / 4.0
    sd = math.sqrt(n * (n + 1) * (2 * n + 1) / 24.0)
    return 0.5 * math.erfc((w_plus - mean) / sd / math.sqrt(2.0))


def _odometry_segments(store: ScanStore) -> tuple[FloatArray, FloatArray, IntArray]:
    """``(N,)`` stamps (s), ``(N, 3)`` odometry poses (NaN rows: none) and ``(N,)`` int64
    odometry segment of each scan of ``store`` (a new one after a break; -1: no odometry)."""
    stamps, odom, breaks = store.odometry
    has = ~np.isnan(odom[:, 2])
    return stamps, odom, np.where(has, np.cumsum(breaks | ~has), -1).astype(np.int64)


def scan_pairs_time_offset(
    scans: Sequence[LaserScan], config: IcegConfig, processes: int = 1
) -> TimeOffsetEstimate | None:
    """:func:`estimate_odometry_time_offset` before a run: each scan ICE-matched against the
    one before it in the same odometry segment (the run's features and matcher, predicted by
    the odometry at the stamps, within the local search's bounds ``slam.match_max_*``), the
    successful matches' rotations against the odometry's.

    On real logs a run's keyframe steps give the same offsets (MIT CSAIL -0.12 s, the
    TurtleBot 4 bag -0.10 s, the Neato bag -0.24 s against -0.25 s; none on ACES, csail.log
    and the Gazebo TurtleBot 3 bag), in about a third of a run's time on MIT CSAIL, so
    ``"auto"`` runs once. A turn matched scan to scan is noisier than a run's optimized one,
    so a small offset in smooth turns can stay below significance here where a run finds
    it (the simulated office with 0.1 s: -0.08 s, p 0.05; with 0.2 s: -0.20 s, p 0.002);
    the run's own measurement still warns of it.

    Args:
        scans: The log's scans, stamps non-decreasing, odometry read at their stamps.
        config: The run's configuration (features with the robot's body left out, matching,
            ``slam`` search bounds).
        processes: With 2 or more, the log's second half is matched in a forked process
            (:func:`~iceg.aside.compute_aside`) meanwhile; the same estimate, bit for bit.

    Returns:
        The estimate, or None when no consecutive pair with odometry matches.
    """
    store = scans if isinstance(scans, ScanStore) else ScanStore(scans)
    stamps, odom, segment = _odometry_segments(store)
    n = len(store)
    half = n // 2 if processes > 1 else n
    with compute_aside(lambda: _matched_turns(store, config, half, n), fork=half < n) as rest:
        first, turn_first = _matched_turns(store, config, 0, half)
        second, turn_second = rest.result()
    step_from = np.concatenate([first, second])
    if step_from.shape[0] == 0:
        return None
    return estimate_odometry_time_offset(
        stamps,
        odom[:, 2],
        segment,
        step_from,
        step_from + 1,
        np.concatenate([turn_first, turn_second]),
    )


def offset_to_read(
    scans: Sequence[LaserScan], config: IcegConfig, processes: int = 1
) -> tuple[float, TimeOffsetEstimate | None]:
    """What ``--odometry-time-offset auto`` reads the odometry at: the offset
    :func:`scan_pairs_time_offset` measures (arguments as there) where significant, else 0
    (seconds); and that measurement (None: nothing to compare)."""
    est = scan_pairs_time_offset(scans, config, processes)
    return (est.offset_s if est is not None and est.significant else 0.0), est


def _matched_turns(
    store: ScanStore, config: IcegConfig, lo: int, hi: int
) -> tuple[IntArray, FloatArray]:
    """The scans ``k`` in ``[lo, hi)`` matched against scan ``k - 1`` (see
    :func:`scan_pairs_time_offset`): ``(M,)`` int64 ``k - 1`` of each successful match and
    ``(M,)`` float64 its rotation, radians."""
    _, odom, segment = _odometry_segments(store)
    matcher = IceMatcher(config.matching)
    bounds = MatchBounds.local(
        config.slam.match_max_translation_m, config.slam.match_max_rotation_deg
    )
    step_from: list[int] = []
    turns: list[float] = []
    before = None  # the previous scan's features
    for k in while_caller_runs(range(max(lo - 1, 0), hi)):
        features = extract(store[k], config.features) if segment[k] >= 0 else None
        if features is not None and before is not None and segment[k] == segment[k - 1]:
            result = matcher.match(features, before, se2.between(odom[k - 1], odom[k]), bounds)
            if result.success:
                step_from.append(k - 1)
                turns.append(float(result.pose[2]))
        before = features
    return np.array(step_from, dtype=np.int64), np.array(turns, dtype=np.float64)


def odometry_time_offset(result: SlamResult) -> TimeOffsetEstimate | None:
    """:func:`estimate_odometry_time_offset` of a finished run: the steps between
    consecutive keyframes joined by a scan-match factor, their rotation from the optimized
    poses, against the odometry of the run's scans. None without such steps (no odometry,
    a laser-only run, every match failed)."""
    scans = result.scans
    store = scans if isinstance(scans, ScanStore) else ScanStore(scans)
    stamps, odom, segment = _odometry_segments(store)
    if stamps.shape[0] == 0:
        return None
    matched = {(f.i, f.j) for f in result.factors if f.kind == FactorKind.SCAN_MATCH}
    ids, poses, scan_of = result.node_ids, result.node_poses, result.node_scan_index
    k = np.array(
        [n for n in range(1, ids.shape[0]) if (int(ids[n - 1]), int(ids[n])) in matched],
        dtype=np.int64,
    )
    if k.shape[0] == 0:
        return None
    return estimate_odometry_time_offset(
        stamps, odom[:, 2], segment, scan_of[k - 1], scan_of[k], poses[k, 2] - poses[k - 1, 2]
    )
