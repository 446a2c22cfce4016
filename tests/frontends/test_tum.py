"""TUM trajectory round trip and error reporting."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from frontends.tum import read_tum, write_tum
from iceg_common.errors import LogFormatError


@settings(max_examples=50, deadline=None)
@given(
    arrays(np.float64, (7, 3), elements=st.floats(-1e4, 1e4, allow_nan=False)),
    st.floats(0, 2e9),
)
def test_round_trip_is_exact(
    tmp_path_factory: pytest.TempPathFactory, xy: np.ndarray, t0: float
) -> None:
    poses = xy.copy()
    poses[:, 2] = np.linspace(-3.1, 3.1, 7)
    stamps = t0 + np.arange(7) * 0.1
    path = tmp_path_factory.mktemp("tum") / "t.tum"
    assert write_tum(path, stamps, poses) == 7
    stamps2, poses2 = read_tum(path)
    np.testing.assert_array_equal(stamps2, stamps)
    np.testing.assert_array_equal(poses2[:, :2], poses[:, :2])
    np.testing.assert_allclose(poses2[:, 2], poses[:, 2], atol=1e-12)


def test_hand_written_line_gives_yaw(tmp_path: Path) -> None:
    # qz = sin(pi/4), qw = cos(pi/4) is a yaw of pi/2.
    path = tmp_path / "t.tum"
    path.write_text(
        "# stamp x y z qx qy qz qw\n1.5 2 3 0 0 0 0.7071067811865476 0.7071067811865476\n"
    )
    stamps, poses = read_tum(path)
    assert stamps.tolist() == [1.5]
    np.testing.assert_allclose(poses, [[2.0, 3.0, np.pi / 2]], atol=1e-12)


def test_a_byte_order_mark_at_the_start_is_dropped(tmp_path: Path) -> None:
    path = tmp_path / "t.tum"  # saved as UTF-8 with a BOM (an editor on Windows)
    path.write_bytes(b"\xef\xbb\xbf1.5 2 3 0 0 0 0 1\n")
    stamps, poses = read_tum(path)
    assert stamps.tolist() == [1.5] and poses.tolist() == [[2.0, 3.0, 0.0]]


def test_bad_line_names_file_and_line(tmp_path: Path) -> None:
    path = tmp_path / "t.tum"
    path.write_text("1 0 0 0 0 0 0 1\n2 0 0 0 0 0 1\n")
    with pytest.raises(LogFormatError, match=r"t\.tum:2: a TUM line needs 8"):
        read_tum(path)
