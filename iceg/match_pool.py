"""A loop-closure search's candidate matches run by a helper process (issue 13).

A search matches the new scan against several candidate places (up to
``loop_closure.max_candidates`` near the estimate, ``global_candidates`` by appearance), each
an independent call of the matcher, a pure function of the scan's features, the place's
reference, the prediction and the bounds. :meth:`MatchPool.submit` sends every match of a
search to a forked helper process and returns at once, so that the calling process goes on
with its own work (the next keyframe's tracking, :mod:`iceg.slam`);
:meth:`MatchPool.collect` then reads the results: while two or more are missing it runs the
last of them itself (the helper works from the first and skips a match taken here), and it
waits for the one left about as long as a match takes before running that one too (the
helper's late result is dropped): a helper starved of CPU costs little. Either process
computes the same result from the same inputs, so the run is the same bit for bit whatever
the timing and with or without a helper (``tests/iceg/test_match_pool.py``). A global
placement in a saved map, a batch of a match per place of the map, shares its matches with the
helper through :meth:`MatchPool.run_all` (:func:`iceg.localize.match_helper`); the places'
references, the same at every placement, are handed to the helper at its fork
(:meth:`MatchPool.share`) and named by a key in the jobs instead of sent.

The helper is forked at the first submitted search, when the calling process has loaded the
matcher's compiled kernels, so it starts warm; it holds the matcher and its configuration
from the fork. It only matches (numpy and numba, no gtsam), which is what makes forking safe
here, as for the feature workers (:mod:`iceg.features.prefetch`). Linux only; elsewhere
every match runs in the calling process.
"""

from __future__ import annotations

import logging
import multiprocessing
import os
import sys
import time
from collections.abc import Iterable
from dataclasses import dataclass, field
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


#: How long :meth:`MatchPool.collect` waits for the last missing result (seconds) before
#: any match's duration is known (a cost setting only: the results are the same).
FIRST_PATIENCE_S = 0.01

#: Most results the helper may have sent that :meth:`MatchPool.submit` has not read: beyond
#: it, submit reads one before sending more. The helper blocks on a full pipe (a socket
#: pair, 208 KiB each way on Linux by default; a result pickles to about 0.8 KiB) and stops
#: reading jobs, so a batch whose results outgrew it deadlocked both processes, each waiting
#: to send (560 matches in ``tests/iceg/test_match_pool.py``; a search sends a few).
MAX_UNREAD_RESULTS = 32


@dataclass(eq=False)
class SentMatches:
    """A search's matches handed to :meth:`MatchPool.submit`, to :meth:`MatchPool.collect`.

    Attributes:
        jobs: The matches, in order.
        remote: Indices of the jobs sent to the helper (none without one).
        batch: The batch number the helper's results carry (a late result names an older one).
    """

    jobs: list[MatchJob]
    remote: list[int] = field(default_factory=list)
    batch: int = 0


class MatchPool:
    """Runs a search's matches in one forked helper process while the caller works on.

    Use as a context manager (the helper is stopped on exit)::

        with MatchPool(slam.matcher, helper=True) as pool:
            sent = pool.submit(jobs)
            ...  # other work
            results = pool.collect(sent)

    Args:
        matcher: The matcher every match uses (the helper holds a copy of it from the fork).
        helper: Whether to start the helper process (Linux only); without it :meth:`collect`
            runs every match in the calling process.
        wait: Wait for the helper's results however long they take, never running a match
            here unless it failed there (for tests).

    Attributes:
        remote: Matches whose result came from the helper so far.
        local: Matches run in the calling process (with no helper, and those the helper had
            not returned in time).
    """

    def __init__(self, matcher: Matcher, helper: bool = True, wait: bool = False) -> None:
        self.matcher = matcher
        self.want_helper = helper
        self.wait = wait
        self.remote = 0
        self.local = 0
        self._conn: Connection | None = None
        self._readable: forked.Readable | None = None  # of _conn
        self._proc: BaseProcess | None = None
        self._open = False  # inside the with-block
        self._started = False  # the helper was forked (or failed to be)
        self._batch = 0  # the current batch's number: a late result names an older one
        self._match_cpu_s = [0.0, 0]  # CPU seconds of the helper's matches, their number
        self._early: dict[int, MatchResult | None] = {}  # results submit read: job -> result
        # [batch, k]: the calling process runs the jobs k.. of that batch (shared with the
        # helper, which skips them; a job both run costs time, not a different result)
        self._taken: Any = None
        # references the helper holds from the fork (:meth:`share`): id -> (key, object)
        self._shared: dict[int, tuple[int, ScanFeatures]] = {}

    def __enter__(self) -> MatchPool:
        self._open = True
        return self

    def _start(self) -> None:
        """Fork the helper (once, when first needed)."""
        self._started = True
        try:
            ctx = multiprocessing.get_context("fork")
            self._conn, child = ctx.Pipe(duplex=True)
            self._taken = ctx.RawArray("q", 2)
            shared = [ref for _, ref in self._shared.values()]
            self._proc = ctx.Process(
                target=_serve,
                args=(child, self._conn, os.getpid(), self.matcher, self._taken, shared),
                daemon=True,
                name="iceg-matches",
            )
            with forked.signals_held():
                self._proc.start()
            child.close()
            self._readable = forked.Readable(self._conn)
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

    def share(self, references: Iterable[ScanFeatures]) -> bool:
        """Let the helper hold ``references`` from its fork, so that a job naming one of
        them (the same object) sends a key instead of the reference: a global placement
        matches every scan against the same places of a map, about 12 KB pickled each, and
        the helper derives each place's pose-independent quantities once instead of once a
        job. Only before the helper is forked (the first :meth:`submit`); returns whether
        the references will be shared. The results are the same either way.

        Raises:
            Whatever iterating ``references`` raises (nothing is iterated once the helper
            runs, or without one).
        """
        if self._started or not self.want_helper or sys.platform != "linux":
            return False
        for ref in references:
            if id(ref) not in self._shared:
                self._shared[id(ref)] = (len(self._shared), ref)
        return True

    def submit(self, jobs: Iterable[MatchJob]) -> SentMatches:
        """Send every job to the helper (forked on first use), each as soon as the iterable
        gives it, and return; nothing is sent without a helper (outside the with-block, or
        not on Linux). Read the results with :meth:`collect` before the next ``submit``. With
        more than :data:`MAX_UNREAD_RESULTS` of the helper's results unread, it waits for one
        and keeps it for :meth:`collect` before sending the next job."""
        sent = SentMatches([])
        self._early = {}
        helper = self._open and self.want_helper and sys.platform == "linux"
        held: ScanFeatures | None = None  # the new scan's features the helper has this batch
        for k, job in enumerate(jobs):
            sent.jobs.append(job)
            if not helper:
                continue
            if not self._started:
                self._start()
            if self._conn is None:
                helper = False
                continue
            if not sent.remote:
                self._batch += 1
                sent.batch = self._batch
            # a search's jobs share the new scan's features: sent with the first only
            features = None if job.features is held else job.features
            # a reference the helper holds from its fork: named by its key (share)
            shared = self._shared.get(id(job.reference))
            key = shared[0] if shared is not None and shared[1] is job.reference else None
            rest = job[1:] if key is None else (key, *job[2:])
            try:
                forked.send(self._conn, (self._batch, k, features, rest))
            except (OSError, ValueError):
                self._conn, helper = None, False
                continue
            sent.remote.append(k)
            held = job.features
            while len(sent.remote) - len(self._early) > MAX_UNREAD_RESULTS:
                got = self._arrived(None, sent.batch)
                if got is None:  # the helper is gone: collect runs the rest here
                    break
                self._early[got[0]] = got[1]
        return sent

    def collect(self, sent: SentMatches) -> list[MatchResult]:
        """The match of every job of ``sent``, in order. Those not sent run here. Of those
        sent, the helper's results that have arrived are taken; while two or more are
        missing, the last of them runs here (the helper works from the first, so this one
        waits longest there); the one left missing is awaited for about as long as one of
        the helper's matches took (their mean CPU time so far, :data:`FIRST_PATIENCE_S`
        before the first), then runs here. The helper skips a job this process has taken
        (``[batch, first index]`` in shared memory); a result it sends for one it had begun
        is dropped.

        Raises:
            Whatever the matcher raises (a match that failed in the helper is run here, so
            its error is raised in this process).
        """
        results: list[MatchResult | None] = [None] * len(sent.jobs)
        missing = set(sent.remote) if sent.batch == self._batch else set()
        early = self._early if sent.batch == self._batch else {}
        for k, job in enumerate(sent.jobs):
            if k not in missing:
                results[k] = self._here(job)
            elif k in early:  # read by submit (None: failed there, run here)
                missing.discard(k)
                got_early = early[k]
                self.remote += got_early is not None
                results[k] = got_early if got_early is not None else self._here(job)
        while missing:
            if self.wait:
                timeout_s: float | None = None
            else:
                timeout_s = self._patience_s() if len(missing) == 1 else 0.0
            got = self._arrived(timeout_s, sent.batch)
            k = max(missing) if got is None else got[0]
            if k not in missing:
                continue
            missing.discard(k)
            if got is not None and got[1] is not None:
                results[k] = got[1]
                self.remote += 1
            else:  # not arrived, or failed there (its error is raised here)
                if got is None:  # the last missing: the helper may skip it
                    self._take(sent.batch, k)
                results[k] = self._here(sent.jobs[k])
        return [r for r in results if r is not None]

    def run_all(self, jobs: Iterable[MatchJob]) -> list[MatchResult]:
        """The match of every job, in order, for a batch larger than a search's (a global
        placement against every place of a map): the jobs alternate between the helper and
        this process, each sent as this process takes up the one after it, so neither waits
        on the other (:meth:`submit` alone would block on the full pipe while the helper
        works through the batch). Without a helper every job runs here.

        Raises:
            Whatever the matcher raises.
        """
        here: dict[int, MatchResult] = {}

        def every_other() -> Iterable[MatchJob]:
            for k, job in enumerate(jobs):
                if k % 2:
                    here[k] = self._here(job)
                else:
                    yield job

        sent = self.submit(every_other())
        helped = iter(self.collect(sent))  # the even jobs, in order
        return [here[k] if k % 2 else next(helped) for k in range(len(sent.jobs) + len(here))]

    def _take(self, batch: int, k: int) -> None:
        """Tell the helper that this process runs job ``k`` of ``batch`` and the later ones
        (taken from the last back). The index is written before the batch, so the helper
        never reads a pair that takes a job of the new batch this process has not taken."""
        if self._taken is not None:
            self._taken[1] = k
            self._taken[0] = batch

    def _patience_s(self) -> float:
        total_s, n = self._match_cpu_s
        return total_s / n if n else FIRST_PATIENCE_S

    def _here(self, job: MatchJob) -> MatchResult:
        self.local += 1
        return self.matcher.match(*job)

    def _arrived(
        self, timeout_s: float | None, batch: int
    ) -> tuple[int, MatchResult | None] | None:
        """A result of ``batch`` from the helper (None for a match that failed there), if
        one arrives within ``timeout_s`` (None: however long it takes; results of older
        batches are dropped)."""
        conn, readable = self._conn, self._readable
        deadline = time.perf_counter() + (0.0 if timeout_s is None else timeout_s)
        try:
            while (
                conn is not None
                and readable is not None
                and readable(None if timeout_s is None else deadline - time.perf_counter())
            ):
                got, k, result, cpu_s = conn.recv()
                if result is not None:
                    self._match_cpu_s[0] += cpu_s
                    self._match_cpu_s[1] += 1
                if got == batch:
                    return k, result
        except (EOFError, OSError):
            self._conn = None
        return None


def _serve(
    conn: Connection,
    parent_end: Connection,
    parent_pid: int,
    matcher: Matcher,
    taken: Any,
    shared: list[ScanFeatures],
) -> None:
    """Helper loop: jobs ``(batch, k, features or None, the job's other arguments)`` in
    (None: the features of the batch's previous job, which one object serves, so its
    pose-independent quantities are derived once; a reference given as an int: that item
    of ``shared``, held from the fork), ``(batch, k, result or None, CPU seconds of the
    match)`` out, except for a job the calling process has taken (``taken``, shared
    ``[batch, first index]``): it runs that one itself. None, the end of the pipe or the
    parent's exit stops it."""
    forked.helper_signals()
    parent_end.close()
    features: ScanFeatures | None = None
    readable = forked.Readable(conn)
    while (msg := forked.next_message(readable, parent_pid)) is not None:
        batch, k, sent, rest = cast(tuple[int, int, ScanFeatures | None, tuple[Any, ...]], msg)
        features = features if sent is None else sent
        if taken[0] == batch and k >= taken[1]:
            continue
        if isinstance(rest[0], int):
            rest = (shared[rest[0]], *rest[1:])
        t0 = time.thread_time()
        try:
            result: MatchResult | None = matcher.match(cast(ScanFeatures, features), *rest)
        except Exception:  # the calling process runs it again and raises it there
            result = None
        try:
            forked.send(conn, (batch, k, result, time.thread_time() - t0))
        except (OSError, ValueError):  # the calling process is gone
            return
