"""Grain optics for fitting: single-scattering albedo and tau_o of the grains at any wavelength.

The physics is the plugin's own C++ code, called through :mod:`mitsuba_powder._optics`
(double-precision Mie efficiencies, Fresnel ``tau_o``, the strict optical-constants loader and
hematite's orientation average); this module only does what the plugin's constructor and
``update_mie_tables`` do around it, so that a fit gets rho(r, lambda) for many radii and
wavelengths without building a plugin instance (or switching Mitsuba variants) for each:

- the complex index at each wavelength: linear interpolation of the material's table
  (``material`` = ``hematite`` | ``magnetite`` | a refractiveindex.info YAML file), or constant
  ``eta``/``k`` numbers;
- rho and its derivatives from the plugin's albedo table (``_optics.albedo_table``: docs/model.md's
  grain models ``sphere``, ``agglomerate`` and ``slab``, one or two populations);
- ``tau_o`` from the Fresnel reflectance at Re(index).

``tests/fitting/test_fit.py`` checks every value against the plugin's ``eval_attribute``.
Units: wavelengths in nm, radii in micrometres.
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np

from .. import _optics
from . import registry

#: Grain models of the plugin's ``grains`` property (docs/model.md, "Grain models")
GRAIN_MODELS = tuple(registry.GRAIN_MODELS)

#: Effective-medium rules of the ``mixing`` property
MIXING_RULES = ("bruggeman", "maxwell_garnett")

#: The fittable grain properties, in the order of the derivative columns of
#: :meth:`GrainOptics.albedo` (and of ``_optics.albedo_table``)
GRAIN_VARIABLES = registry.GRAIN_VARIABLES

#: The plugin's default ``agglomerate_fill``
DEFAULT_FILL = float(registry.DEFAULTS["agglomerate_fill"])
#: The plugin's default grain material (its ``material`` property)
DEFAULT_MATERIAL = str(registry.DEFAULTS["material"])


class GrainOptics:
    """Optical constants of a grain material and the albedo of its grains.

    Args:
        properties: plugin properties; ``material`` or ``eta`` and ``k`` (numbers) are used,
            the default is hematite, as in the plugin; ``grains`` and ``mixing`` (defaults
            ``sphere`` and ``bruggeman``).

    Raises:
        ValueError: an unknown material, ``eta`` without ``k``, both a material and ``eta``,
            ``eta``/``k`` that are not numbers in range, or an unknown grain model or mixing
            rule.
    """

    def __init__(self, properties: dict):
        self.grains = properties.get("grains", registry.DEFAULTS["grains"])
        self.mixing = properties.get("mixing", registry.DEFAULTS["mixing"])
        for name, value, valid in (("grains", self.grains, GRAIN_MODELS),
                                   ("mixing", self.mixing, MIXING_RULES)):
            if value not in valid:
                raise ValueError(f"{name} = {value!r} is not valid; valid values are "
                                 f"{', '.join(valid)}")
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
        material = properties.get("material", DEFAULT_MATERIAL)
        if material in registry.MATERIALS:
            files = registry.material_files(material)
            names = ", ".join(f.name for f in files)
            if len(files) == 2:  # a uniaxial crystal: ordinary and extraordinary indices
                wl, n, k = _optics.hematite_average(*(str(f) for f in files))
                self.source = f"{material} (orientation average of {names})"
            else:
                wl, n, k = _optics.load_optical_constants(str(files[0]))
                self.source = f"{material} ({names})"
        elif isinstance(material, str) and material.endswith((".yml", ".yaml")):
            if not Path(material).is_file():
                raise ValueError(f"material = {material!r}: no such file")
            wl, n, k = _optics.load_optical_constants(material)
            self.source = material
        else:
            raise ValueError(f"material = {material!r} is not valid; valid values are "
                             f"{', '.join(registry.MATERIALS)} or the path of a "
                             "refractiveindex.info YAML file (.yml)")
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

    def albedo(self, wavelengths_nm: np.ndarray, radius: np.ndarray,
               radius2: np.ndarray | None = None, fraction2: np.ndarray | None = None,
               derivatives: bool = False,
               agglomerate_radius: np.ndarray | None = None,
               agglomerate_fill: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray | None]:
        """rho (B, W) of B grain sets at W wavelengths and, with ``derivatives``,
        d rho / d(:data:`GRAIN_VARIABLES`) (B, W, 5) (zero columns for parameters not in use).

        The grain model and mixing rule are this instance's (``grains``, ``mixing``).

        Args:
            wavelengths_nm: (W,) nm.
            radius: (B,) um (the crystallite radius for agglomerates: it does not enter rho).
            radius2, fraction2: (B,) or None (one population).
            agglomerate_radius: (B,) um, required with ``grains = "agglomerate"``.
            agglomerate_fill: (B,) or None (the plugin's default, 0.5).

        Raises:
            ValueError: a size parameter outside the plugin's range, a slab of index <= 1, or
                a parameter the grain model does not take (naming the property).
        """
        wls = [float(w) for w in np.atleast_1d(np.asarray(wavelengths_nm, dtype=float))]
        radius = np.atleast_1d(np.asarray(radius, dtype=float))
        b = len(radius)

        def per_set(values) -> np.ndarray | None:
            if values is None:
                return None
            return np.broadcast_to(np.asarray(values, dtype=float), (b,))

        r2, f2 = per_set(radius2), per_set(fraction2)
        ra = per_set(agglomerate_radius)
        fill = per_set(agglomerate_fill)
        if (r2 is None) != (f2 is None):
            raise ValueError("a second population needs radius2 and fraction2")
        if self.grains == "agglomerate" and ra is None:
            raise ValueError('grains = "agglomerate" needs agglomerate_radius (um); valid '
                             "range is (0, inf)")
        index = [complex(m) for m in self.index(wls)]
        rho = np.empty((b, len(wls)))
        deriv = np.zeros((b, len(wls), len(GRAIN_VARIABLES))) if derivatives else None
        for i in range(b):
            try:
                values, d = _optics.albedo_table(
                    self.grains, wls, index, float(radius[i]),
                    None if r2 is None else float(r2[i]), None if f2 is None else float(f2[i]),
                    None if ra is None else float(ra[i]),
                    DEFAULT_FILL if fill is None else float(fill[i]), self.mixing,
                    derivatives)
            except RuntimeError as error:  # the plugin's message names the property
                raise ValueError(str(error).removeprefix("powder: ")) from None
            rho[i] = values
            if derivatives:
                deriv[i] = d
        return rho, deriv
