"""The robot's own body in its scans, measured from a run.

A lidar mounted among posts, under a plate or beside a mast returns from them at fixed
bearings and ranges in its own frame, whatever the robot does. A return from the world
cannot: when the robot turns through :data:`TURN_DEG` in place (or nearly: within
:data:`MAX_PATH_M` of travel), the world point a bearing saw moves to another bearing, and
the range at that bearing changes (a wall seen head-on is ``1 / cos(30°) - 1`` = 15 % farther
after such a turn, a wall seen obliquely more). So a bearing bin whose nearest return stays
within :data:`AGREEMENT_M` across almost every such turn (:data:`MIN_AGREEMENT`) holds the
robot's body. Those returns give points and features that move with the robot and pull each
match toward "no motion" (a lidar among four posts: the simulated 200 m recess corridor,
seeds 0-3, 0.03-0.11 m -> 0.36-0.58 m ATE); ``features.robot_body_range_m`` removes them.
A driver that reports the body as no return (``+inf``) leaves bearings dark in every scan,
where a turned scan sees the world (:func:`dark_bearings`); ``features.robot_body_dark_deg``
reads them as returns too close to measure. The run of a log measures the body along its
odometry before its first scan and sets both (:func:`with_measured_body`), and warns where
its optimized trajectory shows more (docs/design.md, "The robot's own body").
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import NDArray

from iceg.scan_store import ScanStore
from iceg_common.numba_loading import njit
from iceg_common.se2 import wrap_angle

if TYPE_CHECKING:
    from iceg.config import IcegConfig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]
BoolArray = NDArray[np.bool_]

#: Width of a bearing bin, degrees (the nearest return of each bin is compared).
BIN_DEG = 2.0
#: Heading change of a compared pair of scans, degrees: at least this, at most three times it.
TURN_DEG = 30.0
#: Largest travel between the two scans of a pair, metres (a turn in place, or nearly).
MAX_PATH_M = 1.0
#: Two returns agree when their ranges differ by at most this, metres: well above the 1-3 cm
#: noise of a return at close range, well below the change a turn gives a world point.
AGREEMENT_M = 0.05
#: A bin is the robot's body when its returns agree in at least this share of the pairs.
MIN_AGREEMENT = 0.9
#: Fewest pairs to decide on (fewer: no estimate).
MIN_PAIRS = 20
#: Most pairs compared, evenly spread over the log (a share's standard error about 2 %).
MAX_PAIRS = 200
#: Scans between two compared ones that are read along with them rather than skipped: a
#: read of the store (:meth:`~iceg.scan_store.ScanStore.beam_chunk`) costs about what
#: decoding this many scans more does (MIT CSAIL: 0.1 ms against 4-5 µs a scan).
READ_THROUGH_SCANS = 16
#: Width of a bearing bin in the search for the body's dark bearings, degrees: finer than a
#: beam of the scanners here (0.25-1°), so that a bin holds the beams of one bearing.
DARK_BIN_DEG = 0.25


@dataclass(frozen=True)
class RobotBodyEstimate:
    """What a run's scans show of the robot's own body.

    Attributes:
        range_m: The ``features.robot_body_range_m`` that removes every body return found
            (:func:`body_reach` over the compared scans, rounded up to the centimetre),
            metres; ``None`` when no bin is a body.
        bearings_deg: Centre of each body bin, robot frame (the beam's bearing plus the
            laser's mounting yaw), degrees.
        pairs: Scan pairs compared (turns of :data:`TURN_DEG`; at most :data:`MAX_PAIRS`).
        agreement: Share of the pairs in which each body bin's returns agreed.
        dark_deg: Bearing intervals ``(from, to)`` (degrees, robot frame) where the body
            hides the view and the scans hold no return (``+inf`` or at least
            ``range_max``) for it
            (:func:`dark_bearings`): ``features.robot_body_dark_deg``.
    """

    range_m: float | None
    bearings_deg: tuple[float, ...]
    pairs: int
    agreement: tuple[float, ...]
    dark_deg: tuple[tuple[float, float], ...] = ()

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return asdict(self)


def turn_pairs(poses: FloatArray, breaks: NDArray[np.bool_] | None = None) -> IntArray:
    """``(M, 2)`` int64 index pairs ``(k, l)``, ``l > k``: for each scan ``k`` the first later
    scan whose heading differs from it by at least :data:`TURN_DEG` (and at most three times
    that), if the robot travelled at most :data:`MAX_PATH_M` between them and no odometry
    break lies between them (a jump of the odometry is no turn of the robot).

    Args:
        poses: ``(N, 3)`` float64 robot poses ``[x_m, y_m, theta_rad]``, one per scan, in
            scan order (any frame; NaN rows never pair).
        breaks: ``(N,)`` bool, an odometry break just before each scan (``odom_break``);
            None: none.
    """
    p = np.asarray(poses, dtype=np.float64)
    n = p.shape[0]
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    path = path_travelled(p)
    heading = np.full(n, np.nan)
    known = np.isfinite(p[:, 2])
    heading[known] = np.unwrap(p[known, 2])
    end = np.searchsorted(path, path + MAX_PATH_M, side="right")  # scans within reach
    turned = _first_turns(heading, end, math.radians(TURN_DEG), 3.0 * math.radians(TURN_DEG))
    k = np.flatnonzero(turned >= 0)
    return without_breaks(np.stack([k, turned[k]], axis=1), breaks)


@njit(cache=True, nogil=True)
def _first_turns(heading: FloatArray, end: IntArray, lo: float, hi: float) -> IntArray:
    """``(N,)`` int64 for each scan ``k`` the first scan ``j`` in ``(k, end[k])`` whose
    ``heading`` (rad, unwrapped) differs from ``k``'s by at least ``lo`` when that difference
    is at most ``hi``, else -1 (a NaN heading turns by nothing)."""
    out = np.full(heading.shape[0], -1, dtype=np.int64)
    for k in range(heading.shape[0] - 1):
        for j in range(k + 1, end[k]):
            turn = abs(heading[j] - heading[k])
            if turn >= lo:
                if turn <= hi:
                    out[k] = j
                break
    return out


def path_travelled(poses: FloatArray) -> FloatArray:
    """``(N,)`` float64 metres along the path of ``poses`` (``(N, 3)``, scan order) from the
    first; a step to or from a scan without a pose (a NaN row) counts as twice
    :data:`MAX_PATH_M`, beyond the reach of any pair (its travel is unknown)."""
    step = np.hypot(np.diff(poses[:, 0]), np.diff(poses[:, 1]))
    path = np.concatenate([[0.0], np.cumsum(np.nan_to_num(step, nan=2.0 * MAX_PATH_M))])
    return path[: poses.shape[0]]  # (0,) for no pose


def without_breaks(pairs: IntArray, breaks: NDArray[np.bool_] | None) -> IntArray:
    """The ``(M, 2)`` scan index pairs ``(k, l)``, ``l > k``, with no odometry break between
    their scans (``breaks``: ``(N,)`` bool, a break just before each scan; None: none)."""
    if breaks is None or not np.any(breaks):
        return pairs
    broken = np.concatenate([[0], np.cumsum(breaks, dtype=np.int64)])  # breaks up to scan i-1
    return pairs[broken[pairs[:, 1] + 1] == broken[pairs[:, 0] + 1]]


class ComparedBeams(NamedTuple):
    """Every beam of the compared scans, read from the store once for the steps of
    :func:`robot_body_range` (:meth:`of`).

    Attributes:
        n_scans: Scans compared ``S``.
        row: ``(B,)`` int64 position of each beam's scan among the compared scans.
        bearing_rad: ``(B,)`` float64 bearing in the robot frame (the beam's plus the
            laser's mounting yaw).
        range_m: ``(B,)`` float64 range, metres.
        ok: ``(B,)`` bool a valid return (``range_min < r < range_max``).
        none: ``(B,)`` bool no return (``+inf``, or at least ``range_max``).
    """

    n_scans: int
    row: IntArray
    bearing_rad: FloatArray
    range_m: FloatArray
    ok: BoolArray
    none: BoolArray

    @classmethod
    def of(cls, store: ScanStore, scans: IntArray) -> ComparedBeams:
        """The beams of the scans ``scans`` (``(S,)`` int64 sorted, unique indices into
        ``store``), read in spans of the store (:meth:`ScanStore.beam_chunk`) that take in
        gaps of up to :data:`READ_THROUGH_SCANS` scans.

        Raises:
            IndexError: an index outside ``store``.
        """
        gaps = np.flatnonzero(np.diff(scans) > READ_THROUGH_SCANS + 1) + 1
        firsts, lasts = np.concatenate([[0], gaps]), np.append(gaps, scans.shape[0])
        rows, bearings, ranges, lows, highs = [], [], [], [], []
        for first, last in zip(firsts.tolist(), lasts.tolist(), strict=True):
            lo = int(scans[first])
            c = store.beam_chunk(lo, int(scans[last - 1]) + 1)
            wanted = np.zeros(c.beam_counts.shape[0], dtype=bool)
            wanted[scans[first:last] - lo] = True
            take = np.repeat(wanted, c.beam_counts)
            counts = c.beam_counts[wanted]
            rows.append(np.repeat(np.arange(first, last), counts))
            yaw = np.repeat(c.laser_offsets[wanted, 2], counts)
            bearings.append(c.angles_rad[take] + yaw)
            ranges.append(c.ranges_m[take])
            lows.append(c.range_min_m[take])
            highs.append(c.range_max_m[take])
        r, low, high = (np.concatenate(x) if x else np.zeros(0) for x in (ranges, lows, highs))
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(r) & (r > low) & (r < high)
            none = r >= high  # +inf included, NaN excluded
        row = np.concatenate(rows) if rows else np.zeros(0, dtype=np.int64)
        bearing = np.concatenate(bearings) if bearings else np.zeros(0)
        return cls(int(scans.shape[0]), row, bearing, r, ok, none)

    def keys(self, width_deg: float = BIN_DEG) -> IntArray:
        """``(B,)`` int64 each beam's key ``i * n + b``: ``i`` its scan's position, ``b`` its
        bearing bin of ``width_deg`` (``n = 360 / width_deg`` bins, bin ``b`` centred at
        ``-180 + (b + 0.5) width_deg`` degrees)."""
        n_bins = round(360.0 / width_deg)
        b = np.floor((self.bearing_rad + math.pi) / math.radians(width_deg)).astype(np.int64)
        return self.row * n_bins + b % n_bins


def nearest_by_bearing(beams: ComparedBeams) -> FloatArray:
    """``(S, B)`` float64 the nearest valid return (``range_min < r < range_max``) of each
    compared scan in each bearing bin of :data:`BIN_DEG` (robot frame;
    :meth:`ComparedBeams.keys`, ``B = 360 / BIN_DEG``), metres; NaN where the bin has none."""
    n_bins = round(360.0 / BIN_DEG)
    out = np.full(beams.n_scans * n_bins, np.inf)
    np.minimum.at(out, beams.keys()[beams.ok], beams.range_m[beams.ok])
    out[np.isinf(out)] = np.nan  # valid returns are finite
    return out.reshape(beams.n_scans, n_bins)


def body_reach(beams: ComparedBeams, body_bins: IntArray) -> float:
    """The farthest return of the robot's body in the compared scans, metres: in each
    bearing bin of ``body_bins`` (bin indices as in :func:`nearest_by_bearing`) of each scan,
    the returns from the nearest one up to the first gap wider than :data:`AGREEMENT_M`
    between two in range order (the body's surface, with all of its range noise; past the
    gap the beams see past the body, to the world). The nearest return of a bin alone would
    fall short: it is the least of several noisy returns. NaN when the bins hold no return."""
    n_bins = round(360.0 / BIN_DEG)
    key, r = beams.keys()[beams.ok], beams.range_m[beams.ok]
    keep = np.isin(key % n_bins, body_bins)
    order = np.lexsort((r[keep], key[keep]))  # by key, nearest first
    key, near = key[keep][order], r[keep][order]
    if key.shape[0] == 0:
        return math.nan
    head = np.ones(key.shape, dtype=bool)
    head[1:] = key[1:] != key[:-1]
    # a run of one bin's returns ends at a gap; the body's is each bin's first run
    step = np.ones(key.shape, dtype=bool)
    step[1:] = head[1:] | (np.diff(near) > AGREEMENT_M)
    run = np.cumsum(step)
    body = np.isin(run, run[head])
    return float(near[body].max())


def dark_bearings(
    beams: ComparedBeams, pairs: IntArray, turn_rad: FloatArray
) -> tuple[tuple[float, float], ...]:
    """Bearings where the robot's own body hides the view and the scans hold no return for
    it (``+inf`` or at least ``range_max``: a driver's reading of a body inside its
    ``range_min``), as intervals ``(from, to)`` in degrees, robot frame: the outer edges of
    a run of bins of :data:`DARK_BIN_DEG` (the bins between two beams, which hold none, join
    their neighbours).

    In a turn ``(k, l)`` of ``turn_rad`` the world direction that scan ``k`` sees at bearing
    ``b`` is at ``b - turn`` in scan ``l``. A bin whose beams all hold no return in one scan
    while the other scan has a return in that world direction (its :data:`BIN_DEG` bin) is
    dark where the world is not: evidence of the body; a return in the bin is evidence
    against. A bin is the body's when it has at least :data:`MIN_PAIRS` pieces of evidence
    and they make at least :data:`MIN_AGREEMENT` of both; a run of them grows over the bins
    beside it that never hold a return and are dark where the world is at least once. Open
    ground, dark in both scans, gives neither.

    Args:
        beams: The compared scans' beams.
        pairs: ``(P, 2)`` int64 positions among the compared scans of each turn's two scans.
        turn_rad: ``(P,)`` float64 heading change from the first scan to the second, rad.
    """
    n_fine = round(360.0 / DARK_BIN_DEG)
    per = round(BIN_DEG / DARK_BIN_DEG)
    n_coarse = n_fine // per
    dark: BoolArray = np.zeros(beams.n_scans * n_fine, dtype=bool)
    lit: BoolArray = np.zeros(beams.n_scans * n_fine, dtype=bool)
    beam = np.zeros(n_fine, dtype=bool)  # the bins that hold a beam of some scan
    key = beams.keys(DARK_BIN_DEG)
    lit[key[beams.ok]] = True
    dark[key[beams.none]] = True
    beam[key % n_fine] = True
    dark = (dark & ~lit).reshape(-1, n_fine)
    lit = lit.reshape(-1, n_fine)
    seen = np.any(lit.reshape(-1, n_coarse, per), axis=2)  # a return per 2-degree bin
    shift = np.rint(np.asarray(turn_rad) / math.radians(BIN_DEG)).astype(np.int64)
    coarse = np.arange(n_coarse)
    # world direction of scan k's bin c lies in scan l's bin c - shift, and conversely
    seen_by_l = np.take_along_axis(seen[pairs[:, 1]], (coarse - shift[:, None]) % n_coarse, 1)
    seen_by_k = np.take_along_axis(seen[pairs[:, 0]], (coarse + shift[:, None]) % n_coarse, 1)
    evidence = (dark[pairs[:, 0]] & np.repeat(seen_by_l, per, axis=1)).sum(axis=0) + (
        dark[pairs[:, 1]] & np.repeat(seen_by_k, per, axis=1)
    ).sum(axis=0)
    against = lit[pairs[:, 0]].sum(axis=0) + lit[pairs[:, 1]].sum(axis=0)
    body = (evidence >= MIN_PAIRS) & (evidence >= MIN_AGREEMENT * (evidence + against))
    # runs of body bins among the bins that hold a beam (the bins between beams join them),
    # grown over the bins beside them that never held a return and were dark where the world
    # was at least once (the edges of a shadow that little of the world vouched for)
    held = np.flatnonzero(beam)
    found = body[held]
    joined = found | ((against[held] == 0) & (evidence[held] > 0))
    run = np.cumsum(joined & ~np.concatenate([[False], joined[:-1]]))  # runs of joined bins
    grown = joined & np.isin(run, run[found])  # the runs that hold a body bin
    edges = np.flatnonzero(np.diff(np.concatenate([[0], grown.astype(np.int64), [0]])))
    return tuple(
        (float(-180.0 + held[lo] * DARK_BIN_DEG), float(-180.0 + (held[hi - 1] + 1) * DARK_BIN_DEG))
        for lo, hi in zip(edges[::2].tolist(), edges[1::2].tolist(), strict=True)
    )


def robot_body_range(
    store: ScanStore, poses: FloatArray, breaks: NDArray[np.bool_] | None = None
) -> RobotBodyEstimate | None:
    """The robot's own body in ``store``'s scans (module docstring): bearing bins whose
    nearest return agrees within :data:`AGREEMENT_M` across at least :data:`MIN_AGREEMENT`
    of the turns of :func:`turn_pairs` (at most :data:`MAX_PAIRS` of them, evenly spread).
    None with fewer than :data:`MIN_PAIRS` turns (a robot that never turns in place shows
    nothing: a side wall keeps its range along a straight corridor).

    Args:
        store: The run's scans.
        poses: ``(N, 3)`` float64 a pose per scan (the run's optimized trajectory, or the
            odometry), robot frame -> world.
        breaks: ``(N,)`` bool odometry breaks (:func:`turn_pairs`); None for a trajectory.

    Raises:
        ValueError: ``poses`` does not hold one row per scan.
    """
    p = np.asarray(poses, dtype=np.float64)
    if p.shape != (len(store), 3):
        raise ValueError(f"poses must have shape ({len(store)}, 3), got {p.shape}")
    pairs = turn_pairs(p, breaks)
    if pairs.shape[0] < MIN_PAIRS:
        return None
    if pairs.shape[0] > MAX_PAIRS:
        pairs = pairs[np.linspace(0, pairs.shape[0] - 1, MAX_PAIRS).round().astype(np.int64)]
    scans, row = np.unique(pairs, return_inverse=True)
    beams = ComparedBeams.of(store, scans)
    nearest = nearest_by_bearing(beams)
    row = row.reshape(pairs.shape)
    a, b = nearest[row[:, 0]], nearest[row[:, 1]]
    with np.errstate(invalid="ignore"):
        agreement = (np.abs(a - b) <= AGREEMENT_M).mean(axis=0)
    turn = wrap_angle(p[pairs[:, 1], 2] - p[pairs[:, 0], 2])
    dark = dark_bearings(beams, row, turn)
    body = np.flatnonzero(agreement >= MIN_AGREEMENT)
    if body.shape[0] == 0:
        return RobotBodyEstimate(None, (), int(pairs.shape[0]), (), dark)
    reach = body_reach(beams, body)
    return RobotBodyEstimate(
        math.ceil(round(reach * 100.0, 6)) / 100.0,
        tuple(float(c) for c in -180.0 + (body + 0.5) * BIN_DEG),
        int(pairs.shape[0]),
        tuple(float(x) for x in agreement[body]),
        dark,
    )


def with_measured_body(
    config: IcegConfig, store: ScanStore
) -> tuple[IcegConfig, RobotBodyEstimate | None]:
    """:func:`leaving_out` the robot's body that ``store``'s scans show along their
    odometry (:func:`robot_body_range`), and that estimate; ``(config, None)`` when
    ``features.measure_robot_body`` is off. Odometry is good enough to find turns in place:
    a pair only needs the robot to have turned by 30-90° over at most 1 m of travel.
    """
    if not config.features.measure_robot_body:
        return config, None
    _, odometry, breaks = store.odometry
    estimate = robot_body_range(store, odometry, breaks)
    return leaving_out(config, estimate), estimate


def leaving_out(config: IcegConfig, estimate: RobotBodyEstimate | None) -> IcegConfig:
    """``config`` with ``features.robot_body_range_m`` raised to ``estimate``'s range where
    that reaches farther, and ``features.robot_body_dark_deg`` set to its dark bearings
    where empty; ``config`` itself (the same object) where that changes nothing."""
    if estimate is None:
        return config
    update: dict[str, Any] = {}
    f = config.features
    if estimate.range_m is not None and estimate.range_m > f.robot_body_range_m:
        update["robot_body_range_m"] = estimate.range_m
    if estimate.dark_deg and not f.robot_body_dark_deg:
        update["robot_body_dark_deg"] = estimate.dark_deg
    if not update:
        return config
    return config.model_copy(update={"features": f.model_copy(update=update)})
