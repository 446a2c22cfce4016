"""Feature extraction ahead of the pipeline, in worker processes (issue 13).

A scan's ICE features depend on the scan and the feature configuration only, never on the
pose estimate, so they can be computed while the main process matches the previous scans.
:class:`FeaturePrefetcher` submits the scans a few places ahead to a process pool and hands
each scan back with a callable that returns its features: the worker's result when it is
ready, else (the pool still starting, or a worker failed) :func:`extract` run in the calling
process. Both are the same computation on the same inputs, so the features, and every result
of the run, are bit for bit those of a run without workers, whatever the timing.

Processes rather than threads: most of the extraction is small numpy operations that hold
the GIL. The workers are forked (Linux only; elsewhere, or if the pool breaks, the calling
process extracts alone): a forked worker starts at once with the package and its compiled
kernels loaded and never re-runs the user's ``__main__`` script, which ``spawn`` and
``forkserver`` would (a script without an ``if __name__ == "__main__"`` guard would run
twice). The workers only extract features (numpy and numba, no gtsam, no threads of the
parent), which is what makes forking a process that may hold other threads safe here.
"""

from __future__ import annotations

import logging
import multiprocessing
import signal
import sys
from collections import deque
from collections.abc import Callable, Iterable, Iterator
from concurrent.futures import Future, ProcessPoolExecutor
from concurrent.futures.process import BrokenProcessPool

from frontends.scan import LaserScan
from iceg.features.config import FeatureConfig
from iceg.features.extract import extract
from iceg.types import ScanFeatures

log = logging.getLogger(__name__)

#: Scans submitted ahead of the one being processed, per worker process.
LOOKAHEAD_PER_WORKER = 8

FeaturesOf = Callable[[], ScanFeatures]


class FeaturePrefetcher:
    """Extract features of upcoming scans in ``workers - 1`` processes.

    Use as a context manager (the pool is shut down on exit)::

        with FeaturePrefetcher(config.features, workers=2) as prefetch:
            for scan, features in prefetch.scans(log):
                slam.process(scan, features=features)

    ``features()`` returns exactly ``extract(scan, config)``; it is only worth calling for
    scans that need features (keyframes), the others' results are dropped.

    Args:
        config: The feature configuration (as ``extract`` takes it).
        workers: Processes in all, the calling one included: 1 extracts in the calling
            process only (no pool).
        wait: Wait for a worker's result rather than extracting in the calling process
            when it is not ready (for tests; slower while the pool starts).

    Attributes:
        hits: Features taken from a worker so far.
        misses: Features extracted in the calling process instead (pool starting, worker
            behind or failed).
    """

    def __init__(self, config: FeatureConfig, workers: int, wait: bool = False) -> None:
        self.config = config
        self.workers = max(1, int(workers))
        self.wait = wait
        self.hits = 0
        self.misses = 0
        self._pool: ProcessPoolExecutor | None = None

    def __enter__(self) -> FeaturePrefetcher:
        if self.workers > 1 and sys.platform == "linux":
            ctx = multiprocessing.get_context("fork")
            self._pool = ProcessPoolExecutor(
                max_workers=self.workers - 1, mp_context=ctx, initializer=_worker_init
            )
        return self

    def __exit__(self, *exc: object) -> None:
        if self._pool is not None:
            log.debug("feature prefetch: %d from workers, %d here", self.hits, self.misses)
            self._pool.shutdown(wait=True, cancel_futures=True)
            self._pool = None

    def scans(self, scans: Iterable[LaserScan]) -> Iterator[tuple[LaserScan, FeaturesOf]]:
        """Each scan, in order, with a callable returning its features (see the class)."""
        if self._pool is None:
            for scan in scans:
                yield scan, self._local(scan)
            return
        pool = self._pool
        ahead = LOOKAHEAD_PER_WORKER * (self.workers - 1)
        queue: deque[tuple[LaserScan, Future[ScanFeatures] | None]] = deque()
        it = iter(scans)
        exhausted = broken = False
        while True:
            while not exhausted and len(queue) <= ahead:
                upcoming = next(it, None)
                if upcoming is None:
                    exhausted = True
                    break
                future = None
                if not broken:
                    try:
                        future = pool.submit(extract, upcoming, self.config)
                    except (BrokenProcessPool, RuntimeError) as exc:
                        log.warning("feature prefetch off (%s); extracting here", exc)
                        broken = True
                queue.append((upcoming, future))
            if not queue:
                return
            scan, fut = queue.popleft()
            yield scan, self._local(scan) if fut is None else self._resolver(scan, fut)

    def _local(self, scan: LaserScan) -> FeaturesOf:
        def features() -> ScanFeatures:
            self.misses += 1
            return extract(scan, self.config)

        return features

    def _resolver(self, scan: LaserScan, future: Future[ScanFeatures]) -> FeaturesOf:
        def features() -> ScanFeatures:
            if self.wait:
                try:
                    out = future.result()
                except Exception:  # recomputed below, which raises the error in this process
                    pass
                else:
                    self.hits += 1
                    return out
            elif future.done() and not future.cancelled() and future.exception() is None:
                self.hits += 1
                return future.result()
            self.misses += 1
            # Not ready (the pool is starting) or failed: the same computation here (an
            # error is then raised with this process's traceback).
            future.cancel()
            return extract(scan, self.config)

        return features


def _worker_init() -> None:
    """A worker ignores Ctrl-C: the main process handles it (and shuts the pool down)."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
