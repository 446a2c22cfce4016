"""glibc's malloc on transparent huge pages for the ``iceg`` command (:mod:`iceg.huge_pages`),
where it keeps glibc's malloc (``ICEG_MALLOC=glibc``, :mod:`iceg.malloc`)."""

from __future__ import annotations

import platform
from pathlib import Path

import pytest

from iceg.huge_pages import (
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
