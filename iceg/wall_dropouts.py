"""Whether a log's scanner loses its return on walls at random, measured before the run.

The end-of-wall test (paper §III-B) reads a beam without a return beyond a segment's end as
a view past the wall. A scanner that loses returns at random (weak echoes) makes each such
patch on a wall two ends of wall at places that change from scan to scan: wrong feature
pairs, bent maps and false closures (docs/design.md, "A dropout patch is not an end of
wall"). ``features.eow_dropout_max_gap_m`` reads a patch the wall visibly spans as a dropout
instead, but costs the scanners that need it not (MIT CSAIL 0.0298 -> 0.0368 m), and a
patch that recurs where the scanner looks again (a dark or glossy surface) has edges that
are landmarks like any other.

So the run of a log measures its scanner before the first scan. A *patch* is a run of at
least :data:`MIN_PATCH_BEAMS` no-return beams between two returns less than
:data:`PATCH_MAX_GAP_M` apart (narrower than any doorway, so the surface goes on across it)
and within the usable range. Over up to :data:`MAX_SCANS` scans spread evenly along the
odometry's path (a robot standing before a dark object would count it in every scan):

- the *patch rate*: patches per 1000 returns (each patch is two false ends of wall, so
  patches, not their beams, are counted);
- the *recurrence*: the share of the patches whose middle, carried into the next scan by the
  odometry, is again lost there (no return, or one beyond it) on the nearest beam.

Where the rate reaches :data:`PATCHES_PER_1000_MIN` and the recurrence stays below
:data:`MAX_RECURRENCE` (most patches are gone in the next scan: the losses are random),
:func:`with_measured_dropouts` sets ``features.eow_dropout_max_gap_m`` to
:data:`PATCH_MAX_GAP_M`. Without odometry the recurrence is not measured and nothing changes.

Measured (docs/design.md, "A scanner that loses returns at random"): patch rates of 0.1-1.4
on the SICK logs MIT CSAIL, csail.log, csail-corrected and ACES and 0-1.1 on the simulated
scanners without dropouts; with 5 % of the beams dropped at random in runs of three, 3.0-12.6
on the simulated worlds and 10.7-14.1 on the SICK logs; the real low-cost lidars 7.0
(TurtleBot 4), 8.4 (Neato), 18 (RC car). Recurrence: 0.04-0.12 among random dropouts
(simulated worlds), 0.15-0.19 on the SICK logs with them; the real lidars' patches 0.66
(Neato) and 0.73 (TurtleBot 4), MIT CSAIL's own 0.54: dark surfaces.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np
from numpy.typing import NDArray

from frontends.scan import LaserScan
from iceg.features.config import FeatureConfig
from iceg.features.extract import extract_beams
from iceg.features.points import BeamPoints
from iceg.scan_store import odometry_of
from iceg_common import se2

if TYPE_CHECKING:
    from iceg.config import IcegConfig

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Fewest no-return beams in a patch: a single one is merged across by the segmentation
#: (``features.dropout_max_beams``) and the end-of-wall test needs ``eow_check_beams`` (2).
MIN_PATCH_BEAMS = 2
#: Largest distance between a patch's two bounding returns, metres: below the width of a
#: doorway (0.7 m or more), so the surface goes on across the patch. Also the
#: ``features.eow_dropout_max_gap_m`` set where the scanner loses returns at random.
PATCH_MAX_GAP_M = 0.5
#: Patches per 1000 returns from which the losses matter (see the module docstring for the
#: rates measured on either side: a factor of 1.8 above the SICK logs' highest).
PATCHES_PER_1000_MIN = 2.5
#: Losses recurring in the next scan for fewer than this share of the patches are random.
MAX_RECURRENCE = 0.5
#: Fewest patches followed into the next scan to decide on.
MIN_FOLLOWED = 20
#: Most scans measured, evenly spread over the log's path.
MAX_SCANS = 400


@dataclass(frozen=True)
class WallDropouts:
    """What a log's scans show of lost returns on walls.

    Attributes:
        scans: Scans measured.
        returns: Their beams with a return (points).
        patches: Their patches (see the module docstring).
        patches_per_1000: ``1000 * patches / returns`` (0 without returns).
        followed: Patches followed into the next scan (one with odometry, in the field of
            view); 0 where the rate is below :data:`PATCHES_PER_1000_MIN`.
        recurring: Of those, the ones lost there again.
        rule_on: Whether the losses switched the dropout rule on.
    """

    scans: int
    returns: int
    patches: int
    patches_per_1000: float
    followed: int
    recurring: int
    rule_on: bool

    def as_dict(self) -> dict[str, Any]:
        """JSON-ready fields."""
        return asdict(self)


def patch_middles(beams: BeamPoints, config: FeatureConfig) -> FloatArray:
    """``(K, 2)`` float64 the middle of each patch of a scan (see the module docstring): the
    point halfway between its two bounding returns, metres, robot frame.

    Args:
        beams: The scan's beams as the features read them
            (:func:`~iceg.features.extract.extract_beams`: the usable range and the robot's
            body applied).
        config: ``eow_range_margin_m`` (a patch's returns lie within the usable range less
            it: a surface beyond is not lost, and the end-of-wall test does not read past it).
    """
    edges = np.diff(np.concatenate([[0], beams.no_return.astype(np.int8), [0]]))
    first, stop = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)  # runs [first, stop)
    inside = (first > 0) & (stop < beams.no_return.shape[0])
    first, stop = first[inside], stop[inside]
    keep = (stop - first >= MIN_PATCH_BEAMS) & beams.valid[first - 1] & beams.valid[stop]
    before, after = first[keep] - 1, stop[keep]
    xy = np.full((beams.ranges.shape[0], 2), np.nan)  # each beam's point, NaN without one
    xy[beams.beam_index] = beams.points
    gap = np.hypot(*(xy[after] - xy[before]).T)
    reach = beams.range_max - config.eow_range_margin_m
    near = np.maximum(beams.ranges[before], beams.ranges[after]) < reach
    patch = (gap < PATCH_MAX_GAP_M) & near
    return 0.5 * (xy[before[patch]] + xy[after[patch]])


def lost_again(
    beams: BeamPoints, middles: FloatArray, config: FeatureConfig
) -> tuple[NDArray[np.bool_], NDArray[np.bool_]]:
    """For each point of ``middles`` ``(K, 2)`` (robot frame of ``beams``' scan): whether the
    scan looks there (a beam within one and a half beam spacings of its bearing), and whether
    the nearest such beam has no return or one beyond the point by more than
    ``config.eow_range_margin_m`` (both ``(K,)`` bool)."""
    k = middles.shape[0]
    if k == 0 or beams.bearing_robot.shape[0] < 2:
        return np.zeros(k, dtype=bool), np.zeros(k, dtype=bool)
    v = middles - beams.origin
    bearing, dist = np.arctan2(v[:, 1], v[:, 0]), np.hypot(v[:, 0], v[:, 1])
    off = np.abs(se2.wrap_angle(beams.bearing_robot[None, :] - bearing[:, None]))
    nearest = np.argmin(off, axis=1)
    spacing = float(np.median(np.diff(beams.angles)))
    seen = off[np.arange(k), nearest] <= 1.5 * spacing
    with np.errstate(invalid="ignore"):
        beyond = beams.valid[nearest] & (beams.ranges[nearest] > dist + config.eow_range_margin_m)
    return seen, seen & (beams.no_return[nearest] | beyond)


def spread_scans(odom: FloatArray, count: int) -> IntArray:
    """Indices (sorted, unique) of at most ``count`` of the scans whose odometry poses are
    ``odom`` ``(N, 3)`` (NaN rows: none), spread evenly along the odometry's path (a step to
    or from a scan without odometry counts as none), or evenly over the scans where the
    robot does not move."""
    n = odom.shape[0]
    even = np.unique(np.linspace(0, n - 1, min(n, count)).astype(np.int64))
    if n < 2:
        return even
    step = np.nan_to_num(np.hypot(*np.diff(odom[:, :2], axis=0).T), nan=0.0)
    path = np.concatenate([[0.0], np.cumsum(step)])
    if not path[-1] > 0.0:
        return even
    at = np.searchsorted(path, np.linspace(0.0, path[-1], count))
    return np.unique(np.minimum(at, n - 1).astype(np.int64))


def wall_dropouts(scans: Sequence[LaserScan], config: FeatureConfig) -> WallDropouts:
    """The patch rate of up to :data:`MAX_SCANS` of ``scans`` (:func:`spread_scans`) and,
    where it reaches :data:`PATCHES_PER_1000_MIN`, their recurrence: each scan's patches
    followed into the next scan where both have odometry and no odometry break lies between
    them (``followed`` and ``recurring`` are 0 below the rate).

    Raises:
        ScanError: a measured scan's bearings do not increase strictly.
    """
    _, odom, breaks = odometry_of(scans)
    picked = spread_scans(odom, MAX_SCANS).tolist()
    returns = patches = followed = recurring = 0
    found: list[tuple[int, FloatArray]] = []  # each measured scan with patches, its middles
    for k in picked:
        beams = extract_beams(scans[k], config)
        middles = patch_middles(beams, config)
        returns += int(beams.points.shape[0])
        patches += int(middles.shape[0])
        if middles.shape[0]:
            found.append((k, middles))
    rate = 1000.0 * patches / returns if returns else 0.0
    if rate < PATCHES_PER_1000_MIN:
        return WallDropouts(len(picked), returns, patches, rate, 0, 0, False)
    for k, middles in found:
        if k + 1 >= len(scans) or breaks[k + 1] or not np.isfinite(odom[k : k + 2]).all():
            continue
        moved = se2.transform_points(se2.inverse(se2.between(odom[k], odom[k + 1])), middles)
        seen, lost = lost_again(extract_beams(scans[k + 1], config), moved, config)
        followed += int(np.count_nonzero(seen))
        recurring += int(np.count_nonzero(lost))
    at_random = followed >= MIN_FOLLOWED and recurring < MAX_RECURRENCE * followed
    return WallDropouts(len(picked), returns, patches, rate, followed, recurring, at_random)


def with_measured_dropouts(
    config: IcegConfig, scans: Sequence[LaserScan]
) -> tuple[IcegConfig, WallDropouts | None]:
    """``config`` with ``features.eow_dropout_max_gap_m`` set to :data:`PATCH_MAX_GAP_M`
    where ``scans`` lose returns on walls often and at random (:func:`wall_dropouts`), and
    the measurement; ``(config, None)`` when ``features.measure_wall_dropouts`` is off, the
    rule is set already, or there is no scan. ``config`` itself (the same object) where
    nothing changes."""
    f = config.features
    if not f.measure_wall_dropouts or f.eow_dropout_max_gap_m > 0.0 or not len(scans):
        return config, None
    measured = wall_dropouts(scans, f)
    if not measured.rule_on:
        return config, measured
    update = {"eow_dropout_max_gap_m": PATCH_MAX_GAP_M}
    return config.model_copy(update={"features": f.model_copy(update=update)}), measured
