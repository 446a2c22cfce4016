"""Benchmark: does ``iceg merge`` merge the right sessions and refuse the wrong ones? (issue 15)

Each case splits one log into two sessions A and B (B in its own odometry frame), merges B
into A and prints what decided the merge and how right it is:

- ``placed``: the size of the agreeing group of B's placements in A's map (or the reason the
  placements refused the merge);
- ``B thru A`` / ``A thru B``: the most nodes of one session that saw a wall one step of the
  other robot's path passes through, at the merged estimates (``merge.wall_crossings``;
  refused when both reach ``feature_map.min_expected``);
- ``verdict``: merged or refused, and by which rule;
- ``ATE m`` / ``max m``: the merged trajectory against the truth or the reference, after one
  rigid alignment of the whole (a wrong alignment of B shows as metres), for every case
  whether refused or not;
- ``time s``: sessions and merge.

Cases: the simulated office (a floor that is almost its own mirror image, with little overlap
between its halves; seeds 0-9, and splits at a third and two thirds), the biased office (seeds
0-9), the two-loop (halves and two thirds) and open-loops worlds (seeds 0-2; exact truth);
MIT CSAIL's halves (raw odometry; no reference here, ``bench_lifecycle.py`` scores their
relations); the corrected ACES, csail.log and csail-corrected logs with synthetic biased
odometry (reference: the corrected poses).

Run: ``python benchmarks/bench_merge.py [--only NAME ...]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

import numpy as np
from bench_accuracy import DATA, SYNTH_BIASED  # this folder is on the path of a script
from numpy.typing import NDArray

from frontends import LaserScan, open_log
from frontends.simulate import simulate_scenario, synthetic_odometry
from iceg import session
from iceg.evaluation import position_errors
from iceg.merge import find_closures, merge_arrays, wall_crossings
from iceg.session import Session
from iceg.slam import Slam
from iceg_common import se2
from iceg_common.errors import SessionError

FRAME = np.array([5.0, -3.0, 2.0])  # B's own odometry frame
Case = Callable[[], tuple[list[LaserScan], NDArray[np.float64] | None]]


def _shared(relative: str) -> Path:
    path = DATA / relative
    if not path.is_file():
        raise FileNotFoundError(f"{path} is absent")
    return path


def _sim(name: str, seed: int) -> Case:
    def build() -> tuple[list[LaserScan], NDArray[np.float64] | None]:
        run = simulate_scenario(name, seed)
        return list(run.scans), run.true_poses

    return build


def _corrected(relative: str, restamp_hz: float | None) -> Case:
    def build() -> tuple[list[LaserScan], NDArray[np.float64] | None]:
        synth = synthetic_odometry(list(open_log(_shared(relative))), SYNTH_BIASED, 0, restamp_hz)
        return list(synth.scans), np.array(synth.reference_poses)

    return build


def _csail() -> tuple[list[LaserScan], NDArray[np.float64] | None]:
    return list(open_log(_shared("mit-csail/mit-csail.clf"))), None


#: name -> (scans and reference, where the log is split)
CASES: dict[str, tuple[Case, float]] = {
    **{f"office_s{s}": (_sim("office", s), 0.5) for s in range(10)},
    "office_s0_third": (_sim("office", 0), 1 / 3),
    "office_s1_third": (_sim("office", 1), 1 / 3),
    "office_s0_two_thirds": (_sim("office", 0), 2 / 3),
    **{f"office_biased_s{s}": (_sim("office_biased", s), 0.5) for s in range(10)},
    **{f"two_loop_s{s}": (_sim("two_loop", s), 0.5) for s in range(3)},
    **{f"two_loop_s{s}_two_thirds": (_sim("two_loop", s), 2 / 3) for s in range(3)},
    **{f"open_loops_s{s}": (_sim("open_loops", s), 0.5) for s in range(3)},
    "csail": (_csail, 0.5),
    "aces_synth": (_corrected("aces/aces-corrected.log.gz", None), 0.5),
    "csail_log_synth": (_corrected("mit-csail/csail.log", None), 0.5),
    "csail_corrected_synth": (_corrected("mit-csail/csail-corrected.log.gz", 1.0), 0.5),
}


def _session(scans: list[LaserScan], folder: Path) -> Session:
    slam = Slam()
    for scan in scans:
        slam.process(scan)
    slam.finish()
    return session.read(session.save(slam, folder))


def run_case(name: str, work: Path) -> list[str]:
    """One row of the table (strings)."""
    build, fraction = CASES[name]
    t = time.perf_counter()
    scans, reference = build()
    k = int(len(scans) * fraction)
    # Scans held in memory by the session (not re-read from the log): B's odometry is moved.
    a_scans = [dataclasses.replace(s, source=f"a:{i}") for i, s in enumerate(scans[:k])]
    b_scans = [
        dataclasses.replace(s, odom_pose=se2.compose(FRAME, s.odom_pose), source=f"b:{i}")  # type: ignore[arg-type]
        for i, s in enumerate(scans[k:])
    ]
    a, b = _session(a_scans, work / name / "A"), _session(b_scans, work / name / "B")
    try:
        closures = find_closures(a, b)
    except SessionError as exc:
        why = "two groups tie" if "equally" in str(exc) else "too few agree"
        return [name, "-", "-", "-", f"refused ({why})", "-", "-", f"{time.perf_counter() - t:.1f}"]
    merged = Session(a.path, {}, a.config, merge_arrays(a, b, closures))
    crossings = wall_crossings(merged, int(a.arrays["g_node_ids"].max()) + 1)
    through_a, through_b = crossings.worst
    verdict = "merged" if crossings.consistent else "refused (walls)"
    ate = mx = "-"
    if reference is not None:
        _, poses = merged.trajectory()
        err = position_errors(poses, reference, align=True)
        ate, mx = f"{err.rmse_m:.3f}", f"{err.max_m:.2f}"
    return [
        name,
        str(len(closures)),
        str(through_a),
        str(through_b),
        verdict,
        ate,
        mx,
        f"{time.perf_counter() - t:.1f}",
    ]


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--only", action="append", choices=sorted(CASES), help="case (repeatable)")
    args = ap.parse_args()
    names = args.only or list(CASES)
    head = ["case", "placed", "B thru A", "A thru B", "verdict", "ATE m", "max m", "time s"]
    widths = [24, 6, 8, 8, 22, 7, 6, 7]
    print(
        " ".join(
            h.rjust(w) if i else h.ljust(w)
            for i, (h, w) in enumerate(zip(head, widths, strict=True))
        )
    )
    with tempfile.TemporaryDirectory(prefix="iceg-merge-") as tmp:
        for name in names:
            try:
                row = run_case(name, Path(tmp))
            except FileNotFoundError as exc:
                row = [name, "-", "-", "-", f"skipped ({exc})", "-", "-", "-"]
            print(
                " ".join(
                    c.rjust(w) if i else c.ljust(w)
                    for i, (c, w) in enumerate(zip(row, widths, strict=True))
                ),
                flush=True,
            )
    return 0


if __name__ == "__main__":
    sys.exit(main())
