"""Compact storage of a run's laser scans: a few growing numpy arrays instead of one
:class:`frontends.LaserScan` object per scan (docs/design.md "Scan storage").

A run keeps every input scan for the occupancy grid and for sessions. As Python objects a
361-beam scan costs about 7 KB (two float64 arrays, a dataclass, a pose array, an offset array,
a source string); here it costs its ranges in the narrowest of :data:`RANGE_ENCODINGS` that
gives back every float64 bit (a CARMEN log's ranges, printed with two decimals, as int16
centimetres: 722 bytes for 361 beams; a ROS bag's float32 ranges as float32) and a header of
about 100 bytes: the beam bearings are stored once per distinct bearing array (a log has one or
a few), and the source ``"path:line"`` as an index into a table of paths and the line number.
The encoded ranges fill fixed-size blocks (:data:`BLOCK_BYTES`) that are never copied: a
growing store allocates one more block, so its memory grows by the scans it holds, without the
transient copy of a buffer that doubles.

:meth:`ScanStore.__getitem__` rebuilds a scan equal to the one appended, value for value
(same ranges, bearings, poses, source), so :func:`iceg.session.scan_hash` and the grid see
exactly what the pipeline saw.
"""

from __future__ import annotations

import itertools
from collections.abc import Iterable, Iterator, Sequence
from typing import overload

import numpy as np
from numpy.typing import NDArray

from frontends import LaserScan
from iceg.grid import BeamChunk

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.int64]

#: Initial capacity (scans) of the header arrays.
_MIN_SCANS = 256

#: Size of one block of encoded ranges (bytes); a scan larger than this gets a block of its own.
BLOCK_BYTES = 1 << 22

#: Encodings of a scan's ranges, tried in order: ``(dtype, scale)``, stored as
#: ``round(range * scale)`` for an integer dtype (decoded as ``stored / scale``), as the
#: value for a float dtype. The first whose decoding gives back every float64 bit is used.
RANGE_ENCODINGS: tuple[tuple[type, float], ...] = (
    (np.int16, 100.0),  # centimetres up to 327 m: CARMEN ranges printed with two decimals
    (np.int32, 1000.0),  # millimetres: three decimals
    (np.float32, 1.0),  # a ROS bag's ranges, or a simulator's in float32
    (np.float64, 1.0),  # anything else
)

#: Header columns: name -> (dtype, trailing shape).
_HEADER: dict[str, tuple[type, tuple[int, ...]]] = {
    "stamp_s": (np.float64, ()),
    "range_min_m": (np.float64, ()),
    "range_max_m": (np.float64, ()),
    "odom": (np.float64, (3,)),  # NaN row: no odometry
    "has_odom": (np.bool_, ()),
    "offset": (np.float64, (3,)),
    "odom_break": (np.bool_, ()),
    "block": (np.int64, ()),  # index of the block holding the encoded ranges
    "byte_offset": (np.int64, ()),  # where they start in the block
    "encoding": (np.int8, ()),  # index into RANGE_ENCODINGS
    "n_beams": (np.int64, ()),
    "angles": (np.int64, ()),  # index into the table of bearing arrays
    "source": (np.int64, ()),  # index into the table of source prefixes
    "line": (np.int64, ()),  # source line (-1: the prefix is the whole source)
}


#: The scans stores gave out lately (:meth:`ScanStore.__getitem__`, iteration), by ``id``:
#: the bytes of their ranges then and their encoding there, ``(bytes, encoding index,
#: encoded array)``. A store that appends such a scan, its ranges' bytes unchanged, stores
#: that encoding instead of encoding them again (a run's store takes its scans from the
#: store its log was read into, a few scans behind). The bytes decide, not the ``id``: equal
#: bytes have the same encoding whatever object holds them.
_GIVEN: dict[int, tuple[bytes, int, np.ndarray]] = {}

#: The most scans :data:`_GIVEN` remembers (the oldest forgotten first).
_GIVEN_MAX = 64


def _split_line(source: str) -> tuple[str, int]:
    """``"path:123"`` -> ``("path", 123)`` when that round-trips exactly, else ``(source, -1)``."""
    head, sep, tail = source.rpartition(":")
    if sep and tail.isdigit() and str(int(tail)) == tail:
        return head, int(tail)
    return source, -1


class ScanStore(Sequence[LaserScan]):
    """An append-only sequence of laser scans held as flat arrays.

    Ranges are encoded losslessly (:data:`RANGE_ENCODINGS`) into fixed-size blocks; per scan
    a header row (stamp, range limits, odometry, laser offset, odometry break, where its
    ranges are and how they are encoded, indices of its bearing array and source). Indexing
    returns a new :class:`LaserScan` with the stored values, bit for bit (its arrays are new).

    Args:
        scans: Scans to start with, in order.
    """

    def __init__(self, scans: Iterable[LaserScan] = ()) -> None:
        self._n = 0
        self._head: dict[str, np.ndarray] = {
            k: np.zeros((_MIN_SCANS, *sh), dtype=dt) for k, (dt, sh) in _HEADER.items()
        }
        self._blocks: list[NDArray[np.uint8]] = []
        self._used = 0  # bytes used in the last block
        self._angle_table: list[FloatArray] = []
        self._angle_bits: list[bytes] = []  # each table entry's bytes, for the lookup
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
        ranges = np.asarray(scan.ranges_m, dtype=np.float64)
        known = _GIVEN.pop(id(scan), None)
        if known is not None and known[0] == ranges.tobytes():
            # read from a store: its encoding is the one _encode would choose (the ranges are
            # that encoding's exact decoding, so the same first encoding gives them back)
            encoding, encoded = known[1], known[2]
        else:
            encoding, encoded = _encode(ranges)
        h = self._head
        h["block"][n], h["byte_offset"][n] = self._put(encoded)
        h["encoding"][n] = encoding
        h["stamp_s"][n] = scan.stamp_s
        h["range_min_m"][n] = scan.range_min_m
        h["range_max_m"][n] = scan.range_max_m
        h["has_odom"][n] = scan.odom_pose is not None
        h["odom"][n] = np.nan if scan.odom_pose is None else scan.odom_pose
        h["offset"][n] = scan.laser_offset
        h["odom_break"][n] = scan.odom_break
        h["n_beams"][n] = b
        h["angles"][n] = self._angles_index(np.asarray(scan.angles_rad, dtype=np.float64))
        prefix, line = _split_line(scan.source)
        h["source"][n] = self._source_index.setdefault(prefix, len(self._source_table))
        if h["source"][n] == len(self._source_table):
            self._source_table.append(prefix)
        h["line"][n] = line
        self._n += 1

    def _put(self, encoded: np.ndarray) -> tuple[int, int]:
        """Copy ``encoded`` into the blocks, aligned to its item size; return (block, offset)."""
        size = encoded.nbytes
        offset = -(-self._used // encoded.itemsize) * encoded.itemsize
        if not self._blocks or offset + size > self._blocks[-1].shape[0]:
            self._blocks.append(np.empty(max(BLOCK_BYTES, size), dtype=np.uint8))
            offset = 0
        self._blocks[-1][offset : offset + size] = encoded.view(np.uint8)
        self._used = offset + size
        return len(self._blocks) - 1, offset

    def _ranges(self, k: int, count: int | None = None) -> FloatArray:
        """The ``count`` ranges (default: scan ``k``'s) stored from scan ``k``'s on in its
        block, decoded with its encoding (a new float64 array)."""
        return _decode(self._stored(k, count), RANGE_ENCODINGS[int(self._head["encoding"][k])][1])

    def _stored(self, k: int, count: int | None = None) -> np.ndarray:
        """The ``count`` encoded ranges (default: scan ``k``'s) from scan ``k``'s on: a view
        into its block, never to be written."""
        h = self._head
        return np.frombuffer(
            self._blocks[int(h["block"][k])],
            dtype=RANGE_ENCODINGS[int(h["encoding"][k])][0],
            count=int(h["n_beams"][k]) if count is None else count,
            offset=int(h["byte_offset"][k]),
        )

    def _angles_index(self, angles: FloatArray) -> int:
        """Index of the bearing array with the same bits in the table (the last one used is
        tried first): bits, not values, so that a bearing of -0.0 comes back as -0.0; one bytes
        comparison, a fraction of ``np.array_equal``'s cost."""
        bits = angles.tobytes()
        if self._n:
            last = int(self._head["angles"][self._n - 1])
            if self._angle_bits[last] == bits:
                return last
        for k, known in enumerate(self._angle_bits):
            if known == bits:
                return k
        self._angle_table.append(angles.copy())
        self._angle_bits.append(bits)
        return len(self._angle_table) - 1

    def __getstate__(self) -> dict[str, object]:
        """The pickled state (a store read in another process, :mod:`iceg.aside`):
        the header's rows (at least one: they grow by doubling) and the last block's used
        bytes, not their spare capacity (a later append starts a new block)."""
        state = dict(self.__dict__)
        state["_head"] = {k: v[: max(self._n, 1)] for k, v in self._head.items()}
        if self._blocks:
            state["_blocks"] = [*self._blocks[:-1], self._blocks[-1][: self._used]]
        return state

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
        line = int(h["line"][k])
        prefix = self._source_table[int(h["source"][k])]
        encoding = int(h["encoding"][k])
        stored = self._stored(k)
        ranges = _decode(stored, RANGE_ENCODINGS[encoding][1])
        scan = LaserScan(
            stamp_s=float(h["stamp_s"][k]),
            ranges_m=ranges,
            angles_rad=self._angle_table[int(h["angles"][k])].copy(),
            range_min_m=float(h["range_min_m"][k]),
            range_max_m=float(h["range_max_m"][k]),
            odom_pose=h["odom"][k].copy() if h["has_odom"][k] else None,
            laser_offset=h["offset"][k].copy(),
            source=prefix if line < 0 else f"{prefix}:{line}",
            odom_break=bool(h["odom_break"][k]),
        )
        _GIVEN.pop(id(scan), None)  # an id freed and taken again: the newest entry comes last
        _GIVEN[id(scan)] = (ranges.tobytes(), encoding, stored.copy())
        if len(_GIVEN) > _GIVEN_MAX:
            del _GIVEN[next(iter(_GIVEN))]
        return scan

    def sources(self) -> list[str]:
        """Every scan's ``source`` (``"path:line"``), as its :class:`LaserScan` gives it."""
        h, table, n = self._head, self._source_table, self._n
        return [
            table[s] if line < 0 else f"{table[s]}:{line}"
            for s, line in zip(h["source"][:n].tolist(), h["line"][:n].tolist(), strict=True)
        ]

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
        """Bytes held by the arrays, capacity included (the last block's unused bytes are
        allocated, but a fresh block's pages become resident only once written)."""
        return int(
            sum(b.nbytes for b in self._blocks)
            + sum(v.nbytes for v in self._head.values())
            + 2 * sum(a.nbytes for a in self._angle_table)  # the arrays and their bytes
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
        starts = np.concatenate([[0], np.cumsum(counts)])
        ranges = np.empty(int(starts[-1]))
        for a, b in self._runs(lo, hi):
            first, end = int(starts[a - lo]), int(starts[b - lo])
            ranges[first:end] = self._ranges(a, end - first)
        angles = np.empty(int(starts[-1]))
        which = h["angles"][lo:hi]
        for k, table in enumerate(self._angle_table):
            sel = np.flatnonzero(which == k)
            if sel.shape[0] == 0:
                continue
            idx = (starts[sel, None] + np.arange(table.shape[0])).reshape(-1)
            angles[idx] = np.tile(table, sel.shape[0])
        rmin = np.repeat(h["range_min_m"][lo:hi], counts)
        rmax = np.repeat(h["range_max_m"][lo:hi], counts)
        return BeamChunk(h["offset"][lo:hi].copy(), counts, ranges, angles, rmin, rmax)

    def _runs(self, lo: int, hi: int) -> list[tuple[int, int]]:
        """Scans ``[lo, hi)`` as runs ``[a, b)`` whose encoded ranges lie back to back in one
        block with one encoding, so each run decodes in one call."""
        if hi <= lo:
            return []
        h = self._head
        block, offset, enc = h["block"][lo:hi], h["byte_offset"][lo:hi], h["encoding"][lo:hi]
        item = np.array([np.dtype(d).itemsize for d, _ in RANGE_ENCODINGS])[enc]
        end = offset + item * h["n_beams"][lo:hi]
        joined = (block[1:] == block[:-1]) & (enc[1:] == enc[:-1]) & (offset[1:] == end[:-1])
        cuts = np.concatenate([[lo], lo + 1 + np.flatnonzero(~joined), [hi]]).tolist()
        return list(itertools.pairwise(cuts))


def odometry_of(
    scans: ScanStore | Sequence[LaserScan],
) -> tuple[FloatArray, FloatArray, NDArray[np.bool_]]:
    """Every scan's stamp ``(N,)`` (s), odometry pose ``(N, 3)`` float64 ``[x_m, y_m,
    theta_rad]`` (NaN rows: no odometry) and odometry break flag ``(N,)``, of a store
    (:attr:`ScanStore.odometry`) or a list of scans alike."""
    if isinstance(scans, ScanStore):
        return scans.odometry
    stamps = np.array([s.stamp_s for s in scans], dtype=np.float64)
    nan = np.full(3, np.nan)
    poses = np.array([nan if s.odom_pose is None else s.odom_pose for s in scans])
    breaks = np.array([s.odom_break for s in scans], dtype=bool)
    return stamps, poses.reshape(-1, 3).astype(np.float64), breaks


def _encode(ranges: FloatArray) -> tuple[int, np.ndarray]:
    """The first of :data:`RANGE_ENCODINGS` that gives back every bit of ``ranges``:
    ``(index, encoded array)``. An integer encoding stores ``rint(range * scale)``; its
    decoding lies within the dtype's limits over the scale whatever the cast made of a
    value beyond them (or of NaN, an infinity), so such a value never comes back, and
    -0.0 comes back as +0.0: comparing the bits decides. Numpy only: the process that
    reads the log (:mod:`iceg.aside`) calls no compiled kernel."""
    bits = ranges.view(np.int64)
    for k, (dtype, scale, integer) in enumerate(_ENCODING_TESTS):
        with np.errstate(over="ignore", invalid="ignore"):
            encoded: np.ndarray = (np.rint(ranges * scale) if integer else ranges).astype(dtype)
        if np.array_equal(_decode(encoded, scale).view(np.int64), bits):
            return k, encoded
    return len(RANGE_ENCODINGS) - 1, ranges.copy()


#: The encodings :func:`_encode` tests (all but the last): ``(dtype, scale, integer)``.
_ENCODING_TESTS: tuple[tuple[type, float, bool], ...] = tuple(
    (dtype, scale, bool(np.issubdtype(dtype, np.integer))) for dtype, scale in RANGE_ENCODINGS[:-1]
)


def _decode(stored: np.ndarray, scale: float) -> FloatArray:
    """Float64 ranges from their encoding (a new array)."""
    if np.issubdtype(stored.dtype, np.integer):
        return stored.astype(np.float64) / scale
    return stored.astype(np.float64)


def _grown(a: np.ndarray, rows: int) -> np.ndarray:
    out = np.zeros((rows, *a.shape[1:]), dtype=a.dtype)
    out[: a.shape[0]] = a
    return out


__all__ = ["ScanStore"]
