"""A run's input, or its checks, computed in a forked process while the calling process
starts the run (issue 13).

The first run of a process starts serially: numba's typing registry loads (0.3-0.4 s, at
:func:`iceg.kernel_warmup.cache_is_new`), then the input is made (MIT CSAIL's 1988 CARMEN
lines parsed in about 0.3 s, the built-in office world simulated in 0.1 s), while the
second core has nothing to do. :func:`compute_aside` forks a process that computes the
input and sends it back, with the log records it emitted; :meth:`Aside.result` takes them,
so the two overlap (:mod:`iceg.pipeline` does so where the registry is still to load; a
later run of the process has nothing to overlap, and the forked process would only add its
start). The process runs the same code the calling process would, and the value comes back
through ``pickle`` with its arrays' bytes out of band: the run is the same bit for bit
(``tests/iceg/test_aside.py``). Forked before the calling process has loaded numba's
registry, what it computes must call no compiled kernel, or the process would load the
registry itself.

A run can also go on as if a value computed aside will change nothing, and stop where it
does (:meth:`Aside.until`): :mod:`iceg.pipeline` runs a log's checks so, beside the run.

Where the forked process fails for any reason (an error in the computation, a killed
process, a value that cannot be pickled) the calling process computes the value itself: an
error is then raised in the calling process, with its message and traceback, as without
this module. Off Linux the value is computed in the calling process.
"""

from __future__ import annotations

import contextlib
import logging
import logging.handlers
import multiprocessing
import os
import pickle
import queue
import sys
from collections.abc import Callable, Iterable, Iterator
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import Generic, TypeVar, cast

from iceg import forked

log = logging.getLogger(__name__)

T = TypeVar("T")
S = TypeVar("S")

#: In a process forked by :func:`compute_aside`: the calling process's id (else None).
_CALLER_PID: int | None = None

#: :func:`while_caller_runs` checks every this many items that the calling process runs.
CALLER_CHECK_ITEMS = 256


class Superseded(Exception):
    """The value computed aside says that the work done meanwhile on the items it was
    speculating on must be done again otherwise (:meth:`Aside.until`)."""


@dataclass(eq=False)
class Aside(Generic[T]):
    """A value being computed in a forked process (:func:`compute_aside`); :meth:`result`
    gives it. Use as a context manager: the block's end stops a process whose value was
    never taken (the run failed before).

    Attributes:
        compute: The computation (called again here where the forked process failed).
    """

    compute: Callable[[], T]
    _conn: Connection | None = field(default=None, repr=False)
    _proc: BaseProcess | None = field(default=None, repr=False)
    _value: tuple[T] | None = field(default=None, repr=False)

    def result(self) -> T:
        """The value, from the forked process (its log records handled here as if logged
        here), or computed here where that process failed or never started; waited for
        where it has yet to arrive. A later call gives the same value.

        Raises:
            Whatever ``compute`` raises.
        """
        if self._value is None:
            got = self._received()
            if got is None:
                self._value = (self.compute(),)
            else:
                value, records = got
                for record in records:
                    logging.getLogger(record.name).handle(record)
                self._value = (value,)
        return self._value[0]

    def ready(self) -> bool:
        """Whether :meth:`result` would return without waiting for the forked process (its
        value has arrived, the process has ended, or there is none: then :meth:`result`
        computes the value here)."""
        conn = self._conn
        if conn is None:
            return True
        try:
            return conn.poll()
        except (EOFError, OSError):
            return True

    def until(self, items: Iterable[S], stops: Callable[[T], bool], every: int) -> Iterator[S]:
        """``items``, given on the speculation that the value will not stop the work on them:
        every ``every`` items it is looked at where it has arrived (:meth:`ready`, no wait),
        and after the last item it is waited for; ``stops(value)`` says it stops the work,
        asked once.

        Raises:
            Superseded: ``stops(value)``, at the first look after the value arrived.
            Whatever ``compute`` raises.
        """
        rest = iter(items)
        for k, item in enumerate(rest):
            if k % every == 0 and self.ready():
                if stops(self.result()):
                    raise Superseded
                yield item  # the value goes on: the other items without a look
                yield from rest
                return
            yield item
        if stops(self.result()):
            raise Superseded

    def __enter__(self) -> Aside[T]:
        return self

    def __exit__(self, *exc: object) -> None:
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        if proc is not None:
            proc.terminate()
            proc.join()
        if conn is not None:
            conn.close()

    def _received(self) -> tuple[T, list[logging.LogRecord]] | None:
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        if conn is None or proc is None:
            return None
        try:
            return _receive(conn)
        except (EOFError, OSError):  # the process died (killed, out of memory)
            return None
        finally:
            conn.close()
            proc.join()


def compute_aside(compute: Callable[[], T], fork: bool = True, niceness: int = 0) -> Aside[T]:
    """Start ``compute()`` in a forked process (with ``fork``, on Linux; else, or where the
    fork fails, :meth:`Aside.result` computes it), at ``niceness`` added to this process's
    (a positive one: spare CPU only)::

        with compute_aside(lambda: ScanStore(open_log(path))) as reading:
            ...  # other work
            store = reading.result()

    ``compute`` should stop a long loop once the calling process has exited
    (:func:`while_caller_runs`). Forked before this process has loaded numba's registry, it
    must call no compiled kernel (see the module); after, the forked process has the
    registry and the kernels loaded so far (the offset measured before a run,
    :func:`iceg.odometry_timing.scan_pairs_time_offset`, matches half the log in one).
    """
    aside = Aside(compute)
    if not fork or sys.platform != "linux":
        return aside
    try:
        ctx = multiprocessing.get_context("fork")
        conn, child = ctx.Pipe(duplex=False)
        proc = ctx.Process(
            target=_run,
            args=(child, aside, os.getpid(), niceness),
            daemon=True,
            name="iceg-aside",
        )
        with forked.signals_held():
            proc.start()
        child.close()
    except OSError as exc:
        log.warning("computing the run's input here (%s)", exc)
        return aside
    aside._conn, aside._proc = conn, proc
    return aside


def while_caller_runs(items: Iterable[T]) -> Iterator[T]:
    """``items``; in a process forked by :func:`compute_aside`, stopped
    (:class:`ChildProcessError`) once the calling process has exited, checked every
    :data:`CALLER_CHECK_ITEMS` items: its value has no reader then."""
    for k, item in enumerate(items):
        if k % CALLER_CHECK_ITEMS == 0 and _CALLER_PID is not None and os.getppid() != _CALLER_PID:
            raise ChildProcessError("the calling process exited")
        yield item


def _run(conn: Connection, aside: Aside[T], caller_pid: int, niceness: int) -> None:
    """The forked process: sends the value and the log records (:func:`_send`), or None
    where computing it failed."""
    global _CALLER_PID
    _CALLER_PID = caller_pid
    forked.helper_signals()
    if niceness:
        with contextlib.suppress(OSError):
            os.nice(niceness)
    records = _collect_records()
    try:
        value = aside.compute()
        _send(conn, (value, _drained(records)))
    except BaseException:  # the calling process computes it again and raises the error
        with contextlib.suppress(Exception):
            conn.send(None)
    finally:
        conn.close()


def _send(conn: Connection, message: object) -> None:
    """Send ``message`` with its arrays' bytes out of band (pickle protocol 5): one message
    of the objects and the buffers' sizes, then each buffer as it lies in memory, so
    neither process holds a pickled copy beside them (a large log's scans are hundreds of
    MB)."""
    buffers: list[pickle.PickleBuffer] = []
    payload = pickle.dumps(message, protocol=5, buffer_callback=buffers.append)
    raws = [b.raw() for b in buffers]
    conn.send((payload, [r.nbytes for r in raws]))
    for raw in raws:
        conn.send_bytes(raw)


def _receive(conn: Connection) -> tuple[T, list[logging.LogRecord]] | None:
    """What :func:`_send` sent (None where computing failed): each buffer received into
    writable memory of its own, which the arrays then use as they are."""
    got = conn.recv()
    if got is None:
        return None
    payload, sizes = got
    buffers = [bytearray(n) for n in sizes]
    for buffer in buffers:
        conn.recv_bytes_into(buffer)
    return cast(tuple[T, list[logging.LogRecord]], pickle.loads(payload, buffers=buffers))


def _collect_records() -> queue.SimpleQueue[logging.LogRecord]:
    """In the forked process: every log record goes to the queue returned, its message
    formatted and its arguments dropped so that it pickles (``logging.handlers.QueueHandler``),
    instead of to the handlers inherited from the calling process (which handles them once
    the value arrives)."""
    loggers = [logging.getLogger(), *logging.Logger.manager.loggerDict.values()]
    for logger in loggers:
        if isinstance(logger, logging.Logger):
            for handler in list(logger.handlers):
                logger.removeHandler(handler)
    records: queue.SimpleQueue[logging.LogRecord] = queue.SimpleQueue()
    logging.getLogger().addHandler(logging.handlers.QueueHandler(records))
    return records


def _drained(records: queue.SimpleQueue[logging.LogRecord]) -> list[logging.LogRecord]:
    out = []
    while not records.empty():
        out.append(records.get_nowait())
    return out
