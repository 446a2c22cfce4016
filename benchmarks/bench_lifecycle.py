"""Benchmark: the offline map life cycle on MIT CSAIL in two halves (issue 15 acceptance).

Runs the whole log, a session of its first half (A) and a session of its second half alone
(B, in its own odometry frame), then prints the mean Kümmerle et al. 2009 relation errors:

- ``whole`` over all relations, and over the relations within the second half;
- ``continue``: A continued with the second half (``iceg run --continue``), second half;
- ``localize``: the second half localized in A (``iceg localize``), second half;
- ``merge``: A and B merged (``iceg merge``), over all relations, then split into those within
  each half and those across the halves; ``B alone``: B's own run, second half.

Acceptance: continue, localize and merge within 10 % of the whole run (translation and
rotation). About four SLAM runs of half the log each plus one whole run.

Run: ``python benchmarks/bench_lifecycle.py [--work DIR]`` (``--work`` keeps the sessions).
"""

from __future__ import annotations

import argparse
import dataclasses
import os
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from frontends import LaserScan, open_log
from frontends.relations import Relations, read_relations
from iceg import session
from iceg.continuation import continue_scans
from iceg.evaluation import relation_errors
from iceg.localize import fixed_map_of_session, localize_scans
from iceg.merge import merge_sessions
from iceg.slam import Slam
from iceg_common import se2

DATA = Path(
    os.environ.get("ICEG_SHARED_DATA", Path(__file__).resolve().parents[2] / "shared" / "data")
)
FRAME = np.array([5.0, -3.0, 2.0])  # the second half's own odometry frame


def error(
    rel: Relations,
    stamps: np.ndarray,
    poses: np.ndarray,
    start_s: float | None = None,
    part: str = "2nd half",
) -> tuple[float, float, int]:
    """Mean relation error (m, deg) and matched count: over all relations without
    ``start_s``, else over those with both ends after it (``part`` "2nd half"), both before
    it ("1st half") or one on each side ("across")."""
    keep: np.ndarray = np.ones(len(rel.stamps_s), dtype=bool)
    if start_s is not None:
        after = rel.stamps_s >= start_s
        both, either = np.all(after, axis=1), np.any(after, axis=1)
        keep = {"2nd half": both, "1st half": ~either, "across": either & ~both}[part]
    ok = ~np.isnan(poses[:, 0])
    s, _ = relation_errors(stamps[ok], poses[ok], rel.stamps_s[keep], rel.deltas[keep], 1e-3)
    return s.trans_mean_m, s.rot_mean_deg, s.n_matched


def run(scans: list[LaserScan]) -> Slam:
    slam = Slam()
    for scan in scans:
        slam.process(scan)
    slam.finish()
    return slam


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--work", type=Path, default=None, help="Keep the sessions here.")
    args = parser.parse_args()
    log, rel_path = DATA / "mit-csail" / "mit-csail.clf", DATA / "mit-csail" / "mit-csail.relations"
    if not log.is_file():
        print(f"skipped: {log} is absent")
        return 0
    if args.work is not None:
        return report(args.work, log, rel_path)
    with tempfile.TemporaryDirectory(prefix="iceg-lifecycle-") as tmp:
        return report(Path(tmp), log, rel_path)


def report(work: Path, log: Path, rel_path: Path) -> int:
    """Run the five cases with their sessions in ``work`` and print the table."""
    rel = read_relations(rel_path)
    scans = list(open_log(log))
    k = len(scans) // 2
    start = scans[k].stamp_s
    second = [
        dataclasses.replace(s, odom_pose=se2.compose(FRAME, s.odom_pose), source=f"b:{i}")  # type: ignore[arg-type]
        for i, s in enumerate(scans[k:])
    ]
    rows: list[tuple[str, str, tuple[float, float, int], float]] = []
    t = time.perf_counter()
    whole = run(scans).finish()
    rows.append(("whole", "all", error(rel, whole.stamps_s, whole.poses), time.perf_counter() - t))
    rows.append(("whole", "2nd half", error(rel, whole.stamps_s, whole.poses, start), 0.0))
    session.save(run(scans[:k]), work / "A")
    session.save(run(second), work / "B")
    stamps_b, poses_b = session.read(work / "B").trajectory()
    rows.append(("B alone", "2nd half", error(rel, stamps_b, poses_b, start), 0.0))
    t = time.perf_counter()
    c = continue_scans(work / "A", second)
    rows.append(
        ("continue", "2nd half", error(rel, c.stamps_s, c.poses, start), time.perf_counter() - t)
    )
    t = time.perf_counter()
    loc = localize_scans(fixed_map_of_session(session.read(work / "A")), second)
    rows.append(
        (
            "localize",
            "2nd half",
            error(rel, loc.stamps_s, loc.poses, start),
            time.perf_counter() - t,
        )
    )
    t = time.perf_counter()
    folder, _ = merge_sessions(session.read(work / "A"), session.read(work / "B"), work / "merged")
    stamps, poses = session.read(folder).trajectory()
    rows.append(("merge", "all", error(rel, stamps, poses), time.perf_counter() - t))
    for part in ("1st half", "2nd half", "across"):
        rows.append(("merge", part, error(rel, stamps, poses, start, part), 0.0))
    print(f"{'case':10s} {'relations':9s} {'rel m':>8s} {'rel deg':>8s} {'n':>5s} {'time s':>7s}")
    for name, part, (m, deg, n), sec in rows:
        print(f"{name:10s} {part:9s} {m:8.4f} {deg:8.3f} {n:5d} {sec:7.1f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
