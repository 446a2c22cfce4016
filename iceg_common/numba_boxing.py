"""Arrays a numba kernel returns boxed without a call back into Python (issue 13).

numba boxes each array a kernel returns (``numba.core.boxing.box_array``) with its C
runtime's ``NRT_adapt_ndarray_to_python_acqref``, which takes the array's NumPy dtype and its
Python class. The dtype comes from the kernel's environment constants
(``EnvironmentManager.read_const``: an item of a list the environment holds, no Python code
runs). The class is unpickled at every call instead (``PythonAPI.unserialize``: numba's C
helper ``numba_unpickle`` builds two bytes objects and calls
``numba.core.serialize._numba_unpickle``, a memoized lookup in Python): about 0.4 µs an
array, and a MIT CSAIL run's main process boxes some 210 000 arrays (docs/design.md,
"Returned arrays").

:func:`install` registers a boxer for arrays that passes the class the way numba passes the
dtype, to the same runtime function with the same arguments, so every array returned is the
same (the same class, dtype, shape, strides, flags and data; its code is compiled into the
kernel's wrapper, so a kernel compiled or cached before it keeps numba's way). Where numba's
boxer is not the one this module was checked against (another numba version), numba's stays.
"""

from __future__ import annotations

import functools
import logging
from typing import Any

import numba
from llvmlite import ir
from numba.core import boxing, cgutils, pythonapi, types
from numba.np import numpy_support

__all__ = ["install"]

log = logging.getLogger(__name__)

#: The runtime function numba's array boxing calls (numba 0.68), and the global names of
#: numba's steps :func:`install` takes over: ``box_array``, and the
#: ``PythonAPI.nrt_adapt_ndarray_to_python`` it calls.
_ADAPT = "NRT_adapt_ndarray_to_python_acqref"
_BOX_ARRAY_NAMES = frozenset({"nrt_adapt_ndarray_to_python", "read_const", "add_const"})
_ADAPT_NAMES = frozenset({"unserialize", "serialize_object", "box_type", "_get_function"})


@functools.cache
def install() -> bool:
    """Box returned arrays with their class taken from the kernel's environment (see the
    module docstring), for every kernel compiled in this process from now on; once per
    process.

    Returns:
        Whether numba's array boxer is replaced (False: this numba's is not the one this
        module knows, and numba's own stays).
    """
    box_array = getattr(boxing, "box_array", None)
    adapt = getattr(pythonapi.PythonAPI, "nrt_adapt_ndarray_to_python", None)
    if not (
        box_array is not None
        and pythonapi._boxers.functions.get(types.Array) is box_array
        and set(box_array.__code__.co_names) >= _BOX_ARRAY_NAMES
        and adapt is not None
        and set(adapt.__code__.co_names) >= _ADAPT_NAMES
        and {_ADAPT, "captures(none)"} <= set(adapt.__code__.co_consts)
    ):
        log.debug("numba %s: arrays are boxed by its own step", numba.__version__)
        return False
    pythonapi._boxers.functions[types.Array] = _box_array
    return True


def _box_array(typ: Any, val: Any, c: Any) -> Any:
    """``numba.core.boxing.box_array`` with the array's Python class read from the
    environment's constants, as the dtype is (numba's runtime, NRT, is always on for the
    project's kernels; without it numba's own boxer runs)."""
    if not c.context.enable_nrt:
        return boxing.box_array(typ, val, c)
    env = c.env_manager
    dtype = env.read_const(env.add_const(numpy_support.as_dtype(typ.dtype)))
    pytype = env.read_const(env.add_const(typ.box_type))
    api = c.pyapi
    i32 = ir.IntType(32)
    fnty = ir.FunctionType(api.pyobj, [api.voidptr, api.pyobj, i32, i32, api.pyobj])
    fn = api._get_function(fnty, name=_ADAPT)
    fn.args[0].add_attribute("captures(none)")
    ndim = c.context.get_constant(types.int32, typ.ndim)
    writable = c.context.get_constant(types.int32, int(typ.mutable))
    aryptr = cgutils.alloca_once_value(c.builder, val)
    boxed = c.builder.call(
        fn, [c.builder.bitcast(aryptr, api.voidptr), pytype, ndim, writable, dtype]
    )
    c.context.nrt.decref(c.builder, typ, val)  # the new array holds the reference
    return boxed
