"""The text layer of IPAG files (:mod:`mitsuba_powder.io.ipag` describes the layouts): lines,
fields, numbers with a message naming file, line and column, geometry tags in names, and which
kind of file a path is."""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

from ..outputs import note_input
from .dataset import MeasurementError

CONVENTIONS = ("signed", "physical")
ZERO_ERROR = ("raise", "unweighted", "skip")
LAYOUTS = ("multi", "single")
NEWLINES = ("\r\n", "\n", "\r")

_NUM = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)"
_GEOMETRY = rf"_i(?P<i>{_NUM})e(?P<e>{_NUM})a(?P<a>{_NUM})"
_SINGLE_NAME = re.compile(rf"^(?P<sample>.*){_GEOMETRY}(?P<suffix>(?:_[A-Za-z0-9]+)*)\.txt$",
                          re.IGNORECASE)
_COLUMN = re.compile(rf"^(?P<kind>Refl|Err)_(?P<sample>.*){_GEOMETRY}$", re.IGNORECASE)
_SAMPLE_OK = re.compile(r"^[A-Za-z0-9][A-Za-z0-9.+-]*(?:_[A-Za-z0-9.+-]+)*$")


def read_lines(path: Path) -> list[str]:
    """The lines of a text file, split on CRLF, LF or CR (UTF-8, else Latin-1)."""
    note_input(path)
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    lines = re.split(r"\r\n|\r|\n", text)
    if lines and lines[-1] == "":
        lines.pop()
    return lines


def _fields(line: str) -> list[str]:
    """Tab-separated fields (whitespace-separated if the line has no tab), trailing empty
    fields (a trailing tab) removed."""
    parts = line.split("\t") if "\t" in line else line.split()
    parts = [p.strip() for p in parts]
    while parts and parts[-1] == "":
        parts.pop()
    return parts


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _number(text: str, where: str, what: str, allow_nan: bool = True) -> float:
    """``text`` as a float; NaN allowed (returned) if ``allow_nan``; else a clear error."""
    try:
        value = float(text)
    except ValueError:
        raise MeasurementError(f"{where} ({what}): '{text}' is not a number") from None
    if np.isnan(value) and allow_nan:
        return value
    if not np.isfinite(value):
        raise MeasurementError(f"{where} ({what}): '{text}' is not a finite number")
    return value


def _agrees(name_text: str, value: float) -> bool:
    """Whether an angle written in a name (e.g. '17.5' or '18') agrees with ``value`` to the
    digits the name shows."""
    decimals = len(name_text.split(".")[1]) if "." in name_text else 0
    return abs(float(name_text) - value) <= 0.5 * 10.0 ** (-decimals) + 1e-9


def _tag_number(value: float) -> str:
    """An angle for a column or file name: fixed point, at most 6 decimals, no exponent."""
    text = f"{float(value):.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def geometry_tag(incidence: float, emergence: float, azimuth: float) -> str:
    """``i<inc>e<em>a<az>`` as IPAG writes it in column and file names."""
    return f"i{_tag_number(incidence)}e{_tag_number(emergence)}a{_tag_number(azimuth)}"


def file_kind(path: Path) -> str:
    """``"csv"``, ``"ipag-multi"``, ``"ipag-single"`` or ``"ipag-folder"``.

    Raises:
        MeasurementError: a file that is none of these.
    """
    path = Path(path)
    if path.is_dir():
        return "ipag-folder"
    if path.suffix.lower() == ".csv":
        return "csv"
    lines = [ln for ln in read_lines(path) if ln.strip()]
    for line in lines[:20]:
        f = _fields(line)
        if f and f[0].lower() == "incidence":
            return "ipag-multi"
    first = next((ln for ln in lines if not ln.lstrip().startswith("#")), "")
    if "theta_i" in first and "," in first:
        return "csv"
    if _SINGLE_NAME.match(path.name):
        return "ipag-single"
    raise MeasurementError(
        f"{path}: not a measurement file this package reads: expected a CSV file (header "
        "theta_i,theta_o,phi,wavelength,brf[,sigma]), an IPAG multi-geometry file (an "
        "'Incidence' row among its first lines) or an IPAG single-geometry file named "
        "<sample>_i<inc>e<em>a<az>_c.txt")
