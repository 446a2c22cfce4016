"""Continue a saved session with another log (``iceg run LOG --continue SESSION``, issue 15).

The session is loaded exactly (:func:`iceg.session.load`); the new log's first scan is placed
in the old map by ICE matching, around ``initial_pose`` when given, else globally
(:meth:`iceg.localize.FixedMap.place`), and the placement must be confirmed by tracking the
next scans in the fixed map (:class:`iceg.localize.Localizer`). The first scan then becomes a
node linked to the map by the placement match (:meth:`iceg.slam.Slam.start_segment`) and the
run goes on in the same graph and feature map. A log that cannot be placed is refused
(:class:`~iceg_common.errors.SessionError`), never guessed.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from tqdm.auto import tqdm

from frontends import LaserScan
from frontends.scan import StampPolicy
from iceg import session as sess
from iceg.features import extract
from iceg.localize import FixedMap, Localizer, LocalizeSettings, Placement, Status
from iceg.matching import MatchBounds
from iceg.results import SlamResult
from iceg.slam import Slam
from iceg.types import ScanFeatures
from iceg_common import se2
from iceg_common.errors import SessionError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: Scans of the new log tracked to confirm the first scan's placement (at most).
CONFIRM_SCANS = 150


def fixed_map_of(slam: Slam) -> FixedMap:
    """The Slam's current map as a :class:`FixedMap` (its own feature map: references built
    from it can be given back to the Slam)."""
    ids, poses = slam.graph.estimates()
    return FixedMap(ids, poses, slam.feature_map, slam.config)


#: Scans tried, in order, for a placement when the first ones cannot be placed (a scan with
#: too few features, e.g. facing a bare wall); the placed scan starts the segment and the scans
#: before it are tracked backwards from it (:meth:`iceg.slam.Slam.start_segment`).
START_SCANS = 60

#: Without an initial pose, every this many of those scans is searched globally.
START_STEP = 5


def place_start(
    fixed: FixedMap,
    scans: Sequence[LaserScan],
    initial_pose: ArrayLike | None = None,
    settings: LocalizeSettings | None = None,
) -> tuple[int, Placement]:
    """The first scan among the first :data:`START_SCANS` that can be placed in the map
    (around ``initial_pose``, carried along by odometry, when given; else globally), placed
    and confirmed by tracking the next scans (:func:`_unconfirmed`); a placement they refuse
    (a wrong match, or a right one whose next scans cannot be tracked, as in a fast turn) is
    dropped and the search goes on with the next scans.

    Args:
        fixed: the map.
        scans: the new log's scans.
        initial_pose: ``(3,)`` map-frame guess of the first scan ``[x_m, y_m, theta_rad]``.
        settings: localization tuning.

    Returns:
        ``(k, placement)``: the placed scan's index (odometry runs unbroken from scan 0 to
        it) and its placement (``match.pose`` in the frame of node ``anchor``).

    Raises:
        SessionError: no scan placed and confirmed (the message says why the refused
            placements were refused).
    """
    st = settings or LocalizeSettings()
    guess = None if initial_pose is None else np.asarray(initial_pose, dtype=np.float64)
    unconfirmed: list[str] = []
    for k, scan in enumerate(scans[: odometry_run_end(scans, START_SCANS)]):
        search = k % START_STEP == 0  # a global search is costly: every START_STEP-th scan
        if guess is None and not search:
            continue
        feats = extract(scan, fixed.config.features)
        if feats.n_features < 2:
            continue
        here = None if guess is None else se2.compose(guess, _odometry(scans, 0, k))
        placement = _place_one(fixed, feats, here, st, search)
        if placement is None:
            continue
        refused = _unconfirmed(fixed, scans[k:], placement, st)
        if refused:
            unconfirmed.append(refused)
            continue
        return k, placement
    detail = (
        f"; {len(unconfirmed)} placement(s) refused, first: {unconfirmed[0]}" if unconfirmed else ""
    )
    if guess is None:
        ask = "is it from this building? Give --initial-pose X Y THETA_DEG if it is"
    else:
        x, y, th = guess.tolist()
        ask = (
            f"tried around the initial pose {x:.2f} {y:.2f} {np.degrees(th):.1f} and globally: "
            "is the log from this building, and that pose its first scan's in the map's frame?"
        )
    raise SessionError(
        f"{scans[0].source}: the log cannot be placed in the map (no unambiguous ICE match of "
        f"enough correlation and fit, confirmed by tracking, in its first "
        f"{odometry_run_end(scans, START_SCANS)} scans{detail}); {ask}"
    )


def odometry_run_end(scans: Sequence[LaserScan], limit: int) -> int:
    """The scans from the first on that odometry links to it, at most ``limit``: the index of
    the first later scan without odometry or after an odometry break (1 when the first scan
    has no odometry), else ``min(limit, len(scans))``."""
    end = min(limit, len(scans))
    if end and scans[0].odom_pose is None:
        return 1
    for k in range(1, end):
        if scans[k].odom_pose is None or scans[k].odom_break:
            return k
    return end


def _odometry(scans: Sequence[LaserScan], i: int, j: int) -> FloatArray:
    """Odometry motion from scan ``i`` to scan ``j`` (``(3,)``, frame of scan ``i``; none
    from a scan to itself, with or without odometry)."""
    if i == j:
        return np.zeros(3)
    return se2.between(scans[i].odom_pose, scans[j].odom_pose)  # type: ignore[arg-type]


def _place_one(
    fixed: FixedMap,
    feats: ScanFeatures,
    guess: FloatArray | None,
    st: LocalizeSettings,
    search: bool = True,
) -> Placement | None:
    """Around ``guess`` when given, else (or when that fails) globally if ``search``."""
    if guess is not None:
        bounds = MatchBounds.local(st.initial_translation_m, st.initial_rotation_deg)
        p = fixed.match_at(feats, guess, bounds, st.reference_nodes)
        if p is not None and p.match.correlation >= st.correlation_floor(fixed.config):
            return p
    return fixed.place(feats, st) if search else None


def _unconfirmed(
    fixed: FixedMap, scans: Sequence[LaserScan], p: Placement, st: LocalizeSettings
) -> str:
    """Why the placement ``p`` of ``scans[0]`` is refused: the next :data:`CONFIRM_SCANS`
    scans, tracked from it, are lost or placed elsewhere before ``confirm_keyframes`` of them
    are tracked on the map (an empty string: confirmed, or nothing left to confirm it with)."""
    loc = Localizer(fixed, st, initial_pose=p.pose)
    tracked = 0
    where = (
        f"{scans[0].source} matched the map at {np.round(p.pose, 2).tolist()} (correlation "
        f"{p.match.correlation:.2f})"
    )
    for scan in scans[:CONFIRM_SCANS]:
        _, _, status, _ = loc.process(scan)
        if loc.relocalizations or status == Status.LOST:
            return f"{where} but the next scans do not follow it there"
        tracked += status == Status.TRACKED
        if tracked >= st.confirm_keyframes:
            return ""
    if len(scans) > 1:
        return f"{where} but the next {min(len(scans), CONFIRM_SCANS)} scans did not confirm it"
    return ""


def continue_scans(
    session_path: str | os.PathLike[str],
    scans: Sequence[LaserScan],
    initial_pose: ArrayLike | None = None,
    progress: bool = False,
) -> SlamResult:
    """Continue a session with new scans; the finished result of the extended run.

    Raises:
        SessionError: unreadable session or a log that cannot be placed.
        ScanError: the new scans are earlier than the session's last scan.
    """
    if not scans:
        raise SessionError("the new log holds no laser scans")
    slam = sess.load(session_path)
    last = slam.export_state().scans[-1].stamp_s
    if scans[0].stamp_s < last:
        raise SessionError(
            f"{scans[0].source}: the log starts at {scans[0].stamp_s:.6f} s, before the "
            f"session's last scan ({last:.6f} s); the map's time-validity needs the new log "
            "to come later"
        )
    k, placement = place_start(fixed_map_of(slam), scans, initial_pose)
    logger.info(
        "scan %d placed at %s near node %d (correlation %.2f)",
        k,
        np.round(placement.pose, 3).tolist(),
        placement.anchor,
        placement.match.correlation,
    )
    # The placed scan starts the segment; the scans before it are tracked backwards from it.
    # Scan 0 carried back by odometry would enter the graph with that odometry counted twice
    # (in its placement and in the odometry factors to the placed scan).
    slam.start_segment(scans[k], placement.anchor, placement.match, before=scans[:k])
    for scan in tqdm(scans[k + 1 :], unit="scan", disable=not progress, desc="iceg"):
        slam.process(scan)
    return slam.finish()


def session_path_of(path: Path) -> Path:
    """The session folder given a session or a run folder."""
    return path / sess.SESSION_DIR if (path / sess.SESSION_DIR).is_dir() else path


def continue_log(
    path: str | Path,
    session_path: str | Path,
    relations: str | Path | None = None,
    initial_pose: ArrayLike | None = None,
    progress: bool = False,
    stamps: StampPolicy = "sort",
    reader_options: dict[str, Any] | None = None,
    odometry_time_offset_s: float | Literal["auto"] = 0.0,
) -> SlamResult:
    """:func:`continue_scans` over a log file, scored with ``relations`` like
    :func:`iceg.pipeline.run_log` (the relations that fall on either log's scans count).
    The log's odometry is read at each scan's stamp plus ``odometry_time_offset_s``
    (``"auto"``: measured with the session's configuration,
    :func:`iceg.pipeline.read_log_scans`); ``result.metrics["odometry_time_offset"]`` holds
    it.

    Raises:
        LogFormatError: missing, unreadable or empty log.
        SessionError: unreadable session, or a log that cannot be placed.
        EvaluationError: the relations match no scan.
        ConfigError: an offset neither finite seconds nor ``"auto"``.
    """
    from frontends.relations import read_relations
    from iceg.evaluation import relation_errors
    from iceg.pipeline import RELATION_TOLERANCE_S, check_relations_match, read_log_scans

    config = sess.read_config(session_path)
    scans, offset = read_log_scans(path, config, stamps, reader_options, odometry_time_offset_s)
    rel = read_relations(relations) if relations is not None else None
    if rel is not None:
        check_relations_match(rel, np.array([s.stamp_s for s in scans]))
    result = continue_scans(session_path, scans, initial_pose, progress)
    if result.slam is not None:
        sess.record_reading(result.slam, path, reader_options, offset["applied_s"])
    result.metrics["continued_from"] = str(Path(session_path).resolve())
    result.metrics["odometry_time_offset"] = offset
    if rel is not None:
        summary, _ = relation_errors(
            result.stamps_s, result.poses, rel.stamps_s, rel.deltas, RELATION_TOLERANCE_S
        )
        result.metrics["relations"] = summary.as_dict()
    return result
