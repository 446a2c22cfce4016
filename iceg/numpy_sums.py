"""Sums and medians as numpy takes them, for compiled kernels: a kernel that sums what numpy
summed before gives the same bits (issue 13; docs/design.md, "Exact rewrites, second
round")."""

from __future__ import annotations

import numpy as np

from iceg_common.numba_loading import njit

#: numpy's pairwise summation: blocks up to this long are summed with eight accumulators.
_PW_BLOCKSIZE = 128


@njit(cache=True, nogil=True)
def _block_sum(a: np.ndarray, lo: int, n: int) -> float:
    """numpy's sum of a block of at most :data:`_PW_BLOCKSIZE` terms (see
    :func:`pairwise_sum`)."""
    if n < 8:
        res = -0.0
        for i in range(lo, lo + n):
            res += a[i]
        return res
    r = a[lo : lo + 8].copy()
    i = 8
    while i < n - n % 8:
        for k in range(8):
            r[k] += a[lo + i + k]
        i += 8
    res = ((r[0] + r[1]) + (r[2] + r[3])) + ((r[4] + r[5]) + (r[6] + r[7]))
    while i < n:
        res += a[lo + i]
        i += 1
    return res


@njit(cache=True, nogil=True)
def pairwise_sum(a: np.ndarray, lo: int, n: int) -> float:
    """Sum of ``a[lo:lo + n]`` (float64) in the order numpy's ``add.reduce`` takes along a
    contiguous axis (``pairwise_sum`` in numpy's ``loops_utils.h.src``: under 8 terms one
    by one from -0.0, up to 128 in eight interleaved partial sums, beyond that the sum of
    the two halves, the first a multiple of 8 long), so a kernel's sum has the bits of
    ``np.sum`` over the same values. The halving runs on an explicit stack: numba's cache
    cannot load a recursive function (the process crashes)."""
    if n <= _PW_BLOCKSIZE:
        return _block_sum(a, lo, n)
    todo_lo = np.empty(192, dtype=np.int64)  # 64 halvings at most, three entries each
    todo_n = np.empty(192, dtype=np.int64)
    todo_join = np.empty(192, dtype=np.bool_)
    sums = np.empty(192)
    top, n_sums = 1, 0
    todo_lo[0], todo_n[0], todo_join[0] = lo, n, False
    while top:
        top -= 1
        at, m = todo_lo[top], todo_n[top]
        if todo_join[top]:  # both halves summed: left + right
            sums[n_sums - 2] = sums[n_sums - 2] + sums[n_sums - 1]
            n_sums -= 1
        elif m <= _PW_BLOCKSIZE:
            sums[n_sums] = _block_sum(a, at, m)
            n_sums += 1
        else:
            half = m // 2
            half -= half % 8
            todo_lo[top], todo_n[top], todo_join[top] = at, m, True
            todo_lo[top + 1], todo_n[top + 1], todo_join[top + 1] = at + half, m - half, False
            todo_lo[top + 2], todo_n[top + 2], todo_join[top + 2] = at, half, False
            top += 3
    return sums[0]


@njit(cache=True, nogil=True)
def median(a: np.ndarray) -> float:
    """``np.median`` of ``a`` ``(n,)`` float64 without NaN, ``n >= 1``: the middle value, or
    the mean of the middle two (their sum over 2, as ``np.mean`` takes it)."""
    s = np.sort(a)
    half = s.shape[0] // 2
    return s[half] if s.shape[0] % 2 else (s[half - 1] + s[half]) / 2.0
