"""Grain optics for fitting: single-scattering albedo and tau_o of the grains at any wavelength.

The physics is the plugin's own C++ code, called through :mod:`mitsuba_powder._optics`
(double-precision Mie efficiencies, Fresnel ``tau_o``, the strict optical-constants loader and
hematite's orientation average); this module only does what the plugin's constructor and
``update_mie_tables`` do around it, so that a fit gets rho(r, lambda) for many radii and
wavelengths without building a plugin instance (or switching Mitsuba variants) for each:

- the complex index at each wavelength: linear interpolation of the material's table
  (``material`` = ``hematite`` | ``magnetite`` | a refractiveindex.info YAML file), or constant
  ``eta``/``k`` numbers;
- ``rho = sum_j (f_j / r_j) Q_sca,j / sum_j (f_j / r_j) Q_ext,j`` (MODEL.md, one or two
  populations), its derivatives by the same forward difference as the plugin (relative step
  1e-6 in the size parameter);
- ``tau_o`` from the Fresnel reflectance at Re(index).

``tests/test_fit.py`` checks every value against the plugin's ``eval_attribute``.
Units: wavelengths in nm, radii in micrometres.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from . import _optics

_DATA = Path(__file__).resolve().parent / "data" / "optical_constants"

#: Size parameters the plugin accepts (2 pi r / lambda)
SIZE_PARAMETER_RANGE = (1e-3, 200.0)

#: Relative step of the forward difference of the Mie efficiencies (as in the plugin)
STEP = 1e-6


class GrainOptics:
    """Optical constants of a grain material and the albedo of its grains.

    Args:
        properties: plugin properties; ``material`` or ``eta`` and ``k`` (numbers) are used,
            the default is hematite, as in the plugin.

    Raises:
        ValueError: an unknown material, ``eta`` without ``k``, both a material and ``eta``,
            or ``eta``/``k`` that are not numbers in range.
    """

    def __init__(self, properties: dict):
        has_eta, has_k = "eta" in properties, "k" in properties
        if has_eta or has_k:
            if not (has_eta and has_k):
                raise ValueError(f"give both eta and k (got only {'eta' if has_eta else 'k'})")
            if "material" in properties:
                raise ValueError("give either material or eta and k, not both")
            eta, k = properties["eta"], properties["k"]
            for name, value, ok in (("eta", eta, lambda v: v > 0), ("k", k, lambda v: v >= 0)):
                if not isinstance(value, (int, float)) or not math.isfinite(value) or \
                        not ok(value):
                    raise ValueError(f"{name} = {value!r}: a fit takes {name} as a finite "
                                     f"number ({'> 0' if name == 'eta' else '>= 0'}); give a "
                                     "material YAML file for wavelength-dependent constants")
            self.source = f"eta = {eta:g}, k = {k:g}"
            self.table = (np.array([1e-6, 1e3]), np.array([eta, eta], dtype=float),
                          np.array([k, k], dtype=float))
            return
        material = properties.get("material", "hematite")
        if material == "hematite":
            wl, n, k = _optics.hematite_average(str(_DATA / "hematite_Querry-o.yml"),
                                                str(_DATA / "hematite_Querry-e.yml"))
            self.source = "hematite (Querry 1985, orientation average)"
        elif material == "magnetite":
            wl, n, k = _optics.load_optical_constants(str(_DATA / "magnetite_Querry.yml"))
            self.source = "magnetite (Querry 1985)"
        elif isinstance(material, str) and material.endswith((".yml", ".yaml")):
            if not Path(material).is_file():
                raise ValueError(f"material = {material!r}: no such file")
            wl, n, k = _optics.load_optical_constants(material)
            self.source = material
        else:
            raise ValueError(f"material = {material!r} is not valid; valid values are "
                             "hematite, magnetite or the path of a refractiveindex.info YAML "
                             "file (.yml)")
        self.table = (np.asarray(wl, dtype=float), np.asarray(n, dtype=float),
                      np.asarray(k, dtype=float))

    def index(self, wavelengths_nm: np.ndarray) -> np.ndarray:
        """Complex index n + ik at each wavelength (linear interpolation of the table).

        Raises:
            ValueError: a wavelength outside the table.
        """
        wl_um = np.atleast_1d(np.asarray(wavelengths_nm, dtype=float)) * 1e-3
        wl, n, k = self.table
        outside = (wl_um < wl[0]) | (wl_um > wl[-1])
        if np.any(outside):
            bad = wl_um[outside][0] * 1e3
            raise ValueError(f"wavelength {bad:g} nm lies outside the optical constants of "
                             f"{self.source}, which cover {wl[0] * 1e3:g}-{wl[-1] * 1e3:g} nm")
        return np.interp(wl_um, wl, n) + 1j * np.interp(wl_um, wl, k)

    def tau_o(self, wavelengths_nm: np.ndarray) -> np.ndarray:
        """Extrapolation ratio from the Fresnel reflectance at Re(index), per wavelength."""
        return np.array([_optics.tau_o_fresnel(float(m.real))
                         for m in self.index(wavelengths_nm)])

    @staticmethod
    def _efficiencies(m: complex, r: float, wl_nm: float, name: str, derivative: bool
                      ) -> tuple[float, float, float, float]:
        """(Q_ext, Q_sca, dQ_ext/dr, dQ_sca/dr) of a sphere of radius r (um)."""
        x = 2.0 * math.pi * r / (wl_nm * 1e-3)
        lo, hi = SIZE_PARAMETER_RANGE
        if not (lo * (1.0 - 1e-6) <= x <= hi * (1.0 + 1e-6)):
            raise ValueError(f"{name} = {r:g} um gives the size parameter 2 pi r / lambda = "
                             f"{x:g} at {wl_nm:g} nm; valid range is [{lo:g}, {hi:g}]")
        q_ext, q_sca = _optics.mie_efficiencies(m, x)
        if not q_ext > 0.0:
            raise ValueError(f"grains of index {m} do not interact with light (Q_ext = 0)")
        if not derivative:
            return q_ext, q_sca, 0.0, 0.0
        qe, qs = _optics.mie_efficiencies(m, x * (1.0 + STEP))
        s = 1.0 / (STEP * r)
        return q_ext, q_sca, (qe - q_ext) * s, (qs - q_sca) * s

    def albedo(self, wavelengths_nm: np.ndarray, radius: np.ndarray,
               radius2: np.ndarray | None = None, fraction2: np.ndarray | None = None,
               derivatives: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """rho (B, W) of B grain sets at W wavelengths and, with ``derivatives``,
        d rho / d(radius, radius2, fraction2) (B, W, 3) (zero columns for one population).

        Args:
            wavelengths_nm: (W,) nm.
            radius: (B,) um. radius2, fraction2: (B,) or None (one population).

        Raises:
            ValueError: a size parameter outside the plugin's range (naming the property).
        """
        wls = np.atleast_1d(np.asarray(wavelengths_nm, dtype=float))
        radius = np.atleast_1d(np.asarray(radius, dtype=float))
        b = len(radius)
        two = radius2 is not None
        if two and fraction2 is None:
            raise ValueError("a second population needs radius2 and fraction2")
        r2 = np.broadcast_to(np.asarray(radius2, dtype=float), (b,)) if two else None
        f2 = np.broadcast_to(np.asarray(fraction2, dtype=float), (b,)) if two else np.zeros(b)
        index = self.index(wls)
        rho = np.empty((b, len(wls)))
        deriv = np.zeros((b, len(wls), 3)) if derivatives else None
        for i in range(b):
            r1 = float(radius[i])
            for j, (wl, m) in enumerate(zip(wls, index)):
                qe1, qs1, dqe1, dqs1 = self._efficiencies(m, r1, wl, "radius", derivatives)
                w1 = (1.0 - f2[i]) / r1
                ns, ne = w1 * qs1, w1 * qe1
                dns = [(1.0 - f2[i]) * (dqs1 / r1 - qs1 / r1**2), 0.0, -qs1 / r1]
                dne = [(1.0 - f2[i]) * (dqe1 / r1 - qe1 / r1**2), 0.0, -qe1 / r1]
                if two:
                    rr = float(r2[i])
                    qe2, qs2, dqe2, dqs2 = self._efficiencies(m, rr, wl, "radius2",
                                                              derivatives)
                    w2 = f2[i] / rr
                    ns += w2 * qs2
                    ne += w2 * qe2
                    dns[1] = f2[i] * (dqs2 / rr - qs2 / rr**2)
                    dne[1] = f2[i] * (dqe2 / rr - qe2 / rr**2)
                    dns[2] += qs2 / rr
                    dne[2] += qe2 / rr
                rho[i, j] = ns / ne
                if derivatives:
                    for c in range(3 if two else 1):
                        deriv[i, j, c] = (dns[c] * ne - ns * dne[c]) / (ne * ne)
        return rho, deriv
