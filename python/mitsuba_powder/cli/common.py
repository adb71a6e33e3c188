"""Helpers the commands share: ``--set``/``-D`` values, ``--free`` lists, measurement loading."""

from __future__ import annotations

import argparse


def _value(text: str):
    """A --set value: a number if it parses as one, else the string."""
    try:
        return float(text)
    except ValueError:
        return text


def _parse_define(text: str) -> tuple[str, str]:
    if "=" not in text:
        raise SystemExit(f"mitsuba-powder: -D expects NAME=VALUE, got {text!r}")
    name, value = text.split("=", 1)
    return name, value


def _fixed_properties(items: list[str]) -> dict:
    """--set NAME=VALUE items as a property dict."""
    fixed = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--set {item!r}: expected NAME=VALUE")
        fixed[name] = _value(value)
    return fixed


def _names(text: str | None, option: str = "--free") -> list[str] | None:
    """A comma-separated --free list (None when not given).

    Raises:
        ValueError: a list given but naming nothing (``--free ""``), which would otherwise
            fall back to the defaults without a word.
    """
    if text is None:
        return None
    names = [n.strip() for n in text.split(",") if n.strip()]
    if not names:
        raise ValueError(f"{option} {text!r} names no property; give a comma-separated list "
                         f"(e.g. {option} albedo,g), or leave {option} out for the defaults")
    return names


def _load_data(path: str, args: argparse.Namespace):
    """Load measurements (CSV, IPAG file or folder) and print what the loader did."""
    from ..io.measurements import load_measurements

    data = load_measurements(path, convention=args.convention, zero_error=args.zero_error)
    for line in data.comments:
        if line.startswith("loader: "):
            print(line[len("loader: "):])
    if data.convention == "project":
        g = data.geometry_summary()
        print(f"{path}: {g['rows']} measurements, {g['geometries']} unique geometries "
              f"(incidence, viewing direction, wavelength), {g['replicated_rows']} replicated")
    return data
