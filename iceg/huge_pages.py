"""glibc's malloc on transparent huge pages for a command's whole process (issue 13).

On this project's 2-core virtual benchmark machine a run's heap lies far beyond what the TLB
covers with 4 KiB pages, and every TLB miss of a virtual machine walks two page tables (the
guest's and the host's). The kernel backs memory with 2 MiB pages where a program asks for them
(``madvise(MADV_HUGEPAGE)``, Linux's default ``madvise`` mode of
``/sys/kernel/mm/transparent_hugepage/enabled``), and glibc's malloc asks for them for its
heap when its tunable ``glibc.malloc.hugetlb=1`` is set (glibc 2.35 and later). That heap
holds numpy's arrays, numba's and gtsam's allocations. With it a MIT CSAIL run with two
workers took about 3 % less time on that machine (faster in 29 of 40 alternated pairs; one
process on a core of its own showed no difference), with the same results bit for bit
(docs/design.md, "malloc on huge pages" under "Speed").

A tunable is read once, when the process starts, so the ``iceg`` command
(:mod:`iceg.__main__`) replaces its process by itself with the tunable added to
``GLIBC_TUNABLES`` (:func:`iceg.malloc.exec_with_fast_malloc`) where it keeps glibc's malloc
(mimalloc is not installed, or ``ICEG_MALLOC=glibc``), before it imports anything heavy. A
library user gets the same by starting Python (or Jupyter) with
``GLIBC_TUNABLES=glibc.malloc.hugetlb=1``; ``glibc.malloc.hugetlb=0`` in the variable keeps a
command on the default pages.

This module uses the standard library only.
"""

from __future__ import annotations

import os
import re
from collections.abc import Mapping
from pathlib import Path

#: glibc's malloc tunable that makes its heap ask for transparent huge pages.
TUNABLE = "glibc.malloc.hugetlb"
#: The first glibc release that knows :data:`TUNABLE`.
MIN_GLIBC = (2, 35)
#: The kernel's transparent huge page mode; the one in brackets is in force.
THP_ENABLED = Path("/sys/kernel/mm/transparent_hugepage/enabled")


def glibc_version() -> tuple[int, int] | None:
    """``(major, minor)`` of the C library this process runs on, or None where it is not
    glibc (musl, macOS, Windows) or does not say."""
    try:
        said = os.confstr("CS_GNU_LIBC_VERSION")
    except (AttributeError, ValueError, OSError):
        return None
    name, _, version = (said or "").partition(" ")
    numbers = version.split(".")
    if name != "glibc" or len(numbers) < 2 or not all(n.isdigit() for n in numbers[:2]):
        return None
    return int(numbers[0]), int(numbers[1])


def thp_mode(path: Path = THP_ENABLED) -> str | None:
    """The kernel's transparent huge page mode (``always``, ``madvise`` or ``never``): the
    bracketed word of ``path``; None where it cannot be read (not Linux, no such file)."""
    try:
        text = path.read_text()
    except OSError:
        return None
    found = re.search(r"\[(\w+)\]", text)
    return found.group(1) if found else None


def sets_tunable(environ: Mapping[str, str]) -> bool:
    """Whether ``GLIBC_TUNABLES`` in ``environ`` (``:``-separated ``name=value`` items) sets
    :data:`TUNABLE`, to any value."""
    tunables = environ.get("GLIBC_TUNABLES", "")
    return any(item.partition("=")[0] == TUNABLE for item in tunables.split(":"))


def huge_page_environment(
    environ: Mapping[str, str], glibc: tuple[int, int] | None, thp: str | None
) -> dict[str, str] | None:
    """The environment that starts a process with malloc on huge pages, or None where
    starting again would change nothing.

    Args:
        environ: The current environment (not modified).
        glibc: :func:`glibc_version`.
        thp: :func:`thp_mode`.

    Returns:
        A copy of ``environ`` with ``glibc.malloc.hugetlb=1`` appended to ``GLIBC_TUNABLES``
        (``:``-separated, the other tunables kept); None where the C library is not glibc
        2.35 or later, where the kernel's mode is not ``madvise`` (``always`` backs the heap
        with huge pages already, ``never`` refuses them), or where ``GLIBC_TUNABLES`` sets
        :data:`TUNABLE` already, to any value (a user's choice, and the mark of a process
        started by :func:`iceg.malloc.exec_with_fast_malloc`).
    """
    if glibc is None or glibc < MIN_GLIBC or thp != "madvise" or sets_tunable(environ):
        return None
    tunables = environ.get("GLIBC_TUNABLES", "")
    env = dict(environ)
    env["GLIBC_TUNABLES"] = f"{tunables}:{TUNABLE}=1" if tunables else f"{TUNABLE}=1"
    return env
