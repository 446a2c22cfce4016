"""Sets of integer ids (node and landmark ids) as sorted arrays, for every package."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray

from iceg_common.numba_loading import njit


def sorted_unique(ids: ArrayLike) -> NDArray[np.int64]:
    """``np.unique`` of integer ids: their distinct values, ascending, in a new ``(k,)``
    int64 array.

    One compiled pass (:func:`_sorted_unique`): ids already strictly ascending (a run of
    nodes, a sorted table) are copied after one comparison each, others sorted first;
    ``np.unique``'s general path, or the same steps in numpy calls, cost several times
    more at the few dozen ids of a keyframe's questions.

    Args:
        ids: Integer ids, any shape (flattened); converted to int64.
    """
    return _sorted_unique(np.ascontiguousarray(ids, dtype=np.int64).reshape(-1))


@njit(cache=True, nogil=True)
def _sorted_unique(a: np.ndarray) -> np.ndarray:
    """:func:`sorted_unique` of ``a`` ``(n,)`` int64. Raises nothing."""
    n = a.shape[0]
    ascending = True
    for i in range(1, n):
        if a[i] <= a[i - 1]:
            ascending = False
            break
    if ascending:
        return a.copy()
    s = np.sort(a)
    out = np.empty(n, np.int64)
    out[0] = s[0]
    k = 1
    for i in range(1, n):
        if s[i] != s[i - 1]:
            out[k] = s[i]
            k += 1
    return out[:k].copy()
