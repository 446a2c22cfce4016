"""Feature prefetching in worker processes (issue 13): the result does not depend on the
number of workers (features never depend on the pose), bit for bit. No timings here:
speed is measured by ``benchmarks/bench_pipeline.py``."""

from __future__ import annotations

import numpy as np
import pytest

from frontends.simulate import corridor_world, default_trajectory, simulate
from iceg.config import IcegConfig
from iceg.features import extract
from iceg.features.prefetch import FeaturePrefetcher, auto_workers
from iceg.pipeline import run_scans
from iceg.slam import Slam


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
    with FeaturePrefetcher(slam.config.features, workers=2, wait=True) as prefetch:
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


def test_one_worker_has_no_pool(short_run) -> None:  # type: ignore[no-untyped-def]
    with FeaturePrefetcher(IcegConfig().features, workers=1) as prefetch:
        assert not prefetch._pool
        assert len(list(prefetch.scans(short_run.scans[:3]))) == 3


def test_auto_workers_is_one_or_two() -> None:
    assert auto_workers() in (1, 2)
