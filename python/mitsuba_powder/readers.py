"""Reading the files a command is given, with errors that name the file: text (UTF-8), JSON
and images (through Mitsuba's ``Bitmap``). Every reader of the package that opens a user's file
goes through these, so that a binary file, a broken JSON file or a corrupt image is reported as
``<file>: <what is wrong>``, never as a bare decoder message."""

from __future__ import annotations

import json
from pathlib import Path

__all__ = ["FileFormatError", "read_bitmap", "read_json", "read_text"]


class FileFormatError(ValueError):
    """A file that cannot be read as what it should be; the message names the file."""


def read_text(path: str | Path, what: str = "file") -> str:
    """The text of a UTF-8 file (a byte-order mark is dropped).

    Raises:
        FileFormatError: the file is not UTF-8 text (e.g. binary), naming the file and the
            first bad byte.
    """
    p = Path(path)
    raw = p.read_bytes()
    try:
        return raw.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        raise FileFormatError(f"{what} {p}: not a UTF-8 text file (byte 0x{raw[exc.start]:02x} "
                              f"at offset {exc.start}); is it the right file?") from None


def read_json(path: str | Path, what: str = "file"):
    """The value of a JSON file.

    Raises:
        FileFormatError: not UTF-8 text, or not valid JSON (line and column named).
    """
    p = Path(path)
    try:
        return json.loads(read_text(p, what))
    except json.JSONDecodeError as exc:
        raise FileFormatError(f"{what} {p}: not valid JSON (line {exc.lineno}, column "
                              f"{exc.colno}: {exc.msg})") from None


def read_bitmap(path: str | Path, what: str = "image"):
    """``mi.Bitmap`` of an image file (any Mitsuba variant must be selected).

    Raises:
        FileFormatError: Mitsuba cannot read it (unknown format, truncated file), naming the
            file and Mitsuba's reason.
    """
    import mitsuba as mi

    p = Path(path)
    try:
        return mi.Bitmap(str(p))
    except RuntimeError as exc:
        reason = str(exc).split("]", 1)[-1].strip() or "unreadable"
        raise FileFormatError(f"{what} {p}: cannot be read as an image ({reason}); is the "
                              "file whole?") from None
