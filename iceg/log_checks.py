"""What a log's scans say about how to read them, checked before a run (docs/design.md
"Readers"): a log without a single return is refused (:func:`check_returns`); odometry that
never moves is left out (:func:`motionless_odometry`), and so is odometry where it holds
one pose while the scans move (:func:`~iceg.odometry_stalls.odometry_stalls`); beams that
turn against the odometry are mirrored, and an odometry whose heading or translation the
walls do not follow is left out (:func:`~iceg.odometry_check.odometry_check`).
:func:`reading_adjustments` gives those as the reader options that read the log so (a
session keeps them to read it again), and :func:`~frontends.registry.adjust_scan` applies
them to scans already read.
"""

from __future__ import annotations

import logging
from collections.abc import Iterable, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, NamedTuple

import numpy as np
from numpy.typing import ArrayLike

from frontends import LaserScan
from iceg.odometry_check import OdometryCheck, odometry_check
from iceg.odometry_stalls import OdometryStall, odometry_stalls
from iceg.scan_store import ScanStore, odometry_of
from iceg_common.errors import LogFormatError

if TYPE_CHECKING:
    from iceg.config import IcegConfig

logger = logging.getLogger(__name__)


#: What a run does with a log where the odometry check finds its reader option (the
#: warning), and how it reads the log (``iceg info``).
_WHAT_A_RUN_DOES = {
    "laser_only": "the log is read without its odometry, as with --laser-only",
    "mirror_beams": "the laser is read mirrored, as one mounted upside down (or with its "
    "beams written clockwise); if the odometry is the one mirrored (left-handed), the map is "
    "the mirror image",
}
_HOW_A_RUN_READS = {"laser_only": "without its odometry", "mirror_beams": "with its beams mirrored"}


def check_returns(source: str | Path, scans: Iterable[LaserScan]) -> None:
    """Refuse a log in which no beam of any scan is a return (every range outside its scan's
    ``(range_min_m, range_max_m)``): nothing could be matched or mapped, and the run would
    end with odometry alone. Ranges written in millimetres do that (MIT CSAIL so written:
    1814 nodes, no scan-match factor and an empty map, without a word). Reads up to the
    first scan with a return: one scan of a usable log.

    Raises:
        LogFormatError: no return in the log, naming the range limits and the ranges read.
    """
    ranges: list[np.ndarray] = []
    limits: set[tuple[float, float]] = set()
    for scan in scans:
        if scan.valid_mask().any():
            return
        ranges.append(scan.ranges_m[np.isfinite(scan.ranges_m)])
        limits.add((scan.range_min_m, scan.range_max_m))
    if not ranges:
        return  # no scans: refused where the run starts
    read = np.concatenate(ranges)
    seen = f"from {read.min():.4g} to {read.max():.4g}" if read.size else "none finite"
    bounds = ", ".join(f"{lo:g}..{hi:g} m" for lo, hi in sorted(limits))
    raise LogFormatError(
        f"{source}: none of its {len(ranges)} scans has a return: every range lies outside the "
        f"scan's limits ({bounds}; the ranges read: {seen}); are the ranges in metres, and "
        "is the scanner's maximum range right (PARAM robot_front_laser_max, or the reader's "
        "default_range_max_m)?"
    )


#: The longest median interval (s) between a log's consecutive scans that reads as seconds.
#: A 2D laser scanner sends 1 to 100 scans a second (rotating low-cost lidars 2-10 Hz,
#: Hokuyo and SICK scanners 10-75 Hz), and a log thinned to the scans where the robot moved
#: keeps them seconds apart (ACES: 2.2 s at the median); stamps in milliseconds put even a
#: 100 Hz scanner's scans 10 units apart.
MAX_MEDIAN_SCAN_INTERVAL_S = 10.0
#: What a run asks of a log whose scans lie further apart than that.
_NOT_SECONDS = "a laser scanner sends 1 to 100 scans a second: are the stamps in seconds?"


def warn_sparse_stamps(source: str | Path, stamps_s: ArrayLike) -> float | None:
    """Warn where a log's scans lie further apart than a laser scanner sends them: the
    median interval between consecutive stamps above :data:`MAX_MEDIAN_SCAN_INTERVAL_S`.
    Stamps in milliseconds (or finer) do that, and a run reads them as seconds: every scan
    becomes a keyframe (``slam.keyframe_max_interval_s``), landmarks are pruned within a
    scan or two (``feature_map.validity_s``), and the odometry's time offset
    (:mod:`iceg.odometry_timing`, searched over +-0.5 s) is searched over +-0.5 ms: MIT
    CSAIL so written ran with 1988 nodes instead of 1814 and a time offset found at that
    bound. A warning, not an error: a log thinned to a scan every ten seconds or more is
    read right.

    Args:
        source: The log, for the message.
        stamps_s: ``(N,)`` float64 the scans' stamps as read, in any order.

    Returns:
        The median interval between consecutive stamps (in the stamps' units), None for
        fewer than two scans.
    """
    median = _median_interval(stamps_s)
    if median is not None and median > MAX_MEDIAN_SCAN_INTERVAL_S:
        logger.warning(
            "%s: its scans are %.4g s apart at the median, and %s Read as seconds, stamps in "
            "milliseconds make every scan a keyframe and prune landmarks within a scan: "
            "write them in seconds (a log thinned to a scan every %g s or more can ignore "
            "this)",
            source,
            median,
            _NOT_SECONDS,
            MAX_MEDIAN_SCAN_INTERVAL_S,
        )
    return median


def describe_stamps(stamps_s: ArrayLike) -> list[tuple[str, str]]:
    """``iceg info``'s row on the interval between consecutive scans (the median, s), with
    the question :func:`warn_sparse_stamps` asks above :data:`MAX_MEDIAN_SCAN_INTERVAL_S`;
    none for fewer than two scans. ``stamps_s`` ``(N,)`` float64, in any order."""
    median = _median_interval(stamps_s)
    if median is None:
        return []
    text = f"{median:.4g} s at the median"
    if median > MAX_MEDIAN_SCAN_INTERVAL_S:
        text += f"; {_NOT_SECONDS}"
    return [("scan interval", text)]


def _median_interval(stamps_s: ArrayLike) -> float | None:
    """The median interval between consecutive stamps ``(N,)`` (any order; in their units),
    None for fewer than two."""
    stamps = np.sort(np.asarray(stamps_s, dtype=np.float64).reshape(-1))
    if stamps.shape[0] < 2:
        return None
    return float(np.median(np.diff(stamps)))


def motionless_odometry(source: str | Path, scans: ScanStore | Sequence[LaserScan]) -> bool:
    """Whether a log's odometry carries no motion at all: two or more scans, every one with
    a finite odometry pose, all the same pose bit for bit (a log without odometry written
    with zeros, a wheel odometry that never ran). Such odometry holds every scan in place:
    a run would make a node only every ``slam.keyframe_max_interval_s`` (MIT CSAIL with its
    odometry zeroed: 15 nodes, no scan-match factor, 0.43 m / 18.9 deg against its
    relations). Where it does, a warning says the log is read without it, as
    ``--laser-only`` reads it (each scan predicted by constant velocity, docs/design.md
    "Readers").

    Args:
        source: The log, for the warning.
        scans: Its scans, as read.
    """
    odom_poses = odometry_of(scans)[1]
    n = len(scans)
    if n < 2 or not np.isfinite(odom_poses).all() or not (odom_poses == odom_poses[0]).all():
        return False
    x, y, theta = odom_poses[0].tolist()
    logger.warning(
        "%s: the odometry is the same pose (%.3f m, %.3f m, %.1f deg) in all %d scans: it "
        "carries no motion, so the log is read without it, as with --laser-only",
        source,
        x,
        y,
        np.degrees(theta),
        n,
    )
    return True


class Reading(NamedTuple):
    """How a log must be read (:func:`reading_adjustments`).

    Attributes:
        options: The reader options that read it so (``laser_only``, ``mirror_beams``,
            ``odometry_stalls_s``; empty: as it is).
        check: The odometry check behind them (None: not made, the odometry never moves, or
            nothing to compare).
        stalls: The runs of scans whose odometry stalled (read without it).
    """

    options: dict[str, Any]
    check: OdometryCheck | None
    stalls: tuple[OdometryStall, ...] = ()


def reading_adjustments(
    source: str | Path, scans: ScanStore | Sequence[LaserScan], config: IcegConfig
) -> Reading:
    """How a log must be read, as its scans say: the reader options
    (:func:`frontends.open_log`), each warned, ``laser_only`` where its odometry carries no
    motion (:func:`motionless_odometry`) or its heading or translation is not the robot's
    (the walls stay unturned or unmoved where it turns or moves:
    :func:`~iceg.odometry_check.odometry_check`), ``mirror_beams`` where the walls turn
    against it, ``odometry_stalls_s`` over the runs of scans where it holds one pose while
    they move (:func:`~iceg.odometry_stalls.odometry_stalls`), none where the log reads as
    it is; and the checks behind them.

    Args:
        source: The log, for the warnings.
        scans: Its scans as read (with the reader options it was opened with).
        config: The run's configuration (features, odometry noise).
    """
    if motionless_odometry(source, scans):
        return Reading({"laser_only": True}, None)
    check = odometry_check(scans, config)
    finding = None if check is None else check.finding()
    options: dict[str, Any] = {}
    if finding is not None:
        option, found = finding
        logger.warning("%s: %s: %s", source, found, _WHAT_A_RUN_DOES[option])
        options[option] = True
        if option == "laser_only":  # no odometry left to hold
            return Reading(options, check)
    stalls = tuple(odometry_stalls(scans, config))
    for stall in stalls:
        _warn_stall(source, scans, stall)
    if stalls:
        options["odometry_stalls_s"] = [[stall.start_s, stall.end_s] for stall in stalls]
    return Reading(options, check, stalls)


def _warn_stall(
    source: str | Path, scans: ScanStore | Sequence[LaserScan], stall: OdometryStall
) -> None:
    """The warning of a run of scans read without their odometry, which held there."""
    logger.warning(
        "%s: the odometry holds one pose over %d scans (%s to %s, %.1f s) while the scans "
        "move (in %d of %d pairs of its scans matched, p = %.1g): those scans are read "
        "without odometry",
        source,
        stall.stop - stall.first + 1,
        scans[stall.first - 1].source,
        scans[stall.stop - 1].source,
        stall.held_s,
        stall.moved,
        stall.moved + stall.stood,
        stall.p,
    )


def describe_odometry_checks(
    scans: ScanStore | Sequence[LaserScan], config: IcegConfig
) -> list[tuple[str, str]]:
    """``iceg info``'s rows on how the walls turn and move with the odometry
    (:func:`~iceg.odometry_check.odometry_check`) and where the odometry holds while the
    scans move (:func:`~iceg.odometry_stalls.odometry_stalls`), as
    :func:`reading_adjustments` would read the log; none where the odometry has nothing to
    compare (no odometry, one that never moves, no turn of 30-90 deg within 1 m and no move
    of 0.5 m or more)."""
    check = odometry_check(scans, config)
    if check is None:
        return []
    finding = check.finding()
    if finding is None:
        text = (
            f"they turn and move together ({check.as_read} of "
            f"{check.as_read + check.mirrored} turns, {check.moved} of "
            f"{check.moved + check.unmoved} moves)"
        )
    else:
        option, found = finding
        text = f"{found}: a run reads the log {_HOW_A_RUN_READS[option]}"
    rows = [("walls and odometry", text)]
    if finding is not None and finding[0] == "laser_only":
        return rows
    stalls = odometry_stalls(scans, config)
    held = "; ".join(
        f"scans {stall.first - 1}-{stall.stop - 1} ({stall.held_s:.1f} s, {stall.moved} of "
        f"{stall.moved + stall.stood} pairs moved)"
        for stall in stalls
    )
    if held:
        held += ": a run reads them without odometry"
    return [*rows, ("odometry held while moving", held or "nowhere")]
