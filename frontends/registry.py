"""A registry of log readers, and ``open_log`` which picks one by suffix or first lines.

A reader registers itself with :func:`register_reader`; nothing here knows any format.
"""

from __future__ import annotations

import gzip
import io
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Protocol

from frontends.scan import LaserScan
from iceg_common.errors import LogFormatError


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
    """A registered reader: its name, the suffixes it claims, and a sniffer for first lines."""

    name: str
    suffixes: tuple[str, ...]
    sniff: Callable[[list[str]], bool]
    factory: Callable[..., LogReader]


_READERS: dict[str, ReaderSpec] = {}


def register_reader(
    name: str,
    suffixes: tuple[str, ...],
    sniff: Callable[[list[str]], bool],
) -> Callable[[Callable[..., LogReader]], Callable[..., LogReader]]:
    """Class decorator registering a reader under ``name`` for ``suffixes`` (e.g. ``".clf"``)."""

    def deco(factory: Callable[..., LogReader]) -> Callable[..., LogReader]:
        _READERS[name] = ReaderSpec(name, suffixes, sniff, factory)
        return factory

    return deco


def available_formats() -> list[str]:
    """Names of the registered readers."""
    return sorted(_READERS)


def open_text(path: Path) -> io.TextIOBase:
    """Open ``path`` for streaming text reading; ``.gz`` is decompressed transparently."""
    if path.suffix.lower() == ".gz":
        return io.TextIOWrapper(gzip.open(path, "rb"), encoding="utf-8", errors="replace")
    return open(path, encoding="utf-8", errors="replace")


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


def open_log(path: str | Path, format: str | None = None, **options: object) -> LogReader:
    """Open a laser log for streaming.

    Args:
        path: Log file; a ``.gz`` suffix is decompressed on the fly.
        format: A registered reader name (see :func:`available_formats`); by default the
            reader is chosen from the suffix (ignoring ``.gz``), else from the first lines.
        **options: Passed to the reader (e.g. ``strict=False`` for the CARMEN reader).

    Returns:
        A :class:`LogReader`: iterate it for :class:`~frontends.scan.LaserScan` records.

    Raises:
        LogFormatError: the file does not exist, or no reader recognises it.
    """
    import frontends.carmen  # noqa: F401  (registers the built-in readers)

    p = Path(path)
    if not p.is_file():
        raise LogFormatError(f"{p}: no such log file")
    if format is not None:
        if format not in _READERS:
            raise LogFormatError(
                f"unknown log format {format!r}; available: {', '.join(available_formats())}"
            )
        return _READERS[format].factory(p, **options)
    suffixes = [s.lower() for s in p.suffixes if s.lower() != ".gz"]
    suffix = suffixes[-1] if suffixes else ""
    for spec in _READERS.values():
        if suffix in spec.suffixes:
            return spec.factory(p, **options)
    head = _first_lines(p)
    for spec in _READERS.values():
        if spec.sniff(head):
            return spec.factory(p, **options)
    raise LogFormatError(
        f"{p}: not a recognised laser log (suffix {suffix!r}, and no reader recognised the "
        f"first lines); pass format= one of {', '.join(available_formats())}"
    )
