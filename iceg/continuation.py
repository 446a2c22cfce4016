"""Continue a saved session with another log (``iceg run LOG --continue SESSION``, issue 15).

The session is loaded exactly (:func:`iceg.session.load`); the new log's first scan is placed
in the old map by ICE matching, around ``initial_pose`` when given, else globally
(:meth:`iceg.localize.FixedMap.place`), and the placement must be confirmed by tracking the
next scans in the fixed map (:class:`iceg.localize.Localizer`) and, when global, corroborated
by another scan's global placement (:class:`StartSearch`). The first scan then becomes a
node linked to the map by the placement match (:meth:`iceg.slam.Slam.start_segment`) and the
run goes on in the same graph and feature map. A log that cannot be placed is refused
(:class:`~iceg_common.errors.SessionError`), never guessed.
"""

from __future__ import annotations

import logging
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from numpy.typing import ArrayLike, NDArray
from tqdm.auto import tqdm

from frontends import LaserScan
from frontends.scan import StampPolicy
from iceg import session as sess
from iceg.features import extract
from iceg.localize import (
    FixedMap,
    Localizer,
    LocalizeSettings,
    Placement,
    Status,
    distinct_places,
    match_helper,
)
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
    and confirmed by tracking the next scans (:func:`_unconfirmed`), and, when the
    placement was global, corroborated by the global placement of another scan
    (:class:`StartSearch`); a placement they refuse (a wrong match, or a right one whose
    next scans cannot be tracked, as in a fast turn) is dropped and the search goes on with
    the next scans. One search spans the scans odometry links to its first; in a log
    without odometry (one scan), the next search starts :data:`START_STEP` scans later.

    Args:
        fixed: the map.
        scans: the new log's scans.
        initial_pose: ``(3,)`` map-frame guess of the first scan ``[x_m, y_m, theta_rad]``.
        settings: localization tuning.

    Returns:
        ``(k, placement)``: the placed scan's index (odometry runs unbroken from scan 0 to
        it, or no scan up to it has odometry) and its placement (``match.pose`` in the
        frame of node ``anchor``).

    Raises:
        SessionError: no scan placed, confirmed and corroborated (the message says why the
            refused placements were refused).
    """
    search = StartSearch(fixed, scans, settings)
    i, refusals = 0, []
    while True:
        try:
            _, k, placement = search.place(i, initial_pose if i == 0 else None)
            return k, placement
        except SessionError as exc:
            refusals.append(exc)
        # The scans before the placed one are tracked backwards from it, which odometry
        # must not break: a log with odometry is searched once.
        i = next_search(scans, i)
        if i >= min(len(scans), START_SCANS) or any(s.odom_pose is not None for s in scans[:i]):
            if len(refusals) == 1:
                raise refusals[0]
            raise SessionError(
                f"{refusals[0]}; {len(refusals) - 1} more search(es) from later scans, up to "
                f"scan {i - 1}, placed none either"
            )


@dataclass(frozen=True)
class _Tried:
    """A global placement tried for a segment's start."""

    scan: int  # index in the log
    window: int  # the first scan of the search that found it
    placement: Placement
    confirmed: bool  # the next scans, tracked from it, confirmed it
    track: dict[int, FloatArray] = field(default_factory=dict)  # scan -> pose (no odometry)


class StartSearch:
    """The search for a segment's first placement in one log (:func:`place_start`), keeping
    the global placements it tried until one is accepted.

    A global placement compares a scan with every candidate place of the map, and a log
    that cannot be placed tries again every :data:`START_STEP` scans, so in a large map a
    log of another building eventually gets a placement that is unambiguous and whose next
    scans track it: the Neato bag in MIT CSAIL's map after 285 scans, at correlation 0.75,
    confirmed by the next three scans, which see what the placed one saw. A global
    placement is therefore accepted only when it is **corroborated**: the global placement
    of another scan, taken at a place distinct from it by the odometry between them
    (:func:`~iceg.localize.distinct_places`: another view), lands at the same place through
    that odometry. Two coincidences that agree are far rarer than one, whatever the number
    of tries; this is the consistency of consecutive loop candidates that ORB-SLAM asks of
    a place recognition (Mur-Artal et al. 2015, §VI-A), with the views apart by motion. The
    corroborating placement need not be confirmed itself (its next scans may be a fast
    turn), nor later: the TurtleBot 4's placement at scan 205 in its own map is corroborated
    by scan 5's, through 200 scans of odometry. Without odometry between the two scans, the
    track that confirmed one placement (:func:`_unconfirmed`, followed up to
    :data:`CONFIRM_SCANS` scans) gives the motion to the other's scan: the RC car bag, laser
    only, is placed in its own map and refused in five others. A placement around the
    initial pose is the user's guess confirmed and needs no corroboration.

    Args:
        fixed: the map.
        scans: the log's scans in time order.
        settings: localization tuning.
    """

    def __init__(
        self, fixed: FixedMap, scans: Sequence[LaserScan], settings: LocalizeSettings | None
    ) -> None:
        self.fixed = fixed
        self.scans = scans
        self.settings = settings or LocalizeSettings()
        self._tried: list[_Tried] = []
        self._global: dict[int, Placement | None] = {}  # a scan's global placement
        # scans up to each one (included) without odometry or starting an odometry break
        self._unlinked = np.cumsum([s.odom_pose is None or s.odom_break for s in scans])

    def place(self, i: int, initial_pose: ArrayLike | None) -> tuple[int, int, Placement]:
        """The search from scan ``i`` over the scans odometry links to it (at most
        :data:`START_SCANS`), as :func:`place_start` describes; a placement confirmed there
        may be corroborated by the next scans' global placements (:meth:`_look_ahead`).

        Args:
            i: The first scan of the search (index in the log).
            initial_pose: ``(3,)`` map-frame guess of scan ``i`` ``[x_m, y_m, theta_rad]``,
                or None.

        Returns:
            ``(first, k, placement)``: the placed scan ``k`` and the first scan of the search
            that found it (``first <= k``; earlier than ``i`` when this search corroborated
            a confirmed placement of an earlier one); the scans from ``first`` to ``k`` are
            the segment's, tracked backwards from ``k``.

        Raises:
            SessionError: none placed, confirmed and corroborated in these scans; the
                placements tried stay for the next search.
        """
        st, scans = self.settings, self.scans[i:]
        guess = None if initial_pose is None else np.asarray(initial_pose, dtype=np.float64)
        end = odometry_run_end(scans, START_SCANS)
        unconfirmed: list[str] = []
        for k, scan in enumerate(scans[:end]):
            search = k % START_STEP == 0  # a global search is costly: every START_STEP-th scan
            if guess is None and not search:
                continue
            here = None if guess is None else se2.compose(guess, _odometry(scans, 0, k))
            placement, is_global = self._placement(i + k, here, search)
            if placement is None:
                continue
            follow = scan.odom_pose is None  # no odometry: corroborated along the track
            refused, track = _unconfirmed(self.fixed, scans[k:], placement, st, follow)
            if not is_global and not refused:
                self._tried.clear()
                return i, i + k, placement
            along = dict(enumerate(track, start=i + k)) if follow else {}
            self._tried.append(_Tried(i + k, i, placement, not refused, along))
            if accepted := self._accepted(self._tried):
                return accepted
            unconfirmed.append(
                refused
                or f"{_where(scan, placement)} but no other scan's global placement agreed with it"
            )
        if accepted := self._look_ahead(i, end):
            return accepted
        detail = (
            f"; {len(unconfirmed)} placement(s) refused, first: {unconfirmed[0]}"
            if unconfirmed
            else ""
        )
        if guess is None:
            ask = "is it from this building? Give --initial-pose X Y THETA_DEG if it is"
        else:
            x, y, th = guess.tolist()
            ask = (
                f"tried around the initial pose {x:.2f} {y:.2f} {np.degrees(th):.1f} and "
                "globally: is the log from this building, and that pose its first scan's in the "
                "map's frame?"
            )
        raise SessionError(
            f"{scans[0].source}: the log cannot be placed in the map (no unambiguous ICE match "
            f"of enough correlation and fit, confirmed by tracking and corroborated by another "
            f"scan, in its first {end} scans{detail}); {ask}"
        )

    def _placement(
        self, k: int, here: FloatArray | None, search: bool
    ) -> tuple[Placement | None, bool]:
        """Scan ``k``'s placement (:func:`_place_one`) and whether it is global; a global
        search's result is kept, so a scan is placed globally once per log."""
        if here is None and k in self._global:
            return self._global[k], True
        feats = extract(self.scans[k], self.fixed.config.features)
        if feats.n_features < 2:
            return None, here is None
        placement, is_global = _place_one(self.fixed, feats, here, self.settings, search)
        if here is None:
            self._global[k] = placement
        return placement, is_global

    def _accepted(self, candidates: list[_Tried]) -> tuple[int, int, Placement] | None:
        """The first confirmed and corroborated of ``candidates`` as ``(first, k,
        placement)``; the placements tried are then forgotten."""
        for tried in candidates:
            if tried.confirmed and self._corroborated(tried):
                self._tried.clear()
                return tried.window, tried.scan, tried.placement
        return None

    def _look_ahead(self, i: int, end: int) -> tuple[int, int, Placement] | None:
        """After the search from scan ``i`` (its first ``end`` scans), a placement it
        confirmed but nothing corroborated yet: the global placements of the next scans
        (every :data:`START_STEP`-th, up to :data:`CONFIRM_SCANS` after it, as far as
        odometry links them, or its track reaches without odometry) may corroborate it, as
        its confirmation looked ahead. The placements they give stay for the next search."""
        waiting = [t for t in self._tried if t.confirmed and t.window == i]
        if not waiting:
            return None
        stop = max(
            max(t.track) + 1 if t.track else min(self._linked_end(t.scan), t.scan + CONFIRM_SCANS)
            for t in waiting
        )
        for k in range(-(-end // START_STEP) * START_STEP, stop - i, START_STEP):
            placement, _ = self._placement(i + k, None, True)
            if placement is None:
                continue
            self._tried.append(_Tried(i + k, i, placement, False))
            if accepted := self._accepted(waiting):
                return accepted
        return None

    def _linked_end(self, k: int) -> int:
        """The first scan after scan ``k`` (which has odometry) that odometry does not link
        to it: the first without odometry or starting a break, else the log's length."""
        return int(np.searchsorted(self._unlinked, self._unlinked[k], side="right"))

    def _odometry_between(self, i: int, j: int) -> FloatArray | None:
        """Odometry motion from scan ``i`` to scan ``j`` (either order; ``(3,)``, frame of
        scan ``i``), or None when a scan between them (both included) has no odometry or one
        after the earlier of them starts an odometry break."""
        lo, hi = min(i, j), max(i, j)
        if self.scans[lo].odom_pose is None or self._unlinked[hi] != self._unlinked[lo]:
            return None
        return _odometry(self.scans, i, j)

    def _corroborated(self, tried: _Tried) -> bool:
        """Whether the global placement of another scan, at a place distinct from ``tried``'s
        by the odometry between them (or, without odometry, along the track from one of the
        two placements to the other's scan), lands at ``tried``'s place that way."""
        st = self.settings
        for other in self._tried:
            motion = self._odometry_between(other.scan, tried.scan)
            if motion is not None:
                moved = distinct_places(np.zeros(3), motion, st)
                if moved and not distinct_places(
                    se2.compose(other.placement.pose, motion), tried.placement.pose, st
                ):
                    return True
                continue
            for a, b in ((tried, other), (other, tried)):  # a's track reaching b's scan
                at = a.track.get(b.scan)
                if (
                    at is not None
                    and distinct_places(a.placement.pose, at, st)
                    and not distinct_places(at, b.placement.pose, st)
                ):
                    return True
        return False


def next_search(scans: Sequence[LaserScan], i: int) -> int:
    """The first scan of the search after the one from scan ``i``: a search spans the scans
    odometry links to its first (at most :data:`START_SCANS`); scans without odometry are
    searched from every :data:`START_STEP`-th, as a stretch of odometry is.

    Args:
        scans: the log's scans in time order.
        i: the first scan of the current search (index in ``scans``).

    Returns:
        The index of the next search's first scan (``> i``; may be past the log's end).
    """
    return i + max(odometry_run_end(scans[i:], START_SCANS), START_STEP)


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
) -> tuple[Placement | None, bool]:
    """Around ``guess`` when given, else (or when that fails) globally if ``search``; and
    whether the placement is a global one."""
    if guess is not None:
        bounds = MatchBounds.local(st.initial_translation_m, st.initial_rotation_deg)
        p = fixed.match_at(feats, guess, bounds, st.reference_nodes)
        if p is not None and p.match.correlation >= st.correlation_floor(fixed.config):
            return p, False
    return (fixed.place(feats, st) if search else None), True


def _where(scan: LaserScan, p: Placement) -> str:
    return (
        f"{scan.source} matched the map at {np.round(p.pose, 2).tolist()} (correlation "
        f"{p.match.correlation:.2f})"
    )


def _unconfirmed(
    fixed: FixedMap,
    scans: Sequence[LaserScan],
    p: Placement,
    st: LocalizeSettings,
    follow: bool = False,
) -> tuple[str, list[FloatArray]]:
    """Why the placement ``p`` of ``scans[0]`` is refused: the next :data:`CONFIRM_SCANS`
    scans, tracked from it, are lost or placed elsewhere before ``confirm_keyframes`` of them
    are tracked on the map (an empty string: confirmed, or nothing left to confirm it with);
    and the track: the map-frame pose ``(3,)`` of each scan tracked from ``scans[0]`` on,
    with ``follow`` up to the :data:`CONFIRM_SCANS`-th or the first not followed (a log
    without odometry corroborates a placement along it, :class:`StartSearch`), else until
    the confirmation ends."""
    loc = Localizer(fixed, st, initial_pose=p.pose)
    tracked = 0
    where = _where(scans[0], p)
    track: list[FloatArray] = []
    for scan in scans[:CONFIRM_SCANS]:
        pose, _, status, _ = loc.process(scan)
        if loc.relocalizations or status == Status.LOST:
            if tracked >= st.confirm_keyframes:
                return "", track
            return f"{where} but the next scans do not follow it there", track
        track.append(pose)
        tracked += status == Status.TRACKED
        if tracked >= st.confirm_keyframes and not follow:
            return "", track
    if tracked >= st.confirm_keyframes or len(scans) <= 1:
        return "", track
    return f"{where} but the next {min(len(scans), CONFIRM_SCANS)} scans did not confirm it", track


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
    with match_helper(fixed_map_of(slam)) as fixed:
        k, placement = place_start(fixed, scans, initial_pose)
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
    from iceg.pipeline import check_relations_match, read_log_scans, score_against_relations

    config = sess.read_config(session_path)
    scans, offset, reading = read_log_scans(
        path, config, stamps, reader_options, odometry_time_offset_s
    )
    rel = read_relations(relations) if relations is not None else None
    if rel is not None:
        check_relations_match(rel, np.array([s.stamp_s for s in scans]))
    result = continue_scans(session_path, scans, initial_pose, progress)
    if result.slam is not None:
        sess.record_reading(result.slam, path, reading, offset["applied_s"])
    result.metrics["continued_from"] = str(Path(session_path).resolve())
    result.metrics["odometry_time_offset"] = offset
    if rel is not None:
        score_against_relations(result, rel)
    return result
