"""Goniometric BRDF measurements: the CSV format, a strict loader, a writer, and the dispatch
that also reads the IPAG goniometers' text files (:mod:`mitsuba_powder.io.ipag`).

:func:`load_measurements` recognises what it is given:

- a CSV file in the project's format (below; any file ending in ``.csv``, or a text file whose
  first non-comment line is the CSV header);
- an IPAG multi-geometry file (``*_geo*.txt``: rows ``Incidence``, ``Emergence``, ``Azimuth``);
- an IPAG single-geometry file (three columns, geometry in the name ``..._i20e30a0_c.txt``);
- a folder of IPAG single-geometry files (one data set, one sample).

The IPAG layouts and their angle conventions are described in :mod:`mitsuba_powder.io.ipag` and
docs/fitting.md ("Files from IPAG goniometers and SSHADE").

CSV format (UTF-8; lines starting with ``#`` are comments, kept as provenance; CRLF, LF or CR
line endings)::

    # source: ...
    theta_i,theta_o,phi,wavelength,brf,sigma
    20,-35,0,700,0.95,0.02

Columns (any order; ``sigma`` optional):

- ``theta_i``: incidence angle from the normal, degrees, in [0, 90).
- ``theta_o``: *signed* viewing angle, degrees, in (-90, 90).
- ``phi``: viewing azimuth relative to the plane of incidence, degrees, in [-360, 360].
  The light sits at azimuth 0: ``wi = (sin ti, 0, cos ti)``,
  ``wo = (sin to cos phi, sin to sin phi, cos to)``. So ``phi = 0, theta_o = theta_i`` is
  back-scattering and ``phi = 0, theta_o = -theta_i`` the mirror direction (docs/model.md).
- ``wavelength``: nm, > 0.
- ``brf``: reflectance factor, ``pi * BRDF`` (1 for a white Lambertian), >= 0.
- ``sigma``: 1-sigma uncertainty of ``brf``, > 0.

Replicates. Rows with the same incidence, viewing direction and wavelength are separate
observations (replicated measurements), each counted in a fit's loss and in N. Directions are
compared as unit vectors, so ``(theta_o, phi)`` and ``(-theta_o, phi + 180)`` and ``theta_o = 0``
in any azimuth plane are the same geometry. :meth:`Measurements.geometry_summary` counts rows,
unique geometries and replicated rows. In the CSV every row has the header's columns and units,
so same-geometry rows are always replicates, never contradictory. What is contradictory in the
IPAG layouts (files of different samples in one folder, replicate files whose calibration
metadata disagree) is an error naming both files and lines (see :mod:`mitsuba_powder.io.ipag`).
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from ..outputs import note_input, output_file
from ..readers import read_text
from . import ipag
from .dataset import (
    OPTIONAL,
    RANGES,
    REQUIRED,
    MeasurementError,
    Measurements,
    _check_column_range,
    format_number,
    gonio_directions,
)

__all__ = ["REQUIRED", "OPTIONAL", "RANGES", "MeasurementError", "Measurements",
           "gonio_directions", "format_number", "load_measurements", "save_measurements"]


def load_measurements(path: str | Path, convention: str | None = None,
                      zero_error: str = "raise") -> Measurements:
    """Read and validate measurements: a CSV file, an IPAG file, or a folder of IPAG files.

    Args:
        path: a CSV file (project format, above), an IPAG multi- or single-geometry text file,
            or a folder of IPAG single-geometry files.
        convention: IPAG files only: ``"signed"`` or ``"physical"`` forces the angle
            convention; ``None`` decides it from the file (see :mod:`mitsuba_powder.io.ipag`).
        zero_error: IPAG files only: what to do when some (not all) errors are zero or
            missing: ``"raise"``, ``"unweighted"`` (drop every sigma) or ``"skip"`` (leave
            those values out, counted).

    Returns:
        The measurements; ``comments`` carry the provenance and the loader's notes.

    Raises:
        MeasurementError: a malformed file (the message names the file, line and column), or
            an IPAG file whose angle convention cannot be decided.
        FileNotFoundError: the path does not exist.
    """
    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"measurement file or folder {path} does not exist")
    kind = ipag.file_kind(path)
    if kind == "csv":
        if convention is not None:
            raise MeasurementError(
                f"{path}: convention = {convention!r} applies to IPAG files; a CSV file is in "
                "the project convention (signed theta_o, light at azimuth 0)")
        data = _load_csv(path)
    else:
        data = ipag.load_ipag(path, convention=convention, zero_error=zero_error)
    _check_degrees(data, path)
    return data


#: Largest zenith angle, in radians, of a hemisphere (pi / 2, rounded up): a file whose every
#: angle is at most this many degrees almost surely holds radians
_RADIAN_LIKE = 1.6


def _check_degrees(data: Measurements, path: Path) -> None:
    """Refuse angles that look like radians: every theta_i and theta_o within
    :data:`_RADIAN_LIKE` degrees of the normal (and not all 0)."""
    largest = float(np.max(np.abs(np.concatenate([data.theta_i, data.theta_o]))))
    if 0.0 < largest <= _RADIAN_LIKE:
        raise MeasurementError(
            f"{path}: every angle (theta_i, theta_o) is at most {largest:g} degrees: they look "
            f"like radians; the angles must be in degrees (radians x 57.29578)")


def _load_csv(path: Path) -> Measurements:
    """Read the project's CSV format (see the module docstring)."""
    comments: list[str] = []
    rows: list[tuple[int, list[str]]] = []
    header: list[str] | None = None
    header_line = 0
    note_input(path)
    text = read_text(path, "measurement file")
    for lineno, line in enumerate(text.splitlines(), start=1):
        stripped = line.strip()
        if not stripped:
            continue
        if stripped.startswith("#"):
            comments.append(stripped[1:].strip())
            continue
        fields = next(csv.reader([stripped]))
        if header is None:
            header = [f.strip() for f in fields]
            header_line = lineno
        else:
            rows.append((lineno, [f.strip() for f in fields]))
    if header is None:
        raise MeasurementError(f"{path}: no header line (expected columns {', '.join(REQUIRED)})")
    where0 = f"{path}, line {header_line}"
    unknown = [c for c in header if c not in REQUIRED + OPTIONAL]
    if unknown:
        raise MeasurementError(f"{where0}: unknown column(s) {unknown}; valid columns are "
                               f"{', '.join(REQUIRED + OPTIONAL)}")
    missing = [c for c in REQUIRED if c not in header]
    if missing:
        raise MeasurementError(f"{where0}: missing column(s) {missing}")
    if len(set(header)) != len(header):
        raise MeasurementError(f"{where0}: repeated column names {header}")
    if not rows:
        raise MeasurementError(f"{path}: no data rows")

    columns = {name: np.empty(len(rows)) for name in header}
    for k, (lineno, fields) in enumerate(rows):
        where = f"{path}, line {lineno}"
        if len(fields) != len(header):
            raise MeasurementError(f"{where}: {len(fields)} fields, expected {len(header)} "
                                   f"({', '.join(header)})")
        for name, text in zip(header, fields):
            try:
                value = float(text)
            except ValueError:
                raise MeasurementError(
                    f"{where}, column '{name}': '{text}' is not a number") from None
            if not np.isfinite(value):
                raise MeasurementError(f"{where}, column '{name}': '{text}' is not finite")
            _check_column_range(name, value, where)
            columns[name][k] = value
    return Measurements(columns["theta_i"], columns["theta_o"], columns["phi"],
                        columns["wavelength"], columns["brf"], columns.get("sigma"),
                        comments, str(path), "project")


def save_measurements(path: str | Path, data: Measurements,
                      comments: list[str] | None = None, digits: int | None = 10,
                      newline: str = "\n") -> Path:
    """Write ``data`` in the CSV format above (``comments`` become ``#`` lines first).

    Args:
        digits: significant digits of every number; ``None`` writes the shortest text that
            reads back exactly (no value changes on a round trip).
        newline: line ending, ``"\\n"``, ``"\\r\\n"`` or ``"\\r"``.
    """
    if newline not in ("\n", "\r\n", "\r"):
        raise ValueError(f"newline = {newline!r}: valid values are '\\n', '\\r\\n', '\\r'")
    path = output_file(path)
    names = list(REQUIRED) + (["sigma"] if data.sigma is not None else [])
    with path.open("w", newline="", encoding="utf-8") as fh:
        for c in (comments if comments is not None else data.comments):
            fh.write(f"# {c}{newline}")
        writer = csv.writer(fh, lineterminator=newline)
        writer.writerow(names)
        for i in range(len(data)):
            writer.writerow([format_number(getattr(data, n)[i], digits) for n in names])
    return path
