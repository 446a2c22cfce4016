"""Compact storage of a run's laser scans: a few growing numpy arrays instead of one
:class:`frontends.LaserScan` object per scan (docs/design.md "Scan storage").

A run keeps every input scan for the occupancy grid and for sessions. As Python objects a
361-beam scan costs about 7 KB (two float64 arrays, a dataclass, a pose array, an offset array,
a source string); here it costs its ranges (float64, exact) and a header of about 100 bytes:
the beam bearings are stored once per distinct bearing array (a log has one or a few), and
the source ``"path:line"`` as an index into a table of paths and the line number.

:meth:`ScanStore.__getitem__` rebuilds a scan equal to the one appended, value for value
(same ranges, bearings, poses, source), so :func:`iceg.session.scan_hash` and the grid see
exactly what the pipeline saw.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from typing import overload

import numpy as np
from numpy.typing import NDArray

from frontends import LaserScan
from iceg.grid import BeamChunk

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Initial capacity (scans) of the header arrays; beams start at this times 512.
_MIN_SCANS = 256

#: Header columns: name -> (dtype, trailing shape).
_HEADER: dict[str, tuple[type, tuple[int, ...]]] = {
    "stamp_s": (np.float64, ()),
    "range_min_m": (np.float64, ()),
    "range_max_m": (np.float64, ()),
    "odom": (np.float64, (3,)),  # NaN row: no odometry
    "has_odom": (np.bool_, ()),
    "offset": (np.float64, (3,)),
    "odom_break": (np.bool_, ()),
    "beam_start": (np.int64, ()),
    "n_beams": (np.int64, ()),
    "angles": (np.int64, ()),  # index into the table of bearing arrays
    "source": (np.int64, ()),  # index into the table of source prefixes
    "line": (np.int64, ()),  # source line (-1: the prefix is the whole source)
}


def _split_line(source: str) -> tuple[str, int]:
    """``"path:123"`` -> ``("path", 123)`` when that round-trips exactly, else ``(source, -1)``."""
    head, sep, tail = source.rpartition(":")
    if sep and tail.isdigit() and str(int(tail)) == tail:
        return head, int(tail)
    return source, -1


class ScanStore(Sequence[LaserScan]):
    """An append-only sequence of laser scans held as flat arrays.

    Ranges of all scans are one float64 array ``(total beams,)``; per scan a header row
    (stamp, range limits, odometry, laser offset, odometry break, beam slice, indices of its
    bearing array and source). Indexing returns a new :class:`LaserScan` with the stored
    values (its arrays are copies).

    Args:
        scans: Scans to start with, in order.
    """

    def __init__(self, scans: Iterable[LaserScan] = ()) -> None:
        self._n = 0
        self._n_beams = 0
        self._head: dict[str, np.ndarray] = {
            k: np.zeros((_MIN_SCANS, *sh), dtype=dt) for k, (dt, sh) in _HEADER.items()
        }
        self._ranges = np.zeros(_MIN_SCANS * 512)
        self._angle_table: list[FloatArray] = []
        self._source_table: list[str] = []
        self._source_index: dict[str, int] = {}
        for scan in scans:
            self.append(scan)

    # ------------------------------------------------------------------ building
    def append(self, scan: LaserScan) -> None:
        """Store one more scan (its arrays are copied)."""
        n, b = self._n, int(scan.ranges_m.shape[0])
        if n == self._head["stamp_s"].shape[0]:
            self._head = {k: _grown(v, 2 * n) for k, v in self._head.items()}
        if self._n_beams + b > self._ranges.shape[0]:
            self._ranges = _grown(self._ranges, max(2 * self._ranges.shape[0], self._n_beams + b))
        self._ranges[self._n_beams : self._n_beams + b] = scan.ranges_m
        h = self._head
        h["stamp_s"][n] = scan.stamp_s
        h["range_min_m"][n] = scan.range_min_m
        h["range_max_m"][n] = scan.range_max_m
        h["has_odom"][n] = scan.odom_pose is not None
        h["odom"][n] = np.nan if scan.odom_pose is None else scan.odom_pose
        h["offset"][n] = scan.laser_offset
        h["odom_break"][n] = scan.odom_break
        h["beam_start"][n] = self._n_beams
        h["n_beams"][n] = b
        h["angles"][n] = self._angles_index(np.asarray(scan.angles_rad, dtype=np.float64))
        prefix, line = _split_line(scan.source)
        h["source"][n] = self._source_index.setdefault(prefix, len(self._source_table))
        if h["source"][n] == len(self._source_table):
            self._source_table.append(prefix)
        h["line"][n] = line
        self._n += 1
        self._n_beams += b

    def _angles_index(self, angles: FloatArray) -> int:
        """Index of an equal bearing array in the table (the last one used is tried first)."""
        if self._n:
            last = int(self._head["angles"][self._n - 1])
            if np.array_equal(self._angle_table[last], angles):
                return last
        for k, known in enumerate(self._angle_table):
            if np.array_equal(known, angles):
                return k
        self._angle_table.append(angles.copy())
        return len(self._angle_table) - 1

    # ------------------------------------------------------------------ reading
    def __len__(self) -> int:
        return self._n

    @overload
    def __getitem__(self, index: int) -> LaserScan: ...

    @overload
    def __getitem__(self, index: slice) -> list[LaserScan]: ...

    def __getitem__(self, index: int | slice) -> LaserScan | list[LaserScan]:
        if isinstance(index, slice):
            return [self._scan(k) for k in range(*index.indices(self._n))]
        k = int(index)
        if k < 0:
            k += self._n
        if not 0 <= k < self._n:
            raise IndexError(f"scan index {index} out of range for {self._n} scans")
        return self._scan(k)

    def __iter__(self) -> Iterator[LaserScan]:
        for k in range(self._n):
            yield self._scan(k)

    def _scan(self, k: int) -> LaserScan:
        h = self._head
        start, b = int(h["beam_start"][k]), int(h["n_beams"][k])
        line = int(h["line"][k])
        prefix = self._source_table[int(h["source"][k])]
        return LaserScan(
            stamp_s=float(h["stamp_s"][k]),
            ranges_m=self._ranges[start : start + b].copy(),
            angles_rad=self._angle_table[int(h["angles"][k])].copy(),
            range_min_m=float(h["range_min_m"][k]),
            range_max_m=float(h["range_max_m"][k]),
            odom_pose=h["odom"][k].copy() if h["has_odom"][k] else None,
            laser_offset=h["offset"][k].copy(),
            source=prefix if line < 0 else f"{prefix}:{line}",
            odom_break=bool(h["odom_break"][k]),
        )

    def stamp_s(self, index: int) -> float:
        """Timestamp of scan ``index`` (s; negative indices count from the end)."""
        k = index + self._n if index < 0 else index
        if not 0 <= k < self._n:
            raise IndexError(f"scan index {index} out of range for {self._n} scans")
        return float(self._head["stamp_s"][k])

    @property
    def stamps_s(self) -> FloatArray:
        """``(N,)`` float64 timestamps of all scans (s), a copy."""
        return self._head["stamp_s"][: self._n].copy()

    @property
    def odometry(self) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
        """Copies of every scan's stamp ``(N,)`` (s), odometry pose ``(N, 3)`` float64
        ``[x_m, y_m, theta_rad]`` (NaN rows: no odometry) and odometry break flag ``(N,)``."""
        h, n = self._head, self._n
        return h["stamp_s"][:n].copy(), h["odom"][:n].copy(), h["odom_break"][:n].copy()

    @property
    def nbytes(self) -> int:
        """Bytes held by the arrays (capacity included)."""
        return int(
            self._ranges.nbytes
            + sum(v.nbytes for v in self._head.values())
            + sum(a.nbytes for a in self._angle_table)
        )

    def beams(self) -> tuple[IntArray, FloatArray, FloatArray, FloatArray, FloatArray, FloatArray]:
        """Every beam of every scan, flattened (for the occupancy grid), as new arrays.

        Returns:
            ``beam_counts`` ``(N,)`` int64, ``ranges_m`` ``(B,)``, ``angles_rad`` ``(B,)``
            laser frame, ``range_min_m`` ``(B,)``, ``range_max_m`` ``(B,)`` (each beam its
            scan's limits) and ``laser_offsets`` ``(N, 3)``; ``B`` the total beam count.
        """
        c = self.beam_chunk(0, self._n)
        return (
            c.beam_counts,
            c.ranges_m,
            c.angles_rad,
            c.range_min_m,
            c.range_max_m,
            c.laser_offsets,
        )

    def beam_chunk(self, lo: int, hi: int) -> BeamChunk:
        """The flattened beams of scans ``[lo, hi)`` as new arrays (the grid's chunk reader,
        :func:`iceg.grid.render_tiled_chunks`): memory of the chunk only.

        Raises:
            IndexError: ``[lo, hi)`` is not within ``[0, len(self)]``.
        """
        if not 0 <= lo <= hi <= self._n:
            raise IndexError(f"scans [{lo}, {hi}) outside a store of {self._n} scans")
        h = self._head
        counts = h["n_beams"][lo:hi].copy()
        starts = h["beam_start"][lo:hi]
        b0 = int(starts[0]) if hi > lo else 0
        b1 = int(starts[-1] + counts[-1]) if hi > lo else 0
        ranges = self._ranges[b0:b1].copy()
        angles = np.empty(b1 - b0)
        which = h["angles"][lo:hi]
        for k, table in enumerate(self._angle_table):
            sel = np.flatnonzero(which == k)
            if sel.shape[0] == 0:
                continue
            idx = (starts[sel, None] - b0 + np.arange(table.shape[0])).reshape(-1)
            angles[idx] = np.tile(table, sel.shape[0])
        rmin = np.repeat(h["range_min_m"][lo:hi], counts)
        rmax = np.repeat(h["range_max_m"][lo:hi], counts)
        return BeamChunk(h["offset"][lo:hi].copy(), counts, ranges, angles, rmin, rmax)


def _grown(a: np.ndarray, rows: int) -> np.ndarray:
    out = np.zeros((rows, *a.shape[1:]), dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


__all__ = ["ScanStore"]
