"""A run's input computed in a forked process (iceg.aside): a log read there is the same
store bit for bit, with the same stamp report and log records, and the same error where
reading fails; the built-in demo is the same run."""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import pickle
import signal
import sys
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from frontends import open_log
from frontends.odometry_shift import shift_odometry
from iceg import aside, pipeline
from iceg.aside import compute_aside
from iceg.config import IcegConfig
from iceg.scan_store import ScanStore
from iceg_common.errors import LogFormatError
from tests.conftest import flaser_line, shared_file, write_odometry_jump_log

forked = pytest.mark.skipif(sys.platform != "linux", reason="the forked process is Linux only")


def _bits(x: object) -> bytes:
    return b"" if x is None else np.asarray(x, dtype=np.float64).tobytes()


def _assert_same_store(a: ScanStore, b: ScanStore) -> None:
    """Every scan the same, value for value and bit for bit."""
    assert len(a) == len(b)
    for sa, sb in zip(a, b, strict=True):
        assert (sa.source, sa.odom_break) == (sb.source, sb.odom_break)
        for field in ("ranges_m", "angles_rad", "laser_offset", "odom_pose"):
            assert _bits(getattr(sa, field)) == _bits(getattr(sb, field)), field
        for field in ("stamp_s", "range_min_m", "range_max_m"):
            assert _bits(getattr(sa, field)) == _bits(getattr(sb, field)), field


@forked
def test_the_store_read_aside_is_the_store_read_here_bit_for_bit() -> None:
    path = shared_file("mit-csail/mit-csail.clf")
    here = ScanStore(shift_odometry(open_log(path), -0.12))
    config = IcegConfig()
    with compute_aside(lambda: pipeline._read(path, open_log(path), -0.12)) as reading:
        assert reading._proc is not None  # it is read in another process
        store, report = reading.result()
    _assert_same_store(store, here)
    assert report is not None and report.as_dict()["out_of_order"] == 0
    # then checked and measured: read as it is (its odometry moves, and the walls turn
    # and move with it), a SICK that sees none of its robot and loses few returns on walls
    (run_config, body, dropouts), how = pipeline._reading_checks(path, store, config)
    assert pipeline._as_read(store, how) is store and how.options == {} and how.stalls == ()
    assert how.check is not None and how.check.finding() is None
    assert run_config == config and body is not None and body.range_m is None
    assert dropouts is not None and not dropouts.rule_on and dropouts.patches_per_1000 < 2.5
    assert np.array_equal(store.beams()[1], here.beams()[1])
    # its arrays are its own and writable: the store grows on as one read here
    for scan in here[:3]:
        store.append(scan)
    assert len(store) == len(here) + 3
    _assert_same_store(ScanStore(store[-3:]), ScanStore(here[:3]))


def test_the_forked_process_stops_reading_once_the_calling_process_is_gone(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    items = list(range(10))
    assert list(aside.while_caller_runs(items)) == items  # not in a forked process
    monkeypatch.setattr(aside, "_CALLER_PID", -1)  # forked by a process that is gone
    with pytest.raises(ChildProcessError):
        list(aside.while_caller_runs(items))


@forked
def test_the_readers_findings_and_log_records_come_back(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = write_odometry_jump_log(tmp_path / "jump.clf")
    with (
        caplog.at_level(logging.WARNING),
        compute_aside(lambda: pipeline._read(path, open_log(path), 0.0)) as reading,
    ):
        store, report = reading.result()
    assert [store[k].odom_break for k in range(len(store))] == [False, False, False, True, False]
    assert f"{path}:4: odometry jumps 50.00 m" in caplog.text
    assert report is not None and report.odometry_breaks[0][0] == f"{path}:4"


def test_a_log_that_fails_to_read_raises_here_with_its_line(tmp_path: Path) -> None:
    path = tmp_path / "bad.clf"
    path.write_text(flaser_line(0.0, 10.0) + "\nFLASER 3 1.0 oops 3.0 0 0 0 0 0 0 11.0 h 11.0\n")
    reading = compute_aside(lambda: pipeline._read(path, open_log(path), 0.0))
    with reading, pytest.raises(LogFormatError, match=":2"):
        reading.result()


def test_a_store_pickles_without_its_spare_capacity_and_grows_on() -> None:
    path = shared_file("mit-csail/mit-csail.clf")
    scans = list(open_log(path))[:300]
    store = ScanStore(scans[:200])
    back = pickle.loads(pickle.dumps(store))
    assert back._blocks[-1].nbytes == store._used < store._blocks[-1].nbytes
    assert back._head["stamp_s"].shape[0] == 200
    for scan in scans[200:]:
        back.append(scan)
        store.append(scan)
    _assert_same_store(back, store)
    empty = pickle.loads(pickle.dumps(ScanStore()))
    empty.append(scans[0])
    assert len(empty) == 1 and np.array_equal(empty[0].ranges_m, scans[0].ranges_m)


@forked
def test_a_run_counts_its_idle_cores_before_the_forked_process_takes_one(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    # auto_workers watches the cores' idleness: a forked process already at work on one
    # would make a run on an idle two-core machine choose a single process.
    seen: list[list[str]] = []

    def auto_workers() -> int:
        seen.append([p.name for p in multiprocessing.active_children()])
        return 1

    monkeypatch.setattr(pipeline, "auto_workers", auto_workers)
    monkeypatch.setattr(pipeline, "probed", lambda: False)  # as in a process's first run
    path = tmp_path / "short.clf"
    path.write_text("".join(flaser_line(0.1 * k, 10.0 + 0.1 * k) + "\n" for k in range(5)))
    result = pipeline.run_log(path)
    assert seen == [[]]
    assert len(result.stamps_s) == 5


@forked
def test_a_reading_left_unread_is_stopped_even_where_sigterm_raises() -> None:
    # As in the CLI, whose SIGTERM handler raises: the forked process inherits it. Blocked
    # sending a store larger than the pipe holds, it must still end at terminate().
    class Terminated(Exception):
        pass

    def raise_terminated(signum: int, frame: object) -> None:
        raise Terminated

    previous = signal.signal(signal.SIGTERM, raise_terminated)
    try:
        path = shared_file("mit-csail/mit-csail.clf")
        reading = compute_aside(lambda: ScanStore(open_log(path)))
        proc = reading._proc
        assert proc is not None
        deadline = time.monotonic() + 30.0
        while reading._conn is not None and not reading._conn.poll(0.05):
            assert time.monotonic() < deadline, "the forked process sent nothing"
        # it is now sending (the store is far larger than a pipe's buffer); nobody reads
        stopper = threading.Thread(target=reading.__exit__, args=(None, None, None))
        stopper.start()
        stopper.join(10.0)
        assert not stopper.is_alive(), "the with-block's exit hung on the forked process"
        assert not proc.is_alive()
    finally:
        signal.signal(signal.SIGTERM, previous)


@forked
def test_the_demo_simulated_aside_is_the_demo_simulated_here(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    runs = []
    for first_run in (True, False):  # the world simulated in a forked process, then here
        monkeypatch.setattr(pipeline, "probed", lambda first_run=first_run: not first_run)
        runs.append(pipeline.run_simulated_demo())
    aside_run, here = runs
    assert aside_run.poses.tobytes() == here.poses.tobytes()
    assert aside_run.metrics["ground_truth"] == here.metrics["ground_truth"]


class _ArrivesLate(aside.Aside[bool]):
    """A value (``stops``) that arrives after ``looks`` looks (:meth:`ready`)."""

    def __init__(self, stops: bool, looks: int) -> None:
        super().__init__(lambda: stops)
        self.looks, self.looked = looks, 0

    def ready(self) -> bool:
        self.looked += 1
        return self.looked > self.looks


@pytest.mark.parametrize(
    ("stops", "looks", "given", "looked"),
    [(False, 2, 50, 3), (True, 2, 16, 3), (True, 99, 50, 7)],
)
def test_the_items_go_until_the_value_arrives_saying_they_must_stop(
    stops: bool, looks: int, given: int, looked: int
) -> None:
    # Looked at every 8 items (0, 8, ..., 48) without waiting: a value that arrives at the
    # third look (item 16) and says stop stops there; one that says go on is not looked at
    # again (the other items follow without a look); one that never arrives while the items
    # go is waited for after the last (all 50 given, then stopped). The value is asked once.
    late = _ArrivesLate(stops, looks)
    asked: list[bool] = []

    def ask(value: bool) -> bool:
        asked.append(value)
        return value

    out: list[int] = []
    with pytest.raises(aside.Superseded) if stops else contextlib.nullcontext():
        for item in late.until(range(50), ask, every=8):
            out.append(item)
    assert out == list(range(given))
    assert late.looked == looked
    assert asked == [stops]


@forked
def test_a_value_computed_aside_is_taken_once_and_given_again() -> None:
    calls = []

    def compute() -> int:
        calls.append(1)
        return 42

    with compute_aside(compute, niceness=5) as value:
        while not value.ready():
            time.sleep(0.01)
        assert value.result() == value.result() == 42
    assert calls == []  # computed in the forked process only
