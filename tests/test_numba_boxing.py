"""Arrays a kernel returns boxed without a call back into Python
(``iceg_common.numba_boxing``): the same arrays as numba's own boxing gives, none of its
``_numba_unpickle`` calls, and the same from numba's cache in a fresh process."""

from __future__ import annotations

import json
import os
import subprocess
import sys
import textwrap
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numba
import numpy as np
import pytest
from numba.core import boxing, pythonapi, serialize, types

from iceg_common import numba_boxing
from iceg_common.numba_loading import njit

ROOT = Path(__file__).resolve().parents[1]


def _returns(a: np.ndarray, b: np.ndarray) -> tuple[Any, ...]:
    """Arrays of several dtypes, ranks and layouts: new ones, a view of an argument, and
    the read-only argument itself."""
    return (
        a[:3].copy(),
        (a * 2.0).reshape(2, -1),
        np.arange(4),
        a > 2.0,
        a[::2],
        a.reshape(2, -1).T,
        b,
        np.empty((0, 2)),
    )


def _calls_back(run: Callable[[], Any]) -> tuple[Any, int]:
    """``run()``'s result and how many times it called ``_numba_unpickle``, counted by a
    profile hook on its code (numba's C helper keeps the function it first called, so
    replacing the module's attribute would not see every call)."""
    calls = [0]
    code = serialize._numba_unpickle.__code__

    def hook(frame: Any, event: str, arg: Any) -> None:
        if event == "call" and frame.f_code is code:
            calls[0] += 1

    previous = sys.getprofile()
    sys.setprofile(hook)
    try:
        result = run()
    finally:
        sys.setprofile(previous)
    return result, calls[0]


def _compiled_with(boxer: Callable[..., Any]) -> Callable[..., tuple[Any, ...]]:
    """``_returns`` compiled (not cached) with ``boxer`` as the array boxer."""
    registered = pythonapi._boxers.functions[types.Array]
    pythonapi._boxers.functions[types.Array] = boxer
    try:
        kernel = njit(cache=False)(_returns)
        a = np.arange(6.0)
        b = np.ones(3)
        b.flags.writeable = False
        kernel(a, b)  # compiled here, with this boxer
    finally:
        pythonapi._boxers.functions[types.Array] = registered
    return kernel  # type: ignore[no-any-return]


def test_install_replaces_numbas_array_boxer_on_the_numba_it_knows() -> None:
    # numba 0.68 was checked; a later numba whose boxer differs keeps its own (install()
    # is False): review the module for it before widening this check.
    version = tuple(int(part) for part in numba.__version__.split(".")[:2])
    if version > (0, 68):
        pytest.skip(f"numba {numba.__version__}: newer than numba_boxing was checked on")
    assert numba_boxing.install() is True
    assert pythonapi._boxers.functions[types.Array] is numba_boxing._box_array


def test_a_boxer_other_than_numbas_own_is_left_alone(monkeypatch: pytest.MonkeyPatch) -> None:
    def other(typ: Any, val: Any, c: Any) -> Any:  # another library's boxer
        return boxing.box_array(typ, val, c)

    monkeypatch.setitem(pythonapi._boxers.functions, types.Array, other)
    assert numba_boxing.install.__wrapped__() is False  # type: ignore[attr-defined]
    assert pythonapi._boxers.functions[types.Array] is other


def test_returned_arrays_are_numbas_without_a_call_back_into_python() -> None:
    ours = _compiled_with(numba_boxing._box_array)
    stock = _compiled_with(boxing.box_array)
    a = np.arange(6.0)
    b = np.ones(3)
    b.flags.writeable = False
    got, ours_calls = _calls_back(lambda: ours(a, b))
    want, stock_calls = _calls_back(lambda: stock(a, b))
    assert ours_calls == 0
    assert stock_calls == len(want)  # numba's own boxing: one call an array
    for g, w in zip(got, want, strict=True):
        assert type(g) is type(w) is np.ndarray
        assert (g.dtype, g.shape, g.strides) == (w.dtype, w.shape, w.strides)
        assert g.flags.writeable == w.flags.writeable
        assert g.flags.c_contiguous == w.flags.c_contiguous
        assert g.flags.f_contiguous == w.flags.f_contiguous
        assert np.shares_memory(g, a) == np.shares_memory(w, a)
        assert np.shares_memory(g, b) == np.shares_memory(w, b)
        assert g.tobytes() == w.tobytes()
    assert not got[6].flags.writeable  # the read-only argument stays read-only


_MODULE = """
import numpy as np
from iceg_common.numba_loading import njit

@njit(cache=True)
def kernel(a):
    return a[:3].copy(), (a * 2.0).reshape(2, -1), a > 2.0
"""

_RUN = """
import json
import sys
import numpy as np
from numba.core import serialize
calls = [0]
code = serialize._numba_unpickle.__code__
def hook(frame, event, arg):
    if event == "call" and frame.f_code is code:
        calls[0] += 1
import kernels
out = kernels.kernel(np.arange(6.0))  # compiled and cached, or loaded from the cache
sys.setprofile(hook)
out = kernels.kernel(np.arange(6.0))
sys.setprofile(None)
hits = sum(kernels.kernel.stats.cache_hits.values())
print(json.dumps([[v.tolist() for v in out], [str(v.dtype) for v in out], hits, calls[0]]))
"""


def test_a_kernel_cached_with_this_boxing_loads_and_boxes_the_same(tmp_path: Path) -> None:
    # Fresh processes on an empty cache: the first compiles and caches the kernel, the second
    # loads it (the array class from the cached environment's constants); both return the
    # same arrays without calling back into Python.
    (tmp_path / "kernels.py").write_text(textwrap.dedent(_MODULE))
    env = dict(
        os.environ,
        PYTHONPATH=os.pathsep.join([str(tmp_path), str(ROOT)]),
        NUMBA_CACHE_DIR=str(tmp_path / "numba"),
    )

    def run() -> list[Any]:
        out = subprocess.run(
            [sys.executable, "-c", _RUN], env=env, capture_output=True, text=True, check=True
        ).stdout
        result: list[Any] = json.loads(out.strip().splitlines()[-1])
        return result

    values = [[0.0, 1.0, 2.0], [[0.0, 2.0, 4.0], [6.0, 8.0, 10.0]], [False] * 3 + [True] * 3]
    dtypes = ["float64", "float64", "bool"]
    assert run() == [values, dtypes, 0, 0]
    assert run() == [values, dtypes, 1, 0]
