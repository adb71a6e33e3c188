"""The powder properties an RTI fit varies per pixel: names, bounds, starts and valid ranges,
and the albedo per channel of grains whose size varies per pixel (:class:`GrainAlbedo`)."""

from __future__ import annotations

import math
from collections.abc import Mapping

import numpy as np

from .._checks import out_of_range
from ..fitting.fit import FITTABLE
from ..fitting.optimise import ParamSpec
from ..plugin import registry

__all__ = ["ALBEDO_INTERVAL", "FREE_PROPERTIES", "GRAIN_MAPS", "GrainAlbedo",
           "MAP_DEFAULT_FREE", "MAP_GRAIN_SETTINGS", "MAP_PROPERTIES", "SLOPE_LIMIT", "SPECS",
           "grain_map_name", "property_map", "valid_range"]

#: Float properties of the plugin that may vary per pixel (maps (H, W) or scalars)
MAP_PROPERTIES = ("amplitude_volume", "g", "extinction", "tau_o", "thickness",
                  "amplitude_surface", "correlation_length", "sigma")

#: Grain sizes that may vary per pixel instead of the albedo: the albedo per channel is then
#: the grains' (``radius`` of spheres or slab grains, ``agglomerate_radius``), from
#: :class:`GrainAlbedo`
GRAIN_MAPS = registry.GRAIN_SIZES

#: Properties the per-pixel fit can free besides the normal and the albedo (per channel)
FREE_PROPERTIES = ("albedo",) + MAP_PROPERTIES + GRAIN_MAPS

#: Default free set of the per-pixel fit (besides the normal): what a dome of lights
#: determines (:mod:`mitsuba_powder.rti.fit` gives the evidence)
MAP_DEFAULT_FREE = ["albedo", "amplitude_surface", "correlation_length"]

#: The surface lobe's properties (the free set's optional part)
LOBE = ("amplitude_surface", "correlation_length")

#: The values of the lobe's maps where it is dropped: no lobe (the plugin's default
#: ``amplitude_surface``, 0) and the fit's start of the correlation length (no effect then)
NO_LOBE = {"amplitude_surface": 0.0, "correlation_length": 0.4}

#: Largest normal slope |n_x / n_z|, |n_y / n_z| (tilt up to 85 degrees along an axis)
SLOPE_LIMIT = 11.4

#: Bounds and starts of the fitted properties (the goniometric fit's, with the albedo kept
#: strictly inside (0, 1) and a surface amplitude that can vanish)
SPECS: dict[str, ParamSpec] = {
    **{k: FITTABLE[k] for k in MAP_PROPERTIES},
    "albedo": ParamSpec(1e-3, 0.999, False, 0.8),
    "amplitude_surface": ParamSpec(1e-9, 1e-2, True, 1e-5),
    # a lobe wide enough (1/e half width ~ 25 degrees) to reach the dome's lights from the
    # start: from the goniometric 1 um, LM drifts to an invisible needle. The upper bound is
    # lowered further to the dome's resolution by ``max_correlation_length`` (a wider bound
    # lets the fit put a needle on one light's noise, which relights wildly)
    "correlation_length": ParamSpec(0.05, 1.5, True, 0.4),
    **{k: FITTABLE[k] for k in GRAIN_MAPS},
}

#: Plugin properties that describe the grains: the per-pixel evaluator takes the albedo per
#: pixel instead (``material``, ``eta``, ``k`` stay: they set tau_o)
MAP_GRAIN_SETTINGS = ("grains", "mixing", "agglomerate_fill", "agglomerate_radius", "radius",
                      "radius2", "fraction2")

#: The single-scattering albedo of a channel: [0, 1] (:data:`registry.ALBEDO_INTERVAL`)
ALBEDO_INTERVAL = registry.ALBEDO_INTERVAL


def valid_range(name: str) -> registry.Interval:
    """The values a per-pixel property may take: the plugin's valid range
    (:data:`mitsuba_powder.plugin.registry.INTERVALS`), the albedo's [0, 1], and for a
    per-pixel grain size the range of :class:`GrainAlbedo`'s table (the fit's,
    :data:`SPECS`)."""
    if name in GRAIN_MAPS:
        return registry.Interval(SPECS[name].lower, SPECS[name].upper, True, True)
    if name == "albedo":
        return ALBEDO_INTERVAL
    return registry.INTERVALS[name]


def property_map(name: str, value, shape: tuple[int, int]) -> np.ndarray:
    """A float property given as a scalar or an (H, W) map -> float64 (H, W), range-checked
    against the property's valid range (:func:`valid_range`)."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(shape, float(arr))
    if arr.shape != shape:
        raise ValueError(f"{name} has shape {arr.shape}; expected a scalar or {shape}")
    valid = valid_range(name)
    bad = ~valid.contains(arr)
    if np.any(bad):
        i, j = (int(x[0]) for x in np.nonzero(bad))
        raise ValueError(out_of_range(f"{name}[{i}, {j}] = {float(arr[i, j])!r}", str(valid)))
    return arr


def grain_map_name(settings: Mapping) -> str:
    """The per-pixel grain size of these settings: ``agglomerate_radius`` for agglomerates,
    else ``radius``."""
    return registry.grain_size(settings.get("grains", registry.DEFAULTS["grains"]))


class GrainAlbedo:
    """The albedo per RGB channel of grains whose size varies per pixel: rho(r) and d rho / d r
    at the plugin's ``rgb_wavelengths``, by cubic Hermite interpolation in ln r of a table of
    the plugin's own double-precision albedo (:class:`mitsuba_powder.plugin.grains.GrainOptics`,
    the C++ grain models) over the fittable range of the size (:data:`SPECS`), 3000 nodes.
    ``max_error`` is the largest relative difference from direct theory at the midpoints of the
    table's intervals (measured when built).

    Args:
        name: ``radius`` (``grains`` = ``sphere`` or ``slab``) or ``agglomerate_radius``.
        settings: the plugin properties held for every pixel (``material``, ``eta``/``k``,
            ``grains``, ``agglomerate_fill``, ``mixing``, ``rgb_wavelengths``).
    """

    NODES = 3000

    def __init__(self, name: str, settings: Mapping):
        from ..plugin.grains import GrainOptics

        if name not in GRAIN_MAPS:
            raise ValueError(f"{name!r} is not a per-pixel grain size; choose among "
                             f"{GRAIN_MAPS}")
        model = settings.get("grains", registry.DEFAULTS["grains"])
        models = [m for m, rules in registry.GRAIN_MODELS.items() if rules["size"] == name]
        if model not in models:
            need = " or ".join(models)
            raise ValueError(f"a per-pixel {name} needs grains = {need} (got grains = "
                             f"{model!r})")
        self.name = name
        wl = settings.get("rgb_wavelengths", registry.DEFAULTS["rgb_wavelengths"])
        if isinstance(wl, str):
            wl = [float(v) for v in wl.replace(",", " ").split()]
        self.wavelengths = [float(v) for v in wl]
        self._optics = GrainOptics(dict(settings))
        self._settings = settings
        spec = SPECS[name]
        self.u0, self.u1 = math.log(spec.lower), math.log(spec.upper)
        self.du = (self.u1 - self.u0) / (self.NODES - 1)
        nodes = np.exp(self.u0 + self.du * np.arange(self.NODES))
        mids = np.exp(self.u0 + self.du * (np.arange(self.NODES - 1) + 0.5))
        rho, d = self._theory(nodes, True)
        column = 0 if name == "radius" else 3
        self.rho = rho                                   # (N, 3)
        self.drho_du = d[:, :, column] * nodes[:, None]  # d rho / d ln r
        exact = self._theory(mids, False)[0]
        approx, _ = self(mids)
        self.max_error = float(np.max(np.abs(approx / exact - 1.0)))

    def _theory(self, r: np.ndarray, derivatives: bool):
        """The plugin's albedo (and derivatives) of grains of size r, directly."""
        if self.name == "radius":
            return self._optics.albedo(self.wavelengths, r, derivatives=derivatives)
        crystallite = float(self._settings.get("radius", registry.DEFAULTS["radius"]))
        return self._optics.albedo(self.wavelengths, np.full(len(r), crystallite),
                                   derivatives=derivatives, agglomerate_radius=r,
                                   agglomerate_fill=self._settings.get("agglomerate_fill"))

    def __call__(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rho (P, 3), d rho / d r (P, 3)) at sizes r (P,) in um (inside the fittable range).
        """
        r = np.asarray(r, dtype=np.float64)
        t = np.clip((np.log(r) - self.u0) / self.du, 0.0, self.NODES - 1 - 1e-9)
        j = np.minimum(t.astype(np.int64), self.NODES - 2)
        s = (t - j)[:, None]
        h00, h10 = (1 + 2 * s) * (1 - s) ** 2, s * (1 - s) ** 2
        h01, h11 = s * s * (3 - 2 * s), s * s * (s - 1)
        p0, p1, m0, m1 = self.rho[j], self.rho[j + 1], self.drho_du[j], self.drho_du[j + 1]
        rho = h00 * p0 + h10 * self.du * m0 + h01 * p1 + h11 * self.du * m1
        # derivative of the interpolant with respect to ln r, then r
        d00, d10 = 6 * s * s - 6 * s, 3 * s * s - 4 * s + 1
        d01, d11 = -6 * s * s + 6 * s, 3 * s * s - 2 * s
        drho = (d00 * p0 / self.du + d10 * m0 + d01 * p1 / self.du + d11 * m1) / r[:, None]
        return rho, drho
