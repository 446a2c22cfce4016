"""Acceptance on MIT CSAIL (slow): split runs bit for bit, ``--continue`` of the second half
within 10 % of the whole run, and a log of another building (ACES) refused."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from frontends import open_log
from frontends.relations import read_relations
from iceg import session
from iceg.continuation import continue_scans
from iceg.evaluation import relation_errors
from iceg.slam import Slam
from iceg_common import se2
from iceg_common.errors import SessionError
from tests.conftest import shared_file


def _second_half_error(stamps, poses, rel, start_s):  # type: ignore[no-untyped-def]
    keep = (rel.stamps_s[:, 0] >= start_s) & (rel.stamps_s[:, 1] >= start_s)
    summary, _ = relation_errors(stamps, poses, rel.stamps_s[keep], rel.deltas[keep], 1e-3)
    return summary.trans_mean_m


@pytest.mark.slow
def test_csail_halves(tmp_path) -> None:  # type: ignore[no-untyped-def]
    scans = list(open_log(shared_file("mit-csail/mit-csail.clf")))
    rel = read_relations(shared_file("mit-csail/mit-csail.relations"))
    aces = shared_file("aces/aces-corrected.log.gz")
    k = len(scans) // 2
    whole = Slam()
    for scan in scans:
        whole.process(scan)
    w = whole.finish()
    first = Slam()
    for scan in scans[:k]:
        first.process(scan)
    first.finish()
    session.save(first, tmp_path / "first")
    resumed = session.load(tmp_path / "first")
    for scan in scans[k:]:
        resumed.process(scan)
    assert np.array_equal(resumed.finish().poses, w.poses)  # bit for bit
    # the second half as another log (own odometry frame), placed without an initial pose
    frame = np.array([5.0, -3.0, 2.0])
    second = [
        dataclasses.replace(s, odom_pose=se2.compose(frame, s.odom_pose), source=f"b:{i}")
        for i, s in enumerate(scans[k:])
    ]
    c = continue_scans(tmp_path / "first", second)
    start = scans[k].stamp_s
    e_whole = _second_half_error(w.stamps_s, w.poses, rel, start)
    assert _second_half_error(c.stamps_s, c.poses, rel, start) <= 1.1 * e_whole
    other = [dataclasses.replace(s, stamp_s=s.stamp_s + 2e9) for s in list(open_log(aces))[:300]]
    with pytest.raises(SessionError, match="cannot be placed"):
        continue_scans(tmp_path / "first", other)
