"""Feature prefetching in worker processes (issue 13): the result does not depend on the
number of workers (features, and the products computed beside them, never depend on the
pose), bit for bit. No timings here: speed is measured by ``benchmarks/bench_pipeline.py``."""

from __future__ import annotations

import gc
import multiprocessing
import os
import sys
import time
import weakref
from pathlib import Path

import numpy as np
import pytest

from frontends.scan import LaserScan
from frontends.simulate import corridor_world, default_trajectory, simulate
from iceg.config import IcegConfig
from iceg.features import extract
from iceg.features.prefetch import (
    IDLE_SAMPLE_S,
    CoreWatch,
    FeaturePrefetcher,
    _Inbox,
    _warm_up,
    _Worker,
    auto_workers,
    warm_up_scan,
)
from iceg.pipeline import helper_processes, run_log, run_scans
from iceg.scan_products import ScanPrecompute
from iceg.slam import Slam
from iceg.types import FeatureKind, ScanFeatures
from iceg_common.errors import LogFormatError


def _config(workers: int) -> IcegConfig:
    cfg = IcegConfig()
    return cfg.model_copy(update={"slam": cfg.slam.model_copy(update={"workers": workers})})


@pytest.fixture(scope="module")
def short_run():  # type: ignore[no-untyped-def]
    world = corridor_world(length_m=12.0)
    return simulate(world, trajectory=default_trajectory(world)[:120], seed=3)


def test_trajectory_identical_with_one_and_two_workers(short_run) -> None:  # type: ignore[no-untyped-def]
    one = run_scans(short_run.scans, _config(1))
    two = run_scans(short_run.scans, _config(2))
    assert one.poses.tobytes() == two.poses.tobytes()
    assert one.stamps_s.tobytes() == two.stamps_s.tobytes()
    assert one.node_poses.tobytes() == two.node_poses.tobytes()


def test_trajectory_identical_when_every_feature_comes_from_a_worker(short_run) -> None:  # type: ignore[no-untyped-def]
    one = run_scans(short_run.scans, _config(1))
    slam = Slam(_config(2))
    precompute = ScanPrecompute(slam.config)
    with FeaturePrefetcher(
        slam.config.features, workers=2, wait=True, precompute=precompute
    ) as prefetch:
        for scan, features in prefetch.scans(short_run.scans):
            slam.process(scan, features=features)
    two = slam.finish()
    assert prefetch.hits > 0 and prefetch.misses == 0
    assert one.poses.tobytes() == two.poses.tobytes()
    assert one.node_poses.tobytes() == two.node_poses.tobytes()


def test_prefetched_features_equal_extract(short_run) -> None:  # type: ignore[no-untyped-def]
    cfg = IcegConfig().features
    scans = short_run.scans[:30]
    with FeaturePrefetcher(cfg, workers=2, wait=True) as prefetch:
        got = [(scan, features()) for scan, features in prefetch.scans(scans)]
    assert (prefetch.hits, prefetch.misses) == (len(scans), 0)
    assert [s for s, _ in got] == list(scans)
    for scan, feats in got:
        want = extract(scan, cfg)
        for name in ("points_xy", "seg_lines", "seg_cov", "kind", "xy", "cov", "directions"):
            assert (
                np.asarray(getattr(feats, name)).tobytes()
                == np.asarray(getattr(want, name)).tobytes()
            )


class _Cycle:
    """An object in a reference cycle with itself (only the cyclic collector frees it)."""

    def __init__(self) -> None:
        self.me = self


def test_a_run_keeps_the_objects_alive_at_its_start_out_of_the_collector_until_it_ends(
    short_run,  # type: ignore[no-untyped-def]
) -> None:
    gc.collect()
    assert gc.get_freeze_count() == 0
    garbage = _Cycle()
    freed = []
    gone = weakref.ref(garbage, lambda _: freed.append(True))
    with helper_processes(Slam(_config(2)), workers=2) as prefetch:
        # frozen: the cycle dropped during the run is not collected, the run's own are
        assert gc.get_freeze_count() > 0
        del garbage
        later = _Cycle()
        later_gone = weakref.ref(later)
        del later
        gc.collect()
        assert gone() is not None and later_gone() is None
        assert len(list(prefetch.scans(short_run.scans[:3]))) == 3
    assert gc.get_freeze_count() == 0
    gc.collect()
    assert gone() is None and freed == [True]


def test_a_run_leaves_the_callers_own_freeze_alone(short_run) -> None:  # type: ignore[no-untyped-def]
    gc.freeze()
    try:
        frozen = gc.get_freeze_count()
        run_scans(short_run.scans[:10], _config(1))
        # neither unfrozen (0) nor frozen again with the objects made since (more); some
        # frozen objects were freed by their reference counts
        assert 0 < gc.get_freeze_count() <= frozen
    finally:
        gc.unfreeze()


def test_one_worker_has_no_pool(short_run) -> None:  # type: ignore[no-untyped-def]
    with FeaturePrefetcher(IcegConfig().features, workers=1) as prefetch:
        assert not prefetch._pool
        assert len(list(prefetch.scans(short_run.scans[:3]))) == 3


def test_auto_workers_is_one_or_two() -> None:
    assert auto_workers() in (1, 2)


@pytest.mark.parametrize(
    ("allowed", "busy_percent", "workers"),
    [
        ({0, 1}, [3.0, 2.0], 2),  # an idle machine: a core for the run, one for its helpers
        ({0, 1}, [100.0, 1.0], 1),  # another process holds a core: none spare
        ({0, 1}, [40.0, 5.0], 2),  # light background load: more than half a core spare
        ({0, 1, 2, 3}, [100.0, 100.0, 0.0, 0.0], 2),  # two busy cores of four
        ({0, 1, 2, 3}, [100.0, 100.0, 80.0, 0.0], 1),  # 1.2 idle cores: 0.2 spare
        ({2, 3}, [0.0, 0.0, 100.0, 90.0], 1),  # idle cores this process may not run on
        ({0}, [0.0, 0.0], 1),  # one core allowed (taskset): never a second process
    ],
)
def test_auto_workers_counts_the_idle_cores_now(
    monkeypatch: pytest.MonkeyPatch, allowed: set[int], busy_percent: list[float], workers: int
) -> None:
    # The decision reads the use of the cores this process may run on over the next
    # IDLE_SAMPLE_S seconds (psutil, per core), not the load average, which remembers runs
    # that have finished.
    import psutil

    sampled: list[float | None] = []

    def cpu_percent(interval: float | None = None, percpu: bool = False) -> list[float]:
        assert percpu
        sampled.append(interval)
        return busy_percent

    monkeypatch.setattr(psutil, "cpu_percent", cpu_percent)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: allowed)
    monkeypatch.setattr(os, "getloadavg", lambda: (9.0, 9.0, 9.0))  # must not matter
    monkeypatch.setattr(sys, "platform", "linux")
    start = time.monotonic()
    assert auto_workers() == workers
    # psutil's baseline, then its reading IDLE_SAMPLE_S later
    assert sampled == ([None, None] if len(allowed) > 1 else [])
    assert time.monotonic() - start >= (IDLE_SAMPLE_S if len(allowed) > 1 else 0.0)


@pytest.mark.parametrize(("own_cpu_s", "workers"), [(0.0, 1), (0.15, 2)])
def test_a_core_watch_counts_this_process_work_as_idle(
    monkeypatch: pytest.MonkeyPatch, own_cpu_s: float, workers: int
) -> None:
    # Watched through 0.2 s of this process's own work, a core 75 % busy is this process:
    # what it leaves idle is the other core and a quarter of this one, plus the 0.75 core
    # the process used (1.0 + 0.25 + 0.75 = 2.0 cores: room for the run and its helpers).
    # Without the process's work, someone else keeps the core 75 % busy: 1.25 idle cores,
    # fewer than the run and half a core for its helpers. No wait: the 0.2 s are longer
    # than IDLE_SAMPLE_S.
    import psutil

    clock = {"wall": 100.0, "cpu": 5.0}
    monkeypatch.setattr(time, "monotonic", lambda: clock["wall"])
    monkeypatch.setattr(time, "process_time", lambda: clock["cpu"])
    monkeypatch.setattr(time, "sleep", lambda s: pytest.fail(f"waited {s} s"))
    monkeypatch.setattr(psutil, "cpu_percent", lambda interval=None, percpu=False: [75.0, 0.0])
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    monkeypatch.setattr(sys, "platform", "linux")
    watch = CoreWatch()
    clock["wall"] += 0.2
    clock["cpu"] += own_cpu_s
    assert watch.workers() == workers


def test_auto_workers_is_one_where_the_cores_cannot_be_read(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    import psutil

    def unreadable(interval: float | None = None, percpu: bool = False) -> list[float]:
        raise psutil.AccessDenied()

    monkeypatch.setattr(psutil, "cpu_percent", unreadable)
    monkeypatch.setattr(os, "sched_getaffinity", lambda pid: {0, 1})
    monkeypatch.setattr(sys, "platform", "linux")
    assert auto_workers() == 1


def _leaves(value: object) -> list[object]:
    """The arrays and numbers of a (nested) named tuple / dataclass of products, in order."""
    if isinstance(value, np.ndarray) or (
        not hasattr(value, "__dict__") and not isinstance(value, tuple)
    ):
        return [value]
    items = value if isinstance(value, tuple) else vars(value).values()
    return [leaf for item in items for leaf in _leaves(item)]


def test_products_from_a_worker_equal_the_products_computed_here(short_run) -> None:  # type: ignore[no-untyped-def]
    cfg = IcegConfig()
    precompute = ScanPrecompute(cfg)
    adopted: list[tuple[LaserScan, ScanFeatures, object]] = []

    class Recording(ScanPrecompute):
        def adopt(self, scan, features, products):  # type: ignore[no-untyped-def]
            adopted.append((scan, features, products))
            super().adopt(scan, features, products)

    scans = short_run.scans[:20]
    with FeaturePrefetcher(cfg.features, 2, wait=True, precompute=Recording(cfg)) as prefetch:
        got = [features() for _, features in prefetch.scans(scans)]
    assert [a[1] for a in adopted] == got  # adopted with the features handed out
    for scan, _, products in adopted:
        want = precompute.compute(scan, extract(scan, cfg.features))
        leaves, want_leaves = _leaves(products), _leaves(want)
        assert len(leaves) == len(want_leaves) > 10
        for a, b in zip(leaves, want_leaves, strict=True):
            if isinstance(b, np.ndarray):
                assert a.dtype == b.dtype and a.tobytes() == b.tobytes()
            else:
                assert a == b or (a != a and b != b)  # NaN equals NaN here


class _Bulky:
    """Products of 4 MB a scan: a few fill the pipe, so a worker blocks on sending them."""

    def compute(self, scan: LaserScan, features: ScanFeatures) -> np.ndarray:
        return np.zeros(500_000)

    def adopt(self, scan: LaserScan, features: ScanFeatures, products: np.ndarray) -> None:
        pass


def test_closing_reads_what_a_blocked_worker_still_sends(short_run) -> None:  # type: ignore[no-untyped-def]
    # Nothing is read before the prefetcher closes: the worker is blocked on a full pipe
    # and exits on its own (exit code 0) only if closing reads its results meanwhile; else
    # it is terminated (exit code -SIGTERM).
    with FeaturePrefetcher(IcegConfig().features, 2, precompute=_Bulky()) as prefetch:
        next(iter(prefetch.scans(short_run.scans)))
        workers = list(prefetch._pool)
    assert [w.proc.exitcode for w in workers] == [0]


def test_the_warm_up_scan_has_walls_corners_and_ends_of_wall() -> None:
    # A worker extracts it as it starts, to load the kernels of every kind of feature: the
    # room's two far corners and the doorway's two ends of wall.
    feats = extract(warm_up_scan(), IcegConfig().features)
    kinds = feats.kind.tolist()
    assert kinds.count(int(FeatureKind.CORNER)) >= 2
    assert kinds.count(int(FeatureKind.EOW)) >= 2
    assert feats.seg_endpoints.shape[0] >= 3


def test_a_worker_warms_the_later_stages_around_its_extraction_only_when_asked() -> None:
    # On a new numba cache (later=True) the worker compiles the later stages' kernels: those
    # that need no features before its warm-up extraction, the others with the warm-up scan
    # and its features after it. Otherwise it only extracts.
    cfg = IcegConfig()
    calls: list[tuple[str, LaserScan, ScanFeatures | None]] = []

    class Recording(ScanPrecompute):
        def warm_up_without_features(self, scan: LaserScan) -> None:
            calls.append(("without", scan, None))

        def warm_up_with_features(self, scan: LaserScan, features: ScanFeatures) -> None:
            calls.append(("with", scan, features))

    _warm_up(cfg.features, Recording(cfg), True)
    assert [c[0] for c in calls] == ["without", "with"]
    want = warm_up_scan()
    assert all(np.array_equal(c[1].ranges_m, want.ranges_m) for c in calls)
    feats = calls[1][2]
    assert feats is not None and np.array_equal(feats.xy, extract(want, cfg.features).xy)
    _warm_up(cfg.features, Recording(cfg), False)
    assert len(calls) == 2


def test_a_bounded_wait_for_a_worker_returns_without_the_result_it_never_gets() -> None:
    # Nothing was sent: the wait gives up after its timeout, and the worker stays usable.
    worker = _Worker(IcegConfig().features, None, [], multiprocessing.RawValue("q", 0))
    inbox = _Inbox()
    try:
        worker.wait_for(0, inbox, timeout_s=0.05)
        assert 0 not in inbox.results and worker.alive
    finally:
        worker.close()


def test_a_worker_skips_the_scans_the_calling_process_has_passed() -> None:
    # The calling process is at scan 2 (its shared floor): the worker answers scans 0 and 1
    # without extracting them, and extracts 2 and 3 as the calling process would.
    config = IcegConfig().features
    floor = multiprocessing.RawValue("q", 2)
    worker = _Worker(config, None, [], floor)
    inbox = _Inbox()  # this inbox keeps every answer
    scan = warm_up_scan()
    try:
        assert worker.send([(k, scan) for k in range(4)], inbox, block=False)
        worker.wait_for(3, inbox, timeout_s=60.0)
        assert inbox.results[0] == (None, None) and inbox.results[1] == (None, None)
        want = extract(scan, config)
        for k in (2, 3):
            got = inbox.results[k][0]
            assert got is not None and np.array_equal(got.xy, want.xy)
    finally:
        worker.close()


def test_a_log_that_fails_to_read_leaves_no_worker_behind(tmp_path: Path) -> None:
    # The feature worker starts before the log is read; a log that fails stops it at once
    # (it may still be loading its kernels), and no helper process is left.
    bad = tmp_path / "bad.clf"
    bad.write_text("FLASER 3 1.0 1.0 abc 0 0 0 0 0 0 0 0 1.0 host 1.0\n")
    with pytest.raises(LogFormatError, match=r"bad\.clf:1"):
        run_log(bad, _config(2))
    assert multiprocessing.active_children() == []
