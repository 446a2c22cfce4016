"""Benchmark: ICE matching of consecutive MIT CSAIL keyframes against a local feature map.

The 1988 raw scans (361 beams) are thinned to keyframes (every 0.3 m or 10 deg of odometry);
each keyframe is matched against a :class:`~iceg.feature_map.FeatureMap` reference built
from the last four nodes (landmarks and segments), with the odometry delta as prediction
and bounds of 0.5 m / 15 deg, and then added to the map (node poses chained from the
matches, as a front-end without the graph would). Only ``IceMatcher.match`` is timed.

Prints, for a reference of the nodes' segments and landmarks (the default) and for one that
also carries the nodes' points (``FeatureMapConfig(reference_points=True)``): the numba
compile/cache-load time of the first match, the median, 95th percentile and mean of
``match`` (wall clock, best of 3 passes over the same keyframes, so that other processes on
the shared machine disturb it less), the success rate and failure reasons; then one pass of
the compiled point-to-line system (association + GLS normal equations), the body of each
Gauss-Newton iteration, against the library's numpy association alone on the same data.
Target: median <= 2 ms.

Run: ``/work/venv/bin/python benchmarks/bench_matching.py [path/to/mit-csail.clf]``
"""

from __future__ import annotations

import math
import sys
import time
from collections import Counter
from pathlib import Path

import numpy as np

from frontends import open_log
from iceg.feature_map import FeatureMap, FeatureMapConfig
from iceg.features import extract
from iceg.matching import IceMatcher, MatchBounds
from iceg.matching._kernels import (
    LineSegments,
    SegmentPoints,
    no_segment_grid,
    point_line_system,
)
from iceg.matching.geometry import SegmentSet, associate_points, point_segment_index, rot
from iceg.matching.refine import effective_line_cov
from iceg_common.se2 import between, compose

DEFAULT_LOG = (
    Path(__file__).resolve().parents[2] / "shared" / "data" / "mit-csail" / "mit-csail.clf"
)
LOCAL_NODES = 4
BOUNDS = MatchBounds.local(0.5, 15.0)


def build_jobs(path: Path, config: FeatureMapConfig | None = None) -> list[tuple]:
    """Keyframes with their features, the local-map reference and the prediction."""
    fmap = FeatureMap(config)
    matcher = IceMatcher()
    poses: dict[int, np.ndarray] = {}
    jobs = []
    last_odom: np.ndarray | None = None
    for scan in open_log(path):
        odom = scan.odom_pose
        if odom is None:
            raise SystemExit(f"{scan.source}: the benchmark needs odometry poses")
        if last_odom is not None:
            d = between(last_odom, odom)
            if math.hypot(d[0], d[1]) < 0.3 and abs(d[2]) < math.radians(10):
                continue
        feats = extract(scan)
        node = len(poses)
        if last_odom is None:
            poses[0] = odom.copy()
            fmap.update(0, feats, scan.stamp_s, scan=scan)
        else:
            pred = between(last_odom, odom)
            ref = fmap.reference(poses, range(max(0, node - LOCAL_NODES), node), poses[node - 1])
            res = matcher.match(feats, ref.features, pred, BOUNDS)
            poses[node] = compose(poses[node - 1], res.pose if res.success else pred)
            fmap.update(
                node,
                feats,
                scan.stamp_s,
                reference=ref,
                match=res,
                scan=scan,
                node_poses=poses,
            )
            jobs.append((feats, ref.features, pred))
        last_odom = odom
    return jobs


def kernel_comparison(jobs: list[tuple], matcher: IceMatcher) -> tuple[float, float]:
    """Median time (ms) of one compiled association + normal-equation pass, and of the
    library's numpy association (``geometry.associate_points``) alone."""
    s = matcher._settings
    kernel = s.kernel()
    t_nb, t_np = [], []
    for feats, ref, pred in jobs:
        pseg = point_segment_index(feats)
        on = np.flatnonzero(pseg >= 0)
        if on.shape[0] < 10 or ref.n_segments == 0:
            continue
        pts, pal = feats.points_xy[on], feats.seg_lines[pseg[on], 0]
        segs = SegmentSet.from_features(ref)
        info = np.linalg.inv(effective_line_cov(segs, 0.0) + 1e-12 * np.eye(2))
        lines = LineSegments(
            segs.a, segs.u, segs.length, segs.normal, segs.rho, info, no_segment_grid()
        )
        t0 = time.perf_counter()
        point_line_system(pred, SegmentPoints(pts, pal), lines, s.gate_m, 0.01, kernel)
        t1 = time.perf_counter()
        q = pts @ rot(pred[2]).T + pred[:2]
        associate_points(q, pal + pred[2], segs, s.gate_m, s.end_tol_m, s.normal_gate_rad)
        t2 = time.perf_counter()
        t_nb.append(t1 - t0)
        t_np.append(t2 - t1)
    return 1e3 * float(np.median(t_nb)), 1e3 * float(np.median(t_np))


def time_matches(jobs: list[tuple], matcher: IceMatcher) -> tuple[np.ndarray, int, Counter[str]]:
    """Best-of-3 wall time (ms) of each match, successes and failure reasons."""
    best = np.full(len(jobs), np.inf)
    reasons: Counter[str] = Counter()
    n_ok = 0
    for rep in range(3):
        for k, (feats, ref, pred) in enumerate(jobs):
            t = time.perf_counter()
            res = matcher.match(feats, ref, pred, BOUNDS)
            best[k] = min(best[k], time.perf_counter() - t)
            if rep == 0:
                n_ok += res.success
                if not res.success:
                    reasons[res.reason.split(":")[0]] += 1
    return 1e3 * best, n_ok, reasons


def main() -> None:
    path = Path(sys.argv[1]) if len(sys.argv) > 1 else DEFAULT_LOG
    if not path.is_file():
        print(f"log {path} not found (it lives in ../shared/data beside the repo)")
        return
    matcher = IceMatcher()
    for label, cfg in (
        ("segments and landmarks (default FeatureMapConfig)", FeatureMapConfig()),
        ("plus the nodes' points (reference_points=True)", FeatureMapConfig(reference_points=True)),
    ):
        t0 = time.perf_counter()
        jobs = build_jobs(path, cfg)
        print(f"== reference: {label}")
        print(
            f"{len(jobs)} keyframes matched against the last {LOCAL_NODES} nodes (setup incl. "
            f"feature extraction and map updates {time.perf_counter() - t0:.1f} s)"
        )
        feats, ref, pred = jobs[0]
        t0 = time.perf_counter()
        matcher.match(feats, ref, pred, BOUNDS)
        print(
            f"first match (numba cache load or compile): {1e3 * (time.perf_counter() - t0):.1f} ms"
        )
        ms, n_ok, reasons = time_matches(jobs, matcher)
        print(
            f"match time: median {np.median(ms):.2f} ms, 95th percentile "
            f"{np.percentile(ms, 95):.2f} ms, mean {ms.mean():.2f} ms, max {ms.max():.2f} ms "
            f"(target: median <= 2 ms)"
        )
        print(
            f"succeeded: {n_ok}/{len(jobs)} ({100 * n_ok / len(jobs):.1f} %); "
            f"failures: {dict(reasons)}"
        )
        print(
            f"reference size (median): {np.median([j[1].n_features for j in jobs]):.0f} "
            f"landmarks, {np.median([j[1].n_segments for j in jobs]):.0f} segments, "
            f"{np.median([j[1].points_xy.shape[0] for j in jobs]):.0f} points; new scan: "
            f"{np.median([j[0].points_xy.shape[0] for j in jobs]):.0f} points, "
            f"{np.median([j[0].n_features for j in jobs]):.0f} features"
        )
    t_nb, t_np = kernel_comparison(jobs, matcher)
    print(
        f"one pass: compiled association + normal equations {t_nb:.3f} ms; numpy association "
        f"alone {t_np:.3f} ms ({t_np / t_nb:.0f}x)"
    )


if __name__ == "__main__":
    main()
