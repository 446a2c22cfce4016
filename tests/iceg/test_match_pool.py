"""A search's matches shared with a helper process (issue 13): the results are the matcher's,
bit for bit, whichever process ran each match. No timings here: speed is measured by
``benchmarks/bench_pipeline.py``."""

from __future__ import annotations

import functools
import os
import time
from typing import Any

import numpy as np
import pytest

from frontends.simulate import corridor_world, default_trajectory, simulate
from iceg.features import extract
from iceg.match_pool import MatchJob, MatchPool
from iceg.matching import IceMatcher, MatchBounds, MatchingConfig
from iceg.types import MatchResult
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


def _thunks(jobs: list[MatchJob]) -> list[functools.partial[MatchJob]]:
    return [functools.partial(lambda j: j, job) for job in jobs]


def test_shared_matches_equal_the_matcher_s(jobs: list[MatchJob]) -> None:
    matcher = IceMatcher(MatchingConfig())
    want = [matcher.match(*job) for job in jobs]
    assert sum(r.success for r in want) >= len(jobs) // 2  # real matches, not only failures
    with MatchPool(IceMatcher(MatchingConfig()), wait=True) as pool:
        got = [r for n in (2, 3, 5) for r in pool.map(_thunks(jobs[:n]))]
        got_all = pool.map(_thunks(jobs))
    assert pool.remote == 1 + 1 + 2 + len(jobs) // 2  # the first half of each call
    expect = [r for n in (2, 3, 5) for r in want[:n]]
    assert all(_same(a, b) for a, b in zip(got, expect, strict=True))
    assert all(_same(a, b) for a, b in zip(got_all, want, strict=True))


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
    # The helper is half a second late with every match: the calling process waits as long as
    # one of its own took, then runs the rest itself; the helper's late results are dropped
    # (the next map call sees them from an older batch).
    matcher = IceMatcher(MatchingConfig())
    with MatchPool(_MisbehavesInHelper(slow=True)) as pool:
        first = pool.map(_thunks(jobs[:4]))
        second = pool.map(_thunks(jobs[4:8]))
    assert pool.remote == 0 and pool.local == 8
    want = [matcher.match(*job) for job in jobs[:8]]
    assert all(_same(a, b) for a, b in zip(first + second, want, strict=True))


def test_a_match_that_failed_in_the_helper_is_run_here(jobs: list[MatchJob]) -> None:
    # Even when told to wait for the helper: its failure comes back, and the match runs here.
    matcher = IceMatcher(MatchingConfig())
    with MatchPool(_MisbehavesInHelper(slow=False), wait=True) as pool:
        got = pool.map(_thunks(jobs[:4]))
    assert pool.remote == 0 and pool.local == 4
    want = [matcher.match(*job) for job in jobs[:4]]
    assert all(_same(a, b) for a, b in zip(got, want, strict=True))


def test_without_a_helper_every_match_runs_here(jobs: list[MatchJob]) -> None:
    with MatchPool(IceMatcher(MatchingConfig()), helper=False) as pool:
        pool.map(_thunks(jobs[:4]))
    assert (pool.remote, pool.local) == (0, 4)
