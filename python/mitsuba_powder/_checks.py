"""Argument checks shared by the package: one range check (:func:`check_range`; of every value
of an array: :func:`check_each`) and one wording for a value out of its valid range
(:func:`out_of_range`)."""

from __future__ import annotations

import math

__all__ = ["check_each", "check_range", "interval_text", "out_of_range"]


def interval_text(lower: float, upper: float, closed: str = "[)") -> str:
    """An interval as the messages write it, e.g. ``[1, inf)``; ``closed`` gives its two
    brackets (``"[)"``, ``"[]"``, ``"()"`` or ``"(]"``)."""
    return f"{closed[0]}{lower:g}, {upper:g}{closed[1]}"


def out_of_range(subject: str, valid: str, note: str = "") -> str:
    """The message of a value out of its valid range: ``"<subject> is out of range; valid
    range is <valid> [note]"``, e.g. ``out_of_range("theta_o = 95 degrees", "[0, 90)")``.

    Args:
        subject: what the value is and the value, e.g. ``"spp = 0"`` or ``"file.csv, line 3
            (reflectance factor): -1"``.
        valid: the valid range, e.g. :func:`interval_text`'s.
        note: written after it, e.g. its unit or why the range is what it is.
    """
    return f"{subject} is out of range; valid range is {valid}" + (f" {note}" if note else "")


def _shown(value) -> str:
    """A value as a message shows it: text quoted, numbers as they print."""
    return repr(value) if isinstance(value, str) else f"{value}"


def check_range(name: str, value, lower: float, upper: float = math.inf, closed: str = "[)",
                *, unit: str = "", note: str = "") -> float:
    """``value`` as a float, if it is a number in the interval (NaN never is); else raise
    ``ValueError("<name> = <value> [unit] is out of range; valid range is <interval> [note]")``
    (or ``"<name> = <value> is not a number"``).

    Args:
        name: what the caller calls the value (an argument, or an option with its flag).
        value: the number (or text of one), shown as given.
        lower, upper: the interval's ends.
        closed: its brackets, ``"[)"`` by default (see :func:`interval_text`); a closed
            ``upper = inf`` admits inf.
        unit: written after the value, e.g. ``"px"``.
        note: written after the interval, e.g. its unit or why the range is what it is.
    """
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} = {_shown(value)} is not a number") from None
    lower_ok = v >= lower if closed[0] == "[" else v > lower
    upper_ok = v <= upper if closed[1] == "]" else v < upper
    if not (lower_ok and upper_ok):
        shown = f"{_shown(value)} {unit}" if unit else _shown(value)
        raise ValueError(out_of_range(f"{name} = {shown}", interval_text(lower, upper, closed),
                                      note))
    return v


def check_each(name: str, values, lower: float, upper: float = math.inf, closed: str = "[)",
               where=None) -> None:
    """:func:`check_range` of every value of ``values`` (e.g. a spectrum); the first out of
    range (NaN never is in range) is named ``<name><where[k]>``, e.g. ``"sigma at 500 nm"``.

    Args:
        where: per value, the text that says which one it is (default ``"[k]"``).
    """
    for k, value in enumerate(values):
        check_range(f"{name}{where[k] if where is not None else f'[{k}]'}", float(value), lower,
                    upper, closed)
