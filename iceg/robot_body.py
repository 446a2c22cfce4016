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
The run of a log measures the body along its odometry before its first scan and sets that
range (:func:`with_measured_body`), and warns where its optimized trajectory shows more
(docs/design.md, "The robot's own body").
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from iceg.scan_store import ScanStore

if TYPE_CHECKING:
    from iceg.config import IcegConfig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

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


@dataclass(frozen=True)
class RobotBodyEstimate:
    """What a run's scans show of the robot's own body.

    Attributes:
        range_m: The ``features.robot_body_range_m`` that removes every body return found
            (:func:`body_reach` over the compared scans, rounded up to the centimetre),
            metres; ``None`` when no bin is a body.
        bearings_deg: Centre of each body bin, laser frame, degrees.
        pairs: Scan pairs compared (turns of :data:`TURN_DEG`; at most :data:`MAX_PAIRS`).
        agreement: Share of the pairs in which each body bin's returns agreed.
    """

    range_m: float | None
    bearings_deg: tuple[float, ...]
    pairs: int
    agreement: tuple[float, ...]

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return asdict(self)


def turn_pairs(poses: FloatArray) -> IntArray:
    """``(M, 2)`` int64 index pairs ``(k, l)``, ``l > k``: for each scan ``k`` the first later
    scan whose heading differs from it by at least :data:`TURN_DEG` (and at most three times
    that), if the robot travelled at most :data:`MAX_PATH_M` between them.

    Args:
        poses: ``(N, 3)`` float64 robot poses ``[x_m, y_m, theta_rad]``, one per scan, in
            scan order (any frame; NaN rows never pair).
    """
    p = np.asarray(poses, dtype=np.float64)
    n = p.shape[0]
    if n < 2:
        return np.zeros((0, 2), dtype=np.int64)
    step = np.hypot(np.diff(p[:, 0]), np.diff(p[:, 1]))
    # a step to or from a scan without a pose counts as beyond reach (its travel is unknown)
    path = np.concatenate([[0.0], np.cumsum(np.nan_to_num(step, nan=2.0 * MAX_PATH_M))])
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
    return np.array(pairs, dtype=np.int64).reshape(-1, 2)


def _binned_returns(store: ScanStore, scans: IntArray) -> Iterator[tuple[IntArray, FloatArray]]:
    """The valid returns (``range_min < r < range_max``) of the scans ``scans`` (sorted,
    unique indices into ``store``), a run of consecutive scans at a time: each return's key
    ``i * B + b`` (``i`` its scan's position in ``scans``, ``b`` its laser-frame bearing bin of
    :data:`BIN_DEG`, ``B = 360 / BIN_DEG``, bin ``b`` centred at ``-180 + (b + 0.5) BIN_DEG``
    degrees) and its range, metres."""
    n_bins = round(360.0 / BIN_DEG)
    width = math.radians(BIN_DEG)
    breaks = np.flatnonzero(np.diff(scans) != 1) + 1
    firsts, lasts = np.concatenate([[0], breaks]), np.append(breaks, scans.shape[0])
    for first, last in zip(firsts.tolist(), lasts.tolist(), strict=True):
        c = store.beam_chunk(int(scans[first]), int(scans[last - 1]) + 1)
        row = np.repeat(np.arange(first, last), c.beam_counts)
        r = c.ranges_m
        with np.errstate(invalid="ignore"):
            ok = np.isfinite(r) & (r > c.range_min_m) & (r < c.range_max_m)
        bearing = c.angles_rad + np.repeat(c.laser_offsets[:, 2], c.beam_counts)
        b = np.floor((bearing[ok] + math.pi) / width).astype(np.int64) % n_bins
        yield row[ok] * n_bins + b, r[ok]


def nearest_by_bearing(store: ScanStore, scans: IntArray) -> FloatArray:
    """``(len(scans), B)`` float64 the nearest valid return (``range_min < r < range_max``)
    of each of the scans ``scans`` (sorted, unique indices into ``store``) in each laser-frame
    bearing bin of :data:`BIN_DEG` (``B = 360 / BIN_DEG``, bin ``b`` centred at
    ``-180 + (b + 0.5) BIN_DEG`` degrees), metres; NaN where the bin has none."""
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


def robot_body_range(store: ScanStore, poses: FloatArray) -> RobotBodyEstimate | None:
    """The robot's own body in ``store``'s scans (module docstring): bearing bins whose
    nearest return agrees within :data:`AGREEMENT_M` across at least :data:`MIN_AGREEMENT`
    of the turns of :func:`turn_pairs` (at most :data:`MAX_PAIRS` of them, evenly spread).
    None with fewer than :data:`MIN_PAIRS` turns (a robot that never turns in place shows
    nothing: a side wall keeps its range along a straight corridor).

    Args:
        store: The run's scans.
        poses: ``(N, 3)`` float64 a pose per scan (the run's optimized trajectory, or the
            odometry), robot frame -> world.

    Raises:
        ValueError: ``poses`` does not hold one row per scan.
    """
    p = np.asarray(poses, dtype=np.float64)
    if p.shape != (len(store), 3):
        raise ValueError(f"poses must have shape ({len(store)}, 3), got {p.shape}")
    pairs = turn_pairs(p)
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
    body = np.flatnonzero(agreement >= MIN_AGREEMENT)
    if body.shape[0] == 0:
        return RobotBodyEstimate(None, (), int(pairs.shape[0]), ())
    reach = body_reach(store, scans, body)
    return RobotBodyEstimate(
        math.ceil(round(reach * 100.0, 6)) / 100.0,
        tuple(float(c) for c in -180.0 + (body + 0.5) * BIN_DEG),
        int(pairs.shape[0]),
        tuple(float(x) for x in agreement[body]),
    )


def with_measured_body(
    config: IcegConfig, store: ScanStore
) -> tuple[IcegConfig, RobotBodyEstimate | None]:
    """``config`` with ``features.robot_body_range_m`` raised to the robot's body that
    ``store``'s scans show along their odometry (:func:`robot_body_range`), where it reaches
    farther; and that estimate. Odometry is good enough to find turns in place: a pair only
    needs the robot to have turned by 30-90° over at most 1 m of travel. ``config`` itself
    (the same object) when ``features.measure_robot_body`` is off, when the scans show no
    body (or too few turns to tell), or when the configured range already holds it.
    """
    if not config.features.measure_robot_body:
        return config, None
    _, odometry, _ = store.odometry
    estimate = robot_body_range(store, odometry)
    if (
        estimate is None
        or estimate.range_m is None
        or estimate.range_m <= config.features.robot_body_range_m
    ):
        return config, estimate
    features = config.features.model_copy(update={"robot_body_range_m": estimate.range_m})
    return config.model_copy(update={"features": features}), estimate
