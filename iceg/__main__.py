"""The ``iceg`` command (also ``python -m iceg``): the command line (:mod:`iceg.cli`), started
with mimalloc, or glibc's malloc on transparent huge pages, where the machine offers them
(:func:`iceg.malloc.exec_with_fast_malloc`)."""

from __future__ import annotations

from iceg.malloc import exec_with_fast_malloc


def main() -> None:
    """Run the command line in a process with the faster malloc."""
    exec_with_fast_malloc()
    from iceg.cli import app

    app(prog_name="iceg")


if __name__ == "__main__":
    main()
