"""A loop-closure search's candidate matches shared with a helper process (issue 13).

A search matches the new scan against several candidate places (up to
``loop_closure.max_candidates`` near the estimate, ``global_candidates`` by appearance), each
an independent call of the matcher, a pure function of the scan's features, the place's
reference, the prediction and the bounds. :meth:`MatchPool.submit` sends a search's matches
to a forked helper process, which takes them from the front; :meth:`MatchPool.collect`
returns their results, the calling process first running itself those the helper has not
begun (from the back; a shared claim, so that no match runs twice). The calling process may
do other work between the two, and :meth:`MatchPool.map` is the two at once. A match the
helper began but has not returned within twice the mean time of the matches the calling
process has run is run here too (the helper's late result is dropped): a helper starved of
CPU costs little. Either process computes the same result from the same inputs, so the run
is the same bit for bit whatever the timing and with or without a helper
(``tests/iceg/test_match_pool.py``).

The helper is forked at the first search with matches to share, when the calling process
has loaded the matcher's compiled kernels, so it starts warm; it holds the matcher and its
configuration from the fork. It only matches (numpy and numba, no gtsam), which is what
makes forking safe here, as for the feature workers (:mod:`iceg.features.prefetch`). Linux
only; elsewhere every match runs in the calling process.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import signal
import sys
import time
from collections.abc import Callable, Sequence
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any, NamedTuple, cast

import numpy as np
from numpy.typing import NDArray

from iceg import forked
from iceg.matching import MatchBounds, Matcher
from iceg.types import MatchResult, ScanFeatures

log = logging.getLogger(__name__)


class MatchJob(NamedTuple):
    """The arguments of one :meth:`~iceg.matching.Matcher.match` call.

    Attributes:
        features: The new scan's features (robot frame).
        reference: The place's features, segments and points (reference frame).
        prediction: ``(3,)`` float64 predicted pose ``[x_m, y_m, theta_rad]`` of the new scan
            in the reference frame.
        bounds: Admissible motion around the prediction.
    """

    features: ScanFeatures
    reference: ScanFeatures
    prediction: NDArray[np.float64]
    bounds: MatchBounds


#: Slots of the shared claim: the batch number, the next match the helper may take (from
#: the front) and the end of those it may take (the calling process takes from the back).
_BATCH, _FRONT, _BACK = 0, 1, 2
#: How long the calling process waits for a match the helper began, before it has run one
#: itself (seconds; afterwards twice the mean time of the matches it has run).
_FIRST_PATIENCE_S = 0.01


class MatchBatch(NamedTuple):
    """The matches of one :meth:`MatchPool.submit` (pass it to :meth:`MatchPool.collect`).

    Attributes:
        number: The batch's number (0: not shared with the helper).
        jobs: Each match's arguments, built when submitted if shared, else when collected.
    """

    number: int
    jobs: list[Callable[[], MatchJob]]


class MatchPool:
    """Runs a search's matches in the calling process and one forked helper.

    Use as a context manager (the helper is stopped on exit)::

        with MatchPool(slam.matcher, helper=True) as pool:
            results = pool.map(jobs)  # or: batch = pool.submit(jobs); ...; pool.collect(batch)

    Args:
        matcher: The matcher every match uses (the helper holds a copy of it from the fork).
        helper: Whether to start the helper process (Linux only); without it every match
            runs in the calling process.
        wait: Leave every shared match to the helper, however long it takes (for tests).

    Attributes:
        remote: Matches whose result came from the helper so far.
        local: Matches run in the calling process (those the helper had not begun or not
            returned in time, and every match of an unshared batch).
    """

    def __init__(self, matcher: Matcher, helper: bool = True, wait: bool = False) -> None:
        self.matcher = matcher
        self.want_helper = helper
        self.wait = wait
        self.remote = 0
        self.local = 0
        self._conn: Connection | None = None
        self._proc: BaseProcess | None = None
        self._claim: Any = None  # shared int64 [batch, front, back] with its lock
        self._open = False  # inside the with-block
        self._started = False  # the helper was forked (or failed to be)
        self._batch = 0  # the last shared batch's number: a late result names an older one
        self._n_here = 0  # matches run here so far
        self._here_total_s = 0.0  # and their total time

    def __enter__(self) -> MatchPool:
        self._open = True
        return self

    def _start(self) -> None:
        """Fork the helper (once, when first needed)."""
        self._started = True
        try:
            ctx = multiprocessing.get_context("fork")
            self._claim = ctx.Array("q", 3)
            self._conn, child = ctx.Pipe(duplex=True)
            self._proc = ctx.Process(
                target=_serve,
                args=(child, self._conn, os.getpid(), self.matcher, self._claim),
                daemon=True,
                name="iceg-matches",
            )
            self._proc.start()
            child.close()
        except OSError as exc:
            log.warning("match helper off (%s); matching here", exc)
            self._conn = self._proc = None

    def __exit__(self, *exc: object) -> None:
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        self._open = False
        if conn is None or proc is None:
            return
        log.debug("match helper: %d matches there, %d here", self.remote, self.local)
        forked.stop(conn, proc)

    def map(self, jobs: Sequence[Callable[[], MatchJob]]) -> list[MatchResult]:
        """The match of every job, in order (``matcher.match(*job())`` each): shared with the
        helper when there are two or more, else run here.

        Raises:
            Whatever the matcher raises (a match that failed in the helper is run here, so
            its error is raised in this process).
        """
        if len(jobs) < 2:
            return [self._here(job()) for job in jobs]
        return self.collect(self.submit(jobs))

    def submit(self, jobs: Sequence[Callable[[], MatchJob]]) -> MatchBatch:
        """Start the matches of ``jobs``: each is built and sent to the helper, which takes
        them in order while this process goes on; without a helper they wait for
        :meth:`collect`. Collect every batch before submitting the next."""
        if not jobs or not (self._open and self.want_helper and sys.platform == "linux"):
            return MatchBatch(0, list(jobs))
        if not self._started:
            self._start()
        if self._conn is None:
            return MatchBatch(0, list(jobs))
        self._batch += 1
        with self._claim.get_lock():
            self._claim[_BATCH], self._claim[_FRONT], self._claim[_BACK] = self._batch, 0, len(jobs)
        built = [job() for job in jobs]
        try:
            self._conn.send((self._batch, built))
        except (OSError, ValueError):  # the helper is gone: every match runs here
            self._conn = None
            return MatchBatch(0, [_given(job) for job in built])
        return MatchBatch(self._batch, [_given(job) for job in built])

    def collect(self, batch: MatchBatch) -> list[MatchResult]:
        """The results of a :meth:`submit`, in order: the matches the helper has not begun
        are run here (from the last one back), then those it began are awaited, each for as
        long as twice the mean match run here took, and run here when not back by then.

        Raises:
            Whatever the matcher raises (see :meth:`map`).
        """
        jobs = batch.jobs
        if batch.number == 0:
            return [self._here(job()) for job in jobs]
        results: list[MatchResult | None] = [None] * len(jobs)
        while not self.wait and (k := self._take_last(batch.number)) is not None:
            results[k] = self._here(jobs[k]())
        missing = {k for k, r in enumerate(results) if r is None}
        while missing:
            got = self._arrived(batch.number, None if self.wait else self._patience_s())
            k = max(missing) if got is None else got[0]  # none in time: the last one here
            if k not in missing:
                continue
            missing.discard(k)
            if got is not None and got[1] is not None:
                results[k] = got[1]
                self.remote += 1
            else:  # not arrived in time, or failed there (its error is raised here)
                results[k] = self._here(jobs[k]())
        return [r for r in results if r is not None]

    def _take_last(self, number: int) -> int | None:
        """Claim the last match of batch ``number`` the helper has not begun, if any."""
        with self._claim.get_lock():
            if self._claim[_BATCH] != number or self._claim[_FRONT] >= self._claim[_BACK]:
                return None
            self._claim[_BACK] -= 1
            return int(self._claim[_BACK])

    def _here(self, job: MatchJob) -> MatchResult:
        self.local += 1
        t0 = time.perf_counter()
        result = self.matcher.match(*job)
        self._n_here += 1
        self._here_total_s += time.perf_counter() - t0
        return result

    def _patience_s(self) -> float:
        """How long to wait for a match the helper began (see the module docstring)."""
        n = self._n_here
        return 2.0 * self._here_total_s / n if n else _FIRST_PATIENCE_S

    def _arrived(
        self, number: int, timeout_s: float | None
    ) -> tuple[int, MatchResult | None] | None:
        """A result of batch ``number`` from the helper (None for a match that failed
        there), if one arrives within ``timeout_s`` (None: however long it takes; results
        of older batches are dropped)."""
        conn = self._conn
        deadline = time.perf_counter() + (0.0 if timeout_s is None else timeout_s)
        try:
            while conn is not None and conn.poll(
                None if timeout_s is None else max(0.0, deadline - time.perf_counter())
            ):
                got, k, result = conn.recv()
                if got == number:
                    return k, result
        except (EOFError, OSError):
            self._conn = None
        return None


def _given(job: MatchJob) -> Callable[[], MatchJob]:
    """A job that returns ``job`` (already built)."""
    return lambda: job


def _serve(
    conn: Connection, parent_end: Connection, parent_pid: int, matcher: Matcher, claim: Any
) -> None:
    """Helper loop: batches ``(batch, jobs)`` in, ``(batch, k, result or None)`` out for each
    job ``k`` it claims, from the front, until the calling process has taken the rest; None,
    the end of the pipe or the parent's exit stops it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle
    parent_end.close()
    while (msg := forked.next_message(conn, parent_pid)) is not None:
        batch, jobs = cast(tuple[int, list[MatchJob]], msg)
        for k, job in enumerate(jobs):
            with claim.get_lock():
                mine = claim[_BATCH] == batch and claim[_FRONT] == k and k < claim[_BACK]
                if mine:
                    claim[_FRONT] = k + 1
            if not mine:  # the calling process took the rest
                break
            try:
                result: MatchResult | None = matcher.match(*job)
            except Exception:  # the calling process runs it again and raises it there
                result = None
            try:
                conn.send((batch, k, result))
            except (OSError, ValueError):  # the calling process is gone
                return
