"""The measurement set shared by every file format: :class:`Measurements` (BRF samples at gonio
geometries), the column names and valid ranges, :class:`MeasurementError`, and the geometry
helpers (:func:`gonio_directions`, geometry ids). Angles in degrees, wavelengths in nm; the
columns, units and conventions are described in :mod:`mitsuba_powder.io.measurements`.

The readers of each format (:mod:`mitsuba_powder.io.measurements` for the project's CSV,
:mod:`mitsuba_powder.io.ipag` for the IPAG goniometers) build these objects; this module reads
no file, so that both depend on it and not on each other.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .._checks import interval_text, out_of_range

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
        comments: the file's ``#`` lines (provenance), without the ``#``; the IPAG loader
            adds lines starting with ``loader:`` (file kind, angle convention, skipped
            values).
        source: where the data came from (a path or a description).
        convention: the angle convention the loader converted from: ``"project"`` (CSV),
            ``"signed"`` or ``"physical"`` (IPAG), ``"any"`` (IPAG, every emergence 0: both
            conventions agree), or ``""`` (built in code).
        skipped: what the loader left out, by reason (e.g. ``{"nan_values": 3}``); see
            :mod:`mitsuba_powder.io.ipag`.
    """

    theta_i: np.ndarray
    theta_o: np.ndarray
    phi: np.ndarray
    wavelength: np.ndarray
    brf: np.ndarray
    sigma: np.ndarray | None = None
    comments: list[str] = field(default_factory=list)
    source: str = ""
    convention: str = ""
    skipped: dict[str, int] = field(default_factory=dict)

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
                            list(self.comments), self.source, self.convention,
                            dict(self.skipped))

    def wavelengths(self) -> np.ndarray:
        """The distinct wavelengths, nm, sorted."""
        return np.unique(self.wavelength)

    def geometry_keys(self, with_wavelength: bool = True) -> np.ndarray:
        """One integer id per row: rows with equal ids share incidence and viewing direction
        (unit vectors to 1e-9, so ``theta_o = 0`` in every azimuth plane is one direction) and,
        if ``with_wavelength``, wavelength."""
        return _geometry_ids(self.theta_i, self.theta_o, self.phi,
                             self.wavelength if with_wavelength else None)

    def geometry_summary(self) -> dict[str, int]:
        """Counts for a fit report.

        Returns:
            ``rows``: observations; ``geometries``: distinct (incidence, viewing direction,
            wavelength); ``directions``: distinct (incidence, viewing direction), wavelength
            ignored; ``replicated_rows``: rows beyond the first at their geometry
            (``rows - geometries``); ``replicated_geometries``: geometries observed more than
            once.
        """
        ids = self.geometry_keys(True)
        counts = np.bincount(ids) if len(ids) else np.zeros(0, dtype=int)
        return {"rows": len(self),
                "geometries": int(np.count_nonzero(counts)),
                "directions": int(len(np.unique(self.geometry_keys(False)))),
                "replicated_rows": int(len(self) - np.count_nonzero(counts)),
                "replicated_geometries": int(np.count_nonzero(counts > 1))}


def gonio_directions(theta_i, theta_o, phi) -> tuple[np.ndarray, np.ndarray]:
    """docs/model.md's gonio convention, angles in degrees -> (wi, wo) of shape (N, 3)."""
    ti, to, ph = (np.radians(np.atleast_1d(np.asarray(a, dtype=np.float64)))
                  for a in (theta_i, theta_o, phi))
    ti, to, ph = np.broadcast_arrays(ti, to, ph)
    wi = np.stack([np.sin(ti), np.zeros_like(ti), np.cos(ti)], axis=1)
    wo = np.stack([np.sin(to) * np.cos(ph), np.sin(to) * np.sin(ph), np.cos(to)], axis=1)
    return wi, wo


def _geometry_ids(theta_i, theta_o, phi, wavelength=None) -> np.ndarray:
    """Integer ids of distinct geometries (directions compared as unit vectors to 1e-9)."""
    wi, wo = gonio_directions(theta_i, theta_o, phi)
    cols = [wi, wo] + ([np.asarray(wavelength, dtype=np.float64)[:, None]]
                       if wavelength is not None else [])
    keys = np.round(np.concatenate(cols, axis=1), 9) + 0.0  # + 0.0: -0 -> 0
    if not len(keys):
        return np.zeros(0, dtype=np.int64)
    _, ids = np.unique(keys, axis=0, return_inverse=True)
    return ids.ravel()


def format_number(value: float, digits: int | None = None) -> str:
    """``value`` as text: ``digits`` significant digits, or (``None``) the shortest text that
    reads back to exactly the same float (``%.10g`` when that is exact)."""
    value = float(value)
    if digits is not None:
        return f"{value:.{digits}g}"
    text = f"{value:.10g}"
    return text if float(text) == value else repr(value)


def _check_column_range(name: str, value: float, where: str) -> None:
    """A value of column ``name`` in its range (:data:`RANGES`); ``where`` names the row."""
    lo, hi, lo_in, hi_in = RANGES[name]
    ok = (value >= lo if lo_in else value > lo) and (value <= hi if hi_in else value < hi)
    if not ok:
        closed = ("[" if lo_in else "(") + ("]" if hi_in else ")")
        raise MeasurementError(
            out_of_range(f"{where}, column '{name}': {value:g}", interval_text(lo, hi, closed)))
