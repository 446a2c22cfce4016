"""Benchmark: the whole pipeline on the MIT CSAIL log (1988 scans, 361 beams).

Prints the end-to-end wall time (log reading, SLAM, batch refinement, grid), scans per
second, the time per stage, and the Kümmerle et al. 2009 relation errors. Targets (issue 7):
end to end at most 30 s on the 2-core machine (Cartographer: 35 s), mean relation error at
most 0.10 m and 1.0 deg (Cartographer: 0.032 m, 0.37 deg).

Run: ``python benchmarks/bench_pipeline.py [path/to/mit-csail.clf [path/to/relations]]``
"""

from __future__ import annotations

import sys
import time
from pathlib import Path

from iceg.pipeline import run_log

DATA = Path(__file__).resolve().parents[2] / "shared" / "data" / "mit-csail"


def main() -> None:
    log = Path(sys.argv[1]) if len(sys.argv) > 1 else DATA / "mit-csail.clf"
    rel = Path(sys.argv[2]) if len(sys.argv) > 2 else DATA / "mit-csail.relations"
    t0 = time.perf_counter()
    result = run_log(log, relations=rel)
    wall = time.perf_counter() - t0
    print(f"log: {log}")
    print(
        f"end to end: {wall:.2f} s for {result.n_scans} scans ({result.n_scans / wall:.1f} scans/s)"
    )
    print("time per stage (s):")
    for stage, seconds in sorted(result.stage_seconds.items(), key=lambda kv: -kv[1]):
        print(f"  {stage:<18} {seconds:7.3f}")
    r = result.metrics["relations"]
    print(
        f"relation error: {r['trans_mean_m']:.4f} ± {r['trans_std_m']:.4f} m, "
        f"{r['rot_mean_deg']:.3f} ± {r['rot_std_deg']:.3f} deg "
        f"({r['n_matched']}/{r['n_relations']} relations)"
    )
    print(repr(result))


if __name__ == "__main__":
    main()
