"""The ``iceg`` command (also ``python -m iceg``): the command line (:mod:`iceg.cli`), started
with malloc on transparent huge pages where the machine offers them
(:func:`iceg.huge_pages.exec_with_huge_pages`)."""

from __future__ import annotations

from iceg.huge_pages import exec_with_huge_pages


def main() -> None:
    """Run the command line in a process whose malloc asks for huge pages."""
    exec_with_huge_pages()
    from iceg.cli import app

    app(prog_name="iceg")


if __name__ == "__main__":
    main()
