"""A log read into a :class:`~iceg.scan_store.ScanStore` by a forked process while the
calling process starts its run (issue 13).

The first run of a process starts serially: numba's typing registry loads (0.3-0.4 s, at
:func:`iceg.kernel_warmup.cache_is_new`), then the log is parsed (about 0.3 s for MIT
CSAIL's 1988 CARMEN lines), while the second core has nothing to do. :func:`read_aside`
forks a process that parses the log into a store and sends it back, with the log records
its reader emitted; :meth:`LogReading.result` takes them, so the two overlap
(:func:`iceg.pipeline.run_log` does so where the registry is still to load; later runs
of the process read the log themselves, with nothing to overlap). The process reads with
the same code the calling process would, and the store comes back through ``pickle``, its
arrays' bytes out of band: the run is the same bit for bit
(``tests/iceg/test_log_reading.py``). The reading process never calls a compiled kernel, so
it does not load numba's registry itself.

Where the reading process fails for any reason (a malformed log, a killed process, a result
that cannot be pickled) the calling process reads the log itself: the error is then raised
in the calling process, with its message and traceback, as without this module. Off Linux
the log is read in the calling process.
"""

from __future__ import annotations

import contextlib
import logging
import multiprocessing
import os
import pickle
import signal
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from multiprocessing.connection import Connection
from multiprocessing.process import BaseProcess
from typing import cast

from frontends import LaserScan
from frontends.odometry_shift import shift_odometry
from frontends.scan import StampReport
from iceg.scan_store import ScanStore

log = logging.getLogger(__name__)


#: What the reading process sends: the store, the reader's stamp report, its log records.
_Read = tuple[ScanStore, StampReport | None, list[logging.LogRecord]]


@dataclass(eq=False)
class LogReading:
    """A log being read into a store (:func:`read_aside`); :meth:`result` gives the store.

    Attributes:
        reader: The log's reader (:func:`frontends.open_log`), not yet iterated.
        odometry_time_offset_s: Each scan's odometry is read at its stamp plus this
            (:func:`~frontends.odometry_shift.shift_odometry`).
    """

    reader: Iterable[LaserScan]
    odometry_time_offset_s: float = 0.0
    _conn: Connection | None = field(default=None, repr=False)
    _proc: BaseProcess | None = field(default=None, repr=False)

    def result(self) -> tuple[ScanStore, StampReport | None]:
        """The store of every scan, and the reader's ``stamp_report`` (what its iteration
        found: out-of-order and duplicate stamps, odometry breaks; None for a reader without
        one). Waits for the reading process; where it failed, reads here.

        Raises:
            Whatever reading the log raises (e.g. ``LogFormatError`` naming ``file:line``).
        """
        got = self._received()
        if got is None:
            return _store(self.reader, self.odometry_time_offset_s), _report(self.reader)
        store, report, records = got
        for record in records:  # what the reader logged there, as if logged here
            logging.getLogger(record.name).handle(record)
        return store, report

    def __enter__(self) -> LogReading:
        return self

    def __exit__(self, *exc: object) -> None:
        """Stop the reading process where :meth:`result` was not called (the run failed
        before it)."""
        conn, proc = self._conn, self._proc
        self._conn = self._proc = None
        if proc is not None:
            proc.terminate()
            proc.join()
        if conn is not None:
            conn.close()

    def _received(self) -> _Read | None:
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


def read_aside(
    reader: Iterable[LaserScan], odometry_time_offset_s: float = 0.0, fork: bool = True
) -> LogReading:
    """Start reading the log of ``reader`` (:func:`frontends.open_log`, not yet iterated)
    into a :class:`~iceg.scan_store.ScanStore`, each scan's odometry read at its stamp plus
    ``odometry_time_offset_s``, in a forked process (with ``fork``, on Linux; else, or where
    the fork fails, :meth:`LogReading.result` reads it). Call :meth:`LogReading.result`
    once, in the process that called this, inside the reading's with-block (which stops the
    process where the run fails before)::

        with read_aside(open_log(path)) as reading:
            ...  # other work
            store, report = reading.result()
    """
    reading = LogReading(reader, odometry_time_offset_s)
    if not fork or sys.platform != "linux":
        return reading
    try:
        ctx = multiprocessing.get_context("fork")
        conn, child = ctx.Pipe(duplex=False)
        proc = ctx.Process(
            target=_read, args=(child, reading, os.getpid()), daemon=True, name="iceg-read"
        )
        proc.start()
        child.close()
    except OSError as exc:
        log.warning("reading the log here (%s)", exc)
        return reading
    reading._conn, reading._proc = conn, proc
    return reading


def _store(reader: Iterable[LaserScan], offset_s: float) -> ScanStore:
    return ScanStore(shift_odometry(reader, offset_s))


def _report(reader: Iterable[LaserScan]) -> StampReport | None:
    report = getattr(reader, "stamp_report", None)
    return report if isinstance(report, StampReport) else None


def _read(conn: Connection, reading: LogReading, parent_pid: int) -> None:
    """The reading process: sends the store, the stamp report and the log records
    (:func:`_send`), or None where reading failed or the calling process exited."""
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # Ctrl-C is the calling process's to handle
    # terminate() ends it at once, even where the calling process raises on SIGTERM (the
    # CLI) and this process inherited that handler while it blocks on a full pipe
    signal.signal(signal.SIGTERM, signal.SIG_DFL)
    records: list[logging.LogRecord] = []
    _collect_records(records)
    try:
        scans = _while_alive(reading.reader, parent_pid)
        store = _store(scans, reading.odometry_time_offset_s)
        for record in records:  # pickle the text, not the arguments
            record.msg, record.args = record.getMessage(), None
            record.exc_info = record.exc_text = None
        _send(conn, (store, _report(reading.reader), records))
    except BaseException:  # the calling process reads the log again and raises the error
        with contextlib.suppress(Exception):
            conn.send(None)
    finally:
        conn.close()


#: The reading process checks every this many scans that the calling process still runs.
_PARENT_CHECK_SCANS = 256


def _while_alive(scans: Iterable[LaserScan], parent_pid: int) -> Iterator[LaserScan]:
    """``scans``, stopped (:class:`ChildProcessError`) once the calling process has exited:
    its result has no reader then."""
    for k, scan in enumerate(scans):
        if k % _PARENT_CHECK_SCANS == 0 and os.getppid() != parent_pid:
            raise ChildProcessError("the calling process exited")
        yield scan


def _send(conn: Connection, read: _Read) -> None:
    """Send ``read`` with its arrays' bytes out of band (pickle protocol 5): one message of
    the objects and the buffers' sizes, then each buffer as it lies in memory, so neither
    process holds a pickled copy of the scans beside them (a large log's store is hundreds
    of MB)."""
    buffers: list[pickle.PickleBuffer] = []
    payload = pickle.dumps(read, protocol=5, buffer_callback=buffers.append)
    raws = [b.raw() for b in buffers]
    conn.send((payload, [r.nbytes for r in raws]))
    for raw in raws:
        conn.send_bytes(raw)


def _receive(conn: Connection) -> _Read | None:
    """What :func:`_send` sent (None where reading failed): each buffer received into
    writable memory of its own, which the arrays then use as they are."""
    got = conn.recv()
    if got is None:
        return None
    payload, sizes = got
    buffers = [bytearray(n) for n in sizes]
    for buffer in buffers:
        conn.recv_bytes_into(buffer)
    return cast(_Read, pickle.loads(payload, buffers=buffers))


class _Collector(logging.Handler):
    def __init__(self, records: list[logging.LogRecord]) -> None:
        super().__init__()
        self.records = records

    def emit(self, record: logging.LogRecord) -> None:
        self.records.append(record)


def _collect_records(records: list[logging.LogRecord]) -> None:
    """In the reading process: every log record goes to ``records`` instead of the handlers
    inherited from the calling process (which handles them once the store arrives)."""
    loggers = [logging.getLogger(), *logging.Logger.manager.loggerDict.values()]
    for logger in loggers:
        if isinstance(logger, logging.Logger):
            for handler in list(logger.handlers):
                logger.removeHandler(handler)
    logging.getLogger().addHandler(_Collector(records))
