"""Benchmark: every available scan matcher (``matching.method``) on the same graph back-end.

1. **Pipeline**: MIT CSAIL (raw odometry, Kümmerle et al. 2009 relations) through
   :class:`iceg.slam.Slam` once per method, as one ``iceg batch`` (``iceg.batch.run_batch``,
   a local process pool or Ray): mean relation error, failed local scan matches, keyframes
   with a scan-match factor, ms per scan (wall time of the run over its scans, with
   ``--workers`` runs side by side) and loop closures accepted.
2. **Matchers alone**: scan pairs of the simulated scenarios (office, corridor, outdoor,
   long_corridor; seed 0) a given path length apart (0.3, 0.6, 1.1 m), matched from the
   identity (no prediction, global bounds, as the global-matching tests do): the rate of
   correct matches (within 5 cm and 1 deg of the truth), of wrong ones (success but off),
   the mean position error of the correct ones and ms per match.

Peer libraries (``pip install 'iceg[peers]'``): small_gicp, kiss-icp, open3d; a method whose
library does not import is left out. Real logs come from ``../shared/data`` (or
``$ICEG_SHARED_DATA``).

Run: ``python benchmarks/bench_matchers.py [--out DIR] [--workers N] [--ray] [--pairs N]
[--skip-pipeline]``.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from frontends.simulate import simulate_scenario
from iceg.batch import run_batch, spec_from_dict
from iceg.features import extract
from iceg.matching import MatchBounds, MatchingConfig
from iceg.matching.peers import available_methods, make_matcher, peer_version
from iceg.types import ScanFeatures
from iceg_common.se2 import between

DATA = Path(
    os.environ.get("ICEG_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)
WORLDS = ("office", "corridor", "outdoor", "long_corridor")
GAPS_M = (0.3, 0.6, 1.1)
#: A match is correct within this of the truth.
CORRECT_M = 0.05
CORRECT_DEG = 1.0

Pair = tuple[np.ndarray, ScanFeatures, ScanFeatures]


def _version(method: str) -> str:
    return peer_version(method) or "(iceg)"


# ---------------------------------------------------------------------------- pipeline


def pipeline_table(out: Path, methods: Sequence[str], workers: int, ray: bool) -> str:
    """CSAIL once per method as one batch; the table."""
    log, rel = DATA / "mit-csail" / "mit-csail.clf", DATA / "mit-csail" / "mit-csail.relations"
    if not log.is_file():
        return f"(pipeline skipped: {log} is absent)"
    spec = spec_from_dict(
        {
            "name": "matchers-csail",
            "logs": [{"path": str(log), "relations": str(rel), "name": "csail"}],
            "grid": {"matching.method": list(methods)},
            "outputs": "metrics",
        }
    )
    report = run_batch(spec, out, executor="ray" if ray else "local", workers=workers)
    lines = [
        "| method | version | rel m | rel deg | sm failures | sm/kf | ms/scan | LC acc | status |",
        "|---|---|---|---|---|---|---|---|---|",
    ]
    for row, method in zip(report.rows, methods, strict=True):
        m = row["metrics"]
        ms = 1e3 * row["seconds"] / m["scans"] if m.get("scans") else math.nan
        lines.append(
            f"| {method} | {_version(method)} | {m.get('rel_trans_m', math.nan):.4f} | "
            f"{m.get('rel_rot_deg', math.nan):.3f} | {m.get('match_failures', '-')} | "
            f"{m.get('sm_per_kf', math.nan):.3f} | {ms:.1f} | {m.get('lc_accepted', '-')} | "
            f"{row['status']} {row['error']} |"
        )
    return "\n".join(lines)


# ---------------------------------------------------------------------------- matchers alone


def scenario_pairs(world: str, gap_m: float, n: int) -> list[Pair]:
    """``n`` scan pairs of the scenario's run ``gap_m`` metres of path apart, evenly spread:
    the true relative pose and both scans' features."""
    run = simulate_scenario(world, 0)
    poses = np.asarray(run.true_poses)
    path = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(poses[:, :2], axis=0).T))])
    ends = np.searchsorted(path, path + gap_m)
    starts = np.flatnonzero(ends < len(poses))
    out = []
    for i in starts[np.linspace(0, len(starts) - 1, n).astype(int)]:
        j = int(ends[i])
        out.append((between(poses[i], poses[j]), extract(run.scans[i]), extract(run.scans[j])))
    return out


def score(method: str, pairs: Sequence[Pair]) -> dict[str, float]:
    """Correct and wrong rates, mean error (m) of the correct matches, ms per match."""
    matcher = make_matcher(MatchingConfig.model_validate({"method": method}))
    matcher.match(pairs[0][2], pairs[0][1], np.zeros(3), MatchBounds.global_())  # warm up
    good, wrong, errs, t = 0, 0, [], 0.0
    for truth, fa, fb in pairs:
        t0 = time.perf_counter()
        res = matcher.match(fb, fa, np.zeros(3), MatchBounds.global_())
        t += time.perf_counter() - t0
        if not res.success:
            continue
        e = between(truth, res.pose)
        err = math.hypot(e[0], e[1])
        if err <= CORRECT_M and abs(math.degrees(e[2])) <= CORRECT_DEG:
            good += 1
            errs.append(err)
        else:
            wrong += 1
    n = len(pairs)
    return {
        "correct": good / n,
        "wrong": wrong / n,
        "err_m": float(np.mean(errs)) if errs else math.nan,
        "ms": 1e3 * t / n,
    }


def matcher_table(methods: Sequence[str], n_pairs: int) -> str:
    """The matchers alone on the scenario pairs, one row per method and gap."""
    pairs = {g: [p for w in WORLDS for p in scenario_pairs(w, g, n_pairs)] for g in GAPS_M}
    lines = [
        "| method | gap m | pairs | correct % | wrong % | error cm | ms/match |",
        "|---|---|---|---|---|---|---|",
    ]
    for method in methods:
        for g in GAPS_M:
            s = score(method, pairs[g])
            lines.append(
                f"| {method} | {g} | {len(pairs[g])} | {100 * s['correct']:.0f} | "
                f"{100 * s['wrong']:.0f} | {100 * s['err_m']:.2f} | {s['ms']:.1f} |"
            )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0] if __doc__ else None)
    ap.add_argument("--out", type=Path, default=Path("results/bench-matchers"))
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument("--ray", action="store_true", help="run the CSAIL batch on Ray")
    ap.add_argument("--pairs", type=int, default=15, help="pairs per world and gap")
    ap.add_argument("--skip-pipeline", action="store_true")
    args = ap.parse_args(argv)
    methods = available_methods()
    versions = ", ".join(f"{m} {_version(m)}" for m in methods)
    out: list[Any] = [f"methods: {versions}", ""]
    if not args.skip_pipeline:
        out += [
            "## MIT CSAIL through the pipeline",
            "",
            pipeline_table(args.out, methods, args.workers, args.ray),
            "",
        ]
    out += [
        f"## Matchers alone: scenario pairs ({', '.join(WORLDS)}), from the identity",
        "",
        matcher_table(methods, args.pairs),
    ]
    sys.stdout.write("\n".join(out) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
