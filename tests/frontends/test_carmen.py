"""CARMEN reader and writer: a hand-made log, malformed lines, real logs, round trips."""

from __future__ import annotations

import dataclasses
import gzip
import logging
import math
from pathlib import Path

import numpy as np
import pytest

from frontends import LaserScan, open_log
from frontends.carmen import CarmenReader, flaser_angles, write_carmen
from frontends.registry import describe_log
from iceg_common import se2
from iceg_common.errors import ConfigError, LogFormatError
from tests.conftest import flaser_line, shared_file, write_odometry_jump_log

# ---------------------------------------------------------------------------------------------
# A hand-made log (11 lines). Every expected number below is computed by hand in the comments.
# ---------------------------------------------------------------------------------------------

_R181 = " ".join(["3.0"] * 181)
HAND_LOG = (
    "# hand-made CARMEN log\n"  # 1 comment
    "PARAM robot_use_laser on nohost 0\n"  # 2 PARAM the reader does not use
    "ODOM 0.0 0.0 0.0 0.0 0.0 0.0 10.0 host 10.0\n"  # 3
    "FLASER 4 1.0 2.0 81.91 nan 1.1 2.2 0.5 1.0 2.0 0.5 10.5 host 10.6\n"  # 4
    "ODOM 2.0 0.0 3.0 0.0 0.0 0.0 11.0 host 11.0\n"  # 5
    "VERTEX_SE2 0 0.0 0.0 0.0\n"  # 6 g2o record, skipped
    "\n"  # 7 blank
    "ROBOTLASER1 0 -0.5 1.0 0.25 20.0 0.01 0 5 1 2 3 4 5 0 "
    "0.1 0.0 0.0 0.0 0.0 0.0 0.3 0.1 0.0 0.0 0.0 11.5 host 11.5\n"  # 8
    "PARAM robot_frontlaser_offset 0.25 nohost 0\n"  # 9
    f"FLASER 181 {_R181} 5.0 5.0 0.0 5.0 5.0 0.0 12.0 host 12.0\n"  # 10
    "ODOM 4.0 0.0 -2.9 0.0 0.0 0.0 13.0 host 13.0\n"  # 11
)


@pytest.fixture
def hand_log(tmp_path: Path) -> Path:
    path = tmp_path / "hand.clf"
    path.write_text(HAND_LOG)
    return path


def test_hand_log_record_odometry(hand_log: Path) -> None:
    reader = CarmenReader(hand_log)
    scans = list(reader)
    assert len(scans) == 3
    assert reader.count_scans() == 3
    s1, s2, s3 = scans

    # Line 4: FLASER, 4 beams -> not 181/361, so -pi/2 + i*pi/4 (GMapping convention).
    np.testing.assert_allclose(s1.angles_rad, [-math.pi / 2, -math.pi / 4, 0.0, math.pi / 4])
    assert s1.stamp_s == 10.5  # ipc timestamp, not the logger's 10.6
    assert s1.source == f"{hand_log}:4"
    assert s1.range_min_m == 0.0 and s1.range_max_m == 81.91
    # nan range -> no return, stored as +inf; 81.91 is no return since validity is r < 81.91.
    np.testing.assert_array_equal(s1.ranges_m, [1.0, 2.0, 81.91, np.inf])
    np.testing.assert_array_equal(s1.valid_mask(), [True, True, False, False])
    np.testing.assert_array_equal(s1.odom_pose, [1.0, 2.0, 0.5])
    # Offset = odom^-1 ∘ laser: R(-0.5) [0.1, 0.2] = [0.1 c + 0.2 s, -0.1 s + 0.2 c],
    # c = cos 0.5 = 0.8775825619, s = sin 0.5 = 0.4794255386.
    np.testing.assert_allclose(s1.laser_offset, [0.1836433639, 0.1275739585, 0.0], atol=1e-9)
    # Robot-frame points: beam 0 at (0, -1) and beam 1 at (sqrt2, -sqrt2) in the laser frame,
    # plus the offset (no offset rotation).
    np.testing.assert_allclose(
        s1.points_xy(),
        [
            [0.1836433639, 0.1275739585 - 1.0],
            [0.1836433639 + math.sqrt(2.0), 0.1275739585 - math.sqrt(2.0)],
        ],
        atol=1e-9,
    )

    # Line 8: ROBOTLASER1: angles start + i*res = -0.5, -0.25, 0, 0.25, 0.5; max range 20.
    np.testing.assert_allclose(s2.angles_rad, [-0.5, -0.25, 0.0, 0.25, 0.5])
    np.testing.assert_array_equal(s2.ranges_m, [1, 2, 3, 4, 5])
    assert s2.range_max_m == 20.0 and s2.stamp_s == 11.5
    np.testing.assert_array_equal(s2.odom_pose, [0.0, 0.0, 0.0])
    np.testing.assert_allclose(s2.laser_offset, [0.1, 0.0, 0.0])

    # Line 10: FLASER 181 beams -> endpoint-inclusive 1 deg grid; PARAM offset 0.25 wins over
    # the record's (equal) poses.
    assert s3.n_beams == 181
    assert s3.angles_rad[0] == -math.pi / 2
    assert s3.angles_rad[90] == pytest.approx(0.0, abs=1e-15)
    assert s3.angles_rad[180] == pytest.approx(math.pi / 2, abs=1e-15)
    assert s3.angles_rad[1] - s3.angles_rad[0] == pytest.approx(math.radians(1.0), abs=1e-15)
    np.testing.assert_array_equal(s3.laser_offset, [0.25, 0.0, 0.0])
    np.testing.assert_array_equal(s3.odom_pose, [5.0, 5.0, 0.0])

    # Skipped: 1 comment, 1 unused PARAM, 3 ODOM (record mode), 1 VERTEX_SE2, 1 blank.
    assert reader.skipped_records == {
        "comment": 1,
        "PARAM": 1,
        "ODOM": 3,
        "VERTEX_SE2": 1,
        "blank": 1,
    }
    assert reader.malformed == []


def test_hand_log_odom_interpolation(hand_log: Path) -> None:
    reader = CarmenReader(hand_log, odometry="odom")
    s1, s2, s3 = list(reader)
    # 10.5 between ODOM 10.0 (0,0,0) and 11.0 (2,0,3): f = 0.5 -> (1, 0, 1.5).
    np.testing.assert_allclose(s1.odom_pose, [1.0, 0.0, 1.5], atol=1e-12)
    # 11.5 between 11.0 (2,0,3.0) and 13.0 (4,0,-2.9): f = 0.25; heading difference wrapped:
    # -2.9 - 3.0 = -5.9 -> -5.9 + 2 pi = 0.3831853; 3.0 + 0.25 * 0.3831853 = 3.0957963.
    np.testing.assert_allclose(s2.odom_pose, [2.5, 0.0, 3.0957963], atol=1e-7)
    # 12.0: f = 0.5 -> 3.0 + 0.1915927 = 3.1915927, wrapped to 3.1915927 - 2 pi = -3.0915927.
    np.testing.assert_allclose(s3.odom_pose, [3.0, 0.0, -3.0915927], atol=1e-7)
    # ODOM lines are used, not skipped; the laser offsets still come from the records/PARAM.
    assert "ODOM" not in reader.skipped_records
    assert reader.n_odom_records == 3
    np.testing.assert_allclose(s2.laser_offset, [0.1, 0.0, 0.0])


def test_odom_mode_clamps_before_first_and_after_last(tmp_path: Path) -> None:
    path = tmp_path / "clamp.log"
    path.write_text(
        "FLASER 2 1.0 1.0 0 0 0 0 0 0 1.0 h 1.0\n"  # before the first ODOM -> first ODOM
        "ODOM 1.0 2.0 0.3 0 0 0 2.0 h 2.0\n"
        "ODOM 3.0 2.0 0.3 0 0 0 3.0 h 3.0\n"
        "FLASER 2 1.0 1.0 0 0 0 0 0 0 5.0 h 5.0\n"  # after the last ODOM -> last ODOM
    )
    a, b = list(CarmenReader(path, odometry="odom"))
    np.testing.assert_array_equal(a.odom_pose, [1.0, 2.0, 0.3])
    np.testing.assert_array_equal(b.odom_pose, [3.0, 2.0, 0.3])


def test_odom_mode_without_odom_records_raises(tmp_path: Path) -> None:
    path = tmp_path / "noodom.log"
    path.write_text("FLASER 2 1.0 1.0 0 0 0 0 0 0 1.0 h 1.0\n")
    with pytest.raises(LogFormatError, match="no valid ODOM record"):
        list(CarmenReader(path, odometry="odom"))


def test_rlaser_param_offsets_and_max_range(tmp_path: Path) -> None:
    path = tmp_path / "rear.log"
    path.write_text(
        "PARAM robot_rearlaser_offset -0.3 nohost 0\n"
        "PARAM robot_rear_laser_max 30 nohost 0\n"
        "PARAM laser_front_laser_max_range 50 nohost 0\n"
        "RLASER 3 1 2 3 0 0 0 0 0 0 1.0 h 1.0\n"
        "FLASER 3 1 2 3 0 0 0 0 0 0 2.0 h 2.0\n"
    )
    rear, front = list(CarmenReader(path))
    # RLASER: offset [rear_offset, 0, pi] (GMapping's reader); 3 beams -> -pi/2 + i*pi/3.
    np.testing.assert_allclose(rear.laser_offset, [-0.3, 0.0, math.pi])
    np.testing.assert_allclose(rear.angles_rad, [-math.pi / 2, -math.pi / 6, math.pi / 6])
    assert rear.range_max_m == 30.0
    assert front.range_max_m == 50.0
    np.testing.assert_array_equal(front.laser_offset, [0.0, 0.0, 0.0])


# ---------------------------------------------------------------------------------------------
# Malformed lines
# ---------------------------------------------------------------------------------------------

_GOOD = "FLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 0.1 0.2 0.3 5.0 h 5.0"


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        (
            "FLASER 361 " + " ".join(["1.0"] * 300) + " 0 0 0 0 0 0 5.0 h 5.0",
            "FLASER declares 361 beams but the line has 300 range values",
        ),
        ("FLASER 3 1.0 x2.0 3.0 0.1 0.2 0.3 0.1 0.2 0.3 5.0 h 5.0", "range value 2 of 3"),
        ("FLASER 3 1.0 2.0 3.0 nan 0.2 0.3 0.1 0.2 0.3 5.0 h 5.0", "laser pose x is 'nan'"),
        ("FLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 0.1 inf 0.3 5.0 h 5.0", "odometry pose y is 'inf'"),
        ("FLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 0.1 0.2 0.3 nan h 5.0", "ipc timestamp is 'nan'"),
        ("FLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 0.1 0.2 0.3 5.0 h", "FLASER declares 3 beams"),
        ("FLASER 3.0 1.0 2.0 3.0 0.1 0.2 0.3 0.1 0.2 0.3 5.0 h 5.0", "beam count '3.0'"),
        ("FLASER", "ends after its name"),
        ("ODOM 1 2 3 0 0 0 5.0 h", "ODOM record has 9 fields where 10"),
        ("1.0 2.0 3.0", "not a CARMEN record name"),
        ("ROBOTLASER1 0 -0.5 1.0 0.25 20.0 0.01 0 5 1 2 3", "declares 5 beams but the line"),
        ("PARAM robot_front_laser_max abc nohost 0", "robot_front_laser_max value 'abc'"),
    ],
)
def test_strict_reader_names_file_line_and_problem(tmp_path: Path, bad: str, message: str) -> None:
    path = tmp_path / "bad.clf"
    path.write_text(f"{_GOOD}\n# comment\n{bad}\n{_GOOD}\n")
    with pytest.raises(LogFormatError) as info:
        list(CarmenReader(path))
    text = str(info.value)
    assert text.startswith(f"{path}:3: ")
    assert message in text
    assert "--skip-malformed" in text and "strict=False" in text  # says what to do


def test_lenient_reader_skips_lists_and_warns(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = tmp_path / "bad.clf"
    bad = "FLASER 3 1.0 2.0 0.1 0.2 0.3 0.1 0.2 0.3 5.0 h 5.0"  # one range missing
    path.write_text(f"{_GOOD}\n{bad}\n{_GOOD}\nGARBAGE? 1 2\n")
    reader = CarmenReader(path, strict=False)
    with caplog.at_level(logging.WARNING, logger="frontends.carmen"):
        scans = list(reader)
    assert [s.source for s in scans] == [f"{path}:1", f"{path}:3"]
    assert [line for line, _ in reader.malformed] == [2, 4]
    assert "declares 3 beams but the line has 2 range values" in reader.malformed[0][1]
    # (the two _GOOD lines share stamp 5.0: frontends.scan also warns about the duplicate)
    warnings = [
        r for r in caplog.records if r.levelno == logging.WARNING and r.name == "frontends.carmen"
    ]
    assert len(warnings) == 1 and "skipped 2 malformed line(s)" in warnings[0].getMessage()


# ---------------------------------------------------------------------------------------------
# A recording cut short: read up to the last whole record
# ---------------------------------------------------------------------------------------------


def _flaser(stamp_s: float) -> str:
    """A 3-beam FLASER line whose ranges and poses depend on its stamp."""
    r = f"{1.0 + stamp_s:.3f} {2.0 + stamp_s:.3f} {3.0 + stamp_s:.3f}"
    return f"FLASER 3 {r} {stamp_s:.3f} 0.2 0.3 {stamp_s:.3f} 0.2 0.3 {stamp_s:.6f} h {stamp_s:.6f}"


def _carmen_warnings(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [
        r.getMessage()
        for r in caplog.records
        if r.levelno == logging.WARNING and r.name == "frontends.carmen"
    ]


@pytest.mark.parametrize("strict", [True, False])
def test_a_log_cut_inside_its_last_line_is_read_up_to_it(
    tmp_path: Path, caplog: pytest.LogCaptureFixture, strict: bool
) -> None:
    path = tmp_path / "cut.clf"
    whole = "".join(f"{_flaser(t)}\n" for t in (1.0, 2.0, 3.0))
    path.write_text(whole + _flaser(4.0)[:40])  # the logger stopped 40 characters into line 4
    reader = CarmenReader(path, strict=strict)
    with caplog.at_level(logging.WARNING, logger="frontends.carmen"):
        scans = list(reader)
    assert [s.stamp_s for s in scans] == [1.0, 2.0, 3.0]
    np.testing.assert_array_equal(scans[2].ranges_m, [4.0, 5.0, 6.0])  # 1 + 3, 2 + 3, 3 + 3
    assert reader.truncated_at == 4 and reader.malformed == []
    (warning,) = _carmen_warnings(caplog)
    assert warning.startswith(f"{path}:4: the log ends inside this line")
    assert "interrupted recording" in warning


def test_only_the_unterminated_last_line_counts_as_cut_short(tmp_path: Path) -> None:
    # The same incomplete record with its newline, or in the middle, is a malformed line.
    for text, bad_line in (
        (f"{_flaser(1.0)}\n{_flaser(2.0)[:40]}\n", 2),
        (f"{_flaser(1.0)}\n{_flaser(2.0)[:40]}\n{_flaser(3.0)}", 2),
    ):
        path = tmp_path / "bad.clf"
        path.write_text(text)
        with pytest.raises(LogFormatError, match=rf"bad\.clf:{bad_line}: FLASER declares 3"):
            list(CarmenReader(path))
    # A whole last record without a newline after it is read as it is.
    path.write_text(f"{_flaser(1.0)}\n{_flaser(2.0)}")
    reader = CarmenReader(path)
    assert [s.stamp_s for s in reader] == [1.0, 2.0] and reader.truncated_at is None


def test_a_gz_log_cut_short_is_read_up_to_the_cut(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    stamps = [k / 100 for k in range(1, 2001)]
    text = "".join(f"{_flaser(t)}\n" for t in stamps)
    full = gzip.compress(text.encode())
    path = tmp_path / "cut.clf.gz"
    path.write_bytes(full[: len(full) // 2])
    reader = CarmenReader(path)
    with caplog.at_level(logging.WARNING, logger="frontends.carmen"):
        scans = list(reader)
    n = len(scans)
    # a prefix of the log, each scan as the whole file has it (what zlib could decompress
    # before the cut, less the line the cut fell in)
    assert 0 < n < len(stamps)
    assert [s.stamp_s for s in scans] == stamps[:n]
    t = stamps[n - 1]
    np.testing.assert_array_equal(scans[-1].ranges_m, [float(f"{a + t:.3f}") for a in (1, 2, 3)])
    assert reader.truncated_at == n  # one scan per line: the last line read
    (warning,) = _carmen_warnings(caplog)
    assert warning.startswith(f"{path}:{n}: the compressed log ends after this line")
    assert CarmenReader(path).count_scans() == n  # counted up to the cut, no error


def test_describe_log_counts_returns_and_says_what_a_run_will_do(
    hand_log: Path, tmp_path: Path
) -> None:
    rows = dict(describe_log(CarmenReader(hand_log)))
    # line 4: 4 beams, 2 returns (81.91 and nan are none); line 8: 5 returns below its 20 m;
    # line 10: 181 returns of 3 m
    assert rows["returns"] == "188 of 190 beams (98.9 %)"
    assert rows["odometry"] == "3 of 3 scans have an odometry pose"
    assert "cut short" not in rows
    stuck = tmp_path / "stuck.clf"
    stuck.write_text("".join(f"FLASER 3 1.0 2.0 3.0 0 0 0 0 0 0 {t} h {t}\n" for t in (1, 2)))
    rows = dict(describe_log(CarmenReader(stuck)))
    assert rows["odometry"] == (
        "2 of 2 scans have an odometry pose; the same pose in every scan: no motion (a run "
        "reads the log without it)"
    )
    cut = tmp_path / "cut.clf"
    cut.write_text(f"{_flaser(1.0)}\n{_flaser(2.0)[:30]}")
    rows = dict(describe_log(CarmenReader(cut)))
    assert rows["scans"] == "1" and rows["cut short"] == "the log ends inside a record at line 2"


def test_bad_options_raise_config_error(hand_log: Path) -> None:
    with pytest.raises(ConfigError, match="odometry"):
        CarmenReader(hand_log, odometry="wheel")


# ---------------------------------------------------------------------------------------------
# open_log: suffix, sniffing, gzip
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize("name", ["a.clf", "a.log", "a.carmen", "a.CLF", "a.clf.gz"])
def test_open_log_by_suffix(tmp_path: Path, name: str) -> None:
    path = tmp_path / name
    data = HAND_LOG.encode()
    path.write_bytes(gzip.compress(data) if name.endswith(".gz") else data)
    reader = open_log(path)
    assert isinstance(reader, CarmenReader)
    assert reader.count_scans() == 3
    assert [s.stamp_s for s in reader] == [10.5, 11.5, 12.0]


def test_open_log_sniffs_unknown_suffix(tmp_path: Path) -> None:
    path = tmp_path / "run.txt"
    path.write_text(HAND_LOG)
    reader = open_log(path, strict=False)
    assert isinstance(reader, CarmenReader) and not reader.strict
    assert len(list(reader)) == 3
    other = tmp_path / "notes.txt"
    other.write_text("hello\nworld\n")
    with pytest.raises(LogFormatError, match=r"not a recognised laser log.*\.clf, .*\.mcap"):
        open_log(other)  # the suffixes a command-line user can give it


@pytest.mark.parametrize(("name", "compressed"), [("a.clf", True), ("a.clf.gz", False)])
def test_gzip_is_told_by_its_first_bytes_not_the_suffix(
    tmp_path: Path, name: str, compressed: bool
) -> None:
    # a log saved compressed under .clf; a .gz that a download already decompressed
    path = tmp_path / name
    data = HAND_LOG.encode()
    path.write_bytes(gzip.compress(data) if compressed else data)
    reader = open_log(path)
    assert reader.count_scans() == 3
    assert [s.stamp_s for s in reader] == [10.5, 11.5, 12.0]


@pytest.mark.parametrize("name", ["bom.clf", "bom.txt", "bom.clf.gz"])
def test_a_byte_order_mark_at_the_start_is_dropped(tmp_path: Path, name: str) -> None:
    # An editor on Windows may save the log as UTF-8 with a BOM before its first line.
    path = tmp_path / name
    data = b"\xef\xbb\xbf" + HAND_LOG.encode()
    path.write_bytes(gzip.compress(data) if name.endswith(".gz") else data)
    reader = open_log(path)  # bom.txt: recognised from its first lines
    assert isinstance(reader, CarmenReader)
    assert [s.stamp_s for s in reader] == [10.5, 11.5, 12.0]
    assert reader.skipped_records["comment"] == 1  # line 1 is still the comment


# ---------------------------------------------------------------------------------------------
# Real logs in ../shared/data (skipped when absent). Expected counts: ../shared/data/README.md.
# ---------------------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def mit_csail_scans() -> list[LaserScan]:
    return list(open_log(shared_file("mit-csail/mit-csail.clf")))


def test_mit_csail_clf(mit_csail_scans: list[LaserScan]) -> None:
    scans = mit_csail_scans
    assert len(scans) == 1988
    assert all(s.n_beams == 361 for s in scans)
    assert all(s.odom_pose is not None for s in scans)
    stamps = np.array([s.stamp_s for s in scans])
    assert np.all(np.diff(stamps) >= 0.0)
    # README: ipc timestamps 1134864629.9 .. 1134865053.9.
    assert stamps[0] == pytest.approx(1134864629.9, abs=0.1)
    assert stamps[-1] == pytest.approx(1134865053.9, abs=0.1)
    # Line 4 of the file ends: odom 576.536523 0.106594 -2.255213, ipc ts 1134864629.895182.
    np.testing.assert_array_equal(scans[0].odom_pose, [576.536523, 0.106594, -2.255213])
    assert scans[0].stamp_s == 1134864629.895182
    # Laser pose == odom pose in this log -> zero offset; 0.5 deg endpoint-inclusive grid.
    assert max(np.abs(s.laser_offset).max() for s in scans) == 0.0
    np.testing.assert_allclose(scans[0].angles_rad[[0, 180, 360]], [-math.pi / 2, 0, math.pi / 2])
    assert scans[0].range_max_m == 81.91


def test_mit_csail_count_scans_matches_iteration() -> None:
    reader = open_log(shared_file("mit-csail/mit-csail.clf"))
    assert reader.count_scans() == 1988
    list(reader)
    assert reader.skipped_records == {"comment": 3}


def test_csail_robotlaser1() -> None:
    reader = open_log(shared_file("mit-csail/csail.log"))
    scans = list(reader)
    assert len(scans) == 686 == reader.count_scans()
    s = scans[0]
    # Header of every record: start -1.570796, res 0.008727, max range 80, 361 beams.
    assert s.n_beams == 361 and s.range_max_m == 80.0
    assert s.angles_rad[0] == -1.570796
    assert s.angles_rad[360] == pytest.approx(-1.570796 + 360 * 0.008727, abs=1e-12)
    np.testing.assert_array_equal(s.odom_pose, [0.0, 0.0, 0.0])  # corrected, starts at 0
    assert np.all(np.diff([x.stamp_s for x in scans]) >= 0.0)


def test_aces_corrected_gz() -> None:
    reader = open_log(shared_file("aces/aces-corrected.log.gz"))
    scans = list(reader)
    assert len(scans) == 440
    assert all(s.n_beams == 180 for s in scans)
    # 180 beams -> GMapping's -pi/2 + i*pi/180: last beam at pi/2 - 1 deg.
    assert scans[0].angles_rad[-1] == pytest.approx(math.pi / 2 - math.radians(1.0), abs=1e-12)
    # README: 7814 ODOM and 440 NEFF lines; PARAM robot_frontlaser_offset 0.0 is used (offset
    # 0), the other two PARAM lines are counted.
    assert reader.skipped_records["ODOM"] == 7814
    assert reader.skipped_records["NEFF"] == 440
    assert reader.skipped_records["PARAM"] == 2


def test_aces_odom_interpolation_matches_global_interp() -> None:
    """Streaming interpolation equals np.interp over all ODOM records (an independent path)."""
    path = shared_file("aces/aces-corrected.log.gz")
    odom = []
    with gzip.open(path, "rt") as fh:
        for line in fh:
            tok = line.split()
            if tok and tok[0] == "ODOM" and float(tok[7]) > 0.0:
                # GMapping also writes an ODOM with ipc timestamp 0 after each scan (its
                # corrected pose); the reader's sorted history puts those first, where no scan
                # stamp (>= 21 s) ever reaches, so they are left out of this reference.
                odom.append([float(tok[7]), float(tok[1]), float(tok[2]), float(tok[3])])
    o = np.array(odom)
    o = o[np.argsort(o[:, 0], kind="stable")]
    scans = list(open_log(path, odometry="odom"))
    t = np.array([s.stamp_s for s in scans])
    got = np.array([s.odom_pose for s in scans])
    np.testing.assert_allclose(got[:, 0], np.interp(t, o[:, 0], o[:, 1]), atol=1e-9)
    np.testing.assert_allclose(got[:, 1], np.interp(t, o[:, 0], o[:, 2]), atol=1e-9)
    theta = se2.wrap_angle(np.interp(t, o[:, 0], np.unwrap(o[:, 3])))
    np.testing.assert_allclose(se2.wrap_angle(got[:, 2] - theta), 0.0, atol=1e-9)


# ---------------------------------------------------------------------------------------------
# Writer round trips
# ---------------------------------------------------------------------------------------------


def _synthetic_scans(n_scans: int, n_beams: int, angles: np.ndarray) -> list[LaserScan]:
    rng = np.random.default_rng(7)
    scans = []
    for k in range(n_scans):
        ranges = rng.uniform(0.1, 25.0, n_beams)
        ranges[rng.random(n_beams) < 0.1] = np.inf  # no return
        ranges[rng.random(n_beams) < 0.05] = 20.0  # exactly at max range: no return too
        scans.append(
            LaserScan(
                stamp_s=1_134_864_630.0 + 0.2 * k + rng.uniform(0, 1e-3),
                ranges_m=ranges,
                angles_rad=angles,
                range_min_m=0.0,
                range_max_m=20.0,
                odom_pose=np.array(
                    [rng.uniform(-50, 50), rng.uniform(-50, 50), rng.uniform(-3, 3)]
                ),
                laser_offset=np.array([0.12, -0.03, 0.02]),
                source=f"synthetic:{k}",
            )
        )
    return scans


def _assert_round_trip(orig: list[LaserScan], back: list[LaserScan]) -> None:
    """Equal to the written precision: ranges %.3f, poses %.6f, stamps %.6f."""
    assert len(back) == len(orig)
    for a, b in zip(orig, back, strict=True):
        # %.6f stamps: 5e-7 rounding + 2.4e-7 float64 spacing at 1.1e9 s.
        assert b.stamp_s == pytest.approx(a.stamp_s, abs=1e-6)
        np.testing.assert_array_equal(b.valid_mask(), a.valid_mask())
        m = a.valid_mask()
        # %.3f: 0.5 mm, or up to 1 mm for a beam rounded inwards at a validity bound.
        np.testing.assert_allclose(b.ranges_m[m], a.ranges_m[m], atol=1e-3 + 1e-12)
        np.testing.assert_allclose(b.angles_rad, a.angles_rad, atol=1e-12)
        np.testing.assert_allclose(b.odom_pose[:2], a.odom_pose[:2], atol=5e-7 + 1e-12)
        assert se2.wrap_angle(b.odom_pose[2] - a.odom_pose[2]) == pytest.approx(0.0, abs=5e-7)
        # Offset = between(odom, laser) of two rounded poses: ~1e-6.
        np.testing.assert_allclose(se2.between(a.laser_offset, b.laser_offset), 0.0, atol=2.5e-6)
        assert b.range_max_m == a.range_max_m
        np.testing.assert_allclose(b.points_xy(), a.points_xy(), atol=1e-3)


def test_round_trip_flaser_synthetic(tmp_path: Path) -> None:
    scans = _synthetic_scans(20, 181, flaser_angles(181))
    path = tmp_path / "out.clf"
    assert write_carmen(path, scans) == 20
    back = list(open_log(path))
    _assert_round_trip(scans, back)
    # range_max_m 20 != CARMEN's 81.91 default: one PARAM line carries it.
    assert path.read_text().count("PARAM robot_front_laser_max 20.0 ") == 1
    assert not list(tmp_path.glob(".*tmp"))  # no temporary file left behind


def test_round_trip_keeps_validity_at_bounds(tmp_path: Path) -> None:
    angles = flaser_angles(361)
    ranges = np.full(361, 5.0)
    # Valid beams that %.3f would round onto a bound; beams invalid by range_min_m (0.05),
    # which CARMEN cannot store; a NaN and an inf no-return beam.
    ranges[:6] = [19.9996, 0.0004 + 0.05, 0.0301, 0.05, np.nan, np.inf]
    scan = LaserScan(3.0, ranges, angles, 0.05, 20.0, np.zeros(3), source="edge:1")
    path = tmp_path / "edge.clf"
    write_carmen(path, [scan])
    (back,) = list(open_log(path))
    # valid_mask of the original: 19.9996 < 20 and 0.0504 > 0.05 valid; 0.0301, 0.05 too short.
    np.testing.assert_array_equal(scan.valid_mask()[:6], [True, True, False, False, False, False])
    np.testing.assert_array_equal(back.valid_mask(), scan.valid_mask())
    # 19.9996 -> 19.999 (inwards, not 20.000); 0.0504 -> 0.051 (inwards of the scan's own
    # range_min 0.05, so it stays valid even if that minimum is applied again); the short and
    # no-return beams become 20.0 (no return).
    np.testing.assert_array_equal(back.ranges_m[:6], [19.999, 0.051, 20.0, 20.0, 20.0, 20.0])


def test_round_trip_robotlaser1_arbitrary_fov(tmp_path: Path) -> None:
    # A 270 deg scanner at 0.25 deg (1081 beams): not the FLASER grid, so ROBOTLASER1.
    angles = np.radians(-135.0 + 0.25 * np.arange(1081))
    scans = _synthetic_scans(5, 1081, angles)
    path = tmp_path / "out.log.gz"
    assert write_carmen(path, scans, laser_record="ROBOTLASER1") == 5
    back = list(open_log(path))
    _assert_round_trip(scans, back)
    with pytest.raises(LogFormatError, match="not the FLASER grid"):
        write_carmen(tmp_path / "x.clf", scans)


# ---------------------------------------------------------------------------------------------
# RAWLASER1: the front laser's own records, without a pose, placed by the ODOM records
# ---------------------------------------------------------------------------------------------


def _as_raw_records(robotlaser_log: Path) -> list[str]:
    """The scans of a ROBOTLASER1 log as CARMEN's base and laser modules log them: per scan an
    ODOM record at its stamp (the robot pose) and a RAWLASER1 record (the laser's
    configuration, ranges and remissions, the same text; no pose)."""
    lines = []
    for line in robotlaser_log.read_text().splitlines():
        tok = line.split()
        if tok[:1] != ["ROBOTLASER1"]:
            continue
        n = int(tok[8])
        tail = 10 + n + int(tok[9 + n])  # after the remissions: laser pose, robot pose, ...
        lines.append(" ".join(["ODOM", *tok[tail + 3 : tail + 6], "0 0 0", *tok[-3:]]))
        lines.append(" ".join(["RAWLASER1", *tok[1:tail], *tok[-3:]]))
    return lines


def _front_laser_scans(tmp_path: Path) -> tuple[Path, list[LaserScan]]:
    """A 270 deg scanner at 0.5 deg, 0.12 m ahead of the robot's origin, as ROBOTLASER1 records,
    and the scans read back from them."""
    angles = np.radians(-135.0 + 0.5 * np.arange(541))
    scans = [
        dataclasses.replace(s, laser_offset=np.array([0.12, 0.0, 0.0]))
        for s in _synthetic_scans(20, 541, angles)
    ]
    path = tmp_path / "robot.log"
    write_carmen(path, scans, laser_record="ROBOTLASER1")
    return path, list(open_log(path))


def test_a_rawlaser1_log_reads_as_its_robotlaser1_twin(tmp_path: Path) -> None:
    """The same scans as RAWLASER1 + ODOM records: every scan the same bits as read from the
    ROBOTLASER1 records (the odometry is the ODOM record at the scan's own stamp), the
    laser's mounting from ``PARAM robot_frontlaser_offset``."""
    robot, expected = _front_laser_scans(tmp_path)
    raw = tmp_path / "raw.txt"  # an unknown suffix: told a CARMEN log by its first lines
    raw.write_text(
        "PARAM robot_frontlaser_offset 0.12 nohost 0\n" + "\n".join(_as_raw_records(robot)) + "\n"
    )
    reader = open_log(raw)
    assert isinstance(reader, CarmenReader)
    got = list(reader)
    assert reader.count_scans() == len(got) == 20
    for a, b in zip(expected, got, strict=True):
        assert (b.stamp_s, b.range_max_m, b.odom_break) == (a.stamp_s, a.range_max_m, a.odom_break)
        np.testing.assert_array_equal(b.ranges_m, a.ranges_m)
        np.testing.assert_array_equal(b.angles_rad, a.angles_rad)
        np.testing.assert_array_equal(b.odom_pose, a.odom_pose)
        np.testing.assert_array_equal(b.laser_offset, [0.12, 0.0, 0.0])
        # ROBOTLASER1's offset is between() of two poses written to 1e-6
        np.testing.assert_allclose(b.laser_offset, a.laser_offset, atol=2.5e-6)
    assert reader.n_odom_records == 20 and "ODOM" not in reader.skipped_records


def test_rawlaser1_beside_records_with_a_pose_is_skipped(tmp_path: Path) -> None:
    """A log of both kinds holds every scan twice (CARMEN's laser module and its robot module):
    only the records with a pose are read, even where a RAWLASER1 record comes first."""
    robot, expected = _front_laser_scans(tmp_path)
    raw = _as_raw_records(robot)
    records = [line for line in robot.read_text().splitlines() if line.startswith("ROBOTLASER1")]
    both = tmp_path / "both.log"
    both.write_text(
        "".join(f"{r}\n{o}\n{s}\n" for o, r, s in zip(raw[::2], raw[1::2], records, strict=True))
    )
    reader = CarmenReader(both)
    got = list(reader)
    assert reader.count_scans() == len(got) == 20
    assert reader.skipped_records["RAWLASER1"] == 20 and reader.skipped_records["ODOM"] == 20
    for a, b in zip(expected, got, strict=True):
        np.testing.assert_array_equal(b.ranges_m, a.ranges_m)
        np.testing.assert_array_equal(b.odom_pose, a.odom_pose)
        np.testing.assert_array_equal(b.laser_offset, a.laser_offset)


_RAW_HAND_LOG = (
    "ODOM 0.0 0.0 0.0 0 0 0 10.0 h 10.0\n"
    # start -0.5 rad, 0.25 rad a beam, max range 20; 5 beams, 2 remission values
    "RAWLASER1 0 -0.5 1.0 0.25 20.0 0.01 0 5 1 2 3 20 nan 2 0.5 0.7 10.25 h 10.3\n"
    "ODOM 2.0 0.0 1.0 0 0 0 11.0 h 11.0\n"
    "RAWLASER2 0 -0.5 1.0 0.25 20.0 0.01 0 2 1 2 0 10.5 h 10.5\n"  # a rear laser: not read
)


@pytest.mark.parametrize("odometry", ["record", "odom"])
def test_rawlaser1_by_hand(tmp_path: Path, odometry: str) -> None:
    path = tmp_path / "raw.log"
    path.write_text(_RAW_HAND_LOG)
    reader = CarmenReader(path, odometry=odometry)
    (scan,) = list(reader)
    assert scan.stamp_s == 10.25 and scan.range_max_m == 20.0
    np.testing.assert_array_equal(scan.angles_rad, [-0.5, -0.25, 0.0, 0.25, 0.5])
    np.testing.assert_array_equal(scan.ranges_m, [1.0, 2.0, 3.0, 20.0, np.inf])
    np.testing.assert_array_equal(scan.valid_mask(), [True, True, True, False, False])
    # a quarter of the way from the ODOM at 10 s to the one at 11 s
    np.testing.assert_array_equal(scan.odom_pose, [0.5, 0.0, 0.25])
    np.testing.assert_array_equal(scan.laser_offset, [0.0, 0.0, 0.0])  # no PARAM
    assert reader.skipped_records == {"RAWLASER2": 1}


def test_rawlaser1_without_odom_records_is_a_laser_only_log(tmp_path: Path) -> None:
    path = tmp_path / "raw.log"
    path.write_text("".join(x for x in _RAW_HAND_LOG.splitlines(True) if "ODOM" not in x))
    (scan,) = list(CarmenReader(path))
    assert scan.odom_pose is None and scan.n_beams == 5
    with pytest.raises(LogFormatError, match="no valid ODOM record to place its 1 RAWLASER1"):
        list(CarmenReader(path, odometry="odom"))


@pytest.mark.parametrize(
    ("old", "new", "where", "message"),
    [
        # no laser record the reader reads: the ones it skips, named
        (
            "RAWLASER1",
            "RAWLASER3",
            "",
            "the log's laser records (1 RAWLASER2, 1 RAWLASER3) "
            "are of a kind this reader does not read; it reads FLASER, RLASER and ROBOTLASER1 "
            "records, or RAWLASER1 (the front laser) from a log without those",
        ),
        # one remission value declared too many: the line, and what is wrong with it
        ("nan 2 0.5 0.7", "nan 3 0.5 0.7", ":2", "RAWLASER1 declares 5 beams and 3 remission"),
    ],
)
def test_a_raw_laser_log_refused_says_why_and_where(
    tmp_path: Path, old: str, new: str, where: str, message: str
) -> None:
    path = tmp_path / "raw.log"
    path.write_text(_RAW_HAND_LOG.replace(old, new))
    with pytest.raises(LogFormatError) as info:
        list(CarmenReader(path))
    assert str(info.value).startswith(f"{path}{where}: {message}")


def test_round_trip_real_mit_csail(tmp_path: Path, mit_csail_scans: list[LaserScan]) -> None:
    scans = mit_csail_scans[:200]
    path = tmp_path / "mit.clf"
    write_carmen(path, scans)
    back = list(open_log(path))
    _assert_round_trip(scans, back)
    # The real ranges have 2 decimals and the no-return value 81.91 is the max range itself:
    # every value comes back exactly as the float parsed from the original text.
    for a, b in zip(scans, back, strict=True):
        np.testing.assert_array_equal(a.ranges_m, b.ranges_m)
        np.testing.assert_array_equal(a.odom_pose, b.odom_pose)
        assert a.stamp_s == b.stamp_s


def test_write_is_atomic_on_failure(tmp_path: Path) -> None:
    path = tmp_path / "keep.clf"
    path.write_text("old content\n")
    good = _synthetic_scans(2, 181, flaser_angles(181))
    no_odom = LaserScan(1.0, np.ones(181), flaser_angles(181), 0.0, 20.0, None, source="x:1")
    with pytest.raises(LogFormatError, match="no odom_pose"):
        write_carmen(path, [*good, no_odom])
    assert path.read_text() == "old content\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["keep.clf"]


# ---------------------------------------------------------------------------------------------
# Issue 12: strict numbers, odometry breaks, timestamp policy
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("bad", "message"),
    [
        ("FLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 0.1 0.2 0.3 1_3.9 h 13.9", "ipc timestamp '1_3.9'"),
        ("FLASER 3 1.0 2_0 3.0 0.1 0.2 0.3 0.1 0.2 0.3 6.0 h 6.0", "range value 2 of 3 '2_0'"),
        ("FLASER 3 1.0 2.0 3.0 0.1 0.2 0.3 \uff11.5 0.2 0.3 6.0 h 6.0", "odometry pose x"),
        ("FLASER \uff13 1.0 2.0 3.0 0.1 0.2 0.3 0.1 0.2 0.3 6.0 h 6.0", "beam count"),
    ],
)
def test_numbers_are_ascii_float_syntax_only(tmp_path: Path, bad: str, message: str) -> None:
    path = tmp_path / "bad.clf"
    path.write_text(f"{_GOOD}\n# comment\n{bad}\n", encoding="utf-8")
    with pytest.raises(LogFormatError, match="not a plain ASCII number") as info:
        list(CarmenReader(path))
    assert str(info.value).startswith(f"{path}:3: ")
    assert message in str(info.value)


def _robotlaser(x: float, stamp: float) -> str:
    pose = f"{x} 0.0 0.0"
    return (
        f"ROBOTLASER1 0 -1.5 3.0 1.5 20.0 0.01 0 3 1.0 2.0 3.0 0 {pose} {pose} "
        f"0 0 0 0 0 {stamp} h {stamp}"
    )


def test_odometry_jump_is_a_break_with_file_line(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    path = write_odometry_jump_log(tmp_path / "jump.clf")
    reader = CarmenReader(path)
    with caplog.at_level(logging.WARNING):
        scans = list(reader)
    assert [s.odom_break for s in scans] == [False, False, False, True, False]
    assert f"{path}:4: odometry jumps 50.00 m" in caplog.text
    assert reader.stamp_report.odometry_breaks[0][0] == f"{path}:4"


def test_second_odometry_frame_is_a_break(tmp_path: Path) -> None:
    path = tmp_path / "mixed.clf"
    lines = [flaser_line(0.0, 1.0), flaser_line(0.1, 1.1)]
    lines += [_robotlaser(0.2, 1.2), _robotlaser(0.3, 1.3), flaser_line(0.4, 1.4)]
    path.write_text("\n".join(lines) + "\n")
    reader = CarmenReader(path)
    assert [s.odom_break for s in reader] == [False, False, True, False, True]
    assert "two odometry frames" in reader.stamp_report.odometry_breaks[0][1]


def test_a_laser_only_reading_is_the_log_without_its_odometry(tmp_path: Path) -> None:
    """``open_log(..., laser_only=True)``: the same scans in the same order, without odometry
    poses or breaks, and the reader's own report of the log."""
    path = write_odometry_jump_log(tmp_path / "jump.clf")
    plain = list(open_log(path))
    reader = open_log(path, laser_only=True)
    scans = list(reader)
    assert [s.source for s in scans] == [s.source for s in plain]
    assert [s.stamp_s for s in scans] == [s.stamp_s for s in plain]
    assert all(np.array_equal(a.ranges_m, b.ranges_m) for a, b in zip(scans, plain, strict=True))
    assert all(s.odom_pose is None and not s.odom_break for s in scans)
    assert reader.count_scans() == len(plain) == 5
    assert reader.stamp_report.odometry_breaks[0][0] == f"{path}:4"  # the log's, as read


def test_real_logs_have_no_false_breaks(mit_csail_scans: list[LaserScan]) -> None:
    assert not any(s.odom_break for s in mit_csail_scans)


def test_timestamp_policy_sort_or_refuse(tmp_path: Path) -> None:
    path = tmp_path / "order.clf"
    stamps = [1.0, 3.0, 2.0]
    path.write_text("\n".join(flaser_line(0.1 * k, t) for k, t in enumerate(stamps)) + "\n")
    reader = CarmenReader(path)
    assert [s.stamp_s for s in reader] == [1.0, 2.0, 3.0]
    assert [s.source for s in reader] == [f"{path}:1", f"{path}:3", f"{path}:2"]
    assert reader.stamp_report.out_of_order == 1
    with pytest.raises(LogFormatError, match=f"{path}:3: timestamp 2.0 is earlier"):
        list(CarmenReader(path, stamps="refuse"))
    with pytest.raises(ConfigError, match="stamps"):
        CarmenReader(path, stamps="shuffle")
