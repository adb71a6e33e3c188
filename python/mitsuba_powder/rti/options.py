"""The options of a per-pixel RTI fit, checked once: :func:`fit_options` -> :class:`FitOptions`.

:func:`~mitsuba_powder.rti.fit_maps` and the command ``fit-maps`` build the same frozen
:class:`FitOptions`, here, before the capture is read; the fit's plan
(:mod:`mitsuba_powder.rti.plan`) and the tiles (:mod:`mitsuba_powder.rti.tiles`) take it as it
is. What can only be checked against the capture (its images and lights, the mask, per-pixel
held maps, the initial gains' count, a light distance against the image's half-diagonal) is
checked once by :func:`mitsuba_powder.rti.inputs.check_inputs`. Every message names an option
as its caller does (``names``: the command line gives some of its flags).
"""

from __future__ import annotations

import math
import warnings
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from .._checks import check_range
from .blocks import check_memory, lanes_within
from .checks import check_count
from .forward import MAX_LANES, VARIANT, check_rgb_variant
from .gains import GAIN_PIXELS, GainPolicy, gain_policy
from .lights import parse_light_distance
from .properties import (
    FREE_PROPERTIES,
    GRAIN_MAPS,
    MAP_DEFAULT_FREE,
    MAP_PROPERTIES,
    grain_map_name,
)
from .solvers import SOLVERS

__all__ = ["DEFAULTS", "FitOptions", "RENAMED", "SHADOWS", "check_exposure", "check_free",
           "fit_options"]

#: Every option of a fit and its default (:func:`fit_options`)
DEFAULTS: dict[str, object] = {
    "free": None, "fixed": None, "gains": "fixed", "initial_gains": None, "gain_trend": None,
    "gain_subsample": GAIN_PIXELS, "seed": 0, "light_distance": math.inf,
    "max_iterations": 30, "rounds": 3, "saturation": 0.99, "shadow_ratio": 0.5,
    "shadow_floor": 0.03, "solver": "drjit", "variant": VARIANT, "max_lanes": MAX_LANES,
    "memory_gb": None, "exposure": None, "shadows": "auto", "light_size": 0.5,
    "full_scale": math.inf,
}

#: What :attr:`FitOptions.shadows` may be
SHADOWS = ("auto", "relief", "ratio")

#: Options renamed (old name -> new name): the old names work for one release, with a
#: DeprecationWarning
RENAMED = {"gain_model": "gain_trend", "gain_pixels": "gain_subsample"}


@dataclass(frozen=True, eq=False)
class FitOptions:
    """The checked options of a per-pixel RTI fit (build them with :func:`fit_options`).

    Attributes:
        free: properties fitted per pixel besides the normal: ``albedo`` (3 channels), a grain
            size of :data:`~mitsuba_powder.rti.properties.GRAIN_MAPS` instead of the albedo,
            and any of :data:`~mitsuba_powder.rti.properties.MAP_PROPERTIES`; at most 10
            numbers per pixel (normal 2 + albedo 3 + 5 more). Not given: the default set
            (:data:`~mitsuba_powder.rti.properties.MAP_DEFAULT_FREE`) less the properties
            held in ``fixed``, chosen by cross-validation.
        fixed: plugin properties held: numbers or (H, W) maps of
            :data:`~mitsuba_powder.rti.properties.MAP_PROPERTIES` (not free), ``albedo`` as
            (3,) or (H, W, 3) when not free, and settings (``lobes``, ``specular``,
            ``material``, ``rgb_wavelengths``, ...). Their values are checked against the
            capture (:func:`~mitsuba_powder.rti.inputs.check_inputs`).
        gains: how the per-light gains are found (:class:`~mitsuba_powder.rti.gains.GainPolicy`:
            fitted or held, their start, their trend, the subsample they are fitted on).
        light_distance: the lights' distance from the image's centre in image widths
            (:mod:`mitsuba_powder.rti.lights`): ``inf`` (distant lights), a number or (K,)
            beyond the image's half-diagonal, or ``"fit"`` (the plan's ``distance scan``).
        max_iterations: Levenberg-Marquardt iterations per round, >= 1.
        rounds: alternations of the per-pixel fit with the gains (and the shadow flags), >= 1;
            a final per-pixel fit follows the last gain update.
        saturation: observations with any channel >= this are left out, in (0, inf].
        shadow_ratio, shadow_floor: an observation is "shadowed" (left out) when its channel
            mean is below the model's prediction by more than ``max(shadow_ratio x predicted,
            shadow_floor)``; ratio in (0, 1], floor (linear units) >= 0.
        solver: the per-pixel solver, a key of :data:`~mitsuba_powder.rti.solvers.SOLVERS`.
        variant: an RGB variant (``llvm_ad_rgb``, ``cuda_ad_rgb``).
        max_lanes: pixels x lights per plugin evaluation (and per optimiser batch) at most,
            >= 1; lowered to the memory budget (:attr:`lanes`).
        memory_gb: working memory of the fit besides the images, GiB, > 0 (pixels are fitted
            in blocks that fit in it).
        exposure: one global scale of the gains (the lights' irradiance is ``exposure x``
            the initial gains): a number > 0 (given, e.g. from a reference target), ``"fit"``
            (the plan's ``exposure scan``, :mod:`mitsuba_powder.rti.exposure`) or None (fitted
            when no initial gains are given, else 1: the initial gains are the irradiances).
        shadows: ``auto`` (default): after the per-pixel fit the relief is integrated from
            its normals and kept where it relights held-out lights better: the held-out-light
            RMS with and without the relief's visibility, cross-validated over folds of the
            lights on a subsample of pixels, the relief kept when it lowers the held-out
            squared residuals of the pixels it shades by more than
            :data:`~mitsuba_powder.rti.selection.SHADOW_Z` standard errors
            (:func:`~mitsuba_powder.rti.selection.choose_shadows`), then as ``relief``,
            else as ``ratio``. ``relief``: the relief always (the pixels it shades fitted
            again with each light's visibility over it: observations below the horizon
            left out, the
            soft edge in the model; then the ratio test). ``ratio``: the ratio test only,
            no relief in the fit.
        light_size: the lights' angular radius, degrees in [0, 45]: the soft edge of cast
            shadows (visibility 0.5 where the horizon cuts the light's centre).
        full_scale: the largest linear value the capture's files record, > 0: 1 for PNG and
            JPEG, ``inf`` (the default) for EXR and arrays
            (:attr:`~mitsuba_powder.rti.capture.Capture.full_scale`; the command line sets it
            from the files). The cross-validations (free set, exposure, shadows) score the
            held-out predictions as such a file records them: at most ``full_scale``, as
            ``compare-maps`` scores them.
        names: how messages name the options (e.g. ``{"memory_gb": "--memory-gb"}``).
        given: the options as the caller gave them (before defaults), for the records.
    """

    free: tuple[str, ...]
    fixed: dict
    gains: GainPolicy
    light_distance: float | np.ndarray | str
    max_iterations: int
    rounds: int
    saturation: float
    shadow_ratio: float
    shadow_floor: float
    solver: str
    variant: str
    max_lanes: int
    memory_gb: float
    exposure: float | str | None = None
    shadows: str = "auto"
    light_size: float = 0.5
    full_scale: float = math.inf
    names: dict = field(default_factory=dict)
    given: dict = field(default_factory=dict)

    def name(self, option: str) -> str:
        """How messages name ``option``."""
        return self.names.get(option, option)

    def replace(self, **changes) -> FitOptions:
        """These options with ``changes`` (values already checked, e.g. held gains)."""
        return replace(self, **changes)

    @property
    def fits_exposure(self) -> bool:
        """Whether the fit finds the exposure (``"fit"``, or None without initial gains)."""
        return self.exposure == "fit" or (self.exposure is None and self.gains.initial is None)

    @property
    def chooses_free(self) -> bool:
        """Whether the fit chooses its free set by cross-validation (``free`` not given and
        the albedo free: :mod:`mitsuba_powder.rti.selection`)."""
        return self.given.get("free") is None and "albedo" in self.free

    @property
    def lanes(self) -> int:
        """:attr:`max_lanes` within the memory budget
        (:func:`~mitsuba_powder.rti.blocks.lanes_within`)."""
        return lanes_within(self.memory_gb, self.max_lanes)

    @property
    def grain_name(self) -> str:
        """The per-pixel grain size of the held settings (``radius`` or
        ``agglomerate_radius``)."""
        return grain_map_name(self.fixed)

    @property
    def others(self) -> list[str]:
        """The free properties that are neither the albedo nor a grain size."""
        return [n for n in self.free if n != "albedo" and n not in GRAIN_MAPS]

    @property
    def settings(self) -> dict:
        """The plugin properties held for every pixel (not maps, albedo or the grain size)."""
        return {n: v for n, v in self.fixed.items()
                if n not in MAP_PROPERTIES and n != "albedo" and n != self.grain_name}

    @property
    def albedo_from_grains(self) -> bool:
        """Whether the grains (a free or held grain size) set the albedo per pixel."""
        return self.grain_name in self.free or self.grain_name in self.fixed


def fit_options(names: Mapping[str, str] | None = None, **given) -> FitOptions:
    """The options of a fit (:data:`DEFAULTS`, meanings: :class:`FitOptions`), checked.

    Args:
        names: how messages name the options (default: their names here).
        given: ``free``, ``fixed``, ``gains`` (``fixed``, the default: the initial gains held;
            ``fit``: fitted with the maps), ``initial_gains`` ((K,)
            start or held values, > 0), ``gain_trend`` (a
            :class:`~mitsuba_powder.rti.gains.GainTrend`), ``gain_subsample`` (pixels the gains
            are fitted on, >= 1, or None: every pixel), ``seed`` (of that subsample, >= 0),
            ``light_distance``, ``max_iterations``, ``rounds``, ``saturation``,
            ``shadow_ratio``, ``shadow_floor``, ``solver``, ``variant``, ``max_lanes``,
            ``memory_gb`` (None: :func:`~mitsuba_powder.rti.blocks.default_memory_gb`),
            ``exposure`` (a number > 0, ``"fit"`` or None),
            ``shadows`` (``auto``, ``relief`` or ``ratio``), ``light_size`` (degrees),
            ``full_scale`` (the largest value the files record, > 0; ``inf``: EXR).

    Raises:
        ValueError: an unknown option or a value out of its range (named as ``names`` says).
    """
    names = dict(names or {})
    given = _renamed(given, names)
    unknown = sorted(set(given) - set(DEFAULTS))
    if unknown:
        raise ValueError(f"fit option(s) {unknown} are not fit_maps options; valid are "
                         f"{sorted(DEFAULTS)}")
    o = {**DEFAULTS, **given}

    def name(option: str) -> str:
        return names.get(option, option)

    variant = check_rgb_variant(o["variant"])
    fixed = dict(o["fixed"] or {})
    free = check_free(o["free"], name("free"))
    if o["free"] is None:   # the default set, less what the caller holds
        free = [n for n in free if n not in fixed]
    _check_held_names(free, fixed, name("free"))
    policy = gain_policy(o["gains"], o["initial_gains"], o["gain_trend"], o["gain_subsample"],
                         o["seed"], name)
    if o["solver"] not in SOLVERS:
        raise ValueError(f"{name('solver')} = {o['solver']!r} is not a solver; choose one of "
                         f"{tuple(SOLVERS)}")
    if o["shadows"] not in SHADOWS:
        raise ValueError(f"{name('shadows')} = {o['shadows']!r}; valid values are {SHADOWS}")
    return FitOptions(
        free=tuple(free), fixed=fixed, gains=policy,
        light_distance=parse_light_distance(o["light_distance"], name("light_distance")),
        max_iterations=check_count(name("max_iterations"), o["max_iterations"], 1),
        rounds=check_count(name("rounds"), o["rounds"], 1),
        saturation=check_range(name("saturation"), o["saturation"], 0.0, math.inf, "(]"),
        shadow_ratio=check_range(name("shadow_ratio"), o["shadow_ratio"], 0.0, 1.0, "(]"),
        shadow_floor=check_range(name("shadow_floor"), o["shadow_floor"], 0.0, math.inf,
                                 "[]"),
        solver=o["solver"], variant=variant,
        max_lanes=check_count(name("max_lanes"), o["max_lanes"], 1),
        memory_gb=check_memory(o["memory_gb"], name("memory_gb")),
        exposure=check_exposure(o["exposure"], name("exposure")), shadows=o["shadows"],
        light_size=check_range(name("light_size"), o["light_size"], 0.0, 45.0, "[]",
                               unit="degrees"),
        full_scale=check_range(name("full_scale"), o["full_scale"], 0.0, math.inf, "(]"),
        names=names, given=given)


def check_exposure(value, name: str = "exposure") -> float | str | None:
    """An exposure option: None, ``"fit"`` or a number > 0 (finite)."""
    if value is None or value == "fit":
        return value
    return check_range(name, value, 0.0, math.inf, "()",
                       note="(the lights' irradiance scale), or 'fit'")


def _renamed(given: dict, names: dict) -> dict:
    """``given`` with the old names of :data:`RENAMED` replaced (a DeprecationWarning each);
    messages then name the option as the caller did."""
    out = dict(given)
    for old, new in RENAMED.items():
        if old not in out:
            continue
        if new in out:
            raise ValueError(f"{old} and {new} are the same option ({old} is its old name); "
                             f"give {new} only")
        warnings.warn(f"fit option {old} is renamed {new}; the old name goes in the next "
                      "release", DeprecationWarning, stacklevel=4)
        out[new] = out.pop(old)
        names.setdefault(new, names.get(old, old))
    return out


def check_free(free: Sequence[str] | None, name: str = "free") -> list[str]:
    """The free properties (default :data:`MAP_DEFAULT_FREE`), checked."""
    free = list(MAP_DEFAULT_FREE if free is None else free)
    for prop in free:
        if prop not in FREE_PROPERTIES:
            raise ValueError(f"free property {prop!r} is not fittable per pixel; choose among "
                             f"{list(FREE_PROPERTIES)}")
    if len(set(free)) != len(free):
        raise ValueError(f"{name} = {free} names a property twice")
    n_par = 2 + sum(3 if n == "albedo" else 1 for n in free)
    if n_par > 10:
        raise ValueError(f"{name} = {free} gives {n_par} numbers per pixel; valid range is at "
                         "most 10 (normal 2 + albedo 3 + 5)")
    return free


def _check_held_names(free: Sequence[str], fixed: Mapping, name: str = "free") -> None:
    """The free and held properties together: none both free and held, a free grain size that
    is the grain model's, the albedo from the grains or free or held (exactly one)."""
    for prop in free:
        if prop in fixed:
            value = fixed[prop]
            held = repr(value) if np.ndim(value) == 0 else f"a {np.shape(value)} map"
            raise ValueError(f"property {prop!r} is both free and fixed ({name} = {list(free)} "
                             f"names it and it is held at {held}); leave it out of {name} to "
                             "hold it")
    grain_name = grain_map_name(fixed)
    wrong = [n for n in GRAIN_MAPS if n in free and n != grain_name]
    if wrong:
        raise ValueError(f"{wrong[0]} cannot be free with grains = "
                         f"{fixed.get('grains', 'sphere')!r}; free {grain_name} instead")
    grains = grain_name in free or grain_name in fixed
    if grains and ("albedo" in free or "albedo" in fixed):
        raise ValueError(f"albedo and {grain_name} cannot both be given: the grains set the "
                         "albedo per pixel; free or fix one of them")
    if not grains and "albedo" not in free and "albedo" not in fixed:
        raise ValueError(f"albedo is neither free nor fixed; give fixed={{'albedo': ...}} "
                         f"or free (or fix) the grain size {grain_name}")
