"""A search's matches run by a helper process (issue 13): the results are the matcher's,
bit for bit, whichever process ran each match. No timings here: speed is measured by
``benchmarks/bench_pipeline.py``."""

from __future__ import annotations

import copy
import multiprocessing
import os
import signal
import time
from typing import Any

import numpy as np
import pytest

from frontends.simulate import corridor_world, default_trajectory, simulate
from iceg.features import extract
from iceg.match_pool import MatchJob, MatchPool, _serve
from iceg.matching import IceMatcher, MatchBounds, MatchingConfig
from iceg.types import MatchResult, ScanFeatures
from iceg_common.se2 import between


@pytest.fixture(scope="module")
def jobs() -> list[MatchJob]:
    # Scan k matched against scan k - 3 of a simulated corridor run, locally and globally.
    world = corridor_world(length_m=12.0)
    run = simulate(world, trajectory=default_trajectory(world)[:60], seed=5)
    feats = [extract(s) for s in run.scans[::6]]
    poses = run.true_poses[::6]
    out = []
    for k in range(3, len(feats)):
        prediction = between(poses[k - 3], poses[k])
        for bounds in (MatchBounds.local(1.0, 30.0), MatchBounds.global_()):
            out.append(MatchJob(feats[k], feats[k - 3], prediction, bounds))
    return out


def _same(a: MatchResult, b: MatchResult) -> bool:
    return (
        a.success == b.success
        and a.reason == b.reason
        and a.pose.tobytes() == b.pose.tobytes()
        and np.asarray(a.cov).tobytes() == np.asarray(b.cov).tobytes()
        and np.asarray(a.inlier_pairs).tobytes() == np.asarray(b.inlier_pairs).tobytes()
        and a.correlation == b.correlation
    )


def test_submitted_matches_equal_the_matcher_s(jobs: list[MatchJob]) -> None:
    matcher = IceMatcher(MatchingConfig())
    want = [matcher.match(*job) for job in jobs]
    assert sum(r.success for r in want) >= len(jobs) // 2  # real matches, not only failures
    with MatchPool(IceMatcher(MatchingConfig()), wait=True) as pool:
        got = [r for n in (1, 3, 5) for r in pool.collect(pool.submit(jobs[:n]))]
        got_all = pool.collect(pool.submit(jobs))
    assert (pool.remote, pool.local) == (1 + 3 + 5 + len(jobs), 0)  # every one sent
    expect = [r for n in (1, 3, 5) for r in want[:n]]
    assert all(_same(a, b) for a, b in zip(got, expect, strict=True))
    assert all(_same(a, b) for a, b in zip(got_all, want, strict=True))


def _hung(signum: int, frame: object) -> None:
    raise TimeoutError("the pool hung")


def test_a_batch_of_more_results_than_the_pipe_holds_completes(jobs: list[MatchJob]) -> None:
    # 560 matches: their results (about 0.8 KiB pickled each) outgrow the pipe's buffers (a
    # socket pair, 208 KiB each way here). Sent all before any was read, the helper blocked
    # on its full pipe and the caller on the jobs': both hung (measured: this test timed out).
    many = jobs * 40
    matcher = IceMatcher(MatchingConfig())
    want = [matcher.match(*job) for job in many]
    before = signal.signal(signal.SIGALRM, _hung)
    signal.alarm(120)
    try:
        with MatchPool(IceMatcher(MatchingConfig()), wait=True) as pool:
            got = pool.collect(pool.submit(many))
    finally:
        signal.alarm(0)
        signal.signal(signal.SIGALRM, before)
    assert (pool.remote, pool.local) == (len(many), 0)
    assert all(_same(a, b) for a, b in zip(got, want, strict=True))


def test_a_large_batch_is_shared_with_the_helper_in_order(jobs: list[MatchJob]) -> None:
    # run_all: a global placement's batch (every place of a map), every other match sent to
    # the helper as this process runs the one between; odd and even sizes, and without a
    # helper. The results in the jobs' order, the matcher's bit for bit.
    matcher = IceMatcher(MatchingConfig())
    want = [matcher.match(*job) for job in jobs]
    with MatchPool(IceMatcher(MatchingConfig()), wait=True) as pool:
        got = pool.run_all(iter(jobs))
        got_odd = pool.run_all(jobs[:7])
    assert (pool.remote, pool.local) == ((len(jobs) + 1) // 2 + 4, len(jobs) // 2 + 3)
    without = MatchPool(IceMatcher(MatchingConfig()), helper=False).run_all(jobs)
    for results, expect in ((got, want), (got_odd, want[:7]), (without, want)):
        assert len(results) == len(expect)
        assert all(_same(a, b) for a, b in zip(results, expect, strict=True))


class _SharedOnlyInHelper:
    """IceMatcher's matches; in any other process than the one that made it (the helper),
    raising unless the reference is one of ``shared`` itself, the object the helper holds
    from its fork (the same address in both processes; a copy sent through the pipe is
    another object)."""

    def __init__(self, shared: list[ScanFeatures]) -> None:
        self.inner = IceMatcher(MatchingConfig())
        self.home = os.getpid()
        self.shared = {id(ref) for ref in shared}

    def match(self, *args: Any, **kwargs: Any) -> MatchResult:
        if os.getpid() != self.home and id(args[1]) not in self.shared:
            raise RuntimeError("a reference sent, not shared")
        return self.inner.match(*args, **kwargs)


def test_references_shared_before_the_fork_are_named_not_sent(jobs: list[MatchJob]) -> None:
    # A global placement's places, held by the helper from its fork: a job naming one sends
    # its key, and the helper matches the object it holds (a match that fails there runs
    # here, so `local` counts the references that were sent). A copy of a shared reference,
    # another object, is sent. The results are the matcher's either way.
    refs = [job.reference for job in jobs]
    matcher = IceMatcher(MatchingConfig())
    want = [matcher.match(*job) for job in jobs]
    copies = [job._replace(reference=copy.copy(job.reference)) for job in jobs]
    with MatchPool(_SharedOnlyInHelper(refs), wait=True) as pool:
        assert pool.share(refs)
        got = pool.run_all(jobs)
        assert (pool.remote, pool.local) == ((len(jobs) + 1) // 2, len(jobs) // 2)
        assert not pool.share(refs)  # the helper runs: too late to share more
        got_copies = pool.run_all(copies)
    assert (pool.remote, pool.local) == ((len(jobs) + 1) // 2, len(jobs) // 2 + len(jobs))
    assert not MatchPool(matcher, helper=False).share(refs)
    for results in (got, got_copies):
        assert all(_same(a, b) for a, b in zip(results, want, strict=True))


class _MisbehavesInHelper:
    """IceMatcher's matches; in any other process than the one that made it (the helper),
    half a second late (``slow``) or raising."""

    def __init__(self, slow: bool) -> None:
        self.inner = IceMatcher(MatchingConfig())
        self.home = os.getpid()
        self.slow = slow

    def match(self, *args: Any, **kwargs: Any) -> MatchResult:
        if os.getpid() != self.home:
            if not self.slow:
                raise RuntimeError("only in the helper")
            time.sleep(0.5)
        return self.inner.match(*args, **kwargs)


def test_matches_the_helper_has_not_returned_are_run_here(jobs: list[MatchJob]) -> None:
    # The helper is half a second late with every match: the calling process runs the last
    # missing one while several are missing, waits for the one left about as long as a match
    # takes, then runs it too; the helper's late results are dropped (the next batch sees
    # them from an older one).
    matcher = IceMatcher(MatchingConfig())
    with MatchPool(_MisbehavesInHelper(slow=True)) as pool:
        first = pool.collect(pool.submit(jobs[:4]))
        second = pool.collect(pool.submit(jobs[4:8]))
    assert pool.remote == 0 and pool.local == 8
    want = [matcher.match(*job) for job in jobs[:8]]
    assert all(_same(a, b) for a, b in zip(first + second, want, strict=True))


def test_a_match_that_failed_in_the_helper_is_run_here(jobs: list[MatchJob]) -> None:
    # Even when told to wait for the helper: its failure comes back, and the match runs here.
    matcher = IceMatcher(MatchingConfig())
    with MatchPool(_MisbehavesInHelper(slow=False), wait=True) as pool:
        got = pool.collect(pool.submit(jobs[:4]))
    assert pool.remote == 0 and pool.local == 4
    want = [matcher.match(*job) for job in jobs[:4]]
    assert all(_same(a, b) for a, b in zip(got, want, strict=True))


def test_without_a_helper_every_match_runs_here(jobs: list[MatchJob]) -> None:
    matcher = IceMatcher(MatchingConfig())
    want = [matcher.match(*job) for job in jobs[:4]]
    with MatchPool(matcher, helper=False) as pool:
        got = pool.collect(pool.submit(jobs[:4]))
    outside = MatchPool(matcher)  # never entered: no helper is forked
    got_outside = outside.collect(outside.submit(jobs[:4]))
    assert (pool.remote, pool.local) == (outside.remote, outside.local) == (0, 4)
    assert all(_same(a, b) for a, b in zip(got + got_outside, want + want, strict=True))


def test_the_helper_skips_the_jobs_the_calling_process_has_taken(jobs: list[MatchJob]) -> None:
    # The helper loop, run here on a pipe: of batch 1 the calling process has taken jobs 2
    # and 3 (shared [batch, first index]); the helper answers 0 and 1 of it and every job
    # of batch 2, each with the matcher's result. Jobs 2k and 2k + 1 share their features,
    # which come with the first of them only (None: the previous job's). The reference of
    # the last job comes as its key among the references the helper holds (``shared``).
    matcher = IceMatcher(MatchingConfig())
    here, there = multiprocessing.Pipe(duplex=True)
    parent_end, _ = multiprocessing.Pipe(duplex=True)
    taken = multiprocessing.RawArray("q", [1, 2])
    assert all(jobs[i].features is jobs[i + 1].features for i in (0, 2, 4))
    shared = [jobs[0].reference, jobs[5].reference]
    for batch, k, i in [(1, 0, 0), (1, 1, 1), (1, 2, 2), (1, 3, 3), (2, 0, 4)]:
        here.send((batch, k, None if i % 2 else jobs[i].features, jobs[i][1:]))
    here.send((2, 1, None, (1, *jobs[5][2:])))
    here.send(None)
    previous = signal.getsignal(signal.SIGINT)
    try:
        _serve(there, parent_end, os.getpid(), matcher, taken, shared)
    finally:
        signal.signal(signal.SIGINT, previous)
    answered = []
    while here.poll(0):
        batch, k, result, cpu_s = here.recv()
        answered.append((batch, k))
        want = jobs[{1: 0, 2: 4}[batch] + k]
        assert _same(result, matcher.match(*want)) and cpu_s >= 0.0
    assert answered == [(1, 0), (1, 1), (2, 0), (2, 1)]
