"""A loop-closure search's candidate matches shared with a helper process (issue 13).

A search matches the new scan against several candidate places (up to
``loop_closure.max_candidates`` near the estimate, ``global_candidates`` by appearance), each
an independent call of the matcher, a pure function of the scan's features, the place's
reference, the prediction and the bounds. :class:`MatchPool` sends every second match of a
search to a forked helper process and runs the others in the calling process. When the
calling process is done with its own, it waits for the helper's results, each for as long as
one of its own matches took, and runs a match that has not arrived by then itself (from the
last one back; the helper's late result is dropped): a helper starved of CPU costs little.
Either process computes the same result from the same inputs, so the run is the same bit for
bit whatever the timing and with or without a helper (``tests/iceg/test_match_pool.py``).

The helper is forked at the first search with two matches, when the calling process has
loaded the matcher's compiled kernels, so it starts warm; it holds the matcher and its
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
from typing import NamedTuple, cast

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


class MatchPool:
    """Runs a search's matches in the calling process and one forked helper.

    Use as a context manager (the helper is stopped on exit)::

        with MatchPool(slam.matcher, helper=True) as pool:
            results = pool.map(jobs)

    Args:
        matcher: The matcher every match uses (the helper holds a copy of it from the fork).
        helper: Whether to start the helper process (Linux only); without it :meth:`map`
            runs every match in the calling process.
        wait: Wait for the helper's results however long they take, never running its
            share here (for tests).

    Attributes:
        remote: Matches whose result came from the helper so far.
        local: Matches run in the calling process (its share, and those the helper had not
            returned in time).
    """

    def __init__(self, matcher: Matcher, helper: bool = True, wait: bool = False) -> None:
        self.matcher = matcher
        self.want_helper = helper
        self.wait = wait
        self.remote = 0
        self.local = 0
        self._conn: Connection | None = None
        self._proc: BaseProcess | None = None
        self._open = False  # inside the with-block
        self._started = False  # the helper was forked (or failed to be)
        self._batch = 0  # the current batch's number: a late result names an older one

    def __enter__(self) -> MatchPool:
        self._open = True
        return self

    def _start(self) -> None:
        """Fork the helper (once, when first needed)."""
        self._started = True
        try:
            ctx = multiprocessing.get_context("fork")
            self._conn, child = ctx.Pipe(duplex=True)
            self._proc = ctx.Process(
                target=_serve,
                args=(child, self._conn, os.getpid(), self.matcher),
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
        """The match of every job, in order (``matcher.match(*job())`` each). Each job is
        built when needed: the helper's share (the first half) is built and sent first, so
        that the helper works while this process builds and runs its own.

        Raises:
            Whatever the matcher raises (a match that failed in the helper is run here, so
            its error is raised in this process).
        """
        built: list[MatchJob | None] = [None] * len(jobs)
        results: list[MatchResult | None] = [None] * len(jobs)
        remote = self._send_first_half(jobs, built)
        t0 = time.perf_counter()
        own = range(len(remote), len(jobs))
        for k in own:
            results[k] = self._here(jobs[k]())
        patience_s = (time.perf_counter() - t0) / max(1, len(own))
        missing = set(remote)
        while missing:
            got = self._arrived(None if self.wait else patience_s)
            k = max(missing) if got is None else got[0]  # none in time: the last one here
            if k not in missing:
                continue
            missing.discard(k)
            if got is not None and got[1] is not None:
                results[k] = got[1]
                self.remote += 1
            else:  # not arrived in time, or failed there (its error is raised here)
                results[k] = self._here(built[k] or jobs[k]())
        return [r for r in results if r is not None]

    def _here(self, job: MatchJob) -> MatchResult:
        self.local += 1
        return self.matcher.match(*job)

    def _send_first_half(
        self, jobs: Sequence[Callable[[], MatchJob]], built: list[MatchJob | None]
    ) -> list[int]:
        """Build the first half of the jobs (rounded down) and send each to the helper as
        soon as it is built; the indices sent (none without a helper or with one job)."""
        if len(jobs) < 2 or not (self._open and self.want_helper and sys.platform == "linux"):
            return []
        if not self._started:
            self._start()
        if self._conn is None:
            return []
        self._batch += 1
        sent = []
        for k in range(len(jobs) // 2):
            built[k] = job = jobs[k]()
            try:
                self._conn.send((self._batch, k, job))
            except (OSError, ValueError):
                self._conn = None
                break
            sent.append(k)
        return sent

    def _arrived(self, timeout_s: float | None) -> tuple[int, MatchResult | None] | None:
        """A result of the current batch from the helper (None for a match that failed
        there), if one arrives within ``timeout_s`` (None: however long it takes; results
        of older batches are dropped)."""
        conn = self._conn
        deadline = time.perf_counter() + (0.0 if timeout_s is None else timeout_s)
        try:
            while conn is not None and conn.poll(
                None if timeout_s is None else max(0.0, deadline - time.perf_counter())
            ):
                batch, k, result = conn.recv()
                if batch == self._batch:
                    return k, result
        except (EOFError, OSError):
            self._conn = None
        return None


def _serve(conn: Connection, parent_end: Connection, parent_pid: int, matcher: Matcher) -> None:
    """Helper loop: jobs ``(batch, k, job)`` in, ``(batch, k, result or None)`` out; None,
    the end of the pipe or the parent's exit stops it."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the main process's to handle
    parent_end.close()
    while (msg := forked.next_message(conn, parent_pid)) is not None:
        batch, k, job = cast(tuple[int, int, MatchJob], msg)
        try:
            result: MatchResult | None = matcher.match(*job)
        except Exception:  # the calling process runs it again and raises it there
            result = None
        try:
            conn.send((batch, k, result))
        except (OSError, ValueError):  # the calling process is gone
            return
