"""numba's cached kernels loaded without parsing their linking bitcode (issue 13, cold start).

The project's kernels take :func:`njit` from here, so that :func:`install` (and
:func:`iceg_common.numba_boxing.install`) has run before any of them loads or compiles.

numba keeps a compiled kernel in its cache as object code and, beside it, the kernel's LLVM
bitcode, which a kernel compiled later links in to inline it. Loading a kernel from the
cache (``numba.core.codegen.CPUCodeLibrary._unserialize``) parses that bitcode and walks it
for the names of the functions and globals it defines, which the JIT engine keeps to tell
which symbols exist. For the 58 kernels the first keyframes of a MIT CSAIL run load, that is
3.8 MB of bitcode and 0.43-0.59 s of the cold start's 1.45-1.87 s; loading the object code
itself takes under 0.1 s.

:func:`install` replaces that step: the defined names are read from the object code's ELF
symbol table (:func:`elf_defined_symbols`: the same set, checked on every kernel of a run),
and the bitcode is parsed only when a kernel compiled later links the loaded one in. The
code that runs is the cached object code either way, so every result is the same bit for
bit. Where the object code is not 64-bit little-endian ELF (macOS, Windows), or numba's
loading step is not the one this replaces (another numba version), numba's own path runs.
"""

from __future__ import annotations

import functools
import logging
from typing import Any

import numba
import numpy as np
from numba import njit
from numba.core import codegen

from iceg_common import numba_boxing, scipy_lapack

__all__ = ["elf_defined_symbols", "install", "njit"]

log = logging.getLogger(__name__)

#: The global names numba's loading step (``CPUCodeLibrary._unserialize``) uses, and those of
#: the step that hands a library's bitcode to a kernel linking it in: the numba versions
#: whose steps :func:`install` replaces (the same for many releases; checked on 0.68).
_UNSERIALIZE_NAMES = (
    "create_library",
    "isinstance",
    "ll",
    "parse_bitcode",
    "_final_module",
    "_finalize_final_module",
    "enable_object_caching",
    "_set_compiled_object",
    "_shared_module",
    "_codegen",
    "_engine",
    "_load_defined_symbols",
    "ValueError",
)
_LINKING_NAMES_NEEDED = frozenset({"_ensure_finalized", "_shared_module", "_final_module"})

#: The attribute of a library loaded by :func:`install`'s step holding its bitcode until a
#: kernel links it in.
_PENDING = "_iceg_linking_bitcode"

# ELF64 section header and symbol table entry (System V ABI, little-endian)
_SECTION = np.dtype(
    [
        ("name", "<u4"),
        ("type", "<u4"),
        ("flags", "<u8"),
        ("addr", "<u8"),
        ("offset", "<u8"),
        ("size", "<u8"),
        ("link", "<u4"),
        ("info", "<u4"),
        ("addralign", "<u8"),
        ("entsize", "<u8"),
    ]
)
_SYMBOL = np.dtype(
    [
        ("name", "<u4"),
        ("info", "u1"),
        ("other", "u1"),
        ("shndx", "<u2"),
        ("value", "<u8"),
        ("size", "<u8"),
    ]
)
_SHT_SYMTAB = 2
_STT_SECTION = 3
_STT_FILE = 4


def elf_defined_symbols(object_code: bytes) -> frozenset[str] | None:
    """The names an ELF object file defines: its symbol table's entries with a section (a
    common symbol's counts), but for section and file symbols. For numba's object code
    these are the names of the functions and globals its LLVM module defines.

    Args:
        object_code: The object file's bytes.

    Returns:
        The names, or None where ``object_code`` is not a 64-bit little-endian ELF file
        with one symbol table, or is truncated (a table or name past its end).
    """
    head = memoryview(object_code)
    if len(head) < 64 or bytes(head[:6]) != b"\x7fELF\x02\x01":
        return None
    try:
        return _defined_names(head)
    except (ValueError, IndexError):  # truncated or inconsistent: numba's own step decides
        return None


def _defined_names(head: memoryview) -> frozenset[str] | None:
    """:func:`elf_defined_symbols` of a file with an ELF64 little-endian header.

    Raises:
        ValueError, IndexError: a table or name lies outside the file.
    """
    section_offset = int.from_bytes(head[0x28:0x30], "little")
    entry_size = int.from_bytes(head[0x3A:0x3C], "little")
    n_sections = int.from_bytes(head[0x3C:0x3E], "little")
    if entry_size != _SECTION.itemsize or n_sections == 0:
        return None
    sections = np.frombuffer(head, _SECTION, n_sections, section_offset)
    tables = np.flatnonzero(sections["type"] == _SHT_SYMTAB)
    if tables.shape[0] != 1:
        return None
    table = sections[tables[0]]
    if int(table["entsize"]) != _SYMBOL.itemsize or int(table["link"]) >= n_sections:
        return None
    names = sections[int(table["link"])]
    symbols = np.frombuffer(
        head, _SYMBOL, int(table["size"]) // _SYMBOL.itemsize, int(table["offset"])
    )
    kind = symbols["info"] & 0xF
    defined = (
        (symbols["shndx"] != 0)
        & (symbols["name"] != 0)
        & (kind != _STT_SECTION)
        & (kind != _STT_FILE)
    )
    start = int(names["offset"])
    text = bytes(head[start : start + int(names["size"])])
    return frozenset(
        text[at : text.index(b"\0", at)].decode() for at in symbols["name"][defined].tolist()
    )


@functools.cache
def install() -> bool:
    """Load numba's cached kernels without parsing their bitcode (see the module docstring),
    in this process and the processes it forks; once per process.

    Returns:
        Whether numba's loading step is replaced (False: this numba's step is not the one
        this module knows, and numba's own runs).
    """
    library = codegen.CPUCodeLibrary
    unserialize = library.__dict__.get("_unserialize")
    linking = library.__dict__.get("_get_module_for_linking")
    if not (
        isinstance(unserialize, classmethod)
        and unserialize.__func__.__code__.co_names == _UNSERIALIZE_NAMES
        and callable(linking)
        and set(linking.__code__.co_names) >= _LINKING_NAMES_NEEDED
        and hasattr(codegen.JitEngine, "_load_defined_symbols")
    ):
        log.debug("numba %s: its cached kernels load by its own path", numba.__version__)
        return False
    stock_unserialize = unserialize.__func__

    def _unserialize(cls: Any, codegen_: Any, state: tuple[str, str, Any]) -> Any:
        name, kind, data = state
        if kind != "object":
            return stock_unserialize(cls, codegen_, state)
        object_code, linking_bitcode = data
        symbols = elf_defined_symbols(object_code)
        if symbols is None:
            return stock_unserialize(cls, codegen_, state)
        self = codegen_.create_library(name)
        self.enable_object_caching()
        self._set_compiled_object(object_code)
        setattr(self, _PENDING, linking_bitcode)
        self._finalize_final_module()
        codegen_._engine._defined_symbols |= symbols
        return self

    def _get_module_for_linking(self: Any) -> Any:
        pending = self.__dict__.pop(_PENDING, None)
        if pending is not None:
            self._shared_module = codegen.ll.parse_bitcode(pending)
        return linking(self)

    library._unserialize = classmethod(_unserialize)  # type: ignore[method-assign,assignment]
    library._get_module_for_linking = _get_module_for_linking  # type: ignore[method-assign]
    return True


install()
# the arrays the kernels return boxed without a call back into Python
numba_boxing.install()
# numba's linear algebra finds scipy's BLAS and LAPACK modules without scipy.linalg's package
scipy_lapack.preload()
