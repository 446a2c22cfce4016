"""The forked helpers' shared pieces (iceg.forked): their signals, and the check that a pipe
has something to read."""

from __future__ import annotations

import multiprocessing
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


def test_send_puts_the_bytes_of_connection_send_on_the_pipe() -> None:
    ours, theirs = multiprocessing.Pipe(duplex=True)
    message = (3, 1, {"xy": np.arange(12.0).reshape(6, 2)}, None, 0.25)
    ours.send(message)
    forked.send(ours, message)
    by_send, by_ours = theirs.recv_bytes(), theirs.recv_bytes()
    assert by_ours == by_send
    forked.send(ours, message)
    got = theirs.recv()
    assert got[:2] == (3, 1) and got[3:] == (None, 0.25)
    assert np.array_equal(got[2]["xy"], message[2]["xy"])
    ours.close()
    with pytest.raises(OSError):
        forked.send(ours, message)
