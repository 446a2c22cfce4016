"""glibc's malloc on transparent huge pages for the ``iceg`` command (:mod:`iceg.huge_pages`),
where it keeps glibc's malloc (``ICEG_MALLOC=glibc``, :mod:`iceg.malloc`)."""

from __future__ import annotations

import os
import platform
import subprocess
import sys
from pathlib import Path

import pytest

from iceg import __version__
from iceg.huge_pages import (
    TUNABLE,
    glibc_version,
    huge_page_environment,
    thp_mode,
)

GLIBC = (2, 36)


def test_the_tunable_is_added_to_an_environment_without_it() -> None:
    environ = {"HOME": "/home/u", "PATH": "/bin"}
    env = huge_page_environment(environ, GLIBC, "madvise")
    assert env == {"HOME": "/home/u", "PATH": "/bin", "GLIBC_TUNABLES": "glibc.malloc.hugetlb=1"}
    assert environ == {"HOME": "/home/u", "PATH": "/bin"}  # the caller's is not modified


def test_the_other_tunables_are_kept() -> None:
    environ = {"GLIBC_TUNABLES": "glibc.malloc.arena_max=2:glibc.malloc.hugetlb_x=1"}
    env = huge_page_environment(environ, GLIBC, "madvise")
    assert env is not None
    assert env["GLIBC_TUNABLES"] == (
        "glibc.malloc.arena_max=2:glibc.malloc.hugetlb_x=1:glibc.malloc.hugetlb=1"
    )


@pytest.mark.parametrize(
    "tunables",
    [
        "glibc.malloc.hugetlb=0",
        "glibc.malloc.hugetlb=1",
        "glibc.malloc.arena_max=2:glibc.malloc.hugetlb=2",
    ],
)
def test_a_tunable_set_already_is_the_user_s_choice(tunables: str) -> None:
    assert huge_page_environment({"GLIBC_TUNABLES": tunables}, GLIBC, "madvise") is None


@pytest.mark.parametrize(
    ("glibc", "thp", "starts_again"),
    [
        ((2, 35), "madvise", True),
        ((3, 0), "madvise", True),
        ((2, 34), "madvise", False),  # the tunable is unknown before 2.35
        (None, "madvise", False),  # musl, macOS: no glibc
        (GLIBC, "always", False),  # the kernel backs the heap with huge pages already
        (GLIBC, "never", False),
        (GLIBC, None, False),  # no transparent huge pages (not Linux)
    ],
)
def test_a_process_starts_again_only_where_it_gains_huge_pages(
    glibc: tuple[int, int] | None, thp: str | None, starts_again: bool
) -> None:
    assert (huge_page_environment({}, glibc, thp) is not None) is starts_again


@pytest.mark.parametrize(
    ("text", "mode"),
    [
        ("always [madvise] never\n", "madvise"),
        ("[always] madvise never\n", "always"),
        ("always madvise [never]\n", "never"),
        ("always madvise never\n", None),
    ],
)
def test_the_kernel_s_mode_is_the_bracketed_word(
    tmp_path: Path, text: str, mode: str | None
) -> None:
    path = tmp_path / "enabled"
    path.write_text(text)
    assert thp_mode(path) == mode
    assert thp_mode(tmp_path / "missing") is None


def test_the_glibc_version_is_the_platform_s() -> None:
    name, version = platform.libc_ver()
    if name != "glibc":
        assert glibc_version() is None
        return
    major, minor = (int(v) for v in version.split(".")[:2])
    assert glibc_version() == (major, minor)


def _without_tunables() -> dict[str, str]:
    """This environment on glibc's malloc (``ICEG_MALLOC=glibc``), without tunables."""
    env = dict(os.environ, ICEG_MALLOC="glibc")
    env.pop("GLIBC_TUNABLES", None)
    env.pop("LD_PRELOAD", None)
    return env


@pytest.mark.skipif(
    sys.platform != "linux" or huge_page_environment({}, glibc_version(), thp_mode()) is None,
    reason="this machine offers no transparent huge pages to glibc's malloc "
    "(needs Linux, glibc >= 2.35 and the kernel's 'madvise' mode)",
)
def test_a_command_starts_once_more_with_the_tunable() -> None:
    code = (
        "import os; print('start', flush=True)\n"
        "from iceg.malloc import exec_with_fast_malloc; exec_with_fast_malloc()\n"
        "print(os.environ['GLIBC_TUNABLES'])\n"
        "print(b'glibc.malloc.hugetlb=1' in open('/proc/self/environ', 'rb').read())\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        env=_without_tunables(),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    # printed once by the first process and once by the one it became, which did not start
    # again: the tunable it carries is the mark
    assert done.stdout.splitlines() == ["start", "start", f"{TUNABLE}=1", "True"]


def test_a_chosen_tunable_is_never_replaced() -> None:
    env = dict(_without_tunables(), GLIBC_TUNABLES=f"{TUNABLE}=0")
    code = (
        "import os; print('start', flush=True)\n"
        "from iceg.malloc import exec_with_fast_malloc; exec_with_fast_malloc()\n"
        "print(os.environ['GLIBC_TUNABLES'])\n"
    )
    done = subprocess.run(
        [sys.executable, "-c", code], env=env, capture_output=True, text=True, check=True
    )
    assert done.stdout.splitlines() == ["start", f"{TUNABLE}=0"]


def test_python_m_iceg_is_the_command_line() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "iceg", "--version"],
        env=_without_tunables(),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    assert done.stdout.strip() == f"iceg {__version__}"
