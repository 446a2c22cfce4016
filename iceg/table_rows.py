"""Row moves of the feature map's column tables (:class:`iceg.feature_map._Columns`),
compiled: a drop moves the kept rows of every column down in place in one call, where a
Python loop made a slice assignment per column and per kept block."""

from __future__ import annotations

import numpy as np

from iceg_common.numba_loading import njit


@njit(cache=True, nogil=True)
def drop_rows_in_place(
    columns: tuple[np.ndarray, ...], row_words: np.ndarray, gone: np.ndarray, n: int
) -> None:
    """Remove the rows ``gone`` of ``n`` rows from every column, in place, the others kept in
    order at the front (what a stable gather of the kept rows gives; the rows beyond
    ``n - len(gone)`` are left as they were moved).

    Args:
        columns: Each column's buffer as ``(capacity * row_words[c],)`` int64 words (its
            8-byte values' bits, so that any float64 bit pattern moves unchanged).
        row_words: ``(C,)`` int64 words per row of each column.
        gone: ``(G,)`` int64 sorted unique rows to remove, each in ``[0, n)``.
        n: Rows held before the drop.

    Raises nothing.
    """
    n_gone = gone.shape[0]
    if n_gone == 0:
        return
    for c in range(len(columns)):
        col = columns[c]
        w = row_words[c]
        at = gone[0] * w
        for g in range(n_gone):
            start = (gone[g] + 1) * w
            stop = (gone[g + 1] if g + 1 < n_gone else n) * w
            for k in range(start, stop):
                col[at] = col[k]
                at += 1
