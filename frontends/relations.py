"""Benchmark relations of Kümmerle et al. 2009 (``*.relations``): reading, writing, matching.

R. Kümmerle, B. Steder, C. Dornhege, M. Ruhnke, G. Grisetti, C. Stachniss, A. Kleiner, "On
measuring the accuracy of SLAM algorithms", Autonomous Robots 27:387-407, 2009. Each line is
``t1 t2 x y z roll pitch yaw``: the pose at ``t2`` expressed in the frame of the pose at
``t1`` (``delta = pose(t1)^-1 ∘ pose(t2)``); ``t1``/``t2`` are ipc timestamps of laser
messages of the matching log. ``z roll pitch`` are 0 for the 2D datasets.

Quirks of published files handled here (``../shared/data/README.md``): double spaces, 5 or 6
decimals, lines with ``t1 > t2``, exact duplicate lines, unsorted lines.

Duplicates are counted and reported but **kept by default**, so that a score is the average
over every line of the file, as the figures quoted for the benchmark are. On MIT CSAIL, lines
1098 and 1099 are the same relation; keeping all 1172 lines gives raw odometry 1.681 m /
5.072 deg (the quoted 1.68 m / 5.07 deg), dropping the copy gives 1171 relations and
1.672 m / 5.062 deg. Pass ``drop_duplicates=True`` to score each distinct relation once.
"""

from __future__ import annotations

import logging
import math
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg_common import se2
from iceg_common.atomic import atomic_write
from iceg_common.errors import ConfigError, LogFormatError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]
IntArray = NDArray[np.intp]
BoolArray = NDArray[np.bool_]

#: Decimals written by :func:`write_relations`: timestamps in us, deltas in um / urad.
STAMP_DECIMALS = 6
DELTA_DECIMALS = 6

_N_FIELDS = 8
_PLANAR_ATOL = 1e-9


@dataclass(frozen=True, eq=False)
class Relations:
    """Ground-truth relative poses between pairs of scans (Kümmerle et al. 2009).

    Attributes:
        stamps_s: ``(M, 2)`` float64 ``[t1, t2]`` ipc timestamps in seconds, ``t1 <= t2``,
            rows sorted by ``t1`` then ``t2``.
        deltas: ``(M, 3)`` float64 ``[x_m, y_m, yaw_rad]`` = ``pose(t1)^-1 ∘ pose(t2)``, i.e.
            the pose at ``t2`` in the frame of the robot at ``t1``.
        source: The file read (or ``"<memory>"``).
        n_lines: Relation lines in the file (before dropping duplicates).
        n_duplicates: Lines that exactly repeat an earlier line (same eight numbers).
        n_duplicates_dropped: Of those, how many were dropped (``drop_duplicates=True``).
        n_swapped: Lines with ``t1 > t2`` that were swapped and their delta inverted.
    """

    stamps_s: FloatArray
    deltas: FloatArray
    source: str = "<memory>"
    n_lines: int = 0
    n_duplicates: int = 0
    n_duplicates_dropped: int = 0
    n_swapped: int = 0

    def __post_init__(self) -> None:
        stamps = np.asarray(self.stamps_s, dtype=np.float64).reshape(-1, 2)
        deltas = np.asarray(self.deltas, dtype=np.float64).reshape(-1, 3)
        if stamps.shape[0] != deltas.shape[0]:
            raise ValueError(
                f"{self.source}: {stamps.shape[0]} stamp pairs but {deltas.shape[0]} deltas"
            )
        object.__setattr__(self, "stamps_s", stamps)
        object.__setattr__(self, "deltas", deltas)

    def __len__(self) -> int:
        return int(self.stamps_s.shape[0])

    def __repr__(self) -> str:
        span = f", t {self.stamps_s.min():.3f}..{self.stamps_s.max():.3f} s" if len(self) else ""
        return f"Relations({len(self)} relations from {self.source!r}{span})"


def read_relations(path: str | Path, drop_duplicates: bool = False) -> Relations:
    """Read a ``.relations`` file (Kümmerle et al. 2009).

    Lines with ``t1 > t2`` are stored as ``(t2, t1)`` with the inverted delta
    (``se2.inverse``); exact duplicate lines (same eight numbers) are counted and a warning
    names them (kept unless ``drop_duplicates``); the result is sorted by ``t1`` then ``t2``.
    Blank lines and ``#`` comments are skipped. Pairs that appear with *different* deltas are
    all kept, and logged.

    Args:
        path: The relations file.
        drop_duplicates: Drop exact duplicate lines. Default ``False`` keeps every line, so
            scores average over the file's lines like the quoted benchmark figures (see the
            module docstring).

    Returns:
        A :class:`Relations` with ``(M, 2)`` stamps and ``(M, 3)`` deltas.

    Raises:
        LogFormatError: the file is missing, unreadable or holds no relation, or a line does
            not have 8 finite
            numbers or has a non-zero ``z``/``roll``/``pitch`` (``path:line`` in the message).
    """
    p = Path(path)
    rows, line_nos = _read_rows(p)
    n_lines = len(rows)
    rows, duplicates = _deduplicate(rows, line_nos, drop_duplicates)
    if duplicates:
        _warn_duplicates(p, duplicates, drop_duplicates)
    table = np.array(rows, dtype=np.float64).reshape(-1, _N_FIELDS)
    stamps = table[:, 0:2].copy()
    deltas = table[:, [2, 3, 7]].copy()
    swap = stamps[:, 0] > stamps[:, 1]
    n_swapped = int(swap.sum())
    if n_swapped:
        stamps[swap] = stamps[swap][:, ::-1]
        deltas[swap] = se2.inverse(deltas[swap])
        logger.info("%s: %d relation(s) had t1 > t2; swapped and inverted", p, n_swapped)
    order = np.lexsort((stamps[:, 1], stamps[:, 0]))
    stamps, deltas = stamps[order], deltas[order]
    _warn_conflicts(p, stamps, deltas)
    return Relations(
        stamps_s=stamps,
        deltas=deltas,
        source=str(p),
        n_lines=n_lines,
        n_duplicates=len(duplicates),
        n_duplicates_dropped=len(duplicates) if drop_duplicates else 0,
        n_swapped=n_swapped,
    )


def _read_rows(p: Path) -> tuple[list[tuple[float, ...]], list[int]]:
    """The numeric rows of a relations file and their line numbers (blank lines and ``#``
    comments skipped).

    Raises:
        LogFormatError: the file is unreadable, a line is malformed, or no line holds a relation.
    """
    rows: list[tuple[float, ...]] = []
    line_nos: list[int] = []
    try:
        with open(p, encoding="utf-8-sig", errors="replace") as fh:  # a BOM dropped
            for line_no, line in enumerate(fh, start=1):
                tokens = line.split()
                if not tokens or tokens[0].startswith("#"):
                    continue
                rows.append(_parse_line(p, line_no, tokens))
                line_nos.append(line_no)
    except OSError as exc:
        raise LogFormatError(f"{p}: cannot read the relations file ({exc})") from exc
    if not rows:
        raise LogFormatError(
            f"{p}: the file holds no relations (lines 't1 t2 x y z roll pitch yaw'); "
            "is it the right file?"
        )
    return rows, line_nos


def _deduplicate(
    rows: list[tuple[float, ...]], line_nos: list[int], drop: bool
) -> tuple[list[tuple[float, ...]], list[tuple[int, int]]]:
    """Rows kept (exact repeats dropped when ``drop``) and ``(line, earlier line it repeats)``
    for every exact repeat."""
    seen: dict[tuple[float, ...], int] = {}
    kept: list[tuple[float, ...]] = []
    duplicates: list[tuple[int, int]] = []
    for row, line_no in zip(rows, line_nos, strict=True):
        if row in seen:
            duplicates.append((line_no, seen[row]))
            if drop:
                continue
        else:
            seen[row] = line_no
        kept.append(row)
    return kept, duplicates


def _warn_duplicates(p: Path, duplicates: list[tuple[int, int]], dropped: bool) -> None:
    listed = ", ".join(f"line {a} repeats line {b}" for a, b in duplicates[:5])
    more = f" and {len(duplicates) - 5} more" if len(duplicates) > 5 else ""
    action = (
        "dropped"
        if dropped
        else "kept (scores average over every line); pass drop_duplicates=True to drop them"
    )
    logger.warning(
        "%s: %d exact duplicate relation line(s) (%s%s): %s",
        p,
        len(duplicates),
        listed,
        more,
        action,
    )


def _parse_line(path: Path, line_no: int, tokens: list[str]) -> tuple[float, ...]:
    if len(tokens) != _N_FIELDS:
        raise LogFormatError(
            f"{path}:{line_no}: a relation has {_N_FIELDS} fields (t1 t2 x y z roll pitch yaw) "
            f"but the line has {len(tokens)}; fix or delete the line"
        )
    values: list[float] = []
    for i, tok in enumerate(tokens):
        try:
            v = float(tok)
        except ValueError:
            raise LogFormatError(
                f"{path}:{line_no}: field {i + 1} ({tok!r}) is not a number; fix or delete the line"
            ) from None
        if not math.isfinite(v):
            raise LogFormatError(
                f"{path}:{line_no}: field {i + 1} is {tok!r}; relations need finite numbers, "
                "fix or delete the line"
            )
        values.append(v)
    if max(abs(values[4]), abs(values[5]), abs(values[6])) > _PLANAR_ATOL:
        raise LogFormatError(
            f"{path}:{line_no}: z/roll/pitch are {tokens[4]} {tokens[5]} {tokens[6]}; this "
            "reader handles planar (2D) relations only, where they are 0"
        )
    return tuple(values)


def _warn_conflicts(path: Path, stamps: FloatArray, deltas: FloatArray) -> None:
    """Log pairs ``(t1, t2)`` that appear more than once with different deltas."""
    if stamps.shape[0] < 2:
        return
    same = np.all(stamps[1:] == stamps[:-1], axis=1)
    if not same.any():
        return
    differ = same & np.any(deltas[1:] != deltas[:-1], axis=1)
    if differ.any():
        logger.warning(
            "%s: %d timestamp pair(s) appear more than once with different deltas; all kept",
            path,
            int(differ.sum()),
        )


def write_relations(path: str | Path, relations: Relations) -> None:
    """Write relations in the ``.relations`` format, atomically (temp file + ``os.replace``).

    Timestamps are written with ``%.6f`` (us) and ``x y yaw`` with ``%.6f`` (um, urad);
    ``z roll pitch`` as 0. A round trip through :func:`read_relations` is exact to that
    precision.

    Args:
        path: Destination file (its directory must exist).
        relations: What to write.

    Raises:
        LogFormatError: the file cannot be written.
    """
    p = Path(path)
    ts, dd = STAMP_DECIMALS, DELTA_DECIMALS
    try:
        with atomic_write(p, "w") as fh:
            for (t1, t2), (x, y, yaw) in zip(relations.stamps_s, relations.deltas, strict=True):
                fh.write(
                    f"{t1:.{ts}f} {t2:.{ts}f} {x:.{dd}f} {y:.{dd}f} 0.000000 0.000000 0.000000 "
                    f"{yaw:.{dd}f}\n"
                )
    except OSError as exc:
        raise LogFormatError(f"{p}: cannot write the relations file ({exc})") from exc


def match_stamps(
    query_s: ArrayLike, stamps_s: ArrayLike, tol_s: float
) -> tuple[IntArray, BoolArray]:
    """Nearest timestamp of ``stamps_s`` for each query, and whether it is within ``tol_s``.

    Relation timestamps match scan ipc timestamps by value, not by string (relations files
    round them to 5 or 6 decimals; ``../shared/data/README.md``).

    Args:
        query_s: ``(Q,)`` (or any shape) float64 query timestamps, seconds.
        stamps_s: ``(N,)`` float64 timestamps to search, seconds; need not be sorted.
        tol_s: Largest accepted ``|query - nearest|``, seconds (``>= 0``).

    Returns:
        ``(indices, ok_mask)`` of the query's shape: ``indices`` (intp) into ``stamps_s`` of
        the nearest stamp (the earlier one on a tie; 0 when ``stamps_s`` is empty), and
        ``ok_mask`` (bool) true where ``|query - stamps_s[index]| <= tol_s`` (false for NaN
        queries and when ``stamps_s`` is empty).

    Raises:
        ConfigError: ``tol_s`` is negative or not finite.
    """
    if not (math.isfinite(tol_s) and tol_s >= 0.0):
        raise ConfigError(f"match_stamps: tol_s must be a finite value >= 0, not {tol_s}")
    q = np.asarray(query_s, dtype=np.float64)
    s = np.asarray(stamps_s, dtype=np.float64).ravel()
    if s.shape[0] == 0:
        return np.zeros(q.shape, dtype=np.intp), np.zeros(q.shape, dtype=bool)
    if s.shape[0] > 1 and np.any(s[1:] < s[:-1]):
        order = np.argsort(s, kind="stable")
    else:
        order = np.arange(s.shape[0])
    sorted_s = s[order]
    hi = np.clip(np.searchsorted(sorted_s, q, side="left"), 0, s.shape[0] - 1)
    lo = np.clip(hi - 1, 0, s.shape[0] - 1)
    with np.errstate(invalid="ignore"):
        d_lo = np.abs(q - sorted_s[lo])
        d_hi = np.abs(q - sorted_s[hi])
        pick = np.where(d_lo <= d_hi, lo, hi)
        ok = np.abs(q - sorted_s[pick]) <= tol_s
    return order[pick].astype(np.intp), ok
