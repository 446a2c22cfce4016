"""The later stages' kernels compiled in the feature worker on a new numba cache
(:mod:`iceg.kernel_warmup`): how a new cache is told, and the signatures the warm-up
compiles are the ones a run calls."""

from __future__ import annotations

import gc
import json
import os
import subprocess
import sys
from pathlib import Path

#: In a fresh interpreter (no kernel loaded yet): the signatures of every kernel that
#: ``compile_without_features`` and ``compile_later_stages`` load or compile, then those a
#: short simulated run and its map add to them.
_SCRIPT = r"""
import json
from numba.core.registry import CPUDispatcher
import iceg.features.segmentation, iceg.grid, iceg.landmark_association, iceg.landmark_frames
import iceg.matching._kernels, iceg.node_index, iceg.scan_store, iceg.table_rows
import iceg.visibility
from frontends.simulate import corridor_world, default_trajectory, simulate
from iceg.config import IcegConfig
from iceg.features import extract
from iceg.features.prefetch import warm_up_scan
from iceg.kernel_warmup import compile_later_stages, compile_without_features
from iceg.pipeline import run_scans

MODULES = [iceg.features.segmentation, iceg.grid, iceg.landmark_association,
           iceg.landmark_frames, iceg.matching._kernels, iceg.node_index, iceg.scan_store,
           iceg.table_rows, iceg.visibility]

def signatures():
    return {
        f"{m.__name__}.{k}": {str(s) for s in v.signatures}
        for m in MODULES for k, v in vars(m).items()
        if isinstance(v, CPUDispatcher) and v.py_func.__module__ == m.__name__
    }

cfg = IcegConfig()
cfg = cfg.model_copy(update={"slam": cfg.slam.model_copy(update={"workers": 1})})
scan = warm_up_scan()
features = extract(scan, cfg.features)
before = signatures()
compile_without_features(scan, cfg)
compile_later_stages(scan, features, cfg)
warmed = {k: v - before[k] for k, v in signatures().items()}
world = corridor_world(length_m=12.0)
result = run_scans(simulate(world, trajectory=default_trajectory(world)[:120], seed=3).scans, cfg)
assert result.render_map() is not None
after = signatures()
print(json.dumps({
    "warmed": {k: sorted(v) for k, v in warmed.items() if v},
    "run": {k: sorted(after[k] - before[k] - warmed[k]) for k in after
            if after[k] - before[k] - warmed[k]},
}))
"""


def test_the_warm_up_compiles_the_later_stages_with_the_signatures_a_run_calls() -> None:
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=str(root))
    out = subprocess.run(
        [sys.executable, "-c", _SCRIPT], env=env, capture_output=True, text=True, check=True
    ).stdout
    got = json.loads(out.strip().splitlines()[-1])
    warmed = {k.rsplit(".", 1)[1] for k in got["warmed"]}
    # A run calls no kernel the warm-up compiled with any other argument types: the main
    # process loads from the cache what the worker compiled.
    both = set(got["run"]) & set(got["warmed"])
    assert not both, {k: (got["warmed"][k], got["run"][k]) for k in both}
    # The split: the covariance, the free-space checks, the contradiction test, the feature
    # map, the node index and the grid in the worker ...
    later = {"final_covariances", "ray_wall_check", "finite_points_within"}
    later |= {"associate_scan", "keep_better", "count_observations", "expected_landmarks"}
    later |= {"reference_geometry", "drop_rows_in_place"}
    later |= {"move_point_blocks", "sorted_union", "_trace_scans", "_mark_tiles", "_rows_within"}
    later |= {"_by_distance", "nearest_within", "rows_taking_part"}
    assert later <= warmed, later - warmed
    # ... the hypotheses, the correlation and the refinement in the main process, which the
    # run then compiles (or loads) itself.
    first = {"segment_rotation_peak", "vote_clusters", "correlation_scores", "refine_pose"}
    assert not first & warmed
    assert first <= {k.rsplit(".", 1)[1] for k in got["run"]}


def test_a_new_cache_is_told_from_one_that_holds_the_probe(tmp_path: Path) -> None:
    # An empty NUMBA_CACHE_DIR: the first process compiles the probe kernel and finds the
    # cache new; a second process on the same folder loads it and does not.
    root = Path(__file__).resolve().parents[2]
    env = dict(os.environ, PYTHONPATH=str(root), NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    code = "from iceg.kernel_warmup import cache_is_new; print(cache_is_new(), cache_is_new())"
    answers = [
        subprocess.run(
            [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
        ).stdout.split()
        for _ in range(2)
    ]
    assert answers == [["True", "True"], ["False", "False"]]


def test_numba_s_registry_loads_without_a_full_collection() -> None:
    # A fresh process as a run starts: the probe installs numba's registry (tens of
    # thousands of long-lived objects) with the cyclic collector paused, so no full
    # collection walks the heap for it, and the collector is on again afterwards.
    root = Path(__file__).resolve().parents[2]
    code = (
        "import gc, iceg.pipeline\n"
        "from iceg.kernel_warmup import cache_is_new\n"
        "full = []\n"
        "gc.callbacks.append(lambda phase, info: full.append(info['generation'] == 2))\n"
        "before = len(gc.get_objects())\n"
        "cache_is_new()\n"
        "print(sum(full), len(gc.get_objects()) - before, gc.isenabled())\n"
    )
    env = dict(os.environ, PYTHONPATH=str(root))
    out = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    ).stdout.split()
    assert out[0] == "0" and out[2] == "True"
    assert int(out[1]) > 10_000  # the registry's objects, which a full collection would walk


def test_the_collector_is_left_as_it_was_found() -> None:
    from iceg.kernel_warmup import _collector_paused

    was = gc.isenabled()
    try:
        for enabled in (True, False):
            (gc.enable if enabled else gc.disable)()
            with _collector_paused():
                assert not gc.isenabled()
            assert gc.isenabled() is enabled
    finally:
        (gc.enable if was else gc.disable)()
