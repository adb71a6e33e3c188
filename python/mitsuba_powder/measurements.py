"""Goniometric BRDF measurements: the CSV format, a strict loader and a writer.

Format (UTF-8 CSV; lines starting with ``#`` are comments, kept as provenance)::

    # source: ...
    theta_i,theta_o,phi,wavelength,brf,sigma
    20,-35,0,700,0.95,0.02

Columns (any order; ``sigma`` optional):

- ``theta_i``: incidence angle from the normal, degrees, in [0, 90).
- ``theta_o``: *signed* viewing angle, degrees, in (-90, 90).
- ``phi``: viewing azimuth relative to the plane of incidence, degrees, in [-360, 360].
  The light sits at azimuth 0: ``wi = (sin ti, 0, cos ti)``,
  ``wo = (sin to cos phi, sin to sin phi, cos to)``. So ``phi = 0, theta_o = theta_i`` is
  back-scattering and ``phi = 0, theta_o = -theta_i`` the mirror direction (MODEL.md).
- ``wavelength``: nm, > 0.
- ``brf``: reflectance factor, ``pi * BRDF`` (1 for a white Lambertian), >= 0.
- ``sigma``: 1-sigma uncertainty of ``brf``, > 0.
"""

from __future__ import annotations

import csv
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

REQUIRED = ("theta_i", "theta_o", "phi", "wavelength", "brf")
OPTIONAL = ("sigma",)

# column -> (low, high, low inclusive, high inclusive)
RANGES = {
    "theta_i": (0.0, 90.0, True, False),
    "theta_o": (-90.0, 90.0, False, False),
    "phi": (-360.0, 360.0, True, True),
    "wavelength": (0.0, np.inf, False, False),
    "brf": (0.0, np.inf, True, False),
    "sigma": (0.0, np.inf, False, False),
}


class MeasurementError(ValueError):
    """A measurement file is malformed; the message names the file, line and column."""


@dataclass
class Measurements:
    """BRF samples at gonio geometries (angles in degrees, wavelength in nm).

    Attributes:
        theta_i, theta_o, phi, wavelength, brf: 1D arrays of equal length.
        sigma: 1-sigma uncertainties of ``brf``, or ``None`` if the file has none.
        comments: the file's ``#`` lines (provenance), without the ``#``.
        source: where the data came from (a path or a description).
    """

    theta_i: np.ndarray
    theta_o: np.ndarray
    phi: np.ndarray
    wavelength: np.ndarray
    brf: np.ndarray
    sigma: np.ndarray | None = None
    comments: list[str] = field(default_factory=list)
    source: str = ""

    def __post_init__(self) -> None:
        for name in REQUIRED:
            setattr(self, name, np.asarray(getattr(self, name), dtype=np.float64))
        if self.sigma is not None:
            self.sigma = np.asarray(self.sigma, dtype=np.float64)
        n = len(self.brf)
        if any(len(getattr(self, k)) != n for k in REQUIRED) or (
                self.sigma is not None and len(self.sigma) != n):
            raise ValueError("all measurement columns must have the same length")

    def __len__(self) -> int:
        return len(self.brf)

    def directions(self) -> tuple[np.ndarray, np.ndarray]:
        """(wi, wo): (N, 3) unit vectors in the local frame (normal +z)."""
        return gonio_directions(self.theta_i, self.theta_o, self.phi)

    def subset(self, mask: np.ndarray) -> Measurements:
        """The rows where ``mask`` is true."""
        mask = np.asarray(mask, dtype=bool)
        return Measurements(self.theta_i[mask], self.theta_o[mask], self.phi[mask],
                            self.wavelength[mask], self.brf[mask],
                            None if self.sigma is None else self.sigma[mask],
                            list(self.comments), self.source)

    def wavelengths(self) -> np.ndarray:
        """The distinct wavelengths, nm, sorted."""
        return np.unique(self.wavelength)


def gonio_directions(theta_i, theta_o, phi) -> tuple[np.ndarray, np.ndarray]:
    """MODEL.md's gonio convention, angles in degrees -> (wi, wo) of shape (N, 3)."""
    ti, to, ph = (np.radians(np.atleast_1d(np.asarray(a, dtype=np.float64)))
                  for a in (theta_i, theta_o, phi))
    ti, to, ph = np.broadcast_arrays(ti, to, ph)
    wi = np.stack([np.sin(ti), np.zeros_like(ti), np.cos(ti)], axis=1)
    wo = np.stack([np.sin(to) * np.cos(ph), np.sin(to) * np.sin(ph), np.cos(to)], axis=1)
    return wi, wo


def _check_range(name: str, value: float, where: str) -> None:
    lo, hi, lo_in, hi_in = RANGES[name]
    ok = (value >= lo if lo_in else value > lo) and (value <= hi if hi_in else value < hi)
    if not ok:
        raise MeasurementError(
            f"{where}, column '{name}': {value:g} is out of range; valid range is "
            f"{'[' if lo_in else '('}{lo:g}, {hi:g}{']' if hi_in else ')'}")


def load_measurements(path: str | Path) -> Measurements:
    """Read and validate a measurement CSV file.

    Raises:
        MeasurementError: missing or unknown column, a field that is not a finite number, a
            value out of range, a row of the wrong length, a duplicate geometry (same
            directions and wavelength), or no data. The message names the line and column.
        FileNotFoundError: the file does not exist.
    """
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"measurement file {path} does not exist")
    comments: list[str] = []
    rows: list[tuple[int, list[str]]] = []
    header: list[str] | None = None
    header_line = 0
    with path.open(newline="", encoding="utf-8") as fh:
        for lineno, line in enumerate(fh, start=1):
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
    seen: dict[tuple, int] = {}
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
            _check_range(name, value, where)
            columns[name][k] = value
    # duplicates: same directions (theta_o, phi) and (-theta_o, phi + 180) coincide
    wi, wo = gonio_directions(columns["theta_i"], columns["theta_o"], columns["phi"])
    keys = np.round(np.concatenate([wi, wo, columns["wavelength"][:, None]], axis=1), 9)
    for k, key in enumerate(map(tuple, keys)):
        if key in seen:
            raise MeasurementError(f"{path}, line {rows[k][0]}: duplicate of line {seen[key]} "
                                   "(same incidence, viewing direction and wavelength)")
        seen[key] = rows[k][0]
    return Measurements(columns["theta_i"], columns["theta_o"], columns["phi"],
                        columns["wavelength"], columns["brf"], columns.get("sigma"),
                        comments, str(path))


def save_measurements(path: str | Path, data: Measurements,
                      comments: list[str] | None = None) -> Path:
    """Write ``data`` in the CSV format above (``comments`` become ``#`` lines first)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    names = list(REQUIRED) + (["sigma"] if data.sigma is not None else [])
    with path.open("w", newline="", encoding="utf-8") as fh:
        for c in (comments if comments is not None else data.comments):
            fh.write(f"# {c}\n")
        writer = csv.writer(fh)
        writer.writerow(names)
        for i in range(len(data)):
            writer.writerow([f"{getattr(data, n)[i]:.10g}" for n in names])
    return path
