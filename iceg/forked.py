"""What the forked helper processes share (the feature workers, :mod:`iceg.features.prefetch`;
the match helper, :mod:`iceg.match_pool`; the input's process, :mod:`iceg.aside`): their
signals, and the two ends of a helper's pipe: messages pickled for it (:func:`send`), the
check that one has arrived (:class:`Readable`), the helper waiting for its next message
while its parent lives, and the parent stopping it without losing the pipe to a helper
blocked on sending."""

from __future__ import annotations

import contextlib
import io
import math
import os
import pickle
import select
import signal
import time
from collections.abc import Iterator
from multiprocessing.connection import Connection, wait
from multiprocessing.process import BaseProcess
from typing import Any

import numpy as np

#: An idle helper checks this often (seconds) that its parent process still runs.
PARENT_CHECK_S = 1.0
#: Seconds to wait for a helper to exit before it is terminated.
JOIN_TIMEOUT_S = 2.0


#: The signals a helper handles its own way (:func:`helper_signals`).
_HELPER_SIGNALS = {signal.SIGINT, signal.SIGTERM}


@contextlib.contextmanager
def signals_held() -> Iterator[None]:
    """Around a helper's start (its fork), in the thread that starts it: SIGINT and SIGTERM
    are held (blocked) in this thread, so the helper starts with them held until
    :func:`helper_signals` has set its own handling; a ``terminate()`` that comes first is
    held until then. The calling process's other threads (the CLI's main thread) take
    them meanwhile; a signal to this thread alone waits the fork's few milliseconds."""
    held = signal.pthread_sigmask(signal.SIG_BLOCK, _HELPER_SIGNALS)
    try:
        yield
    finally:
        signal.pthread_sigmask(signal.SIG_SETMASK, held)


def helper_signals() -> None:
    """A forked helper's signals, set first thing (it starts with them held,
    :func:`signals_held`): Ctrl-C (SIGINT) is the calling process's to handle, so it is
    ignored here; ``terminate()`` (SIGTERM) ends the helper at once, the default action,
    whatever handler the calling process had installed: the CLI's raises an exception,
    which a helper would inherit and print as a traceback, or catch and carry on where it
    catches errors (a blocked send, a match). Then they are released."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    signal.pthread_sigmask(signal.SIG_UNBLOCK, _HELPER_SIGNALS)


class Readable:
    """Whether a connection has something to read, as ``Connection.poll``: a message, its
    end, or an error (a read then raises). ``Connection.poll`` builds a selector, registers
    the connection in it and closes it at every call (about 8 µs, several times that in a
    run's cold caches); this keeps one ``select.poll`` object with the connection's file
    descriptor, made once (about 1 µs a call). A timeout is rounded up to whole
    milliseconds, as ``Connection.poll`` rounds it (the resolution of ``poll(2)``).

    Args:
        conn: An open connection (its file descriptor is registered now); kept as ``conn``.

    Raises:
        OSError: ``conn`` is closed (here, or at a call after it was closed: its file
            descriptor's number may belong to another file by then).
    """

    def __init__(self, conn: Connection) -> None:
        self.conn = conn
        self._poller = select.poll()
        self._poller.register(conn.fileno(), select.POLLIN)

    def __call__(self, timeout_s: float | None = 0.0) -> bool:
        """Whether it is readable within ``timeout_s`` seconds (0: now, without waiting;
        None: wait however long it takes)."""
        if self.conn.closed:
            raise OSError("handle is closed")
        ms = None if timeout_s is None else math.ceil(max(timeout_s, 0.0) * 1e3)
        return bool(self._poller.poll(ms))


class _Pickler(pickle.Pickler):
    """A pickler whose C-contiguous numpy arrays of plain native dtypes load as one
    constructor call: ``numpy.ndarray(shape, dtype.str, bytearray)`` over their bytes, a
    writable array of the same dtype, shape, strides and bytes, as numpy's own pickle gives.
    numpy's own reduction loads each array as a ``_reconstruct`` call, a dtype built and set,
    and a ``__setstate__`` copying the bytes once more. Other arrays (structured, object or
    non-native dtypes, strided views) take numpy's reduction of protocols before 5, which
    ``Connection.send`` uses; every other object is pickled as usual."""

    def reducer_override(self, obj: object) -> Any:
        if type(obj) is not np.ndarray:
            return NotImplemented
        if (
            obj.flags.c_contiguous
            and obj.dtype.isnative
            and obj.dtype.fields is None
            and not obj.dtype.hasobject
        ):
            return np.ndarray, (obj.shape, obj.dtype.str, bytearray(obj.data))
        return obj.__reduce__()


def dumps(message: object) -> memoryview:
    """The pickle of ``message`` that :func:`send` sends, protocol 5 (an array's bytes in
    band as a ``bytearray``); ``pickle.loads`` (``Connection.recv``) reads it.

    Raises:
        pickle.PicklingError: ``message`` cannot be pickled.
    """
    out = io.BytesIO()
    _Pickler(out, protocol=5).dump(message)
    return out.getbuffer()


def send(conn: Connection, message: object) -> None:
    """``conn.send(message)``, for ``conn.recv()`` at the other end, pickled by
    :func:`dumps`. ``Connection.send`` pickles with ``multiprocessing``'s ``ForkingPickler``,
    which copies ``copyreg``'s dispatch table into each new instance for its reducers of
    connections, sockets and file descriptors (none of them in a helper's messages), and
    numpy's reduction of arrays. A feature worker's result (features and products, about 40
    arrays, 33 KB) loads in about two thirds of the time, a match result in one half to
    three quarters (docs/design.md, "The helpers' pipes made cheaper").

    Raises:
        OSError: ``conn`` is closed or read-only, or the pipe broke (as ``Connection.send``).
        pickle.PicklingError: ``message`` cannot be pickled (as ``Connection.send``).
    """
    conn.send_bytes(dumps(message))


def next_message(readable: Readable, parent_pid: int) -> object | None:
    """The helper's next message from its parent on the connection ``readable`` checks, or
    None when the parent has exited, the pipe ended or broke (the helper should then
    return)."""
    try:
        while not readable(PARENT_CHECK_S):
            if os.getppid() != parent_pid:
                return None
        return readable.conn.recv()
    except Exception:  # the pipe ended or broke: the calling process is gone
        return None


def stop(conn: Connection, proc: BaseProcess, at_once: bool = False) -> None:
    """Ask a helper to exit (a None message) and wait for it, terminated after
    ``JOIN_TIMEOUT_S`` (``at_once``: terminated now, when the run failed and nothing it
    computes is wanted); close the parent's end. What it still sends meanwhile is read and
    dropped: a helper blocked on a full pipe would never read the request."""
    if at_once:
        proc.terminate()
    with contextlib.suppress(OSError, ValueError):
        conn.send(None)
    deadline = time.monotonic() + JOIN_TIMEOUT_S
    with contextlib.suppress(EOFError, OSError):
        while (left := deadline - time.monotonic()) > 0:
            ready = wait([conn, proc.sentinel], left)
            if proc.sentinel in ready or not ready:
                break
            conn.recv()
    proc.join(max(0.0, deadline - time.monotonic()))
    if proc.is_alive():
        proc.terminate()
        proc.join(JOIN_TIMEOUT_S)
    conn.close()
