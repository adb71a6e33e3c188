"""The checked inputs of a per-pixel RTI fit (:class:`FitData`, :func:`set_up`): images,
lights, free and held properties, options, the pixels to fit and their observations."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from .checks import check_count, check_directions, check_gains, check_images, check_range
from .forward import near_field
from .gains import GainOptions
from .properties import (
    FREE_PROPERTIES,
    GRAIN_MAPS,
    MAP_DEFAULT_FREE,
    MAP_PROPERTIES,
    GrainAlbedo,
    grain_map_name,
    property_map,
)

__all__ = ["GAIN_MODES", "SOLVERS", "FitData", "check_free", "check_mask", "check_options",
           "set_up"]

#: Gain modes of :func:`~mitsuba_powder.rti.fit.fit_maps`
GAIN_MODES = ("fit", "fixed")

#: Per-pixel solvers of :func:`~mitsuba_powder.rti.fit.fit_maps`: the Dr.Jit engine
#: (:mod:`mitsuba_powder.rti.engine`) and the NumPy reference
#: (:func:`mitsuba_powder.fitting.optimise.batch_levenberg_marquardt`)
SOLVERS = ("drjit", "numpy")



@dataclass
class FitData:
    """The checked inputs of a fit, restricted to the masked pixels (P of them)."""

    obs: np.ndarray                    # (P, K, 3) float32 observations
    d: np.ndarray                      # (K, 3) unit vectors towards the lights
    mask: np.ndarray                   # (H, W) bool, the fitted pixels (P of them)
    free: list[str]                    # the free properties (besides the normal)
    others: list[str]                  # the free ones that are neither albedo nor grain size
    grain_name: str                    # the per-pixel grain size of the settings
    grain: GrainAlbedo | None          # the albedo of a free or fixed grain size
    fixed: dict                        # the held properties as given
    fixed_maps: dict[str, np.ndarray]  # held per-pixel float property -> (P,)
    fixed_albedo: np.ndarray | None    # (P, 3) when neither the albedo nor a grain size is free
    settings: dict                     # plugin properties held for every pixel
    gains: np.ndarray                  # (K,) initial gains
    scale: float                       # their mean: a calibration, not fitted
    gain_mode: str
    max_iterations: int
    rounds: int
    saturation: float
    shadow_ratio: float
    shadow_floor: float
    max_lanes: int
    gain_model: GainOptions = GainOptions()
    solver: str = "drjit"
    field: tuple[np.ndarray, np.ndarray] | None = None  # near-field lights: (P, K, 3), (P, K)
    light_distance: float | np.ndarray = math.inf        # r in image widths

    def lights(self, s: slice = slice(None)) -> np.ndarray:
        """The light directions of the pixels ``s``: (K, 3), or (P_s, K, 3) per pixel."""
        return self.d if self.field is None else self.field[0][s]

    def irradiance(self, s: slice = slice(None)) -> np.ndarray | None:
        """The irradiance factors (P_s, K) of the pixels ``s``; None for distant lights."""
        return None if self.field is None else self.field[1][s]

    def light_gains(self, gains: np.ndarray, s: slice = slice(None)) -> np.ndarray:
        """(1, K, 1) or (P_s, K, 1): the gains times the pixels' irradiance factors."""
        if self.field is None:
            return gains[None, :, None]
        return (gains[None, :] * self.field[1][s])[:, :, None]

    @property
    def saturated(self) -> np.ndarray:
        """(P, K): observations with a channel at or above the saturation level."""
        return np.any(self.obs >= self.saturation, axis=2)

    def flags(self, predicted: np.ndarray) -> np.ndarray:
        """Weights (P, K): 0 where saturated or where the observed channel mean is below the
        ``predicted`` one (P, K, 3) by more than ``max(shadow_ratio x predicted,
        shadow_floor)``."""
        obs = self.obs.mean(axis=2)
        pred = predicted.mean(axis=2)
        shadow = (pred - obs) > np.maximum(self.shadow_ratio * pred, self.shadow_floor)
        return (~self.saturated & ~shadow).astype(np.float64)


def check_free(free: Sequence[str] | None) -> list[str]:
    """The free properties (default :data:`MAP_DEFAULT_FREE`), checked."""
    free = list(MAP_DEFAULT_FREE if free is None else free)
    for name in free:
        if name not in FREE_PROPERTIES:
            raise ValueError(f"free property {name!r} is not fittable per pixel; choose among "
                             f"{list(FREE_PROPERTIES)}")
    if len(set(free)) != len(free):
        raise ValueError(f"free = {free} names a property twice")
    n_par = 2 + sum(3 if n == "albedo" else 1 for n in free)
    if n_par > 10:
        raise ValueError(f"free = {free} gives {n_par} numbers per pixel; valid range is at "
                         "most 10 (normal 2 + albedo 3 + 5)")
    return free


def check_options(gains: str, max_iterations: int, rounds: int, saturation: float,
                   shadow_ratio: float, shadow_floor: float, max_lanes: int,
                   solver: str = "drjit") -> dict:
    """The fit's scalar options, checked, by :class:`_FitData` field name."""
    if gains not in GAIN_MODES:
        raise ValueError(f"gains = {gains!r} is not a gain mode; choose one of {GAIN_MODES}")
    if solver not in SOLVERS:
        raise ValueError(f"solver = {solver!r} is not a solver; choose one of {SOLVERS}")
    return {"gain_mode": gains, "solver": solver,
            "max_iterations": check_count("max_iterations", max_iterations, 1),
            "rounds": check_count("rounds", rounds, 1),
            "saturation": check_range("saturation", saturation, 0.0, math.inf,
                                      open_lower=True),
            "shadow_ratio": check_range("shadow_ratio", shadow_ratio, 0.0, 1.0,
                                        open_lower=True),
            "shadow_floor": check_range("shadow_floor", shadow_floor, 0.0, math.inf),
            "max_lanes": check_count("max_lanes", max_lanes, 1)}


def check_mask(mask: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """The pixels to fit, bool (H, W) (default all); at least one."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise ValueError(f"mask has shape {mask.shape}; expected {shape}")
    mask = mask.astype(bool)
    if not mask.any():
        raise ValueError("mask selects no pixel; it needs at least one True")
    return mask


def _fixed_albedo(fixed: Mapping, free: Sequence[str], grain_name: str,
                  grain: GrainAlbedo | None, mask: np.ndarray) -> np.ndarray | None:
    """The held albedo of the masked pixels (P, 3): a fixed grain size's, or the fixed albedo;
    None when the albedo or the grain size is free."""
    shape = mask.shape
    if grain is not None and grain_name in fixed:
        return grain(property_map(grain_name, fixed[grain_name], shape)[mask])[0]
    if "albedo" in free or grain_name in free:
        return None
    if "albedo" not in fixed:
        raise ValueError(f"albedo is neither free nor fixed; give fixed={{'albedo': ...}} "
                         f"or free (or fix) the grain size {grain_name}")
    a = np.asarray(fixed["albedo"], dtype=np.float64)
    a = np.broadcast_to(a, shape + (3,)) if a.shape == (3,) else a
    if a.shape != shape + (3,):
        raise ValueError(f"fixed albedo has shape {a.shape}; expected (3,) or "
                         f"({shape[0]}, {shape[1]}, 3)")
    for c in range(3):
        property_map("albedo", a[..., c], shape)
    return a[mask]


def _held(fixed: Mapping | None, free: list[str], mask: np.ndarray) -> dict:
    """The held properties, checked against the free ones, by :class:`_FitData` field name:
    ``fixed``, ``fixed_maps``, ``grain_name``, ``settings``, ``grain``, ``fixed_albedo``."""
    fixed = dict(fixed or {})
    for name in free:
        if name in fixed:
            raise ValueError(f"property {name!r} is both free and fixed")
    fixed_maps = {n: property_map(n, v, mask.shape)[mask] for n, v in fixed.items()
                  if n in MAP_PROPERTIES}
    grain_name = grain_map_name(fixed)
    wrong = [n for n in GRAIN_MAPS if n in free and n != grain_name]
    if wrong:
        raise ValueError(f"{wrong[0]} cannot be free with grains = "
                         f"{fixed.get('grains', 'sphere')!r}; free {grain_name} instead")
    settings = {n: v for n, v in fixed.items()
                if n not in MAP_PROPERTIES and n != "albedo" and n != grain_name}
    grain = None
    if grain_name in free or grain_name in fixed:
        if "albedo" in free or "albedo" in fixed:
            raise ValueError(f"albedo and {grain_name} cannot both be given: the grains set the "
                             "albedo per pixel; free or fix one of them")
        grain = GrainAlbedo(grain_name, settings)
    return {"fixed": fixed, "fixed_maps": fixed_maps, "grain_name": grain_name,
            "settings": settings, "grain": grain,
            "fixed_albedo": _fixed_albedo(fixed, free, grain_name, grain, mask)}


def set_up(images: np.ndarray, directions: np.ndarray, free: Sequence[str] | None,
            mask: np.ndarray | None, fixed: Mapping | None, initial_gains: np.ndarray | None,
            options: Mapping, light_distance: float | np.ndarray = math.inf,
            pixels: np.ndarray | bool | None = None) -> FitData:
    """Check every input of :func:`~mitsuba_powder.rti.fit.fit_maps` (in the order of its
    arguments) and gather the observations of the masked pixels, or of ``pixels`` (bool
    (H, W), a subset of the mask: a block), or of none (``pixels=False``: a plan, whose
    ``mask`` is the whole mask)."""
    imgs = check_images(images)
    k, h, w, _ = imgs.shape
    d = check_directions(directions)
    if len(d) != k:
        raise ValueError(f"directions has {len(d)} rows for {k} images; expected one per image")
    free = check_free(free)
    checked = check_options(**options)
    g = check_gains(initial_gains, k)
    mask = check_mask(mask, (h, w))
    if pixels is False:
        sel = np.zeros_like(mask)
    else:
        sel = mask if pixels is None else mask & pixels
        mask = sel
    held = _held(fixed, free, sel)
    others = [n for n in free if n != "albedo" and n not in GRAIN_MAPS]
    obs = np.ascontiguousarray(imgs[:, sel].transpose(1, 0, 2), dtype=np.float32)
    return FitData(obs=obs, d=d, mask=mask, free=free, others=others, gains=g,
                    scale=float(np.mean(g)), **held, **checked,
                    field=near_field(d, light_distance, (h, w), sel),
                    light_distance=light_distance)
