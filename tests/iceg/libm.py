"""numpy's transcendental ufuncs as the C library computes them, for the references of the
bit-for-bit tests of compiled kernels.

The kernels call the C library (numba lowers ``math.atan2`` and ``math.acos`` to it, as
Python's ``math`` does). numpy's ``arctan2`` and ``arccos`` do too on most machines, but on a
CPU with AVX-512 numpy dispatches them to its own SIMD code, whose last bit differs for some
inputs (``np.show_runtime()`` lists ``X86_V4`` among the features found). The numpy
expressions the kernels replaced are the references of those tests; with these two functions
they give the same values on every machine.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

import numpy as np


def _elementwise(fn: Callable[..., float], n_in: int) -> Callable[..., np.ndarray]:
    ufunc = np.frompyfunc(fn, n_in, 1)

    def call(*args: Any) -> np.ndarray:
        return np.asarray(ufunc(*args), dtype=np.float64)

    return call


#: ``np.arctan2`` by the C library's ``atan2``, element by element (float64).
arctan2 = _elementwise(math.atan2, 2)
#: ``np.arccos`` by the C library's ``acos``, element by element (float64).
arccos = _elementwise(math.acos, 1)
