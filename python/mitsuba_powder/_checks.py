"""Argument checks shared by the package: one wording for a value out of its valid range."""

from __future__ import annotations

import math


def interval_text(lower: float, upper: float, closed: str = "[)") -> str:
    """An interval as the messages write it, e.g. ``[1, inf)``; ``closed`` gives its two
    brackets (``"[)"``, ``"[]"``, ``"()"`` or ``"(]"``)."""
    return f"{closed[0]}{lower:g}, {upper:g}{closed[1]}"


def check_range(name: str, value, lower: float, upper: float = math.inf, closed: str = "[)",
                *, unit: str = "", note: str = "") -> None:
    """Raise ``ValueError("<name> = <value> [unit] is out of range; valid range is
    <interval> [note]")`` unless ``value`` lies in the interval (NaN never does).

    Args:
        name: what the caller calls the value (an argument, or an option with its flag).
        value: the number, shown as given.
        lower, upper: the interval's ends.
        closed: its brackets, ``"[)"`` by default (see :func:`interval_text`).
        unit: written after the value, e.g. ``"px"``.
        note: written after the interval, e.g. its unit or why the range is what it is.
    """
    lower_ok = value >= lower if closed[0] == "[" else value > lower
    upper_ok = value <= upper if closed[1] == "]" else value < upper
    if not (lower_ok and upper_ok):
        shown = f"{value} {unit}" if unit else f"{value}"
        raise ValueError(f"{name} = {shown} is out of range; valid range is "
                         f"{interval_text(lower, upper, closed)}" + (f" {note}" if note else ""))
