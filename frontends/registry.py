"""A registry of log readers, and ``open_log`` which picks one by suffix or first lines.

A reader registers itself with :func:`register_reader` (suffixes, a sniffer for a file's first
lines, optionally one for folders such as ROS 2 bags). This module knows no format itself;
:func:`open_log` imports the built-in readers (CARMEN, ROS bags) so that they register.
"""

from __future__ import annotations

import gzip
import inspect
import io
import math
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Protocol

import numpy as np
from numpy.typing import NDArray

from frontends.scan import LaserScan, StampReport
from iceg_common.errors import ConfigError, LogFormatError


class LogReader(Protocol):
    """What every reader returned by :func:`open_log` offers."""

    path: Path

    def __iter__(self) -> Iterator[LaserScan]:
        """Stream the scans in file order."""
        ...

    def count_scans(self) -> int:
        """Number of scans in the log (a fast pass that does not parse ranges)."""
        ...


@dataclass(frozen=True)
class ReaderSpec:
    """A registered reader: its name, the suffixes it claims, a sniffer for first lines, and
    optionally a sniffer for folders (a log that is a directory, e.g. a ROS 2 bag)."""

    name: str
    suffixes: tuple[str, ...]
    sniff: Callable[[list[str]], bool]
    factory: Callable[..., LogReader]
    sniff_dir: Callable[[Path], bool] | None = None


_READERS: dict[str, ReaderSpec] = {}


def register_reader(
    name: str,
    suffixes: tuple[str, ...],
    sniff: Callable[[list[str]], bool],
    sniff_dir: Callable[[Path], bool] | None = None,
) -> Callable[[Callable[..., LogReader]], Callable[..., LogReader]]:
    """Class decorator registering a reader under ``name`` for ``suffixes`` (e.g. ``".clf"``);
    ``sniff_dir`` claims folders (e.g. a ROS 2 bag folder holding ``metadata.yaml``)."""

    def deco(factory: Callable[..., LogReader]) -> Callable[..., LogReader]:
        _READERS[name] = ReaderSpec(name, suffixes, sniff, factory, sniff_dir)
        return factory

    return deco


def available_formats() -> list[str]:
    """Names of the registered readers."""
    return sorted(_READERS)


#: The first two bytes of a gzip stream (RFC 1952).
GZIP_MAGIC = b"\x1f\x8b"


def open_text(path: Path) -> io.TextIOBase:
    """Open ``path`` for streaming text reading. Gzip data is decompressed on the fly, told
    by its first two bytes (:data:`GZIP_MAGIC`), not by the suffix: a log saved compressed
    under ``.clf`` and a ``.gz`` that a download already decompressed both read. A UTF-8
    byte order mark at the start (which an editor on Windows may add) is dropped.

    Raises:
        OSError: the file cannot be opened.
    """
    with open(path, "rb") as fh:
        compressed = fh.read(len(GZIP_MAGIC)) == GZIP_MAGIC
    if compressed:
        return io.TextIOWrapper(gzip.open(path, "rb"), encoding="utf-8-sig", errors="replace")
    return open(path, encoding="utf-8-sig", errors="replace")


def _first_lines(path: Path, n: int = 50) -> list[str]:
    lines: list[str] = []
    try:
        with open_text(path) as fh:
            for line in fh:
                lines.append(line)
                if len(lines) >= n:
                    break
    except (OSError, EOFError) as exc:
        raise LogFormatError(f"{path}: cannot read the log ({exc})") from exc
    return lines


def open_log(
    path: str | Path,
    format: str | None = None,
    *,
    laser_only: bool = False,
    mirror_beams: bool = False,
    odometry_stalls_s: Sequence[Sequence[float]] = (),
    **options: Any,
) -> LogReader:
    """Open a laser log for streaming.

    Args:
        path: Log file (a ``.gz`` suffix is decompressed on the fly), or a folder a reader
            claims (a ROS 2 bag folder with ``metadata.yaml``).
        format: A registered reader name (see :func:`available_formats`); by default the
            reader is chosen from the suffix (ignoring ``.gz``), else from the first lines.
        laser_only: A reading without the odometry (:class:`AdjustedReader`): every scan
            comes with ``odom_pose=None``, as from a log without odometry. The log is read as
            it is otherwise (a bag's frames and laser mounting included).
        mirror_beams: Every scan's beams mirrored in the laser frame
            (:meth:`~frontends.scan.LaserScan.mirrored`): a laser mounted upside down that
            the log does not say is (:mod:`iceg.odometry_check` finds one).
        odometry_stalls_s: ``[start_s, end_s]`` stamp intervals (inclusive) whose scans are
            read without odometry: where it held one pose while the robot moved
            (:mod:`iceg.odometry_stalls` finds them).
        **options: Passed to the reader (e.g. ``strict=False`` for the CARMEN reader,
            ``scan_topic="/scan"`` for ROS bags).

    Returns:
        A :class:`LogReader`: iterate it for :class:`~frontends.scan.LaserScan` records.

    Raises:
        LogFormatError: the file does not exist, or no reader recognises it.
        ConfigError: the chosen reader takes none of ``options``' names.
    """
    _register_builtin_readers()
    p = Path(path)
    spec = _choose(p, format)
    signature = inspect.signature(spec.factory)
    try:
        signature.bind(p, **options)
    except TypeError as exc:
        takes = [name for name in list(signature.parameters)[1:] if name != "stamps"]
        strict = "strict" in options and "strict" not in takes
        raise ConfigError(
            f"{p}: the {spec.name} reader does not take these options ({exc}); it takes "
            f"{', '.join(takes)}"
            + (" (strict: --skip-malformed, for CARMEN logs)" if strict else "")
        ) from None
    reader = spec.factory(p, **options)
    if laser_only or mirror_beams or len(odometry_stalls_s):
        return AdjustedReader(reader, laser_only, mirror_beams, odometry_stalls_s)
    return reader


def adjust_scan(
    scan: LaserScan,
    laser_only: bool = False,
    mirror_beams: bool = False,
    odometry_stalls_s: Sequence[Sequence[float]] = (),
) -> LaserScan:
    """``scan`` as :class:`AdjustedReader` reads it with these options."""
    if laser_only or any(start <= scan.stamp_s <= end for start, end in odometry_stalls_s):
        scan = scan.without_odometry()
    return scan.mirrored() if mirror_beams else scan


class AdjustedReader:
    """A reader's scans read otherwise than the log has them: with their odometry left out
    (``laser_only``: ``odom_pose=None`` and no ``odom_break``; a laser-only run, e.g. of a
    log whose wheel odometry is wrong; the SLAM predicts each scan by constant velocity),
    and/or with their beams mirrored (``mirror_beams``: a laser mounted upside down), and/or
    the scans of stamp intervals without their odometry (``odometry_stalls_s``: where it held
    one pose while the robot moved). Everything else (stamps, laser mounting, sources) is the
    reader's.

    Args:
        reader: The log's own reader.
        laser_only: Leave the odometry out (:meth:`~frontends.scan.LaserScan.without_odometry`).
        mirror_beams: Mirror the beams (:meth:`~frontends.scan.LaserScan.mirrored`).
        odometry_stalls_s: ``[start_s, end_s]`` stamp intervals (inclusive) whose scans are
            read without odometry.

    Attributes:
        path: The log (the reader's).
    """

    def __init__(
        self,
        reader: LogReader,
        laser_only: bool = False,
        mirror_beams: bool = False,
        odometry_stalls_s: Sequence[Sequence[float]] = (),
    ) -> None:
        self.reader = reader
        self.path = reader.path
        self.laser_only = laser_only
        self.mirror_beams = mirror_beams
        self.odometry_stalls_s = [(float(a), float(b)) for a, b in odometry_stalls_s]

    @property
    def stamp_report(self) -> StampReport | None:
        """The reader's report of disordered stamps and odometry breaks, as it read the log
        (None for a reader without one)."""
        report = getattr(self.reader, "stamp_report", None)
        return report if isinstance(report, StampReport) else None

    def __iter__(self) -> Iterator[LaserScan]:
        for scan in self.reader:
            yield adjust_scan(scan, self.laser_only, self.mirror_beams, self.odometry_stalls_s)

    def count_scans(self) -> int:
        """Number of scans in the log (the reader's count)."""
        return self.reader.count_scans()


def _choose(p: Path, format: str | None) -> ReaderSpec:
    if format is not None:
        if format not in _READERS:
            raise LogFormatError(
                f"unknown log format {format!r}; available: {', '.join(available_formats())}"
            )
        if not p.exists():
            raise LogFormatError(f"{p}: no such log file")
        return _READERS[format]
    if p.is_dir():
        return folder_reader(p)
    if not p.is_file():
        raise LogFormatError(f"{p}: no such log file")
    suffixes = [s.lower() for s in p.suffixes if s.lower() != ".gz"]
    suffix = suffixes[-1] if suffixes else ""
    for spec in _READERS.values():
        if suffix in spec.suffixes:
            return spec
    head = _first_lines(p)
    for spec in _READERS.values():
        if spec.sniff(head):
            return spec
    own = sorted({x for spec in _READERS.values() for x in spec.suffixes if x})
    raise LogFormatError(
        f"{p}: not a recognised laser log (suffix {suffix!r}, and no reader recognised the "
        f"first lines); if it is one, give it a reader's suffix ({', '.join(own)}) or open it "
        f"with format= one of {', '.join(available_formats())}"
    )


def folder_reader(path: Path) -> ReaderSpec:
    """The reader that claims the folder ``path`` (a ROS 2 bag folder, which holds
    ``metadata.yaml``).

    Raises:
        LogFormatError: no reader claims it; the message names the log files the folder
            holds (a ROS 1 ``.bag``, a CARMEN ``.clf``), the first five, to pass instead.
    """
    _register_builtin_readers()
    for spec in _READERS.values():
        if spec.sniff_dir is not None and spec.sniff_dir(path):
            return spec
    logs = sorted(
        f.name
        for f in path.iterdir()
        if f.is_file() and any(f.name.lower().endswith(x) for x in _claimed_suffixes())
    )
    inside = f"; it holds {', '.join(logs[:5])}: pass the log file itself" if logs else ""
    raise LogFormatError(
        f"{path}: a folder no reader recognises (a ROS 2 bag folder holds metadata.yaml){inside}"
    )


def _register_builtin_readers() -> None:
    """Import the built-in readers (CARMEN, ROS bags): importing one registers it."""
    import frontends.carmen
    import frontends.rosbag  # noqa: F401


def _claimed_suffixes() -> set[str]:
    """The file suffixes some reader claims (``.clf``, ``.bag``, ...), with ``.gz`` forms."""
    out = {x for spec in _READERS.values() for x in spec.suffixes if x}
    return out | {x + ".gz" for x in out}


def describe_log(
    reader: LogReader, on_scan: Callable[[LaserScan], object] | None = None
) -> list[tuple[str, str]]:
    """``(key, value)`` rows saying what a log holds, for ``iceg info``.

    A reader with a ``describe()`` method (ROS bags: topics, types, counts, frames) answers
    itself; otherwise the scans are streamed once and summarized: count, duration, beams,
    range limits, returns (beams inside their scan's limits), odometry (and whether it is one
    pose throughout), the reader's skipped record types and where a recording was cut short,
    if it keeps them.

    Args:
        reader: The log's reader, not yet iterated.
        on_scan: Called with each streamed scan, for the caller's own look at them (not
            called by a reader that answers itself).

    Raises:
        LogFormatError: the log cannot be read or holds no scans.
    """
    describe = getattr(reader, "describe", None)
    if callable(describe):
        rows: list[tuple[str, str]] = describe()
        return rows
    n, with_odom, n_beams, n_returns, moved = 0, 0, 0, 0, False
    first: LaserScan | None = None
    last_stamp = math.nan
    beams: set[int] = set()
    limits: set[tuple[float, float]] = set()
    for scan in reader:
        if on_scan is not None:
            on_scan(scan)
        first = scan if first is None else first
        n += 1
        with_odom += scan.odom_pose is not None
        moved = moved or not _same_pose(scan.odom_pose, first.odom_pose)
        beams.add(scan.n_beams)
        n_beams += scan.n_beams
        n_returns += int(np.count_nonzero(scan.valid_mask()))
        limits.add((scan.range_min_m, scan.range_max_m))
        last_stamp = scan.stamp_s
    if first is None:
        raise LogFormatError(f"{reader.path}: the log holds no laser scans")
    odometry = f"{with_odom} of {n} scans have an odometry pose"
    if with_odom == n > 1 and not moved:  # as iceg.pipeline.motionless_odometry finds it
        odometry += "; the same pose in every scan: no motion (a run reads the log without it)"
    return [
        ("reader", type(reader).__name__),
        ("scans", str(n)),
        ("duration", f"{last_stamp - first.stamp_s:.1f} s"),
        ("beams", ", ".join(str(b) for b in sorted(beams))),
        ("range limits", ", ".join(f"{a:g} to {b:g} m" for a, b in sorted(limits))),
        (
            "returns",
            f"{n_returns} of {n_beams} beams ({100.0 * n_returns / max(n_beams, 1):.1f} %)",
        ),
        ("odometry", odometry),
        *_record_rows(reader),
    ]


def _same_pose(a: NDArray[np.float64] | None, b: NDArray[np.float64] | None) -> bool:
    """Whether two odometry poses (None: none) are the same, bit for bit."""
    if a is None or b is None:
        return a is b
    return bool(np.array_equal(a, b))


def _record_rows(reader: object) -> list[tuple[str, str]]:
    rows = []
    n_odom = getattr(reader, "n_odom_records", None)
    if isinstance(n_odom, int):
        rows.append(("ODOM records", str(n_odom)))
    skipped = getattr(reader, "skipped_records", None)
    if skipped:
        rows.append(("other records", ", ".join(f"{k} {v}" for k, v in sorted(skipped.items()))))
    cut = getattr(reader, "truncated_at", None)
    if isinstance(cut, int):
        rows.append(("cut short", f"the log ends inside a record at line {cut}"))
    return rows
