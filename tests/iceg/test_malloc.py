"""The ``iceg`` command's malloc: mimalloc where installed (:mod:`iceg.malloc`)."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest
from typer.testing import CliRunner

from iceg import __version__
from iceg.cli import app
from iceg.huge_pages import TUNABLE, glibc_version, huge_page_environment, thp_mode
from iceg.malloc import (
    CHOICE_VARIABLE,
    LARGE_PAGES_VARIABLE,
    MIMALLOC_LIBRARY,
    chosen_malloc,
    find_mimalloc,
    malloc_environment,
)
from iceg_common.errors import ConfigError

GLIBC = (2, 36)
LIB = Path("/site/cmeel.prefix/lib/libmimalloc.so")
ON_MIMALLOC_WHEELS = sys.platform == "linux" and os.uname().machine in ("x86_64", "aarch64")


def test_mimalloc_is_preloaded_with_huge_pages_where_the_kernel_gives_them_on_request() -> None:
    environ = {"HOME": "/home/u"}
    env = malloc_environment(environ, "mimalloc", LIB, GLIBC, "madvise")
    assert env == {"HOME": "/home/u", "LD_PRELOAD": str(LIB), LARGE_PAGES_VARIABLE: "1"}
    assert environ == {"HOME": "/home/u"}  # the caller's is not modified
    # the kernel backs memory with huge pages already, or never: mimalloc's option unset
    for thp in ("always", "never", None):
        assert malloc_environment({}, "mimalloc", LIB, GLIBC, thp) == {"LD_PRELOAD": str(LIB)}


def test_a_user_s_mimalloc_option_is_kept() -> None:
    env = malloc_environment({LARGE_PAGES_VARIABLE: "0"}, "mimalloc", LIB, GLIBC, "madvise")
    assert env == {"LD_PRELOAD": str(LIB), LARGE_PAGES_VARIABLE: "0"}


def test_a_process_started_on_mimalloc_starts_no_more() -> None:
    for preload in (str(LIB), f"/lib/libfaketime.so:{LIB}", f"{LIB} /lib/x.so"):
        assert (
            malloc_environment({"LD_PRELOAD": preload}, "mimalloc", LIB, GLIBC, "madvise") is None
        )


@pytest.mark.parametrize(
    ("environ", "choice", "mimalloc"),
    [
        ({}, "glibc", LIB),  # ICEG_MALLOC=glibc
        ({}, "mimalloc", None),  # not installed
        ({"LD_PRELOAD": "/usr/lib/libjemalloc.so.2"}, "mimalloc", LIB),  # the user's allocator
        # LD_PRELOAD is split at spaces and colons: no name for these (nor a mark, so no end)
        ({}, "mimalloc", Path("/home/A User/site/cmeel.prefix/lib/libmimalloc.so")),
        ({}, "mimalloc", Path("/opt/a:b/cmeel.prefix/lib/libmimalloc.so")),
    ],
)
def test_without_mimalloc_glibc_s_malloc_gets_huge_pages(
    environ: dict[str, str], choice: str, mimalloc: Path | None
) -> None:
    env = malloc_environment(environ, choice, mimalloc, GLIBC, "madvise")
    assert env == dict(environ, GLIBC_TUNABLES=f"{TUNABLE}=1")
    # and nothing at all where glibc offers no huge pages
    assert malloc_environment(environ, choice, mimalloc, (2, 34), "madvise") is None


def test_the_choice_is_mimalloc_unless_glibc_is_asked_for() -> None:
    assert chosen_malloc({}) == "mimalloc"
    assert chosen_malloc({CHOICE_VARIABLE: ""}) == "mimalloc"
    assert chosen_malloc({CHOICE_VARIABLE: " GLIBC "}) == "glibc"
    with pytest.raises(
        ConfigError, match="ICEG_MALLOC='tcmalloc': set it to one of mimalloc, glibc"
    ):
        chosen_malloc({CHOICE_VARIABLE: "tcmalloc"})


def test_a_wrong_choice_is_one_line_from_the_command_line(tmp_path: Path) -> None:
    done = CliRunner().invoke(app, ["info", str(tmp_path / "x.clf")], env={CHOICE_VARIABLE: "tc"})
    assert done.exit_code == 1
    assert done.output.strip().splitlines() == [
        "iceg: error: ICEG_MALLOC='tc': set it to one of mimalloc, glibc, or unset it "
        "(mimalloc where installed)"
    ]


def test_the_library_is_found_below_a_folder_of_the_path(tmp_path: Path) -> None:
    library = tmp_path / "site" / MIMALLOC_LIBRARY
    assert find_mimalloc([str(tmp_path / "site")]) in (None, library)  # None off Linux
    library.parent.mkdir(parents=True)
    library.write_bytes(b"")
    found = find_mimalloc([str(tmp_path / "elsewhere"), str(tmp_path / "site")])
    assert found == (library.resolve() if sys.platform == "linux" else None)


@pytest.mark.skipif(
    not ON_MIMALLOC_WHEELS, reason="cmeel-mimalloc is a dependency on x86-64 and arm64 Linux only"
)
def test_the_dependency_installs_the_library() -> None:
    found = find_mimalloc()
    assert found is not None and found.name.startswith("libmimalloc.so")


def _fresh_environment(**set_: str) -> dict[str, str]:
    """This environment without any malloc setting, then ``set_``."""
    env = dict(os.environ)
    for name in (CHOICE_VARIABLE, "LD_PRELOAD", "GLIBC_TUNABLES", LARGE_PAGES_VARIABLE):
        env.pop(name, None)
    return dict(env, **set_)


def _started(env: dict[str, str], then: str) -> list[str]:
    """The lines a fresh process prints: "start", :func:`exec_with_fast_malloc`, then the
    code ``then`` (the process it became prints "start" again)."""
    code = (
        "import os; print('start', flush=True)\n"
        "from iceg.malloc import exec_with_fast_malloc; exec_with_fast_malloc()\n" + then
    )
    done = subprocess.run(
        [sys.executable, "-c", code],
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    return done.stdout.splitlines()


@pytest.mark.skipif(not ON_MIMALLOC_WHEELS, reason="mimalloc is preloaded on Linux only")
def test_a_command_starts_once_more_on_mimalloc() -> None:
    # started again once: the one it became has mimalloc mapped and its path is the mark
    then = "print(any('libmimalloc.so' in line for line in open('/proc/self/maps')))\n"
    assert _started(_fresh_environment(), then) == ["start", "start", "True"]


@pytest.mark.skipif(
    sys.platform != "linux" or huge_page_environment({}, glibc_version(), thp_mode()) is None,
    reason="this machine offers no transparent huge pages to glibc's malloc "
    "(needs Linux, glibc >= 2.35 and the kernel's 'madvise' mode)",
)
def test_on_glibc_a_command_starts_once_more_with_the_huge_page_tunable() -> None:
    then = (
        "print(os.environ['GLIBC_TUNABLES'])\n"
        "print(b'glibc.malloc.hugetlb=1' in open('/proc/self/environ', 'rb').read())\n"
    )
    lines = _started(_fresh_environment(**{CHOICE_VARIABLE: "glibc"}), then)
    assert lines == ["start", "start", f"{TUNABLE}=1", "True"]  # the tunable is the mark


def test_a_chosen_tunable_is_never_replaced() -> None:
    env = _fresh_environment(**{CHOICE_VARIABLE: "glibc", "GLIBC_TUNABLES": f"{TUNABLE}=0"})
    then = "print(os.environ['GLIBC_TUNABLES'])\n"
    assert _started(env, then) == ["start", f"{TUNABLE}=0"]


def test_python_m_iceg_is_the_command_line() -> None:
    done = subprocess.run(
        [sys.executable, "-m", "iceg", "--version"],
        env=_fresh_environment(),
        capture_output=True,
        text=True,
        timeout=120,
        check=True,
    )
    assert done.stdout.strip() == f"iceg {__version__}"


def test_a_run_is_the_same_bits_with_every_malloc(tmp_path: Path) -> None:
    # The same log and config in fresh processes with mimalloc (where installed), glibc's
    # malloc on huge pages and on its default pages: other memory layouts, the same
    # trajectory bit for bit (two workers: the forked helpers inherit the malloc).
    from frontends.carmen import write_carmen
    from frontends.simulate import office_world, simulate

    log = tmp_path / "office.clf"
    write_carmen(log, simulate(office_world(), seed=3).scans[:250])
    code = (
        "import hashlib, sys\n"
        "from iceg.config import IcegConfig\n"
        "from iceg.pipeline import run_log\n"
        "config = IcegConfig.model_validate({'slam': {'workers': 2}})\n"
        "result = run_log(sys.argv[1], config)\n"
        "mimalloc = any('libmimalloc.so' in line for line in open('/proc/self/maps'))\n"
        "print(len(result.poses), hashlib.sha256(result.poses.tobytes()).hexdigest(), mimalloc)\n"
    )
    mimalloc = find_mimalloc()
    environments = [
        dict(_fresh_environment(), GLIBC_TUNABLES=f"{TUNABLE}={value}") for value in (1, 0)
    ]
    if mimalloc is not None:
        environments.append(dict(_fresh_environment(), LD_PRELOAD=str(mimalloc)))
    outputs = [
        subprocess.run(
            [sys.executable, "-c", code, str(log)],
            env=env,
            capture_output=True,
            text=True,
            timeout=300,
            check=True,
        ).stdout.split()
        for env in environments
    ]
    assert outputs[0][0] == "250"
    assert [o[:2] for o in outputs] == [outputs[0][:2]] * len(outputs)
    assert [o[2] for o in outputs] == ["False", "False", "True"][: len(outputs)]
