"""CARMEN laser logs: a streaming reader (FLASER, RLASER, ROBOTLASER1, RAWLASER1, ODOM, PARAM)
and a writer.

The format is the one of the CARMEN robot toolkit (Montemerlo, Roy, Thrun 2003) as written by
its logger and by GMapping into ``*-corrected`` logs; see ``../shared/data/README.md``. One
message per line; the last three fields of a message are always
``ipc_timestamp ipc_hostname logger_timestamp``::

    FLASER n r_1 .. r_n  x y theta  odom_x odom_y odom_theta            ts host ts
    RLASER n r_1 .. r_n  x y theta  odom_x odom_y odom_theta            ts host ts
    ROBOTLASER1 laser_type start_angle fov angular_res max_range accuracy remission_mode
                n r_1 .. r_n  n_rem rem_1 .. rem_nrem
                laser_x laser_y laser_theta  robot_x robot_y robot_theta
                tv rv forward_safety_dist side_safety_dist turn_axis     ts host ts
    RAWLASER1 laser_type start_angle fov angular_res max_range accuracy remission_mode
              n r_1 .. r_n  n_rem rem_1 .. rem_nrem                     ts host ts
    ODOM x y theta tv rv accel                                          ts host ts
    PARAM name value                                                    [ts host ts]

Angle conventions (FLASER/RLASER carry no angles): ``-pi/2 + i*pi/(n-1)`` for 181 or 361
beams (endpoint-inclusive 1 deg / 0.5 deg), ``-pi/2 + i*pi/n`` otherwise (GMapping's CARMEN
reader, ``carmenconfiguration.cpp``). ROBOTLASER1 and RAWLASER1: ``start_angle +
i*angular_res``.

``RAWLASER1`` is the front laser's own message (CARMEN's laser module; ``RAWLASER2-4`` are the
other lasers), without a pose. CARMEN's robot module republishes the same scans with poses as
``FLASER`` or ``ROBOTLASER1``, so a log holding both has every scan twice: the raw records are
read only from a log that holds none of the records with a pose, their odometry interpolated
from the ODOM records.
"""

from __future__ import annotations

import bisect
import contextlib
import dataclasses
import gzip
import logging
import math
import re
import zlib
from collections import Counter, deque
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Literal

import numpy as np
from numpy.typing import NDArray
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from frontends.registry import open_text, register_reader
from frontends.scan import LaserScan, StampPolicy, StampReport, order_by_stamp
from iceg_common import se2
from iceg_common.atomic import atomic_write
from iceg_common.errors import ConfigError, LogFormatError

logger = logging.getLogger(__name__)

FloatArray = NDArray[np.float64]

#: CARMEN's no-return value for FLASER/RLASER ranges (SICK LMS "max range" code, metres).
CARMEN_NO_RETURN_M = 81.91

_LASER_RECORDS = ("FLASER", "RLASER", "ROBOTLASER1")
#: The laser record without a pose that a log holding none of ``_LASER_RECORDS`` is read from.
_RAW_LASER = "RAWLASER1"
_SNIFF = re.compile(r"\s*(?:FLASER|RLASER|ROBOTLASER1|RAWLASER[1-4]|ODOM|PARAM)(?:\s|$)")
_LASER_LINE = re.compile(r"\s*(?:FLASER|RLASER|ROBOTLASER1)(?:\s|$)")
_RAW_LASER_LINE = re.compile(r"\s*RAWLASER1(?:\s|$)")
_ODOM_LINE = re.compile(r"\s*ODOM(?:\s|$)")
_RECORD_NAME = re.compile(r"[A-Z][A-Z0-9_]*\Z")
_FIX_HINT = (
    "fix or delete the line, or skip malformed lines (iceg --skip-malformed; "
    "CarmenReader(strict=False))"
)

# PARAM names this reader uses (anything else is skipped and counted as "PARAM").
_PARAM_FRONT_OFFSET = "robot_frontlaser_offset"
_PARAM_REAR_OFFSET = "robot_rearlaser_offset"
_PARAM_FRONT_MAX = ("robot_front_laser_max", "laser_front_laser_max_range")
_PARAM_REAR_MAX = ("robot_rear_laser_max", "laser_rear_laser_max_range")
_USED_PARAMS = frozenset(
    (_PARAM_FRONT_OFFSET, _PARAM_REAR_OFFSET, *_PARAM_FRONT_MAX, *_PARAM_REAR_MAX)
)

#: Decimals written by :func:`write_carmen`: ranges in mm, poses in um / urad, stamps in us.
RANGE_DECIMALS = 3
POSE_DECIMALS = 6
STAMP_DECIMALS = 6


class CarmenReaderConfig(BaseModel):
    """Options of :class:`CarmenReader` (validated; a bad value raises ``ConfigError``)."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    strict: bool = Field(
        True,
        description="Raise LogFormatError on the first malformed line (True), or skip malformed "
        "lines and list them in reader.malformed (False).",
    )
    odometry: Literal["record", "odom"] = Field(
        "record",
        description="Where a scan's odom_pose comes from: the pose inside the laser record "
        "('record'), or ODOM records interpolated at the scan's ipc timestamp ('odom').",
    )
    default_range_max_m: float = Field(
        CARMEN_NO_RETURN_M,
        gt=0.0,
        description="range_max_m of FLASER/RLASER scans when no PARAM gives the laser's max "
        "range: CARMEN's no-return value 81.91 m (../shared/data/README.md).",
    )
    max_pending_scans: int = Field(
        100_000,
        ge=1,
        description="With odometry='odom', how many scans may wait for the next ODOM record "
        "before the log is declared to lack odometry (bounds memory on a 1 GB log).",
    )
    stamps: StampPolicy = Field(
        "sort",
        description="Out-of-order or duplicate ipc timestamps: 'sort' reorders the scans "
        "(stable, warning with file:line), 'refuse' raises LogFormatError at the first.",
    )
    max_reorder_scans: int = Field(
        10_000,
        ge=1,
        description="With stamps='sort', how far (in scans) a scan may be out of "
        "order (the reorder buffer; bounds memory).",
    )
    odom_jump_m: float = Field(
        2.0,
        gt=0.0,
        allow_inf_nan=False,
        description="Odometry between consecutive scans longer than odom_jump_m + "
        "max_speed_mps * dt is a jump: the scan gets odom_break=True.",
    )
    max_speed_mps: float = Field(
        5.0,
        ge=0.0,
        allow_inf_nan=False,
        description="Fastest plausible robot speed for the jump test, m/s (MIT CSAIL's "
        "odometry peaks at 4.5 m/s between two scans).",
    )


class _Malformed(Exception):
    """A line that does not parse; carries the reason (without file:line)."""


@dataclass
class _Params:
    """PARAM values seen so far (a PARAM applies to the lines after it)."""

    front_offset_m: float | None = None
    rear_offset_m: float | None = None
    front_max_m: float | None = None
    rear_max_m: float | None = None


@dataclass
class _PendingScan:
    """A parsed laser record waiting for its odometry pose (``odometry="odom"``)."""

    line_no: int
    stamp_s: float
    ranges_m: FloatArray
    angles_rad: FloatArray
    range_max_m: float
    record_odom: FloatArray | None  # None: the record has no pose (RAWLASER1)
    laser_offset: FloatArray
    frame: str  # odometry frame: "FLASER" (FLASER/RLASER), "ROBOTLASER1", or "ODOM"


@dataclass(frozen=True)
class _RawLasers:
    """Whether a log's RAWLASER1 records are read (it holds no laser record with a pose) and
    whether it holds ODOM records to place them with."""

    read: bool
    has_odom: bool


def _sniff(lines: list[str]) -> bool:
    """True if any of the first lines starts with a CARMEN laser, ODOM or PARAM record."""
    return any(_SNIFF.match(line) for line in lines)


# ---------------------------------------------------------------------------------------------
# Token parsing helpers (raise _Malformed with a reason)
# ---------------------------------------------------------------------------------------------


def _ascii_number(tok: str, what: str) -> None:
    """Python's float()/int() also take '1_3.9' and non-ASCII digits; CARMEN numbers do not."""
    if "_" in tok or not tok.isascii():
        raise _Malformed(f"{what} {tok!r} is not a plain ASCII number")


def _float(tok: str, what: str) -> float:
    _ascii_number(tok, what)
    try:
        value = float(tok)
    except ValueError:
        raise _Malformed(f"{what} {tok!r} is not a number") from None
    if not math.isfinite(value):
        raise _Malformed(f"{what} is {tok!r}; it must be a finite number")
    return value


def _int(tok: str, what: str) -> int:
    _ascii_number(tok, what)
    try:
        value = int(tok)
    except ValueError:
        raise _Malformed(f"{what} {tok!r} is not a non-negative integer") from None
    if value < 0:
        raise _Malformed(f"{what} {tok!r} is not a non-negative integer")
    return value


def _pose(tokens: list[str], start: int, what: str) -> FloatArray:
    return np.array(
        [
            _float(tokens[start], f"{what} x"),
            _float(tokens[start + 1], f"{what} y"),
            _float(tokens[start + 2], f"{what} theta"),
        ]
    )


def _ranges(tokens: list[str], start: int, n: int, record: str) -> FloatArray:
    """``(n,)`` ranges; NaN or +-inf becomes +inf (a no-return beam)."""
    chunk = tokens[start : start + n]
    joined = "".join(chunk)
    if "_" in joined or not joined.isascii():
        for i, tok in enumerate(chunk):
            _ascii_number(tok, f"{record} range value {i + 1} of {n}")
    try:
        r = np.fromiter(map(float, chunk), np.float64, n)
    except ValueError:
        for i, tok in enumerate(chunk):
            try:
                float(tok)
            except ValueError:
                raise _Malformed(
                    f"{record} range value {i + 1} of {n} ({tok!r}) is not a number"
                ) from None
        raise  # pragma: no cover  (numpy and float() agree on what parses)
    if not np.isfinite(r).all():
        r[~np.isfinite(r)] = np.inf
    return r


def _numbers(tokens: list[str], start: int, stop: int, what: str) -> None:
    """Check that ``tokens[start:stop]`` are numbers (values unused, e.g. remissions)."""
    for tok in tokens[start:stop]:
        _ascii_number(tok, what)
        try:
            float(tok)
        except ValueError:
            raise _Malformed(f"{what} {tok!r} is not a number") from None


def _trailer(tokens: list[str], record: str) -> float:
    """The ipc timestamp from the trailing ``ipc_ts host logger_ts`` (also checks logger_ts)."""
    _float(tokens[-1], f"{record} logger timestamp")
    return _float(tokens[-3], f"{record} ipc timestamp")


_ANGLE_CACHE: dict[tuple[str, int] | tuple[str, str, str, int], FloatArray] = {}


def _readonly(a: NDArray[np.floating]) -> FloatArray:
    out = np.asarray(a, dtype=np.float64)
    out.flags.writeable = False
    return out


def flaser_angles(n: int) -> FloatArray:
    """Beam bearings of an ``n``-beam FLASER/RLASER scan in the laser frame.

    Args:
        n: Number of beams.

    Returns:
        ``(n,)`` float64 radians (read-only, shared between scans): ``-pi/2 + i*pi/(n-1)`` for
        181 or 361 beams, ``-pi/2 + i*pi/n`` otherwise (GMapping's CARMEN convention, see
        ``../shared/data/README.md``).
    """
    key = ("F", n)
    angles = _ANGLE_CACHE.get(key)
    if angles is None:
        step = math.pi / (n - 1) if n in (181, 361) else math.pi / max(n, 1)
        angles = _readonly(-math.pi / 2 + np.arange(n, dtype=np.float64) * step)
        _ANGLE_CACHE[key] = angles
    return angles


def _configured_angles(start_tok: str, res_tok: str, n: int, kind: str) -> FloatArray:
    """``start_angle + i*angular_res`` of a ROBOTLASER1 or RAWLASER1 record (cached)."""
    key = ("R", start_tok, res_tok, n)
    angles = _ANGLE_CACHE.get(key)
    if angles is None:
        start = _float(start_tok, f"{kind} start_angle")
        res = _float(res_tok, f"{kind} angular_res")
        angles = _readonly(start + np.arange(n, dtype=np.float64) * res)
        if len(_ANGLE_CACHE) > 1024:
            _ANGLE_CACHE.clear()
        _ANGLE_CACHE[key] = angles
    return angles


#: Fields after the remissions: RAWLASER1 ends with ``ipc_timestamp ipc_hostname
#: logger_timestamp``; ROBOTLASER1 has 11 more before them (laser and robot poses, ``tv rv``,
#: two safety distances, the turn axis).
_TRAILER_FIELDS = 3
_ROBOTLASER_TAIL = 11 + _TRAILER_FIELDS


@dataclass(frozen=True)
class _Beams:
    """The beams of a ROBOTLASER1 or RAWLASER1 record, and where its tail starts."""

    ranges_m: FloatArray
    angles_rad: FloatArray
    range_max_m: float
    tail: int  # index of the first field after the remissions


def _configured_beams(tokens: list[str], kind: str, tail_fields: int) -> _Beams:
    """The laser configuration, ranges and remissions that ROBOTLASER1 and RAWLASER1 records
    share (``laser_type start_angle fov angular_res max_range accuracy remission_mode n
    r_1..r_n n_rem rem_1..rem_nrem``), the record ending ``tail_fields`` fields later.

    Raises:
        _Malformed: a field is not a number, or the counts and the line's length disagree.
    """
    if len(tokens) < 9:
        raise _Malformed(
            f"{kind} record has {len(tokens)} fields; the header alone needs 9 (a truncated line?)"
        )
    _numbers(tokens, 1, 2, f"{kind} laser_type")
    max_range = _float(tokens[5], f"{kind} max_range")
    if max_range <= 0.0:
        raise _Malformed(f"{kind} max_range {tokens[5]!r} must be positive")
    _numbers(tokens, 3, 4, f"{kind} fov")
    _numbers(tokens, 6, 8, f"{kind} accuracy/remission_mode")
    n = _int(tokens[8], f"{kind} beam count")
    if len(tokens) < 9 + n + 1:
        raise _Malformed(
            f"{kind} declares {n} beams but the line ends after {len(tokens) - 9} values "
            "(a truncated line?)"
        )
    n_rem = _int(tokens[9 + n], f"{kind} remission count (field {10 + n}, after {n} beams)")
    expected = 10 + n + n_rem + tail_fields
    if len(tokens) != expected:
        raise _Malformed(
            f"{kind} declares {n} beams and {n_rem} remission values: {expected} fields "
            f"expected, the line has {len(tokens)} (wrong beam count, or a truncated line?)"
        )
    ranges = _ranges(tokens, 9, n, kind)
    _numbers(tokens, 10 + n, 10 + n + n_rem, f"{kind} remission value")
    angles = _configured_angles(tokens[2], tokens[4], n, kind)
    return _Beams(ranges, angles, max_range, 10 + n + n_rem)


# ---------------------------------------------------------------------------------------------
# The reader
# ---------------------------------------------------------------------------------------------


@register_reader("carmen", (".clf", ".log", ".carmen"), _sniff)
class CarmenReader:
    """Stream :class:`~frontends.scan.LaserScan` records from a CARMEN log (``.gz`` allowed).

    The file is read line by line, never whole. Record handling:

    - ``FLASER`` / ``RLASER``: ``x y theta`` is the **laser** pose and ``odom_*`` the robot
      odometry pose. ``laser_offset = between(odom, laser)``, unless a preceding PARAM gives
      ``robot_frontlaser_offset`` (FLASER: ``[offset, 0, 0]``) or ``robot_rearlaser_offset``
      (RLASER: ``[offset, 0, pi]``, as GMapping's reader does). ``range_max_m`` is PARAM
      ``robot_front_laser_max`` / ``laser_front_laser_max_range`` (``rear`` for RLASER) if
      given, else 81.91 (CARMEN's no-return value; validity is strict ``r < range_max_m``).
      Angles: see :func:`flaser_angles`.
    - ``ROBOTLASER1``: angles ``start_angle + i*angular_res``, ``range_max_m = max_range``,
      ``odom_pose`` the robot pose, ``laser_offset = between(robot, laser)``.
    - ``RAWLASER1`` (the front laser's message, no pose), read only from a log that holds no
      FLASER, RLASER or ROBOTLASER1 record (a log with both has each scan twice; the first
      RAWLASER1 record sets off one pass over the log's first words to tell): angles and
      ``range_max_m`` as ROBOTLASER1, ``laser_offset`` ``[offset, 0, 0]`` from PARAM
      ``robot_frontlaser_offset`` (else zero), ``odom_pose`` interpolated from the ODOM
      records as with ``odometry="odom"`` in either mode, or None in a log without ODOM
      records (a laser-only run). Otherwise, and ``RAWLASER2``-``RAWLASER4`` (lasers whose
      mounting the log does not give) always, they are skipped and counted.
    - ``ODOM``: with ``odometry="odom"`` a scan's ``odom_pose`` is interpolated (linear in
      x, y and in the wrapped heading difference) between the ODOM records bracketing its
      ipc timestamp; scans wait until an ODOM record at or after their stamp arrives, scans
      before the first ODOM take the first one and scans after the last take the last one.
      With ``odometry="record"`` (default) ODOM lines are only checked and counted, unless
      RAWLASER1 records are read.
    - Everything else (NEFF, PARAMs not listed above, g2o ``VERTEX_SE2``/``EDGE_SE2``,
      ``#`` comments, blank lines, any other upper-case record name) is skipped and counted in
      :attr:`skipped_records` by type (``"comment"``, ``"blank"`` or the record name).

    ``stamp_s`` is the ipc timestamp (first of the three trailing fields); ``range_min_m`` is
    0. A range value ``nan``/``inf`` is read as a no-return beam and stored as ``+inf``; NaN or
    inf in a pose, a timestamp or a header field is malformed.

    Scans are yielded in ipc-timestamp order: ``stamps="sort"`` (default) reorders
    out-of-order scans (stable, through a buffer of ``max_reorder_scans``) and warns with the
    first ``path:line``; ``stamps="refuse"`` raises at the first stamp not after the previous
    one. :attr:`stamp_report` counts them. A scan whose odometry is discontinuous with the
    previous scan's gets ``odom_break=True`` (warning with ``path:line``): a step longer than
    ``odom_jump_m + max_speed_mps * dt``, or a change of odometry frame (FLASER/RLASER
    records to ROBOTLASER1 records or back, in a mixed log with ``odometry="record"``).

    Numbers are ASCII float syntax only (Python's ``float`` also takes ``1_3.9`` and
    full-width digits: those lines are malformed). A malformed line (wrong beam count,
    non-numeric token, non-finite pose or stamp, truncated
    record, missing trailing fields, a first token that is not a record name) raises
    :class:`~iceg_common.errors.LogFormatError` ``"path:line: what is wrong; what to do"`` in
    strict mode. With ``strict=False`` it is skipped, listed in :attr:`malformed` as
    ``(line_number, reason)`` and summarized in one warning at the end of the iteration.

    A log whose recording was interrupted (the logger killed, the disk full, a copy cut
    short) ends inside a record. That is read in either mode up to the last complete record,
    with one warning naming the file and line, and :attr:`truncated_at` set: a malformed
    last line without a newline after it (the file ends inside it), or a ``.gz`` stream that
    ends before its end-of-stream marker (the text after the last whole line decompressed
    is lost with the missing bytes). A malformed line anywhere else stays malformed.

    Attributes:
        path: The log file.
        config: The validated :class:`CarmenReaderConfig`.
        skipped_records: ``Counter`` of skipped lines by type, filled during iteration.
        malformed: ``(line_number, reason)`` of lines skipped in lenient mode.
        truncated_at: After an iteration over a log whose recording was cut short, the line
            where it ends (the incomplete line left out, or the last line read before a
            ``.gz`` stream ended early); None for a log that ends after a whole record.
        n_odom_records: ODOM records seen during the last iteration.
        stamp_report: timestamp disorder and odometry breaks of the last iteration
            (:class:`~frontends.scan.StampReport`).

    Raises:
        ConfigError: an option is invalid (e.g. ``odometry="wheel"``).
    """

    def __init__(
        self,
        path: str | Path,
        strict: bool = True,
        odometry: str = "record",
        default_range_max_m: float = CARMEN_NO_RETURN_M,
        max_pending_scans: int = 100_000,
        stamps: str = "sort",
        max_reorder_scans: int = 10_000,
        odom_jump_m: float = 2.0,
        max_speed_mps: float = 5.0,
    ) -> None:
        try:
            self.config = CarmenReaderConfig(
                strict=strict,
                odometry=odometry,  # type: ignore[arg-type]
                default_range_max_m=default_range_max_m,
                max_pending_scans=max_pending_scans,
                stamps=stamps,  # type: ignore[arg-type]
                max_reorder_scans=max_reorder_scans,
                odom_jump_m=odom_jump_m,
                max_speed_mps=max_speed_mps,
            )
        except ValidationError as exc:
            raise ConfigError(f"CarmenReader options: {exc}") from exc
        self.path = Path(path)
        self.skipped_records: Counter[str] = Counter()
        self.malformed: list[tuple[int, str]] = []
        self.truncated_at: int | None = None
        self.n_odom_records = 0
        self.stamp_report = StampReport(policy=self.config.stamps)
        self._line_no = 0  # the last line read by _record_lines
        self._unterminated = 0  # the line the file ends inside (no newline after it), or 0
        self._raw: _RawLasers | None = None  # set at the first RAWLASER1 record (_raw_lasers)

    @property
    def strict(self) -> bool:
        """Whether a malformed line raises (True) or is skipped and listed (False)."""
        return self.config.strict

    def __repr__(self) -> str:
        return (
            f"CarmenReader({str(self.path)!r}, strict={self.config.strict}, "
            f"odometry={self.config.odometry!r})"
        )

    def count_scans(self) -> int:
        """Number of laser records the log is read from: FLASER, RLASER and ROBOTLASER1, or
        RAWLASER1 in a log without those (see the class).

        A fast pass that looks only at the first token of each line and parses no ranges, so
        malformed laser records are counted too (in lenient mode iteration may yield fewer).

        Raises:
            LogFormatError: the file cannot be read.
        """
        match, match_raw = _LASER_LINE.match, _RAW_LASER_LINE.match
        count = raw = 0
        with self._quick_pass() as lines:
            for line in lines:
                if match(line):
                    count += 1
                elif match_raw(line):
                    raw += 1
        return count or raw

    @contextlib.contextmanager
    def _quick_pass(self) -> Iterator[Iterable[str]]:
        """The log's lines for a pass that reads their first words only; a ``.gz`` cut short
        ends it at the cut (see the class).

        Raises:
            LogFormatError: the file cannot be read.
        """
        try:
            with open_text(self.path) as fh:
                yield fh
        except EOFError:  # a .gz cut short: the records before the cut
            pass
        except (OSError, zlib.error) as exc:
            raise LogFormatError(f"{self.path}: cannot read the log ({exc})") from exc

    def _raw_lasers(self) -> _RawLasers:
        """Whether this log's RAWLASER1 records are read: one pass over the first words of its
        lines, to the first laser record with a pose (then not) or to the end (then they
        are; and whether it holds ODOM records). Kept for the iteration.

        Raises:
            LogFormatError: the file cannot be read.
        """
        if self._raw is None:
            has_odom = False
            with self._quick_pass() as lines:
                for line in lines:
                    if _LASER_LINE.match(line):
                        self._raw = _RawLasers(read=False, has_odom=has_odom)
                        return self._raw
                    has_odom = has_odom or _ODOM_LINE.match(line) is not None
            self._raw = _RawLasers(read=True, has_odom=has_odom)
        return self._raw

    def __iter__(self) -> Iterator[LaserScan]:
        """Stream the scans in timestamp order (see the class docstring for the rules).

        Raises:
            LogFormatError: the file cannot be read; in strict mode, a malformed line; with
                ``odometry="odom"``, a log without usable ODOM records; with
                ``stamps="refuse"``, a timestamp not after the previous one.
        """
        self.stamp_report = StampReport(policy=self.config.stamps)
        ordered = order_by_stamp(self._records(), self.stamp_report, self.config.max_reorder_scans)
        previous: tuple[str, LaserScan] | None = None
        for frame, scan in ordered:
            reason = None if previous is None else self._odom_break(previous, frame, scan)
            if reason is not None:
                scan = dataclasses.replace(scan, odom_break=True)
                self._note_break(scan, reason)
            previous = (frame, scan)
            yield scan
        breaks = self.stamp_report.odometry_breaks
        if len(breaks) > _LOGGED_BREAKS:
            logger.warning(
                "%s: %d odometry breaks in all (first at %s: %s)",
                self.path,
                len(breaks),
                *breaks[0],
            )

    def _odom_break(
        self, previous: tuple[str, LaserScan], frame: str, scan: LaserScan
    ) -> str | None:
        """Why the odometry from the previous scan to ``scan`` is not a motion, or None."""
        prev_frame, prev = previous
        if frame != prev_frame:
            return (
                f"odometry switches from {prev_frame} to {frame} records (two odometry "
                "frames in one log)"
            )
        if prev.odom_pose is None or scan.odom_pose is None:
            return None
        step = math.hypot(*(scan.odom_pose[:2] - prev.odom_pose[:2]))
        dt = max(scan.stamp_s - prev.stamp_s, 0.0)
        limit = self.config.odom_jump_m + self.config.max_speed_mps * dt
        if step > limit:
            return f"odometry jumps {step:.2f} m in {dt:.3f} s (more than {limit:.2f} m)"
        return None

    def _note_break(self, scan: LaserScan, reason: str) -> None:
        breaks = self.stamp_report.odometry_breaks
        breaks.append((scan.source, reason))
        if len(breaks) <= _LOGGED_BREAKS:
            logger.warning("%s: %s; no odometry factor across it", scan.source, reason)

    def _records(self) -> Iterator[tuple[str, LaserScan]]:
        """``(odometry frame, scan)`` in file order."""
        self.skipped_records = Counter()
        self.malformed = []
        self.truncated_at = None
        self._line_no = self._unterminated = 0
        self.n_odom_records = 0
        self._raw = None
        params = _Params()
        use_odom = self.config.odometry == "odom"
        odom = _OdomTrack()
        n_scans = 0
        try:
            with open_text(self.path) as fh:
                try:
                    for line_no, kind, tokens in self._record_lines(fh):
                        try:
                            item = self._parse_record(kind, tokens, params, line_no, use_odom)
                        except _Malformed as exc:
                            if line_no == self._unterminated:
                                self._cut_short(
                                    line_no, "the log ends inside this line: it is left out"
                                )
                            else:
                                self._malformed(line_no, str(exc))
                            continue
                        if item is None:
                            continue
                        if isinstance(item, _PendingScan):
                            # a RAWLASER1 scan has no pose: the ODOM records place it
                            by_odom = use_odom or (
                                item.record_odom is None and self._raw_lasers().has_odom
                            )
                            ready = self._place_scan(item, odom, by_odom, line_no)
                        else:
                            ready = [
                                ("ODOM", self._finish(sc, odom.t, odom.p)) for sc in odom.add(*item)
                            ]
                        n_scans += len(ready)
                        yield from ready
                except EOFError as exc:  # a .gz stream without its end: read up to the cut
                    self._cut_short(
                        self._line_no,
                        f"the compressed log ends after this line ({exc}): the rest of "
                        "the recording is not in the file",
                    )
        except (OSError, EOFError, zlib.error) as exc:
            raise LogFormatError(f"{self.path}: cannot read the log ({exc})") from exc
        for scan in self._flush_pending(odom):
            n_scans += 1
            yield "ODOM", scan
        if self._raw is not None and self._raw.read:
            self.skipped_records.pop("ODOM", None)  # they placed the RAWLASER1 scans
        if n_scans == 0:
            self._refuse_unread_lasers()
        self._warn_malformed(n_scans)

    def _refuse_unread_lasers(self) -> None:
        """For a log that gave no scan: refuse it if it holds laser records of a kind this
        reader does not read, naming them (a log of ``RAWLASER2`` records, say).

        Raises:
            LogFormatError: the log holds such records.
        """
        unread = sorted(k for k in self.skipped_records if "LASER" in k)
        if unread:
            held = ", ".join(f"{self.skipped_records[k]} {k}" for k in unread)
            raise LogFormatError(
                f"{self.path}: the log's laser records ({held}) are of a kind this reader does "
                "not read; it reads FLASER, RLASER and ROBOTLASER1 records, or RAWLASER1 (the "
                "front laser) from a log without those"
            )

    def _record_lines(self, fh: Iterable[str]) -> Iterator[tuple[int, str, list[str]]]:
        """``(line number, record name, tokens)`` of every line that is not blank or a comment
        (those are counted in :attr:`skipped_records`)."""
        for line_no, line in enumerate(fh, start=1):
            self._line_no = line_no
            if not line.endswith("\n"):  # only the last line can lack it
                self._unterminated = line_no
            tokens = line.split()
            if not tokens:
                self.skipped_records["blank"] += 1
            elif tokens[0].startswith("#"):
                self.skipped_records["comment"] += 1
            else:
                yield line_no, tokens[0], tokens

    def _parse_record(
        self, kind: str, tokens: list[str], params: _Params, line_no: int, use_odom: bool
    ) -> _PendingScan | tuple[float, FloatArray] | None:
        """A laser record's scan, an ODOM record's ``(stamp, pose)``, or ``None`` for a record
        that is skipped (counted) or a PARAM.

        Raises:
            _Malformed: the line is not a valid record.
        """
        if kind in _LASER_RECORDS:
            return self._parse_laser(kind, tokens, params, line_no)
        if kind == _RAW_LASER and self._raw_lasers().read:
            return self._parse_rawlaser(tokens, params, line_no)
        if kind == "ODOM":
            t, pose = self._parse_odom(tokens)
            self.n_odom_records += 1
            if not use_odom:
                self.skipped_records["ODOM"] += 1
            return t, pose  # kept in either mode: RAWLASER1 scans are placed with them
        if kind == "PARAM":
            if not self._parse_param(tokens, params):
                self.skipped_records["PARAM"] += 1
        elif _RECORD_NAME.match(kind):
            self.skipped_records[kind] += 1
        else:
            raise _Malformed(
                f"the line starts with {kind[:40]!r}, which is not a CARMEN record name (a "
                "broken or wrapped line?)"
            )
        return None

    def _place_scan(
        self, scan: _PendingScan, odom: _OdomTrack, use_odom: bool, line_no: int
    ) -> list[tuple[str, LaserScan]]:
        """The scans ready to yield once ``scan`` is read: itself when its odometry is known
        (in the record, or ODOM records at or after its stamp), else none (it waits).

        Raises:
            LogFormatError: more than ``max_pending_scans`` scans wait for an ODOM record.
        """
        if not use_odom:
            return [(scan.frame, self._finish(scan, None, None))]
        if not odom.pending and odom.t and scan.stamp_s <= odom.t[-1]:
            return [("ODOM", self._finish(scan, odom.t, odom.p))]
        odom.pending.append(scan)
        if len(odom.pending) > self.config.max_pending_scans:
            hint = (
                "RAWLASER1 records carry no pose of their own"
                if scan.record_odom is None
                else "open the log with odometry='record' to use the poses inside the laser records"
            )
            raise LogFormatError(
                f"{self.path}:{line_no}: {len(odom.pending)} scans since line "
                f"{odom.pending[0].line_no} have no ODOM record at or after their timestamp; "
                f"{hint}"
            )
        return []

    def _flush_pending(self, odom: _OdomTrack) -> Iterator[LaserScan]:
        """Scans still waiting at the end of the file, interpolated with the last ODOM poses.

        Raises:
            LogFormatError: scans wait but the log has no valid ODOM record at all.
        """
        if odom.pending and not odom.t:
            if odom.pending[0].record_odom is None:
                raise LogFormatError(
                    f"{self.path}: the log has no valid ODOM record to place its "
                    f"{len(odom.pending)} RAWLASER1 scans (they carry no pose of their own)"
                )
            raise LogFormatError(
                f"{self.path}: odometry='odom' but the log has no valid ODOM record for its "
                f"{len(odom.pending)} scans; open it with odometry='record' to use the poses "
                "inside the laser records"
            )
        while odom.pending:
            yield self._finish(odom.pending.popleft(), odom.t, odom.p)

    def _warn_malformed(self, n_scans: int) -> None:
        if self.malformed:
            first_line, first_reason = self.malformed[0]
            logger.warning(
                "%s: skipped %d malformed line(s) of %d scans read (first: line %d: %s); "
                "see reader.malformed for the list",
                self.path,
                len(self.malformed),
                n_scans,
                first_line,
                first_reason,
            )

    # -- helpers ---------------------------------------------------------------------------

    def _cut_short(self, line_no: int, what: str) -> None:
        """Note a log whose recording was cut short at ``line_no`` (see the class)."""
        self.truncated_at = line_no
        logger.warning(
            "%s:%d: %s (an interrupted recording, or an incomplete copy?); every whole "
            "record is read",
            self.path,
            line_no,
            what,
        )

    def _malformed(self, line_no: int, reason: str) -> None:
        if self.config.strict:
            raise LogFormatError(f"{self.path}:{line_no}: {reason}; {_FIX_HINT}")
        self.malformed.append((line_no, reason))

    def _finish(
        self, s: _PendingScan, odom_t: list[float] | None, odom_p: list[FloatArray] | None
    ) -> LaserScan:
        odom = s.record_odom if odom_t is None else _interpolate(odom_t, odom_p, s.stamp_s)
        return LaserScan(
            stamp_s=s.stamp_s,
            ranges_m=s.ranges_m,
            angles_rad=s.angles_rad,
            range_min_m=0.0,
            range_max_m=s.range_max_m,
            odom_pose=odom,
            laser_offset=s.laser_offset,
            source=f"{self.path}:{s.line_no}",
        )

    def _parse_laser(
        self, kind: str, tokens: list[str], params: _Params, line_no: int
    ) -> _PendingScan:
        if kind == "ROBOTLASER1":
            return self._parse_robotlaser(tokens, line_no)
        if len(tokens) < 2:
            raise _Malformed(f"{kind} record ends after its name; expected a beam count")
        n = _int(tokens[1], f"{kind} beam count")
        expected = n + 11
        if len(tokens) != expected:
            raise _Malformed(
                f"{kind} declares {n} beams but the line has {len(tokens) - 11} range values "
                f"({len(tokens)} fields where {expected} are expected: n, ranges, laser pose, "
                "odom pose, ipc_ts host logger_ts; a truncated or corrupted line?)"
            )
        ranges = _ranges(tokens, 2, n, kind)
        laser = _pose(tokens, n + 2, f"{kind} laser pose")
        odom = _pose(tokens, n + 5, f"{kind} odometry pose")
        stamp = _trailer(tokens, kind)
        if kind == "FLASER":
            offset_m, max_m = params.front_offset_m, params.front_max_m
            offset = None if offset_m is None else np.array([offset_m, 0.0, 0.0])
        else:
            offset_m, max_m = params.rear_offset_m, params.rear_max_m
            offset = None if offset_m is None else np.array([offset_m, 0.0, math.pi])
        if offset is None:
            offset = _between(odom, laser)
        return _PendingScan(
            line_no=line_no,
            stamp_s=stamp,
            ranges_m=ranges,
            angles_rad=flaser_angles(n),
            range_max_m=self.config.default_range_max_m if max_m is None else max_m,
            record_odom=odom,
            laser_offset=offset,
            frame="FLASER",
        )

    def _parse_robotlaser(self, tokens: list[str], line_no: int) -> _PendingScan:
        kind = "ROBOTLASER1"
        beams = _configured_beams(tokens, kind, _ROBOTLASER_TAIL)
        at = beams.tail
        laser = _pose(tokens, at, f"{kind} laser pose")
        robot = _pose(tokens, at + 3, f"{kind} robot pose")
        for i, name in enumerate(("tv", "rv", "forward_safety_dist", "side_safety_dist")):
            _float(tokens[at + 6 + i], f"{kind} {name}")
        _numbers(tokens, at + 10, at + 11, f"{kind} turn_axis")
        stamp = _trailer(tokens, kind)
        return _PendingScan(
            line_no=line_no,
            stamp_s=stamp,
            ranges_m=beams.ranges_m,
            angles_rad=beams.angles_rad,
            range_max_m=beams.range_max_m,
            record_odom=robot,
            laser_offset=_between(robot, laser),
            frame="ROBOTLASER1",
        )

    @staticmethod
    def _parse_rawlaser(tokens: list[str], params: _Params, line_no: int) -> _PendingScan:
        beams = _configured_beams(tokens, _RAW_LASER, _TRAILER_FIELDS)
        offset_m = params.front_offset_m
        return _PendingScan(
            line_no=line_no,
            stamp_s=_trailer(tokens, _RAW_LASER),
            ranges_m=beams.ranges_m,
            angles_rad=beams.angles_rad,
            range_max_m=beams.range_max_m,
            record_odom=None,
            laser_offset=np.array([0.0 if offset_m is None else offset_m, 0.0, 0.0]),
            frame="ODOM",
        )

    @staticmethod
    def _parse_odom(tokens: list[str]) -> tuple[float, FloatArray]:
        if len(tokens) != 10:
            raise _Malformed(
                f"ODOM record has {len(tokens)} fields where 10 are expected "
                "(ODOM x y theta tv rv accel ipc_ts host logger_ts)"
            )
        pose = _pose(tokens, 1, "ODOM pose")
        for i, name in enumerate(("tv", "rv", "accel")):
            _float(tokens[4 + i], f"ODOM {name}")
        return _trailer(tokens, "ODOM"), pose

    @staticmethod
    def _parse_param(tokens: list[str], params: _Params) -> bool:
        """Apply a PARAM line; True if it is one this reader uses."""
        if len(tokens) < 3:
            raise _Malformed(f"PARAM record has {len(tokens)} fields; expected PARAM name value")
        name = tokens[1]
        if name not in _USED_PARAMS:
            return False
        value = _float(tokens[2], f"PARAM {name} value")
        if name == _PARAM_FRONT_OFFSET:
            params.front_offset_m = value
        elif name == _PARAM_REAR_OFFSET:
            params.rear_offset_m = value
        elif value <= 0.0:
            raise _Malformed(f"PARAM {name} value {tokens[2]!r} must be a positive range")
        elif name in _PARAM_FRONT_MAX:
            params.front_max_m = value
        else:
            params.rear_max_m = value
        return True


def _between(a: FloatArray, b: FloatArray) -> FloatArray:
    """``a^-1 ∘ b`` for single poses (3,), as ``se2.between`` but with scalar math: it runs
    once per scan and numpy's per-call overhead was a third of the reading time."""
    if a[0] == b[0] and a[1] == b[1] and a[2] == b[2]:
        return np.zeros(3)
    c, s = math.cos(a[2]), math.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    dtheta = (b[2] - a[2] + math.pi) % (2.0 * math.pi) - math.pi
    return np.array([c * dx + s * dy, -s * dx + c * dy, dtheta])


_ODOM_HISTORY = 256

#: Odometry breaks logged one by one; the rest are summarized in one warning.
_LOGGED_BREAKS = 5


class _OdomTrack:
    """ODOM records seen so far (sorted stamps and poses, for interpolation) and the scans that
    wait for an ODOM record at or after their stamp."""

    def __init__(self) -> None:
        self.t: list[float] = []
        self.p: list[FloatArray] = []
        self.pending: deque[_PendingScan] = deque()

    def add(self, t: float, pose: FloatArray) -> list[_PendingScan]:
        """Insert an ODOM pose; return the waiting scans it now brackets (oldest first)."""
        _insert_odom(self.t, self.p, t, pose)
        ready = []
        while self.pending and self.pending[0].stamp_s <= self.t[-1]:
            ready.append(self.pending.popleft())
        return ready


def _insert_odom(odom_t: list[float], odom_p: list[FloatArray], t: float, pose: FloatArray) -> None:
    """Insert an ODOM record keeping stamps sorted; keep only the last ``_ODOM_HISTORY``."""
    if not odom_t or t >= odom_t[-1]:
        odom_t.append(t)
        odom_p.append(pose)
    else:
        i = bisect.bisect_right(odom_t, t)
        odom_t.insert(i, t)
        odom_p.insert(i, pose)
    if len(odom_t) > 2 * _ODOM_HISTORY:
        del odom_t[:-_ODOM_HISTORY]
        del odom_p[:-_ODOM_HISTORY]


def _interpolate(odom_t: list[float], odom_p: list[FloatArray] | None, t: float) -> FloatArray:
    """Odometry pose at ``t``: linear in x, y and the wrapped heading difference; clamped."""
    assert odom_p is not None
    i = bisect.bisect_right(odom_t, t)
    if i == 0:
        return odom_p[0].copy()
    if i == len(odom_t):
        return odom_p[-1].copy()
    t0, t1 = odom_t[i - 1], odom_t[i]
    p0, p1 = odom_p[i - 1], odom_p[i]
    if t1 <= t0:
        return p1.copy()
    f = (t - t0) / (t1 - t0)
    dtheta = float(se2.wrap_angle(p1[2] - p0[2]))
    out = p0 + f * (p1 - p0)
    out[2] = float(se2.wrap_angle(p0[2] + f * dtheta))
    return out


# ---------------------------------------------------------------------------------------------
# The writer
# ---------------------------------------------------------------------------------------------


def write_carmen(
    path: str | Path,
    scans: Iterable[LaserScan],
    laser_record: Literal["FLASER", "ROBOTLASER1"] = "FLASER",
) -> int:
    """Write scans as a CARMEN log that :class:`CarmenReader` reads back.

    Precision (a round trip is exact to it): ranges ``%.3f`` (mm), poses ``%.6f`` (um, urad),
    timestamps ``%.6f`` (us). Every beam keeps its validity: a non-finite range (no return)
    is written as the scan's ``range_max_m``, which the reader treats as no return (validity
    is ``r < range_max_m``); CARMEN stores no minimum range (the reader's ``range_min_m`` is
    0), so a beam invalid for ``r <= range_min_m > 0`` is also written as ``range_max_m``; a
    valid range that rounding would put on a bound is rounded inwards (by < 1 mm). Other
    finite ranges are written as they are. Each record carries the laser pose
    ``odom_pose ∘ laser_offset`` and the odometry pose, so the reader recovers the offset as
    ``between(odom, laser)`` (to about 1e-6). For FLASER a ``PARAM robot_front_laser_max``
    line is written before the first scan and whenever ``range_max_m`` changes, unless it is
    CARMEN's default 81.91. ROBOTLASER1 records carry the angles (start and step at full
    float precision) and the max range themselves. A ``.gz`` suffix writes gzip.

    The file is written to a temporary file in the same directory and moved into place
    (``os.replace``), so an interrupted write leaves no partial log.

    Args:
        path: Destination file (its directory must exist).
        scans: Scans with an ``odom_pose``; for FLASER their ``angles_rad`` must be the FLASER
            grid of :func:`flaser_angles`, for ROBOTLASER1 any evenly spaced bearings.
        laser_record: ``"FLASER"`` or ``"ROBOTLASER1"``.

    Returns:
        The number of scans written.

    Raises:
        LogFormatError: a scan cannot be represented (no odometry, bearings off the FLASER
            grid or not evenly spaced, non-finite pose or stamp), or the file cannot be written.
        ConfigError: ``laser_record`` is not one of the two record types.
    """
    if laser_record not in ("FLASER", "ROBOTLASER1"):
        raise ConfigError(f"laser_record must be 'FLASER' or 'ROBOTLASER1', not {laser_record!r}")
    p = Path(path)
    try:
        if p.suffix == ".gz":
            with atomic_write(p, "wb") as raw, gzip.GzipFile(fileobj=raw, mode="wb") as gz:
                text = _TextSink(gz)
                return _write_scans(text, scans, laser_record)
        with atomic_write(p, "w") as fh:
            return _write_scans(fh, scans, laser_record)
    except OSError as exc:
        raise LogFormatError(f"{p}: cannot write the log ({exc})") from exc


class _TextSink:
    """Minimal text ``write`` over a binary stream (for gzip output)."""

    def __init__(self, raw: IO[bytes] | gzip.GzipFile) -> None:
        self._raw = raw

    def write(self, s: str) -> int:
        return self._raw.write(s.encode("utf-8"))


def _write_scans(fh: IO[str] | _TextSink, scans: Iterable[LaserScan], laser_record: str) -> int:
    fh.write(
        f"# written by iceg frontends.carmen.write_carmen ({laser_record}); ranges %.3f m, "
        "poses %.6f, timestamps %.6f s\n"
    )
    fmt_r = f"%.{RANGE_DECIMALS}f"
    current_max: float | None = CARMEN_NO_RETURN_M
    count = 0
    for scan in scans:
        where = scan.source
        if scan.odom_pose is None:
            raise LogFormatError(
                f"{where}: the scan has no odom_pose; CARMEN laser records need the odometry "
                "pose (set odom_pose, e.g. to zeros, before writing)"
            )
        odom = scan.odom_pose
        laser = se2.compose(odom, scan.laser_offset)
        if not (np.isfinite(odom).all() and np.isfinite(laser).all()):
            raise LogFormatError(f"{where}: non-finite odom_pose or laser_offset; cannot write")
        if not math.isfinite(scan.stamp_s):
            raise LogFormatError(f"{where}: non-finite stamp_s {scan.stamp_s}; cannot write")
        if not (math.isfinite(scan.range_max_m) and scan.range_max_m > 0.0):
            raise LogFormatError(
                f"{where}: range_max_m {scan.range_max_m} must be finite and positive to write"
            )
        ranges = _ranges_to_write(scan)
        n = scan.n_beams
        ranges_txt = " ".join(np.char.mod(fmt_r, ranges).tolist()) if n else ""
        stamp = f"{scan.stamp_s:.{STAMP_DECIMALS}f}"
        trailer = f"{stamp} iceg {stamp}"
        if laser_record == "FLASER":
            grid = flaser_angles(n)
            if not np.allclose(scan.angles_rad, grid, rtol=0.0, atol=1e-9):
                raise LogFormatError(
                    f"{where}: the {n} bearings are not the FLASER grid (-pi/2 .. pi/2, "
                    "see flaser_angles); write with laser_record='ROBOTLASER1', which carries "
                    "the start angle and step"
                )
            if scan.range_max_m != current_max:
                fh.write(f"PARAM robot_front_laser_max {_g(scan.range_max_m)} {trailer}\n")
                current_max = float(scan.range_max_m)
            fh.write(f"FLASER {n} {ranges_txt} {_fmt_pose(laser)} {_fmt_pose(odom)} {trailer}\n")
        else:
            start, res = _even_spacing(scan)
            fov = res * max(n - 1, 0)
            fh.write(
                f"ROBOTLASER1 0 {_g(start)} {_g(fov)} {_g(res)} {_g(scan.range_max_m)} 0.01 0 "
                f"{n} {ranges_txt} 0 {_fmt_pose(laser)} {_fmt_pose(odom)} "
                f"0.0 0.0 0.0 0.0 0.0 {trailer}\n"
            )
        count += 1
    return count


def _ranges_to_write(scan: LaserScan) -> FloatArray:
    """Ranges as written, so that every beam keeps its validity after rounding and reading.

    Non-finite ranges and (when ``range_min_m > 0``, which CARMEN cannot store) ranges
    ``<= range_min_m`` become ``range_max_m`` (no return); a valid range that rounding would
    push onto a bound is rounded towards the inside instead (at most one unit of the last
    written decimal).
    """
    r = scan.ranges_m
    valid = scan.valid_mask()
    out = np.where(np.isfinite(r), r, scan.range_max_m)
    if scan.range_min_m > 0.0:
        out[~valid & (out <= scan.range_min_m)] = scan.range_max_m
    q = 10.0**RANGE_DECIMALS
    rounded = np.round(out, RANGE_DECIMALS)
    up = valid & (rounded >= scan.range_max_m)
    out[up] = np.floor(r[up] * q) / q
    down = valid & (rounded <= max(scan.range_min_m, 0.0))
    out[down] = np.ceil(r[down] * q) / q
    return out


def _g(x: float) -> str:
    """Shortest text that reads back as the same float64."""
    return repr(float(x))


def _fmt_pose(p: FloatArray) -> str:
    d = POSE_DECIMALS
    return f"{p[0]:.{d}f} {p[1]:.{d}f} {p[2]:.{d}f}"


def _even_spacing(scan: LaserScan) -> tuple[float, float]:
    """``(start, step)`` of evenly spaced bearings; LogFormatError if they are not."""
    a = scan.angles_rad
    if a.shape[0] == 0:
        return 0.0, 0.0
    if a.shape[0] == 1:
        return float(a[0]), 0.0
    start = float(a[0])
    res = float((a[-1] - a[0]) / (a.shape[0] - 1))
    recon = start + np.arange(a.shape[0]) * res
    if not np.allclose(a, recon, rtol=0.0, atol=1e-9):
        raise LogFormatError(
            f"{scan.source}: bearings are not evenly spaced (max deviation "
            f"{float(np.max(np.abs(a - recon))):.3g} rad); ROBOTLASER1 stores start + i*step only"
        )
    return start, res
