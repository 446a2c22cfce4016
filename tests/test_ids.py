"""iceg_common.ids: sorted id sets, checked against numpy's own answer."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from iceg_common.ids import sorted_unique


@settings(deadline=None)  # the first example loads (or compiles) the kernel
@given(st.lists(st.integers(-(2**62), 2**62), max_size=60), st.booleans())
def test_sorted_unique_is_numpys_unique(ids: list[int], presorted: bool) -> None:
    # Ascending runs (the fast path), repeats and any order all give np.unique's answer, in
    # a new int64 array the caller may write to.
    given_ids = np.array(sorted(set(ids)) if presorted else ids, dtype=np.int64)
    got = sorted_unique(given_ids)
    np.testing.assert_array_equal(got, np.unique(given_ids))
    assert got.dtype == np.int64
    assert not np.shares_memory(got, given_ids)


def test_sorted_unique_flattens_and_converts() -> None:
    got = sorted_unique([[5, 3], [3, 9]])
    np.testing.assert_array_equal(got, [3, 5, 9])
    assert got.dtype == np.int64
    assert sorted_unique([]).shape == (0,)


def test_sorted_unique_takes_strided_and_read_only_arrays() -> None:
    # The compiled pass gets a contiguous int64 copy where needed; the answer is still a new
    # array the caller may write to.
    a = np.array([9, 4, 4, 7, 1, 8], dtype=np.int32)
    np.testing.assert_array_equal(sorted_unique(a[::-2]), [4, 7, 8])
    frozen = np.arange(5, dtype=np.int64)
    frozen.flags.writeable = False
    got = sorted_unique(frozen)
    got[0] = 7
    np.testing.assert_array_equal(frozen, np.arange(5))
