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
from ..outputs import note_input
from . import registry

#: Grain models of the plugin's ``grains`` property (docs/model.md, "Grain models")
GRAIN_MODELS = tuple(registry.GRAIN_MODELS)

#: Effective-medium rules of the ``mixing`` property
MIXING_RULES = ("bruggeman", "maxwell_garnett")

#: The fittable grain properties, in the order of the derivative columns of
#: :meth:`GrainOptics.albedo` (``_optics.albedo_table``'s, then populations 3 and 4)
GRAIN_VARIABLES = registry.GRAIN_VARIABLES + ("radius3", "fraction3", "radius4", "fraction4")
#: The material properties of populations 2..4 (docs/model.md, "Several materials")
POPULATION_MATERIALS = tuple(f"{k}{j}" for j in range(2, registry.MAX_POPULATIONS + 1)
                             for k in ("material", "eta", "k"))

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
        # populations 2..4 of their own materials (a pigment mixture)
        self.population_optics: dict[int, GrainOptics] = {}
        for j in range(2, registry.MAX_POPULATIONS + 1):
            own = {k: properties[f"{k}{j}"] for k in ("material", "eta", "k")
                   if f"{k}{j}" in properties}
            if own:
                self.population_optics[j] = GrainOptics(own)
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
            note_input(material)  # an input of the command: nothing is written over it
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

    def tau_o(self, wavelengths_nm: np.ndarray, fractions: dict | None = None) -> np.ndarray:
        """Extrapolation ratio from the Fresnel reflectance at Re(index), per wavelength; for
        populations of their own materials, of the mixture's Bruggeman index at the volume
        ``fractions`` ({"fraction2": ..., ...}; docs/model.md, "The mixture's index for
        tau_o").

        Raises:
            ValueError: a mixture without the fractions of its populations.
        """
        if not self.population_optics:
            return np.array([_optics.tau_o_fresnel(float(m.real))
                             for m in self.index(wavelengths_nm)])
        fractions = fractions or {}
        last = max(self.population_optics)
        missing = [f"fraction{j}" for j in range(2, last + 1) if f"fraction{j}" not in fractions]
        if missing:
            raise ValueError(f"tau_o of a mixture needs {', '.join(missing)}")
        f = [float(fractions[f"fraction{j}"]) for j in range(2, last + 1)]
        f = [max(0.0, 1.0 - sum(f))] + f
        f = [v / sum(f) for v in f]
        indices = [self.index(wavelengths_nm)] + [
            self.population_optics.get(j, self).index(wavelengths_nm) for j in range(2, last + 1)]
        return np.array([_optics.tau_o_fresnel(_optics.bruggeman_mixture(
            [complex(idx[i]) for idx in indices], f).real) for i in range(len(indices[0]))])

    def mixture(self, wls: list[float], radius: np.ndarray, others: list,
                derivatives: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """rho (B, W) and d rho / d(:data:`GRAIN_VARIABLES`) of a mixture: population 1 of this
        material and radii ``radius``, ``others`` the (radii, fractions) of populations 2..4 (None
        where absent), each of its own material or this one."""
        if self.grains == "agglomerate":
            raise ValueError('grains = "agglomerate" has one population')
        present = [(j + 2, r, f) for j, (r, f) in enumerate(others) if r is not None]
        for j, _, f in present:
            if f is None:
                raise ValueError(f"population {j} needs radius{j} and fraction{j}")
        if [j for j, _, _ in present] != list(range(2, 2 + len(present))):
            raise ValueError("populations are numbered 2, 3, 4 without gaps")
        indices = [[complex(m) for m in self.index(wls)]] + [
            [complex(m) for m in self.population_optics.get(j, self).index(wls)]
            for j, _, _ in present]
        b = len(radius)
        rho = np.empty((b, len(wls)))
        deriv = np.zeros((b, len(wls), len(GRAIN_VARIABLES))) if derivatives else None
        columns = [GRAIN_VARIABLES.index("radius")]
        for j, _, _ in present:
            columns += [GRAIN_VARIABLES.index(f"radius{j}"), GRAIN_VARIABLES.index(f"fraction{j}")]
        for i in range(b):
            fr = np.array([float(fs[i]) for _, _, fs in present])
            if fr.sum() > 1.0:
                fr = fr / fr.sum()
            pops = [(float(radius[i]), None, indices[0])] + [
                (float(r[i]), float(fj), idx)
                for (_, r, _), fj, idx in zip(present, fr, indices[1:])]
            try:
                values, d = _optics.mixture_albedo(self.grains, wls, pops, derivatives)
            except RuntimeError as error:
                raise ValueError(str(error).removeprefix("powder: ")) from None
            rho[i] = values
            if derivatives:
                deriv[i][:, columns] = np.asarray(d)
        return rho, deriv

    def albedo(self, wavelengths_nm: np.ndarray, radius: np.ndarray,
               radius2: np.ndarray | None = None, fraction2: np.ndarray | None = None,
               derivatives: bool = False,
               agglomerate_radius: np.ndarray | None = None,
               agglomerate_fill: np.ndarray | None = None,
               radius3: np.ndarray | None = None, fraction3: np.ndarray | None = None,
               radius4: np.ndarray | None = None, fraction4: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray | None]:
        """rho (B, W) of B grain sets at W wavelengths and, with ``derivatives``,
        d rho / d(:data:`GRAIN_VARIABLES`) (B, W, 9) (zero columns for parameters not in use).

        The grain model and mixing rule are this instance's (``grains``, ``mixing``).

        Args:
            wavelengths_nm: (W,) nm.
            radius: (B,) um (the crystallite radius for agglomerates: it does not enter rho).
            radius2, fraction2: (B,) or None (one population).
            radius3, fraction3, radius4, fraction4: (B,) or None: populations 3 and 4.
                With them, or with populations of their own materials, the mixture rule
                (:meth:`mixture`); fractions summing above 1 are scaled to sum 1 (population
                1 then 0), which keeps a search's trial points evaluable.
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
        if radius3 is not None or self.population_optics:
            return self.mixture(wls, radius, [(r2, f2), (per_set(radius3), per_set(fraction3)),
                                              (per_set(radius4), per_set(fraction4))],
                                derivatives)
        ra = per_set(agglomerate_radius)
        fill = per_set(agglomerate_fill)
        if (r2 is None) != (f2 is None):
            raise ValueError("a second population needs radius2 and fraction2")
        if self.grains == "agglomerate" and ra is None:
            raise ValueError('grains = "agglomerate" needs agglomerate_radius (um); valid '
                             "range is (0, inf)")
        return self._albedo_tables(wls, radius, r2, f2, ra, fill, derivatives)

    def _albedo_tables(self, wls: list[float], radius: np.ndarray, r2, f2, ra, fill,
                       derivatives: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """:meth:`albedo` of up to two populations of this material, one grain set at a time
        (``r2``, ``f2``, ``ra``, ``fill``: (B,) or None)."""
        b = len(radius)
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
            if derivatives:  # albedo_table's columns: the first of GRAIN_VARIABLES
                deriv[i][:, :len(registry.GRAIN_VARIABLES)] = d
        return rho, deriv


#: how the fractions of a mixture are given (:func:`volume_fractions`)
FRACTION_BASES = ("mass", "volume")


def volume_fractions(parts: list[tuple[str, float]], by: str = "volume") -> list[float]:
    """Volume fractions of the solid of a mixture's populations (docs/model.md, "Several
    materials"), from ``(material, fraction)`` pairs given by ``mass`` or by ``volume``.

    A mass fraction ``w_j`` of a material of density ``d_j`` (g/cm^3, :data:`registry.DENSITIES`,
    measurements/README.md) occupies the volume fraction ``(w_j / d_j) / sum_k (w_k / d_k)``.
    The fractions must be in [0, 1] and sum to 1 (to 1e-6).

    Raises:
        ValueError: ``by`` not ``mass`` or ``volume``, a fraction out of range, fractions not
            summing to 1, or (by mass) a material without a known density (a YAML file or
            ``eta``/``k``: give volume fractions).
    """
    if by not in FRACTION_BASES:
        raise ValueError(f"by = {by!r} is not valid; valid values are {', '.join(FRACTION_BASES)}")
    if not 1 <= len(parts) <= registry.MAX_POPULATIONS:
        raise ValueError(f"a mixture of {len(parts)} populations; valid range is "
                         f"[1, {registry.MAX_POPULATIONS}]")
    for material, f in parts:
        if not (isinstance(f, (int, float)) and math.isfinite(f) and 0.0 <= f <= 1.0):
            raise ValueError(f"the {by} fraction of {material} = {f!r} is out of range; valid "
                             "range is [0, 1]")
    total = sum(f for _, f in parts)
    if abs(total - 1.0) > 1e-6:
        raise ValueError(f"the {by} fractions {', '.join(f'{m}: {f:g}' for m, f in parts)} sum "
                         f"to {total:g}; they must sum to 1")
    if by == "volume":
        return [float(f) for _, f in parts]
    unknown = [m for m, _ in parts if m not in registry.DENSITIES]
    if unknown:
        raise ValueError(f"no density for material {unknown[0]!r} (mass fractions need one); "
                         f"materials with a density: {', '.join(registry.DENSITIES)}; or give "
                         "volume fractions")
    volumes = [f / registry.DENSITIES[m] for m, f in parts]
    return [v / sum(volumes) for v in volumes]


def mixture_properties(parts: list[tuple[str, float, float]], by: str = "volume") -> dict:
    """The ``powder`` properties of a mixture of ``(material, fraction, radius um)``
    populations (fractions by ``mass`` or ``volume``, :func:`volume_fractions`): ``material``
    and ``radius`` for the first, ``material{j}``, ``radius{j}``, ``fraction{j}`` (volume) for
    the others.

    Raises:
        ValueError: as :func:`volume_fractions`, or a radius that is not a positive number.
    """
    volumes = volume_fractions([(m, f) for m, f, _ in parts], by)
    props: dict = {}
    for j, ((material, _, radius), f) in enumerate(zip(parts, volumes), start=1):
        if not (isinstance(radius, (int, float)) and math.isfinite(radius) and radius > 0):
            raise ValueError(f"the radius of {material} = {radius!r} um is out of range; valid "
                             "range is (0, inf)")
        suffix = "" if j == 1 else str(j)
        props[f"material{suffix}"] = material
        props[f"radius{suffix}"] = float(radius)
        if j > 1:
            props[f"fraction{j}"] = float(f)
    return props


def mixture_albedo(properties: dict, wavelengths_nm) -> tuple[np.ndarray, np.ndarray]:
    """(rho, tau_o) per wavelength of the grain populations of ``powder`` properties (one to
    four: ``material``/``eta``/``k``, ``radius`` and ``material{j}``/``eta{j}``/``k{j}``,
    ``radius{j}``, ``fraction{j}``), with the plugin's own double-precision code: rho from
    ``_optics.mixture_albedo``, tau_o from the Fresnel reflectance of the mixture's Bruggeman
    index (docs/model.md, "The mixture's index for tau_o").

    Raises:
        ValueError: a material, radius or fraction the plugin refuses (its message).
    """
    wls = [float(w) for w in np.atleast_1d(np.asarray(wavelengths_nm, dtype=float))]
    first = {k: properties[k] for k in ("material", "eta", "k") if k in properties}
    optics = [GrainOptics({**first, "grains": properties.get("grains", "sphere")})]
    populations = [(float(properties.get("radius", registry.DEFAULTS["radius"])), None)]
    for j in range(2, registry.MAX_POPULATIONS + 1):
        if f"radius{j}" not in properties:
            break
        own = {k: properties[f"{k}{j}"] for k in ("material", "eta", "k")
               if f"{k}{j}" in properties}
        optics.append(GrainOptics(own) if own else optics[0])
        populations.append((float(properties[f"radius{j}"]), float(properties[f"fraction{j}"])))
    indices = [[complex(m) for m in o.index(wls)] for o in optics]
    try:
        rho, _ = _optics.mixture_albedo(
            properties.get("grains", "sphere"), wls,
            [(r, f, idx) for (r, f), idx in zip(populations, indices)], False)
    except RuntimeError as error:
        raise ValueError(str(error).removeprefix("powder: ")) from None
    fractions = [1.0 - sum(f for _, f in populations[1:])] + [f for _, f in populations[1:]]
    fractions[0] = max(fractions[0], 0.0)
    tau = [_optics.tau_o_fresnel(_optics.bruggeman_mixture(
        [idx[i] for idx in indices], fractions).real) for i in range(len(wls))]
    return np.asarray(rho), np.asarray(tau)


def parse_mix(spec: str) -> list[tuple[str, float, float]]:
    """``(material, fraction, radius um)`` populations of a mixture written
    ``material:fraction:radius,...``, e.g. ``hematite:5%:0.1um,kaolinite:95%:1um``: a fraction
    as a number in [0, 1] or a percentage, a radius in um (``um`` or no unit) or ``nm``.

    Raises:
        ValueError: an item that is not three fields, a fraction or radius that is not a
            number (the item is named).
    """
    parts = []
    for item in (s.strip() for s in spec.split(",")):
        fields = [f.strip() for f in item.split(":")]
        if len(fields) != 3 or not all(fields):
            raise ValueError(f"mixture item {item!r} is not material:fraction:radius (e.g. "
                             "hematite:5%:0.1um)")
        material, fraction, radius = fields
        try:
            f = float(fraction[:-1]) / 100.0 if fraction.endswith("%") else float(fraction)
            scale = 1e-3 if radius.endswith("nm") else 1.0
            r = float(radius.removesuffix("nm").removesuffix("um")) * scale
        except ValueError:
            raise ValueError(f"mixture item {item!r}: the fraction ({fraction!r}: a number or "
                             f"a percentage) or the radius ({radius!r}: um or nm) is not a "
                             "number") from None
        parts.append((material, f, r))
    return parts

