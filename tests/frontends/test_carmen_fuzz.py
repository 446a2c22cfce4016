"""Property test of the CARMEN reader on mutated logs (hypothesis).

A log of valid records (FLASER, RLASER, ROBOTLASER1, ODOM, PARAM, NEFF, comments) is generated
with known content; some lines are then mutated (truncation, a garbage token, a wrong beam count,
NaN/inf in a pose or timestamp, NaN in a range) and empty lines are inserted. The truth is the
generator's own bookkeeping: which final line numbers are malformed, which are scans, and their
ranges. The strict reader must raise LogFormatError naming the first malformed line (and no other
exception); the lenient reader must yield every valid scan and list exactly the malformed lines.
A malformed last line without a newline after it is a recording cut short: both readers read up
to it and set ``truncated_at``.
"""

from __future__ import annotations

import string
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from frontends.carmen import CarmenReader
from iceg_common.errors import LogFormatError


@dataclass
class _Line:
    """A generated line and what the reader must make of it."""

    tokens: list[str]
    is_scan: bool = False
    ranges: list[float] = field(default_factory=list)
    range_pos: list[int] = field(default_factory=list)  # token index of each range
    numeric_pos: list[int] = field(default_factory=list)  # positions the reader parses
    finite_pos: list[int] = field(default_factory=list)  # poses, stamps, header values
    n_pos: int | None = None  # the beam count
    truncatable: bool = False


def _is_float(tok: str) -> bool:
    try:
        float(tok)
    except ValueError:
        return False
    return True


_GARBAGE = st.text(
    alphabet=string.ascii_letters + string.punctuation, min_size=1, max_size=6
).filter(lambda s: not _is_float(s))
_RANGE = st.floats(0.0, 90.0).map(lambda x: f"{x:.2f}")
_POSE = st.floats(-100.0, 100.0).map(lambda x: f"{x:.6f}")


@st.composite
def _record(draw: st.DrawFn, stamp: float) -> _Line:
    kind = draw(
        st.sampled_from(
            ["FLASER", "FLASER", "RLASER", "ROBOTLASER1", "ODOM", "PARAM", "PARAMX", "NEFF", "#"]
        )
    )
    ts = f"{stamp:.6f}"
    if kind in ("FLASER", "RLASER"):
        n = draw(st.integers(1, 8))
        ranges = draw(st.lists(_RANGE, min_size=n, max_size=n))
        poses = draw(st.lists(_POSE, min_size=6, max_size=6))
        tokens = [kind, str(n), *ranges, *poses, ts, "host", ts]
        return _Line(
            tokens,
            is_scan=True,
            ranges=[float(r) for r in ranges],
            range_pos=list(range(2, 2 + n)),
            numeric_pos=[*range(1, n + 8), n + 8, n + 10],
            finite_pos=[*range(n + 2, n + 8), n + 8, n + 10],
            n_pos=1,
            truncatable=True,
        )
    if kind == "ROBOTLASER1":
        n = draw(st.integers(1, 8))
        n_rem = draw(st.sampled_from([0, 2]))
        ranges = draw(st.lists(_RANGE, min_size=n, max_size=n))
        rems = draw(st.lists(_RANGE, min_size=n_rem, max_size=n_rem))
        poses = draw(st.lists(_POSE, min_size=6, max_size=6))
        head = ["0", "-1.570796", "3.141593", "0.017453", "50.000000", "0.010000", "0"]
        tail = ["0.100", "0.200", "0.300", "0.400", "0.000"]
        tokens = [kind, *head, str(n), *ranges, str(n_rem), *rems, *poses, *tail, ts, "h", ts]
        at = 10 + n + n_rem  # first pose token
        return _Line(
            tokens,
            is_scan=True,
            ranges=[float(r) for r in ranges],
            range_pos=list(range(9, 9 + n)),
            numeric_pos=[*range(1, at + 11), at + 11, at + 13],
            finite_pos=[2, 4, 5, *range(at, at + 10), at + 11, at + 13],
            n_pos=8,
            truncatable=True,
        )
    if kind == "ODOM":
        values = draw(st.lists(_POSE, min_size=6, max_size=6))
        tokens = ["ODOM", *values, ts, "host", ts]
        pos = [*range(1, 8), 9]
        return _Line(tokens, numeric_pos=pos, finite_pos=pos, truncatable=True)
    if kind == "PARAM":  # a PARAM the reader uses: its value must be a finite positive number
        value = f"{draw(st.floats(1.0, 100.0)):.3f}"
        return _Line(
            ["PARAM", "robot_front_laser_max", value, "nohost", "0"],
            numeric_pos=[2],
            finite_pos=[2],
        )
    if kind == "PARAMX":
        return _Line(["PARAM", "robot_use_laser", "on", ts, "host", ts])
    if kind == "NEFF":
        return _Line(["NEFF", "12.5", ts, "host", ts])
    return _Line(["#", "a", "comment"])


@st.composite
def _mutated_log(draw: st.DrawFn) -> tuple[str, list[str], list[list[float]], int]:
    """Returns (text, outcome per final line: scan/skip/malformed/cut, ranges of expected scans,
    number of lines whose first token is a laser record name)."""
    n_records = draw(st.integers(1, 10))
    stamp = 1000.0
    lines: list[_Line] = []
    for _ in range(n_records):
        stamp += draw(st.floats(0.01, 1.0))
        lines.append(draw(_record(stamp)))
    sep = draw(st.sampled_from([" ", "  ", "\t"]))
    texts: list[str] = []
    outcomes: list[str] = []
    expected_ranges: list[list[float]] = []
    n_laser_lines = 0
    for line in lines:
        kinds = ["none", "none"]
        if line.truncatable:
            kinds.append("truncate")
        if line.numeric_pos:
            kinds.append("garbage")
        if line.finite_pos:
            kinds.append("nonfinite")
        if line.n_pos is not None:
            kinds += ["beam_count", "nan_range"]
        mutation = draw(st.sampled_from(kinds))
        tokens = list(line.tokens)
        ranges = list(line.ranges)
        malformed = True
        if mutation == "garbage":
            tokens[draw(st.sampled_from(line.numeric_pos))] = draw(_GARBAGE)
        elif mutation == "nonfinite":
            tokens[draw(st.sampled_from(line.finite_pos))] = draw(
                st.sampled_from(["nan", "NaN", "inf", "-inf"])
            )
        elif mutation == "beam_count":
            assert line.n_pos is not None
            n = int(tokens[line.n_pos])
            k = draw(st.integers(0, n + 4))
            tokens[line.n_pos] = str(k if k < n else k + 1)  # any count in 0..n+5 but n
        elif mutation == "nan_range":
            i = draw(st.integers(0, len(line.range_pos) - 1))
            tokens[line.range_pos[i]] = draw(st.sampled_from(["nan", "inf", "-inf"]))
            ranges[i] = np.inf  # the reader stores a no-return beam as +inf
            malformed = False
        elif mutation == "none":
            malformed = False
        text = sep.join(tokens)
        if mutation == "truncate":
            # Cut between the record name and the last token: at least the last field is gone
            # (a cut inside the last token could leave a valid line, e.g. "0.27" of "0.273").
            last_start = len(text) - len(tokens[-1])
            text = text[: draw(st.integers(len(tokens[0]), last_start - len(sep)))]
        # Empty or blank lines before this one: skipped and counted, never malformed.
        for _ in range(draw(st.integers(0, 1))):
            texts.append(draw(st.sampled_from(["", "   ", "\t"])))
            outcomes.append("skip")
        texts.append(text)
        n_laser_lines += text.split()[0] in ("FLASER", "RLASER", "ROBOTLASER1")
        if malformed:
            outcomes.append("malformed")
        elif line.is_scan:
            outcomes.append("scan")
            expected_ranges.append(ranges)
        else:
            outcomes.append("skip")
    ending = draw(st.sampled_from(["\n", ""]))
    if not ending and outcomes[-1] == "malformed":
        outcomes[-1] = "cut"  # the file ends inside this line: an interrupted recording
    return "\n".join(texts) + ending, outcomes, expected_ranges, n_laser_lines


@settings(
    max_examples=150,
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)
@given(_mutated_log())
def test_mutated_logs(case: tuple[str, list[str], list[list[float]], int]) -> None:
    text, outcomes, expected_ranges, n_laser_lines = case
    malformed_lines = [i + 1 for i, o in enumerate(outcomes) if o == "malformed"]
    scan_lines = [i + 1 for i, o in enumerate(outcomes) if o == "scan"]
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "fuzz.clf"
        path.write_text(text)

        # Strict: the first malformed line is named, and only LogFormatError is raised.
        if malformed_lines:
            with pytest.raises(LogFormatError) as info:
                list(CarmenReader(path))
            assert str(info.value).startswith(f"{path}:{malformed_lines[0]}: ")
        else:
            strict_scans = list(CarmenReader(path))
            assert [s.source for s in strict_scans] == [f"{path}:{n}" for n in scan_lines]

        # Lenient: every valid scan kept (same ranges), every malformed line listed.
        reader = CarmenReader(path, strict=False)
        scans = list(reader)
        assert [line for line, _ in reader.malformed] == malformed_lines
        assert reader.truncated_at == (len(outcomes) if outcomes[-1] == "cut" else None)
        assert [s.source for s in scans] == [f"{path}:{n}" for n in scan_lines]
        for scan, ranges in zip(scans, expected_ranges, strict=True):
            np.testing.assert_array_equal(scan.ranges_m, ranges)
        # count_scans counts laser records by their first token, malformed ones included.
        assert reader.count_scans() == n_laser_lines
