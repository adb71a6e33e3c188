"""Convert T. A. Germer's NIST PTFE BRDF data (Applied Optics 56(33), 9333, 2017) to the
project's measurement format (:mod:`mitsuba_powder.io.measurements`).

Source convention (``PTFE.data.csv``): ``lambda`` in micrometres; ``thetai`` stored negative
with ``phi = 0``, i.e. the source sits at azimuth 180 deg; ``thetar``, ``phir`` the viewing
direction, so the mirror direction is ``phir = 0`` and back-scattering ``phir = 180``;
``f_r11`` the unpolarised BRDF in 1/sr. In the gonio convention of docs/model.md the source sits at
azimuth 0, so the viewing azimuth is ``phir - 180``; ``theta_o = thetar`` (>= 0),
``theta_i = |thetai|``, ``brf = pi f_r11``. The data carry no uncertainty column.
"""

from __future__ import annotations

import csv
from pathlib import Path

import numpy as np

from .measurements import Measurements, save_measurements

PROVENANCE = [
    "NIST sintered PTFE BRDF, real measurements: T. A. Germer, 'Full four-dimensional and",
    "reciprocal Mueller matrix bidirectional reflectance distribution function of sintered",
    "polytetrafluoroethylene', Applied Optics 56(33), 9333 (2017).",
    "Converted by mitsuba_powder.io.ptfe from PTFE.data.csv (the project's shared data folder):",
    "theta_i = |thetai|, theta_o = thetar, phi = phir - 180 (wrapped to (-180, 180]),",
    "wavelength = 1000 * lambda (nm), brf = pi * f_r11; Mueller elements dropped.",
]


def convert_germer_ptfe(source: str | Path, destination: str | Path) -> Measurements:
    """Read ``PTFE.data.csv`` and write it as a measurement file; returns the data."""
    source = Path(source)
    with source.open(newline="", encoding="utf-8") as fh:
        reader = csv.DictReader(fh)
        missing = {"lambda", "thetai", "phi", "thetar", "phir", "f_r11"} - set(
            reader.fieldnames or [])
        if missing:
            raise ValueError(f"{source}: not a Germer PTFE file, missing columns {missing}")
        rows = [(float(r["lambda"]), float(r["thetai"]), float(r["phi"]), float(r["thetar"]),
                 float(r["phir"]), float(r["f_r11"])) for r in reader]
    a = np.array(rows)
    if np.any(a[:, 2] != 0.0):
        raise ValueError(f"{source}: expected the incidence azimuth phi = 0 in every row")
    phi = a[:, 4] - 180.0
    phi = np.where(phi <= -180.0, phi + 360.0, phi)
    data = Measurements(theta_i=np.abs(a[:, 1]), theta_o=a[:, 3], phi=phi,
                        wavelength=np.round(a[:, 0] * 1000.0, 6), brf=np.pi * a[:, 5],
                        comments=list(PROVENANCE), source=str(source))
    save_measurements(destination, data)
    return data
