"""Sets of integer ids (node and landmark ids) as sorted arrays, for every package."""

from __future__ import annotations

import numpy as np
from numpy.typing import ArrayLike, NDArray


def sorted_unique(ids: ArrayLike) -> NDArray[np.int64]:
    """``np.unique`` of integer ids: their distinct values, ascending, in a new ``(k,)``
    int64 array.

    Ids already strictly ascending (a run of nodes, a sorted table) take one comparison,
    others one sort and one comparison; ``np.unique``'s general path costs several times
    more at the few dozen ids of a keyframe's questions.

    Args:
        ids: Integer ids, any shape (flattened); converted to int64.
    """
    a = np.asarray(ids, dtype=np.int64).reshape(-1)
    if a.shape[0] < 2 or bool((a[1:] > a[:-1]).all()):
        return a.copy()
    out = np.sort(a)
    keep = np.empty(out.shape[0], dtype=bool)
    keep[0] = True
    np.not_equal(out[1:], out[:-1], out=keep[1:])
    return out if bool(keep.all()) else out[keep]
