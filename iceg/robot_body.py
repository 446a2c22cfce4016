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
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from iceg.scan_store import ScanStore
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
    lo, hi = math.radians(TURN_DEG), 3.0 * math.radians(TURN_DEG)
    pairs = []
    for k in range(n - 1):
        turn = np.abs(heading[k + 1 : end[k]] - heading[k])
        first = np.flatnonzero(turn >= lo)
        if first.shape[0] and turn[first[0]] <= hi:
            pairs.append((k, k + 1 + int(first[0])))
    return without_breaks(np.array(pairs, dtype=np.int64).reshape(-1, 2), breaks)


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


def _binned_beams(
    store: ScanStore, scans: IntArray, width_deg: float = BIN_DEG
) -> Iterator[tuple[IntArray, FloatArray, BoolArray, BoolArray]]:
    """Every beam of the scans ``scans`` (sorted, unique indices into ``store``), a run of
    consecutive scans at a time: its key ``i * B + b`` (``i`` its scan's position in
    ``scans``, ``b`` its bearing bin of ``width_deg``, ``B = 360 / width_deg``, bin ``b``
    centred at ``-180 + (b + 0.5) width_deg`` degrees; the bearing is the robot frame's: the
    beam's plus the laser's mounting yaw), its range (metres), and whether it is a valid
    return (``range_min < r < range_max``) or no return (``+inf``, or at least
    ``range_max``)."""
    n_bins = round(360.0 / width_deg)
    width = math.radians(width_deg)
    breaks = np.flatnonzero(np.diff(scans) != 1) + 1
    firsts, lasts = np.concatenate([[0], breaks]), np.append(breaks, scans.shape[0])
    for first, last in zip(firsts.tolist(), lasts.tolist(), strict=True):
        c = store.beam_chunk(int(scans[first]), int(scans[last - 1]) + 1)
        row = np.repeat(np.arange(first, last), c.beam_counts)
        r = c.ranges_m
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(r) & (r > c.range_min_m) & (r < c.range_max_m)
            none = r >= c.range_max_m  # +inf included, NaN excluded
        bearing = c.angles_rad + np.repeat(c.laser_offsets[:, 2], c.beam_counts)
        b = np.floor((bearing + math.pi) / width).astype(np.int64) % n_bins
        yield row * n_bins + b, r, ok, none


def _binned_returns(store: ScanStore, scans: IntArray) -> Iterator[tuple[IntArray, FloatArray]]:
    """The valid returns of :func:`_binned_beams` (bins of :data:`BIN_DEG`): keys, ranges."""
    for key, r, ok, _ in _binned_beams(store, scans):
        yield key[ok], r[ok]


def nearest_by_bearing(store: ScanStore, scans: IntArray) -> FloatArray:
    """``(len(scans), B)`` float64 the nearest valid return (``range_min < r < range_max``)
    of each of the scans ``scans`` (sorted, unique indices into ``store``) in each bearing
    bin of :data:`BIN_DEG` (robot frame, as in :func:`_binned_beams`; ``B = 360 / BIN_DEG``,
    bin ``b`` centred at ``-180 + (b + 0.5) BIN_DEG`` degrees), metres; NaN where the bin
    has none."""
    n_bins = round(360.0 / BIN_DEG)
    out = np.full(scans.shape[0] * n_bins, np.inf)
    for key, r in _binned_returns(store, scans):
        order = np.lexsort((r, key))  # by key, nearest first
        key, nearest = key[order], r[order]
        head = np.ones(key.shape, dtype=bool)
        head[1:] = key[1:] != key[:-1]
        out[key[head]] = nearest[head]
    out[np.isinf(out)] = np.nan
    return out.reshape(scans.shape[0], n_bins)


def body_reach(store: ScanStore, scans: IntArray, body_bins: IntArray) -> float:
    """The farthest return of the robot's body in the scans ``scans`` (sorted, unique indices
    into ``store``), metres: in each bearing bin of ``body_bins`` (bin indices as in
    :func:`nearest_by_bearing`) of each scan, the returns from the nearest one up to the
    first gap wider than :data:`AGREEMENT_M` between two in range order (the body's surface,
    with all of its range noise; past the gap the beams see past the body, to the world).
    The nearest return of a bin alone would fall short: it is the least of several noisy
    returns. NaN when the bins hold no return."""
    n_bins = round(360.0 / BIN_DEG)
    reach = math.nan
    for key, r in _binned_returns(store, scans):
        keep = np.isin(key % n_bins, body_bins)
        order = np.lexsort((r[keep], key[keep]))  # by key, nearest first
        key, near = key[keep][order], r[keep][order]
        if key.shape[0] == 0:
            continue
        head = np.ones(key.shape, dtype=bool)
        head[1:] = key[1:] != key[:-1]
        # a run of one bin's returns ends at a gap; the body's is each bin's first run
        step = np.ones(key.shape, dtype=bool)
        step[1:] = head[1:] | (np.diff(near) > AGREEMENT_M)
        run = np.cumsum(step)
        body = np.isin(run, run[head])
        reach = float(np.fmax(reach, near[body].max()))
    return reach


def dark_bearings(
    store: ScanStore, scans: IntArray, pairs: IntArray, turn_rad: FloatArray
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
        store: The run's scans.
        scans: ``(S,)`` sorted, unique indices into ``store`` of the compared scans.
        pairs: ``(P, 2)`` int64 positions in ``scans`` of each turn's two scans.
        turn_rad: ``(P,)`` float64 heading change from the first scan to the second, rad.
    """
    n_fine = round(360.0 / DARK_BIN_DEG)
    per = round(BIN_DEG / DARK_BIN_DEG)
    n_coarse = n_fine // per
    dark = np.zeros(scans.shape[0] * n_fine, dtype=bool)
    lit = np.zeros(scans.shape[0] * n_fine, dtype=bool)
    beam = np.zeros(n_fine, dtype=bool)  # the bins that hold a beam of some scan
    for key, _, ok, none in _binned_beams(store, scans, DARK_BIN_DEG):
        lit[key[ok]] = True
        dark[key[none]] = True
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
    nearest = nearest_by_bearing(store, scans)
    row = row.reshape(pairs.shape)
    a, b = nearest[row[:, 0]], nearest[row[:, 1]]
    with np.errstate(invalid="ignore"):
        agreement = (np.abs(a - b) <= AGREEMENT_M).mean(axis=0)
    turn = wrap_angle(p[pairs[:, 1], 2] - p[pairs[:, 0], 2])
    dark = dark_bearings(store, scans, row, turn)
    body = np.flatnonzero(agreement >= MIN_AGREEMENT)
    if body.shape[0] == 0:
        return RobotBodyEstimate(None, (), int(pairs.shape[0]), (), dark)
    reach = body_reach(store, scans, body)
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
