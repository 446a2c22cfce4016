"""The forked helpers' shared pieces (iceg.forked): their signals, and the check that a pipe
has something to read."""

from __future__ import annotations

import multiprocessing
import os
import signal
import sys
import time
from multiprocessing.connection import Connection

import numpy as np
import pytest

from iceg import forked

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="the helpers are forked (Linux)")


class _Terminated(Exception):
    pass


def _raise_terminated(signum: int, frame: object) -> None:
    raise _Terminated


def _helper(set_signals: bool) -> None:
    """A helper forked from a process whose SIGTERM handler raises (as the CLI's does)."""
    if set_signals:
        forked.helper_signals()
    try:
        time.sleep(30.0)
    except _Terminated:  # what a helper that catches errors would do with it
        time.sleep(30.0)


@pytest.mark.parametrize("set_signals", [True, False])
def test_a_helper_ends_at_terminate_whatever_handler_it_inherited(set_signals: bool) -> None:
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        proc = multiprocessing.get_context("fork").Process(target=_helper, args=(set_signals,))
        proc.start()
    finally:
        signal.signal(signal.SIGTERM, previous)
    time.sleep(0.5)  # the helper is asleep in its loop
    proc.terminate()
    proc.join(2.0)
    ended = not proc.is_alive()
    if not ended:
        proc.kill()
        proc.join()
    # with the helper's signals, SIGTERM's default action ends it at once; with the
    # inherited handler it raises inside the helper, which carries on
    assert ended == set_signals
    if set_signals:
        assert proc.exitcode == -signal.SIGTERM
    assert signal.getsignal(signal.SIGINT) is not signal.SIG_IGN  # this process untouched


def test_a_helper_terminated_as_it_starts_ends_by_the_signal() -> None:
    # A run that fails at once stops a helper just forked, before its target has set its
    # signals: held across the fork, the SIGTERM waits for them (it used to raise the
    # inherited handler's exception in multiprocessing's bootstrap and print its traceback).
    previous = signal.signal(signal.SIGTERM, _raise_terminated)
    try:
        codes = []
        for _ in range(5):
            proc = multiprocessing.get_context("fork").Process(target=_helper, args=(True,))
            with forked.signals_held():
                proc.start()
            proc.terminate()
            proc.join(5.0)
            codes.append(proc.exitcode)
    finally:
        signal.signal(signal.SIGTERM, previous)
    assert codes == [-signal.SIGTERM] * 5


def test_readable_answers_as_connection_poll_in_every_state_of_a_pipe() -> None:
    ours, theirs = multiprocessing.Pipe(duplex=True)
    readable = forked.Readable(ours)
    # nothing sent yet
    assert readable() is False
    assert ours.poll(0) is False
    # a message waiting, then read
    theirs.send(("a", 1))
    assert readable() is True
    assert ours.poll(0) is True
    assert ours.recv() == ("a", 1)
    assert readable() is False
    # the other end closed: readable (the read then raises), as poll says
    theirs.close()
    assert readable() is True
    assert ours.poll(0) is True
    with pytest.raises(EOFError):
        ours.recv()
    # this end closed: an error, as poll's
    ours.close()
    with pytest.raises(OSError):
        readable()
    with pytest.raises(OSError):
        ours.poll(0)


def test_readable_waits_its_timeout_rounded_up_to_milliseconds_or_until_a_message() -> None:
    ours, theirs = multiprocessing.Pipe(duplex=True)
    readable = forked.Readable(ours)
    t0 = time.monotonic()
    assert readable(0.0004) is False  # waits at least the timeout: 1 ms, poll(2)'s step
    assert time.monotonic() - t0 >= 0.0009
    assert readable(-1.0) is False  # a deadline passed: no wait, as Connection.poll
    sender = multiprocessing.get_context("fork").Process(
        target=_send_later, args=(theirs, 0.2, "late")
    )
    sender.start()
    try:
        assert readable(None) is True  # no timeout: until the message arrives
        assert ours.recv() == "late"
    finally:
        sender.join(5.0)


def _send_later(conn: Connection, delay_s: float, msg: str) -> None:
    time.sleep(delay_s)
    conn.send(msg)


def _arrays() -> dict[str, np.ndarray]:
    read_only = np.arange(4.0)
    read_only.flags.writeable = False
    return {
        "f8": np.arange(12.0).reshape(6, 2) / 7.0,
        "i8": np.arange(-3, 3, dtype=np.int64),
        "f4": np.linspace(0, 1, 5, dtype=np.float32),
        "bool": np.array([True, False, True]),
        "empty": np.zeros((0, 2)),
        "empty_middle": np.zeros((2, 0, 3), dtype=np.int32),
        "scalar": np.array(3.25),
        "big_endian": np.arange(3, dtype=">f8"),
        "read_only": read_only,
        "fortran": np.asfortranarray(np.arange(6.0).reshape(2, 3)),
        "strided": np.arange(10.0)[::3],
        "structured": np.zeros(2, dtype=[("x", "f8"), ("n", "i4")]),
        "objects": np.array([None, "a"], dtype=object),
    }


def test_send_delivers_what_connection_send_delivers() -> None:
    # every array as numpy's own pickle gives it back: dtype, shape, strides, flags, bytes
    ours, theirs = multiprocessing.Pipe(duplex=True)
    message = (3, 1, _arrays(), None, 0.25, "text")
    ours.send(message)
    by_send = theirs.recv()
    forked.send(ours, message)
    by_ours = theirs.recv()
    assert by_ours[:2] == (3, 1) and by_ours[3:] == (None, 0.25, "text")
    assert by_ours[2].keys() == by_send[2].keys()
    for name, a in by_send[2].items():
        b = by_ours[2][name]
        assert type(b) is np.ndarray, name
        assert (b.dtype, b.shape, b.strides) == (a.dtype, a.shape, a.strides), name
        for flag in ("c_contiguous", "f_contiguous", "aligned", "writeable"):
            assert getattr(b.flags, flag) == getattr(a.flags, flag), (name, flag)
        assert b.tobytes() == a.tobytes(), name
    assert by_ours[2]["read_only"].flags.writeable  # as numpy's pickle: a new array
    ours.close()
    with pytest.raises(OSError):
        forked.send(ours, message)


def test_a_plain_array_loads_as_one_constructor_call_over_its_bytes() -> None:
    # what makes it cheaper to load: no _reconstruct, dtype built or __setstate__
    import pickletools

    text = bytes(forked.dumps(np.arange(6.0).reshape(2, 3)))
    ops = [op.name for op, _, _ in pickletools.genops(text)]
    assert ops.count("REDUCE") == 1 and "BUILD" not in ops and "BYTEARRAY8" in ops
    assert "_reconstruct" not in str(text) and "dtype" not in str(text)


def test_next_message_reads_until_the_pipe_ends() -> None:
    ours, theirs = multiprocessing.Pipe(duplex=True)
    readable = forked.Readable(ours)
    theirs.send(("job", 7))
    assert forked.next_message(readable, os.getppid()) == ("job", 7)
    theirs.close()  # the parent's end gone: the helper's loop ends
    assert forked.next_message(readable, os.getppid()) is None
