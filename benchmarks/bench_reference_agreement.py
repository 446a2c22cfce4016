"""Benchmark: how well a corrected log's reference poses agree with its own scans.

The corrected logs of ``../shared/data`` (ACES, csail.log, csail-corrected) serve as
references for the synthetic-odometry cases of ``bench_accuracy.py``. Their poses come from
another SLAM system, so they carry their own error. This script measures it from the scans
themselves: consecutive scans are matched pairwise by two independent matchers (ICE and
point-to-line ICP, both seeded by the synthetic odometry), and the table prints how far each
lies from the reference's relative pose, and how far the two matchers lie from each other.

When the two matchers agree much more closely with each other than with the reference, the
per-step disagreement is the reference's own error (or a property of the scans, such as
motion distortion during turns, that no scan matcher can undo), and it bounds the ATE any
scan-matching SLAM can reach against that reference. The fourth line of each case lists the steps
the reference disputes: both matchers agree with each other (within ``AGREE_DEG`` /
``AGREE_CM``) and put the heading change more than ``DISPUTE_DEG`` from the reference's.
Then the whole log (every scan, whatever ``--steps``) runs through the default pipeline with
the reference poses as its odometry: its ATE against the reference is what following these
scans costs with no odometry error at all, the floor of the synthetic-odometry cases.

Run: ``python benchmarks/bench_reference_agreement.py [--only CASE ...] [--steps N]``.
"""

from __future__ import annotations

import argparse
import dataclasses
import math

import numpy as np
from bench_accuracy import CASES, CaseSkipped
from numpy.typing import NDArray

from frontends import LaserScan
from iceg.config import IcegConfig
from iceg.evaluation import position_errors
from iceg.features import extract
from iceg.matching import IceMatcher
from iceg.matching.config import MatchBounds
from iceg.matching.plicp import PlIcpMatcher
from iceg.slam import Slam
from iceg.types import MatchResult, ScanFeatures
from iceg_common import se2

FloatArray = NDArray[np.float64]
#: Cases with a reference from another system's corrected poses.
CORRECTED = ("aces_synth", "csail_log_synth", "csail_corrected_synth")
#: Turns at least this large (degrees) are reported on their own.
TURN_DEG = 15.0
#: A step whose two matchers agree within these, and lie farther than DISPUTE_DEG from the
#: reference's heading change, is one the reference disputes.
AGREE_DEG = 1.0
AGREE_CM = 10.0
DISPUTE_DEG = 5.0


def _error(truth: FloatArray, result: MatchResult) -> FloatArray | None:
    return se2.between(truth, result.pose) if result.success else None


def _row(name: str, errors: list[FloatArray | None], turns: NDArray[np.bool_]) -> str:
    ok = np.array([e is not None for e in errors])
    e = np.array([x for x in errors if x is not None]).reshape(-1, 3)
    txy = 100.0 * np.hypot(e[:, 0], e[:, 1])
    th = np.degrees(np.abs(e[:, 2]))
    on_turns = [x[2] for x, t in zip(errors, turns, strict=True) if t and x is not None]
    th_turn = np.degrees(np.abs(np.array(on_turns)))
    turn = f"{np.median(th_turn):6.3f}" if th_turn.size else "     -"
    return (
        f"{name:32s} {int(ok.sum()):4d}/{ok.size:<4d} {np.median(txy):7.2f} "
        f"{np.percentile(txy, 90):7.2f} {np.median(th):8.3f} {np.percentile(th, 90):8.3f} {turn}"
    )


def run(case: str, steps: int) -> list[str]:
    """The table rows of one case (its first ``steps`` consecutive scan pairs)."""
    data = CASES[case](0)
    assert data.reference is not None
    cfg = IcegConfig()
    ice, plicp = IceMatcher(cfg.matching), PlIcpMatcher(cfg.matching)
    bounds = MatchBounds.local(cfg.slam.match_max_translation_m, cfg.slam.match_max_rotation_deg)
    n = min(len(data.scans) - 1, steps)
    feats = [extract(s, cfg.features) for s in data.scans[: n + 1]]
    e_ice: list[FloatArray | None] = []
    e_pl: list[FloatArray | None] = []
    e_pair: list[FloatArray | None] = []
    turns = np.zeros(n, dtype=bool)
    for k in range(1, n + 1):
        a, b = data.scans[k - 1], data.scans[k]
        assert a.odom_pose is not None and b.odom_pose is not None
        truth = se2.between(data.reference[k - 1], data.reference[k])
        turns[k - 1] = abs(math.degrees(truth[2])) >= TURN_DEG
        prediction = se2.between(a.odom_pose, b.odom_pose)
        r_ice = ice.match(feats[k], feats[k - 1], prediction, bounds)
        r_pl = plicp.match(feats[k], ScanFeatures.empty(feats[k - 1].points_xy), prediction, bounds)
        e_ice.append(_error(truth, r_ice))
        e_pl.append(_error(truth, r_pl))
        both = r_ice.success and r_pl.success
        e_pair.append(se2.between(r_pl.pose, r_ice.pose) if both else None)
    disputed = _disputed_steps(e_ice, e_pair)
    ate = _slam_ate_on_exact_odometry(data.scans, data.reference)
    return [
        _row(f"{case}: ICE - reference", e_ice, turns),
        _row(f"{case}: ICP - reference", e_pl, turns),
        _row(f"{case}: ICE - ICP", e_pair, turns),
        f"{case}: {len(disputed)} steps where ICE and ICP agree (<= {AGREE_DEG} deg, "
        f"<= {AGREE_CM} cm) and the reference turns > {DISPUTE_DEG} deg otherwise: "
        + (", ".join(f"{k} ({d:+.1f} deg)" for k, d in disputed) or "none"),
        f"{case}: the default pipeline with the reference itself as odometry ends "
        f"{ate:.3f} m ATE from it",
    ]


def _slam_ate_on_exact_odometry(scans: list[LaserScan], reference: FloatArray) -> float:
    """ATE (m, RMSE after SE(2) alignment) of the default pipeline run on the scans with the
    reference poses as their odometry: what following the scans costs against the reference
    when the odometry has no error at all."""
    slam = Slam(IcegConfig())
    for scan, pose in zip(scans, reference, strict=True):
        slam.process(dataclasses.replace(scan, odom_pose=np.array(pose, dtype=np.float64)))
    return position_errors(slam.finish().poses, reference).rmse_m


def _disputed_steps(
    e_ice: list[FloatArray | None], e_pair: list[FloatArray | None]
) -> list[tuple[int, float]]:
    """``(step, heading error in degrees)`` of the steps ``k-1 -> k`` where the two matchers
    agree with each other and both put the heading far from the reference's."""
    out = []
    for k, (ei, ep) in enumerate(zip(e_ice, e_pair, strict=True), start=1):
        if ei is None or ep is None:
            continue
        agree = math.degrees(abs(ep[2])) <= AGREE_DEG and 100 * math.hypot(ep[0], ep[1]) <= AGREE_CM
        if agree and math.degrees(abs(ei[2])) > DISPUTE_DEG:
            out.append((k, math.degrees(ei[2])))
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--only", action="append", choices=CORRECTED, help="case (repeatable)")
    parser.add_argument("--steps", type=int, default=300, help="scan pairs per case")
    args = parser.parse_args()
    print(
        f"{'pair':32s} {'matched':>9s} {'xy cm':>7s} {'p90 cm':>7s} {'th deg':>8s} "
        f"{'p90 deg':>8s} {'turns':>6s}"
    )
    print(f"(medians of |error|; turns: median |heading error| of steps turning >= {TURN_DEG} deg)")
    for case in args.only or CORRECTED:
        try:
            for line in run(case, args.steps):
                print(line, flush=True)
        except CaseSkipped as exc:
            print(f"{case}: skipped ({exc})")


if __name__ == "__main__":
    main()
