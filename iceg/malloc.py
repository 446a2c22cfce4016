"""The ``iceg`` command's malloc: mimalloc where it is installed, else glibc's on huge pages
(issue 13).

A run allocates and frees arrays by the hundred thousand: numba's kernels return new arrays,
numpy's calls make temporaries, gtsam allocates its factors and cliques. In a profile of the
main process of a MIT CSAIL run, glibc's ``malloc`` and ``free`` held about 8 % of the
samples. mimalloc (Leijen, Zorn and de Moura, "Mimalloc: Free List Sharding in Action",
APLAS 2019; Microsoft's allocator, MIT licence) serves the same calls from per-page free
lists. Linux lets a process use it without a rebuild of anything: the dynamic loader maps a
library named in ``LD_PRELOAD`` before the C library, and its ``malloc``, ``free`` and the
rest then serve the whole process, the interpreter's large objects, numpy, numba's runtime
and gtsam's C++ ``new`` alike (Python's small objects stay in its own arenas). The package
``cmeel-mimalloc`` (a dependency on x86-64 and arm64 Linux) ships the library as a wheel.

With it a MIT CSAIL run in a fresh process took about 5 % less time on the benchmark machine,
17 runs one after another in one process 15-26 % less, and the results are the same bit for
bit; the peak memory is about 15 % higher (docs/design.md, "malloc from mimalloc" under
"Speed"). Its own
option ``MIMALLOC_ALLOW_LARGE_OS_PAGES=1`` is set with it where the kernel hands out
transparent huge pages on request (its ``madvise`` mode), as glibc's tunable was before
(:mod:`iceg.huge_pages`).

``LD_PRELOAD`` is read once, when a process starts, so the ``iceg`` command
(:mod:`iceg.__main__`) replaces its process by itself with the variable set
(:func:`exec_with_fast_malloc`) before it imports anything heavy: about one interpreter start
(20-40 ms). Where mimalloc is not installed, where ``ICEG_MALLOC=glibc`` is set, or where
``LD_PRELOAD`` names a library already (a user's allocator or tool), the command keeps
glibc's malloc and asks it for huge pages (:func:`iceg.huge_pages.huge_page_environment`). A
library user gets mimalloc by starting Python (or Jupyter) with ``LD_PRELOAD`` set to
:func:`find_mimalloc`'s path. The forked helpers of a run, and any process a command starts,
inherit the variable.

Besides the standard library it imports :mod:`iceg.huge_pages` and :mod:`iceg_common.errors`
only (both light), since it runs before the command imports anything heavy.
"""

from __future__ import annotations

import logging
import os
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path

from iceg.huge_pages import glibc_version, huge_page_environment, thp_mode
from iceg_common.errors import ConfigError, IcegError

log = logging.getLogger(__name__)

#: Where ``cmeel-mimalloc`` puts the library, below a folder of ``sys.path`` (site-packages).
MIMALLOC_LIBRARY = Path("cmeel.prefix", "lib", "libmimalloc.so")
#: The environment variable that chooses the command's malloc: ``mimalloc`` (the default,
#: where installed) or ``glibc``.
CHOICE_VARIABLE = "ICEG_MALLOC"
#: The values :data:`CHOICE_VARIABLE` takes.
CHOICES = ("mimalloc", "glibc")
#: mimalloc's option that asks the kernel for transparent huge pages.
LARGE_PAGES_VARIABLE = "MIMALLOC_ALLOW_LARGE_OS_PAGES"


def find_mimalloc(folders: Iterable[str] | None = None) -> Path | None:
    """The mimalloc shared library of the installed ``cmeel-mimalloc`` package, or None.

    Args:
        folders: Where to look for :data:`MIMALLOC_LIBRARY` (default: ``sys.path``, whose
            site-packages folders hold the packages).

    Returns:
        The absolute path of the library, or None where no folder holds it (another
        platform than Linux, or the package not installed).
    """
    if sys.platform != "linux":
        return None
    for folder in sys.path if folders is None else folders:
        path = Path(folder or ".", MIMALLOC_LIBRARY)
        if path.is_file():
            return path.resolve()
    return None


def chosen_malloc(environ: Mapping[str, str]) -> str:
    """The malloc :data:`CHOICE_VARIABLE` asks for: one of :data:`CHOICES` (unset or empty:
    the first).

    Raises:
        ConfigError: The variable holds another value.
    """
    said = environ.get(CHOICE_VARIABLE, "")
    choice = said.strip().lower() or CHOICES[0]
    if choice not in CHOICES:
        raise ConfigError(
            f"{CHOICE_VARIABLE}={said!r}: set it to one of {', '.join(CHOICES)}, or unset it "
            "(mimalloc where installed)"
        )
    return choice


def malloc_environment(
    environ: Mapping[str, str],
    choice: str,
    mimalloc: Path | None,
    glibc: tuple[int, int] | None,
    thp: str | None,
) -> dict[str, str] | None:
    """The environment to start the command in for a faster malloc, or None where starting
    again would change nothing.

    Args:
        environ: The current environment (not modified).
        choice: :func:`chosen_malloc`.
        mimalloc: :func:`find_mimalloc`.
        glibc: :func:`~iceg.huge_pages.glibc_version`.
        thp: :func:`~iceg.huge_pages.thp_mode`.

    Returns:
        A copy of ``environ`` with ``LD_PRELOAD`` set to ``mimalloc`` (and
        :data:`LARGE_PAGES_VARIABLE` set to 1 where ``thp`` is ``madvise`` and the variable
        is unset) where ``choice`` is ``mimalloc``, it is installed (at a path without spaces
        or colons, which ``LD_PRELOAD`` cannot name) and ``LD_PRELOAD`` names no library;
        None where ``LD_PRELOAD`` names ``mimalloc`` already (the mark of a process this
        module started); otherwise :func:`~iceg.huge_pages.huge_page_environment` (glibc's
        malloc on huge pages).
    """
    preloaded = environ.get("LD_PRELOAD", "").replace(":", " ").split()
    if mimalloc is not None and str(mimalloc) in preloaded:
        return None
    # the dynamic loader splits LD_PRELOAD at spaces and colons: such a path cannot be named
    unnamable = mimalloc is None or any(c in str(mimalloc) for c in " :")
    if choice != "mimalloc" or unnamable or preloaded:
        return huge_page_environment(environ, glibc, thp)
    env = dict(environ)
    env["LD_PRELOAD"] = str(mimalloc)
    if thp == "madvise":
        env.setdefault(LARGE_PAGES_VARIABLE, "1")
    return env


def exec_with_fast_malloc() -> None:
    """Replace this process by the same command (``sys.orig_argv``) started with the malloc
    of :func:`malloc_environment`; return where that would change nothing or cannot be done
    (then the command runs on as it is). Call it first thing in a command's entry point,
    before anything has been read or written: the process image is replaced.

    A wrong :data:`CHOICE_VARIABLE` leaves the process as it is, for the command line to
    report (:func:`chosen_malloc`).
    """
    if sys.platform != "linux":
        return
    try:
        choice = chosen_malloc(os.environ)
    except IcegError:
        return
    env = malloc_environment(os.environ, choice, find_mimalloc(), glibc_version(), thp_mode())
    argv = list(getattr(sys, "orig_argv", []))
    if env is None or not sys.executable or not argv:
        return
    sys.stdout.flush()
    sys.stderr.flush()
    try:
        os.execve(sys.executable, argv, env)
    except OSError as exc:  # the command runs on with the malloc it has
        log.debug("malloc unchanged: cannot start %s again (%s)", argv[0], exc)
