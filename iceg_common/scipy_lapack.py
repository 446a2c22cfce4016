"""scipy's BLAS and LAPACK modules loaded without the rest of ``scipy.linalg`` (issue 13,
cold start).

numba runs ``np.linalg`` inside a kernel through scipy's Cython modules
``scipy.linalg.cython_blas`` and ``scipy.linalg.cython_lapack``: numba imports the first as
it installs its typing registry (the first kernel a process loads) and each LAPACK routine's
module the first time a kernel calls it. Importing a submodule first runs its package, and
``scipy/linalg/__init__.py`` imports the whole of ``scipy.linalg`` and scipy's array-API layer
(which imports ``numpy.f2py``): about 0.2 s of a fresh process's start, of which numba reads
two extension modules.

:func:`preload` loads those two modules from their files under their own names (about 35 ms,
with scipy's top-level package, which they import), so that numba finds them in
``sys.modules`` and ``scipy.linalg`` itself is imported only by code that uses it. The
modules are the ones the package would load (the same files), so the kernels call the same
LAPACK routines. Where something imports ``scipy.linalg`` later, the two modules are set as
its attributes, as importing them through the package would have.
"""

from __future__ import annotations

import functools
import importlib.machinery
import importlib.util
import logging
import os
import sys
from collections.abc import Sequence
from importlib.abc import Loader, MetaPathFinder
from types import ModuleType

__all__ = ["PACKAGE", "SUBMODULES", "preload"]

log = logging.getLogger(__name__)

#: The package whose extension modules numba's linear algebra imports.
PACKAGE = "scipy.linalg"
#: Those modules' full names, in the order they load (LAPACK's imports BLAS's).
SUBMODULES = (f"{PACKAGE}.cython_blas", f"{PACKAGE}.cython_lapack")


@functools.cache
def preload() -> bool:
    """Load :data:`SUBMODULES` without running their package (see the module docstring), in
    this process and the processes it forks; once per process.

    Returns:
        Whether they were loaded here. False where ``scipy.linalg`` or one of them is
        imported already, or where they cannot be loaded from scipy's folder (then nothing is
        left in ``sys.modules``, and numba imports them through the package as before).
    """
    if PACKAGE in sys.modules or any(name in sys.modules for name in SUBMODULES):
        return False
    scipy_spec = importlib.util.find_spec("scipy")  # a top-level name: imports nothing
    if scipy_spec is None or not scipy_spec.submodule_search_locations:
        return False
    folders = [os.path.join(folder, "linalg") for folder in scipy_spec.submodule_search_locations]
    try:
        for name in SUBMODULES:
            _load_extension(name, folders)
    except Exception as exc:  # numba's own path imports them as before
        for name in SUBMODULES:  # none was there before
            sys.modules.pop(name, None)
        log.debug("%s: loaded through its package (%s)", PACKAGE, exc)
        return False
    sys.meta_path.insert(0, _AttachToPackage())
    return True


def _load_extension(name: str, folders: Sequence[str]) -> None:
    """Load the extension module ``name`` from ``folders`` into ``sys.modules``.

    Raises:
        ImportError: no extension module of that name there; whatever its initialisation
            raises (it is then left in ``sys.modules`` for the caller to remove).
    """
    spec = importlib.machinery.PathFinder.find_spec(name, list(folders))
    if spec is None or not isinstance(spec.loader, importlib.machinery.ExtensionFileLoader):
        raise ImportError(f"no extension module {name} in {list(folders)}")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)


class _AttachToPackage(MetaPathFinder):
    """Where ``scipy.linalg`` is imported after :func:`preload`: its own finder's spec, with a
    loader that runs the package's loader and then sets the preloaded modules as its
    attributes. Removes itself at that import."""

    def find_spec(
        self,
        fullname: str,
        path: Sequence[str] | None,
        target: ModuleType | None = None,
    ) -> importlib.machinery.ModuleSpec | None:
        if fullname != PACKAGE:
            return None
        sys.meta_path.remove(self)
        spec = importlib.util.find_spec(fullname)  # the remaining finders: the package's spec
        if spec is not None and spec.loader is not None:
            spec.loader = _Attaching(spec.loader)
        return spec


class _Attaching(Loader):
    """The package's loader, then the preloaded modules set as its attributes."""

    def __init__(self, loader: Loader) -> None:
        self._loader = loader

    def create_module(self, spec: importlib.machinery.ModuleSpec) -> ModuleType | None:
        return self._loader.create_module(spec)

    def exec_module(self, module: ModuleType) -> None:
        # the package's own loader, before its code runs, as if this one had not been here
        module.__loader__ = self._loader
        if module.__spec__ is not None:
            module.__spec__.loader = self._loader
        self._loader.exec_module(module)
        for name in SUBMODULES:
            if name in sys.modules:
                setattr(module, name.rpartition(".")[2], sys.modules[name])
