"""Feature extraction ahead of the pipeline, in worker processes (issue 13).

A scan's ICE features depend on the scan and the feature configuration only, never on the
pose estimate, so they can be computed while the main process matches the previous scans.
:class:`FeaturePrefetcher` sends the scans a few places ahead to worker processes and hands
each scan back with a callable that returns its features: the worker's result when it has
arrived, else (a worker starting, behind or failed) :func:`extract` run in the calling
process. Both are the same computation on the same inputs, so the features, and every result
of the run, are bit for bit those of a run without workers, whatever the timing.

Processes rather than threads: most of the extraction is small numpy operations that hold
the GIL. Each worker is a forked process (Linux only; elsewhere the calling process extracts
alone) fed through its own pipe, read and written by the calling thread only: no helper
thread competes with the main process for the GIL (a ``concurrent.futures`` pool's manager
thread did, and cost more than the extraction it saved). A forked worker starts at once with
the package loaded and never re-runs the user's ``__main__`` script, which ``spawn`` and
``forkserver`` would (a script without an ``if __name__ == "__main__"`` guard would run
twice). The workers only extract features (numpy and numba: no gtsam, no threads of the
parent), which is what makes forking a process that may hold other threads safe here. With
a :class:`Precompute` they also compute what the run derives from a scan and its features
alone (:mod:`iceg.scan_products`), which the calling process adopts with the features.
Scans go out in batches (one wake-up of a worker per few scans), never more than
``LOOKAHEAD_PER_WORKER`` unfinished per worker; a worker skips the scans the calling process
has passed meanwhile (a shared floor: through a stretch without keyframes the calling
process outruns the extraction and reads none of it), and workers run at a lower priority
(``WORKER_NICENESS``): on a busy machine they take spare CPU only, and the main process
extracts what they have not done yet. A worker loads the extraction's compiled kernels as
it starts (a synthetic scan), while the calling process reads its log; until the calling
process has extracted a scan itself, which would load them there too, it waits for the
workers' results instead (``UNLOADED_WAIT_S`` in all).
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import sys
import time
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Any, Protocol, TypeVar, cast

import numpy as np

from frontends.scan import LaserScan
from iceg import forked
from iceg.features.config import FeatureConfig
from iceg.features.extract import extract
from iceg.types import ScanFeatures

log = logging.getLogger(__name__)

#: Scans sent ahead of the one being processed, per worker process.
LOOKAHEAD_PER_WORKER = 8
#: Scheduling niceness added to a worker (it uses spare cores, not the main process's).
WORKER_NICENESS = 10
#: Most time (seconds, in all) the calling process waits for the workers' features while
#: it has extracted none itself: about what its first extraction would cost, loading the
#: compiled kernels (0.3-0.5 s) that the workers load as they start. Past it, it extracts
#: what has not arrived, as it always does once it has extracted one.
UNLOADED_WAIT_S = 0.5

#: Seconds :func:`auto_workers` watches the cores before deciding.
IDLE_SAMPLE_S = 0.05
#: Idle capacity (cores) beyond the one a run takes for :func:`auto_workers` to add a
#: second process: its helpers use about half a core (MIT CSAIL: 4.8 s of CPU in a 9.5 s
#: run, nearly all of it the features of every scan, 1.3 ms each with their products).
MIN_SPARE_CORES = 0.5

FeaturesOf = Callable[[], ScanFeatures]


_P = TypeVar("_P")


class Precompute(Protocol[_P]):
    """Pose-independent products of a scan and its features, computed in a worker right
    after the features (:meth:`compute`, any picklable value) and handed over in the calling
    process with them (:meth:`adopt`). ``compute`` must be a pure function of its inputs, so
    that the run is the same whether a product comes from a worker or not."""

    def compute(self, scan: LaserScan, features: ScanFeatures) -> _P: ...

    def adopt(self, scan: LaserScan, features: ScanFeatures, products: _P) -> None: ...

    def warm_up_without_features(self, scan: LaserScan) -> None:
        """Called in the first worker before its warm-up extraction where numba's cache is
        new (:class:`FeaturePrefetcher`'s ``warm_up_later``): compile kernels the calling
        process needs late that need no features, while it compiles those it needs first
        (:mod:`iceg.kernel_warmup`). Results are dropped; an exception ends the warm-up."""

    def warm_up_with_features(self, scan: LaserScan, features: ScanFeatures) -> None:
        """As :meth:`warm_up_without_features`, after the warm-up extraction, for the
        kernels that need the scan's features."""


#: A worker's result for one scan: its features (None: extraction failed) and products (None:
#: none asked, or their computation failed).
_Result = tuple[ScanFeatures | None, object]


class _Inbox:
    """Results arrived from the workers, by scan index; those below ``floor`` (scans already
    handed out) are dropped on arrival. The floor is also in shared memory (``shared``),
    where the workers read it to skip the scans the calling process has passed."""

    def __init__(self, shared: Any = None) -> None:
        self.results: dict[int, _Result] = {}
        self.floor = 0
        self.shared = shared

    def put(self, index: int, feats: ScanFeatures | None, products: object = None) -> None:
        if index >= self.floor:
            self.results[index] = (feats, products)

    def advance(self, floor: int) -> None:
        self.floor = floor
        if self.shared is not None:
            self.shared.value = floor
        for k in [k for k in self.results if k < floor]:
            del self.results[k]


class _Worker:
    """One forked extraction process and the calling side of its pipe. ``others`` are the
    calling sides of the workers started before (the child closes its copies of them, so
    that every worker sees the end of its pipe when the calling process exits). With
    ``later`` it first compiles the later stages' kernels (:func:`_warm_up`)."""

    def __init__(
        self,
        config: FeatureConfig,
        precompute: Precompute[Any] | None,
        others: list[Connection],
        floor: Any,
        later: bool = False,
    ) -> None:
        ctx = multiprocessing.get_context("fork")
        self.conn, child = ctx.Pipe(duplex=True)
        self.proc: BaseProcess = ctx.Process(
            target=_serve,
            args=(child, [self.conn, *others], os.getpid(), config, precompute, floor, later),
            daemon=True,
            name="iceg-features",
        )
        with forked.signals_held():
            self.proc.start()
        child.close()
        self.readable = forked.Readable(self.conn)
        self.alive = True
        self.outstanding = 0  # scans sent whose results have not been read

    def send(self, batch: list[tuple[int, LaserScan]], inbox: _Inbox, block: bool) -> bool:
        """Send a batch unless the worker is gone or still has ``LOOKAHEAD_PER_WORKER``
        scans to do (a worker starved of CPU must not fill the pipe and block the calling
        process), or with ``block`` after waiting for it to catch up; whether it was sent."""
        if block:
            self.catch_up(inbox)
        if not self.alive or not batch or self.outstanding >= LOOKAHEAD_PER_WORKER:
            return False
        try:
            forked.send(self.conn, batch)
        except (OSError, ValueError):
            self.alive = False
            return False
        self.outstanding += len(batch)
        return True

    def drain(self, inbox: _Inbox) -> None:
        """Move every result already arrived into ``inbox`` (never blocks)."""
        try:
            while self.alive and self.readable():
                inbox.put(*self.conn.recv())
                self.outstanding -= 1
        except (EOFError, OSError):
            self.alive = False

    def catch_up(self, inbox: _Inbox, timeout_s: float | None = None) -> None:
        """Block until the worker has fewer than ``LOOKAHEAD_PER_WORKER`` scans to do, or for
        at most ``timeout_s`` seconds."""
        self._receive_while(inbox, lambda: self.outstanding >= LOOKAHEAD_PER_WORKER, timeout_s)

    def wait_for(self, index: int, inbox: _Inbox, timeout_s: float | None = None) -> None:
        """Block until the result for ``index`` (sent to this worker) has arrived, or for at
        most ``timeout_s`` seconds."""
        self._receive_while(inbox, lambda: index not in inbox.results, timeout_s)

    def _receive_while(
        self, inbox: _Inbox, pending: Callable[[], bool], timeout_s: float | None
    ) -> None:
        """Move results into ``inbox`` as they arrive while ``pending()`` holds, for at most
        ``timeout_s`` seconds (None: however long it takes)."""
        deadline = None if timeout_s is None else time.monotonic() + timeout_s
        try:
            while self.alive and pending():
                if deadline is not None and not self.readable(deadline - time.monotonic()):
                    return
                inbox.put(*self.conn.recv())
                self.outstanding -= 1
        except (EOFError, OSError):
            self.alive = False

    def close(self, at_once: bool = False) -> None:
        forked.stop(self.conn, self.proc, at_once)


def _serve(
    conn: Connection,
    inherited: list[Connection],
    parent_pid: int,
    config: FeatureConfig,
    precompute: Precompute[Any] | None,
    floor: Any,
    later: bool,
) -> None:
    """Worker loop: batches ``[(index, scan), ...]`` in, one ``(index, features or None,
    products or None)`` out per scan; None, the end of the pipe or the parent's exit stops
    it. A scan below the calling process's ``floor`` (shared memory) is passed already:
    it is answered with None, not extracted (a stretch of scans that make no keyframe goes
    by faster than the worker extracts them). With ``later`` its warm-up also compiles the
    later stages' kernels (:func:`_warm_up`)."""
    forked.helper_signals()
    with contextlib.suppress(OSError):
        # Spare CPU only: on a busy machine the worker must not take the main process's
        # time (it would then fall behind, and the main process extract itself).
        os.nice(WORKER_NICENESS)
    for other in inherited:  # the parent's ends: never hold them open here
        other.close()
    _warm_up(config, precompute, later)
    readable = forked.Readable(conn)
    while (msg := forked.next_message(readable, parent_pid)) is not None:
        for index, scan in cast(list[tuple[int, LaserScan]], msg):
            if index < floor.value:
                feats: ScanFeatures | None = None
            else:
                try:
                    feats = extract(scan, config)
                except Exception:  # the calling process recomputes it and raises it there
                    feats = None
            products = None
            if precompute is not None and feats is not None:
                try:
                    products = precompute.compute(scan, feats)
                except Exception:  # the calling process computes them when it reads them
                    products = None
            try:
                forked.send(conn, (index, feats, products))
            except (OSError, ValueError):  # the calling process is gone
                return


def warm_up_scan() -> LaserScan:
    """The synthetic scan a worker extracts as it starts (:func:`_warm_up`): 181 beams over
    180 degrees in a 4 m x 3 m room seen from (1, 1.5) m, with a doorway of no returns, so
    that it has walls, corners and ends of wall."""
    bearing = np.linspace(-0.5 * np.pi, 0.5 * np.pi, 181)
    with np.errstate(divide="ignore"):
        # the walls x = 3 m ahead and y = +-1.5 m on both sides, in the sensor's frame
        ranges = np.minimum(
            np.where(np.cos(bearing) > 0, 3.0 / np.cos(bearing), np.inf),
            1.5 / np.abs(np.sin(bearing)),
        )
    ranges[100:110] = 25.0  # a doorway: no return, so the walls beside it end
    return LaserScan(0.0, ranges, bearing, 0.05, 25.0, None)


def _warm_up(config: FeatureConfig, precompute: Precompute[Any] | None, later: bool) -> None:
    """Load the compiled kernels of the extraction (numba's cache) before the first scan
    arrives, while the calling process reads its log: extract :func:`warm_up_scan` and drop
    the result. With ``later`` (a new cache) and ``precompute``, the products' warm-up
    hooks compile the later stages' kernels before and after that extraction."""
    scan = warm_up_scan()
    try:
        if later and precompute is not None:
            precompute.warm_up_without_features(scan)
        feats = extract(scan, config)
        if precompute is not None:
            precompute.compute(scan, feats)
            if later:
                precompute.warm_up_with_features(scan, feats)
    except Exception:  # only a warm-up: the first real scan loads what it needs
        return


def auto_workers() -> int:
    """Processes for a run when the configuration leaves it open (``slam.workers: 0``; also
    the grid's threads): 2 when the idle capacity of the cores this process may run on
    (``os.sched_getaffinity``), measured over the next ``IDLE_SAMPLE_S`` seconds
    (``psutil.cpu_percent`` per core), is at least one core for this run and
    ``MIN_SPARE_CORES`` more for the helpers (Linux), else 1. A second process pays off only
    on a free core: on a saturated machine it slowed runs down.

    Measured now, not by the load average: its minute-long memory counts runs that have
    finished, so of runs started one after another (a loop over logs), once the 1-minute
    load reached 1.0 every later one ran in one process on an otherwise idle machine.
    :class:`CoreWatch` gives the same answer from the time this process works through.
    """
    return CoreWatch().workers()


class CoreWatch:
    """:func:`auto_workers`'s answer, measured while this process works instead of in a wait
    of its own: the cores' use from the watch's start to :meth:`workers` (at least
    ``IDLE_SAMPLE_S``: it waits for the rest), with this process's own CPU time over that
    interval counted as idle capacity, since it is the work the answer is for. Start it
    where no helper process of this one is at work (their use would count as busy).
    ``psutil.cpu_percent`` keeps one baseline per process, so two watches must not overlap.
    """

    def __init__(self) -> None:
        self._start_s = time.monotonic()
        self._start_cpu_s = time.process_time()
        self._allowed: list[int] = []
        if sys.platform != "linux":
            return
        allowed = sorted(os.sched_getaffinity(0))
        if len(allowed) < 2:
            return
        import psutil  # on first use: a run that sets its workers never needs it

        try:
            psutil.cpu_percent(interval=None, percpu=True)  # the baseline of the next call
        except (OSError, psutil.Error):
            return
        self._allowed = allowed

    def workers(self) -> int:
        """2 or 1, as :func:`auto_workers` decides, from the cores' use since the start (1
        off Linux, with one allowed core, or where psutil cannot read the cores); raises
        nothing."""
        if not self._allowed:
            return 1
        import psutil

        rest_s = IDLE_SAMPLE_S - (time.monotonic() - self._start_s)
        if rest_s > 0.0:
            time.sleep(rest_s)
        try:
            busy_percent = psutil.cpu_percent(interval=None, percpu=True)
        except (OSError, psutil.Error):
            return 1
        own = (time.process_time() - self._start_cpu_s) / (time.monotonic() - self._start_s)
        idle = (
            own
            + sum(100.0 - busy_percent[c] for c in self._allowed if c < len(busy_percent)) / 100.0
        )
        return 2 if idle >= 1.0 + MIN_SPARE_CORES else 1


class FeaturePrefetcher:
    """Extract features of upcoming scans in ``workers - 1`` processes.

    Use as a context manager (the workers are stopped on exit)::

        with FeaturePrefetcher(config.features, workers=2) as prefetch:
            for scan, features in prefetch.scans(log):
                slam.process(scan, features=features)

    ``features()`` returns exactly ``extract(scan, config)``; it is only worth calling for
    scans that need features (keyframes), the others' results are dropped.

    Args:
        config: The feature configuration (as ``extract`` takes it).
        workers: Processes in all, the calling one included: 1 extracts in the calling
            process only (no worker).
        wait: Wait for a worker's result rather than extracting in the calling process
            when it has not arrived (for tests).
        precompute: Products the workers also compute for each scan, adopted in the calling
            process with the features (:class:`Precompute`; None: features only).
        warm_up_later: numba's cache is new (:func:`iceg.kernel_warmup.cache_is_new`): the
            first worker compiles the later stages' kernels through ``precompute``'s warm-up
            hooks while the calling process compiles the first ones (the run is the same).

    Attributes:
        hits: Features taken from a worker so far.
        misses: Features extracted in the calling process instead (no worker, a worker
            behind or failed).
    """

    def __init__(
        self,
        config: FeatureConfig,
        workers: int,
        wait: bool = False,
        precompute: Precompute[Any] | None = None,
        warm_up_later: bool = False,
    ) -> None:
        self.config = config
        self.warm_up_later = warm_up_later
        self.workers = max(1, int(workers))
        self.wait = wait
        self._waited_s = 0.0  # waited for workers before extracting here (UNLOADED_WAIT_S)
        self.precompute = precompute
        self.hits = 0
        self.misses = 0
        self._pool: list[_Worker] = []
        self._inbox = _Inbox()

    def __enter__(self) -> FeaturePrefetcher:
        if self.workers > 1 and sys.platform == "linux":
            try:
                floor = multiprocessing.get_context("fork").RawValue("q", 0)
                self._inbox = _Inbox(floor)
                for _ in range(self.workers - 1):
                    others = [w.conn for w in self._pool]
                    later = self.warm_up_later and not others
                    self._pool.append(_Worker(self.config, self.precompute, others, floor, later))
            except OSError as exc:
                log.warning("feature prefetch off (%s); extracting here", exc)
                self.__exit__()
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pool:
            log.debug("feature prefetch: %d from workers, %d here", self.hits, self.misses)
        failed = bool(exc) and exc[0] is not None  # a worker may still be warming up: no wait
        for worker in self._pool:
            worker.close(at_once=failed)
        self._pool = []
        self._inbox = _Inbox()

    def scans(self, scans: Iterable[LaserScan]) -> Iterator[tuple[LaserScan, FeaturesOf]]:
        """Each scan, in order, with a callable returning its features (see the class)."""
        if not self._pool:
            for scan in scans:
                yield scan, self._local(scan)
            return
        pool = self._pool
        ahead = LOOKAHEAD_PER_WORKER * len(pool)
        queue: deque[tuple[int, LaserScan, _Worker | None]] = deque()
        it = iter(scans)
        sent = 0
        exhausted = False
        while True:
            if not exhausted and len(queue) <= ahead // 2:
                # Refill in batches: one message (one wake-up of a worker) per few scans.
                batches: list[list[tuple[int, LaserScan]]] = [[] for _ in pool]
                fresh: list[tuple[int, LaserScan]] = []
                while len(queue) + len(fresh) < ahead:
                    upcoming = next(it, None)
                    if upcoming is None:
                        exhausted = True
                        break
                    batches[sent % len(pool)].append((sent, upcoming))
                    fresh.append((sent, upcoming))
                    sent += 1
                taken: dict[int, _Worker | None] = {}
                for worker, batch in zip(pool, batches, strict=True):
                    worker.drain(self._inbox)
                    if not self.wait:
                        with self._unloaded_wait() as left_s:
                            if left_s is not None:
                                worker.catch_up(self._inbox, left_s)
                    ok = worker.send(batch, self._inbox, block=self.wait)
                    taken.update((i, worker if ok else None) for i, _ in batch)
                queue.extend((i, scan, taken[i]) for i, scan in fresh)
            if not queue:
                return
            index, scan, owner = queue.popleft()
            yield scan, (self._local(scan) if owner is None else self._resolver(index, scan, owner))
            self._inbox.advance(index + 1)

    @contextlib.contextmanager
    def _unloaded_wait(self) -> Iterator[float | None]:
        """The time (seconds) left to wait for the workers while this process has extracted
        no scan itself (its first extraction would load the compiled kernels the workers
        loaded as they started; ``UNLOADED_WAIT_S`` in all), or None: do not wait. The time
        spent in the block is counted against it."""
        if self.misses or self._waited_s >= UNLOADED_WAIT_S:
            yield None
            return
        t0 = time.monotonic()
        try:
            yield UNLOADED_WAIT_S - self._waited_s
        finally:
            self._waited_s += time.monotonic() - t0

    def _local(self, scan: LaserScan) -> FeaturesOf:
        def features() -> ScanFeatures:
            self.misses += 1
            return extract(scan, self.config)

        return features

    def _resolver(self, index: int, scan: LaserScan, worker: _Worker) -> FeaturesOf:
        def features() -> ScanFeatures:
            if self.wait:
                worker.wait_for(index, self._inbox)
            else:
                with self._unloaded_wait() as left_s:
                    if left_s is None:
                        worker.drain(self._inbox)
                    else:
                        worker.wait_for(index, self._inbox, left_s)
            got, products = self._inbox.results.get(index, (None, None))
            if got is not None:
                self.hits += 1
                if products is not None and self.precompute is not None:
                    self.precompute.adopt(scan, got, products)
                return got
            # Not arrived (the worker is behind) or failed: the same computation here (an
            # error is then raised in this process).
            self.misses += 1
            return extract(scan, self.config)

        return features
