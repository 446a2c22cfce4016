"""Reading small text files with one-line errors (a binary or unreadable file is an error of the
caller's concern, naming the file)."""

from __future__ import annotations

from pathlib import Path

from iceg_common.errors import IcegError


def read_text_lines(path: Path, what: str, error: type[IcegError]) -> list[str]:
    """The lines of a UTF-8 text file (a byte order mark at its start, which an editor on
    Windows may add, dropped).

    Args:
        path: The file.
        what: What the file should be, for messages (e.g. ``"TUM trajectory"``).
        error: The :class:`IcegError` subclass to raise.

    Raises:
        error: the file is not UTF-8 text (naming the first bad byte) or cannot be read.
    """
    try:
        return path.read_text(encoding="utf-8-sig").splitlines()
    except UnicodeDecodeError as exc:
        raise error(
            f"{path}: not a text {what} (byte {exc.start} is not UTF-8; a binary file?)"
        ) from None
    except OSError as exc:
        raise error(f"{path}: cannot read the {what} ({exc})") from exc
