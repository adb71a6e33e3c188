"""The plugin's property registry as Python sees it: defaults, ranges, built-in materials and
grain models, read from the C++ tables the plugin itself parses with
(``src/bsdfs/powder_registry.h``, through :mod:`mitsuba_powder._optics`), so that no rule or
default of the plugin is written a second time in Python.

Sizes are in micrometres, as the plugin's properties.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .. import _optics
from .._checks import interval_text, out_of_range

__all__ = ["ALBEDO_INTERVAL", "DEFAULTS", "DENSITIES", "GRAIN_MODELS", "GRAIN_SIZES",
           "GRAIN_VARIABLES", "INTERVALS", "Interval", "MATERIALS", "MAX_POPULATIONS", "RANGES",
           "check_grain_model", "check_value", "grain_size", "interval", "material_files",
           "second_population"]


@dataclass(frozen=True)
class Interval:
    """A property's valid values as the plugin checks them (``Range`` of
    ``powder_registry.h``): ``lower`` to ``upper``, each end closed or open."""

    lower: float
    upper: float
    lower_closed: bool
    upper_closed: bool

    @property
    def brackets(self) -> str:
        """``"[)"``, ``"()"``, ``"[]"`` or ``"(]"``."""
        return ("[" if self.lower_closed else "(") + ("]" if self.upper_closed else ")")

    def __str__(self) -> str:
        """As the messages write it, e.g. ``[0, inf)``."""
        return interval_text(self.lower, self.upper, self.brackets)

    def contains(self, values) -> np.ndarray:
        """bool of ``values`` (any shape) inside, as the plugin's ``Range::contains``: never
        NaN, closed ends compared in single precision (the plugin stores floats), open ends
        in double."""
        v = np.asarray(values, dtype=np.float64)
        v32 = v.astype(np.float32)
        lower = (v32 >= np.float32(self.lower)) if self.lower_closed else (v > self.lower)
        upper = (v32 <= np.float32(self.upper)) if self.upper_closed else (v < self.upper)
        return ~np.isnan(v) & lower & upper


_PACKAGE = Path(__file__).resolve().parents[1]

#: {property: default} of every plugin property that has one (numbers and strings)
DEFAULTS: dict[str, float | str] = dict(_optics.property_defaults())
#: {property: (lower, upper)} valid range of every numeric property
RANGES: dict[str, tuple[float, float]] = dict(_optics.property_ranges())
#: {property: Interval} valid range of every numeric property, with its open or closed ends
INTERVALS: dict[str, Interval] = {name: Interval(*ends)
                                  for name, ends in _optics.property_intervals().items()}
#: the albedo's valid range (rho, per channel or wavelength; checked by the plugin's
#: ``powder_textures.h``, not in its table of float parameters)
ALBEDO_INTERVAL = Interval(0.0, 1.0, True, True)


def interval(name: str) -> Interval | None:
    """The valid range of numeric property ``name`` (:data:`INTERVALS`, the albedo's
    :data:`ALBEDO_INTERVAL`), or None for a property without one (strings)."""
    return ALBEDO_INTERVAL if name == "albedo" else INTERVALS.get(name)


def check_value(name: str, value, what: str = "") -> float:
    """``value`` as a float, if it lies in the plugin's valid range of property ``name``
    (:func:`interval`); else ``ValueError`` naming it, its value and the range (the plugin's
    own rule: :meth:`Interval.contains`).

    Args:
        name: a numeric plugin property.
        value: a number (or its text).
        what: how the value was given, written before the name (e.g. ``"--set "``).
    """
    valid = interval(name)
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{what}{name} = {value!r} is not a number") from None
    if valid is not None and not bool(valid.contains(v)):
        raise ValueError(out_of_range(f"{what}{name} = {value!r}", str(valid)))
    return v


#: names of the built-in grain materials (the ``material`` property)
MATERIALS: tuple[str, ...] = tuple(_optics.materials())
#: {built-in material: density in g/cm^3} (mass to volume fractions; measurements/README.md)
DENSITIES: dict[str, float] = dict(_optics.material_densities())
#: the most grain populations of a powder (population j = 2..4: radius{j}, fraction{j},
#: material{j} or eta{j} and k{j}; docs/model.md, "Several materials")
MAX_POPULATIONS = 4
#: {grain model: {"size", "allowed", "required", "two_populations"}} (the ``grains`` property)
GRAIN_MODELS: dict[str, dict] = {name: dict(rules)
                                 for name, rules in _optics.grain_models().items()}
#: the per-grain size property of some grain model, in the models' order
GRAIN_SIZES: tuple[str, ...] = tuple(dict.fromkeys(r["size"] for r in GRAIN_MODELS.values()))
#: the numeric grain properties of every model, in the order of the derivative columns of
#: ``_optics.albedo_table`` (each model's allowed properties in turn, numbers only)
GRAIN_VARIABLES: tuple[str, ...] = tuple(dict.fromkeys(
    name for rules in GRAIN_MODELS.values() for name in rules["allowed"] if name in RANGES))
#: the properties of a second grain population
SECOND_POPULATION = ("radius2", "fraction2")
#: the properties of grain populations 2..4 (docs/model.md, "Several materials")
POPULATIONS = SECOND_POPULATION + ("radius3", "fraction3", "radius4", "fraction4") + tuple(
    f"{k}{j}" for j in range(2, MAX_POPULATIONS + 1) for k in ("material", "eta", "k"))


def material_files(material: str) -> list[Path]:
    """The optical-constant files of a built-in material (several: an orientation average).

    Raises:
        ValueError: ``material`` is not built in.
    """
    files = _optics.material_files()
    if material not in files:
        raise ValueError(f"material = {material!r} is not built in; built-in materials are "
                         f"{', '.join(MATERIALS)}")
    return [_PACKAGE / f for f in files[material]]


def grain_size(grains: str) -> str:
    """The property holding the size of one grain of model ``grains`` (``radius`` or
    ``agglomerate_radius``).

    Raises:
        ValueError: an unknown grain model.
    """
    if grains not in GRAIN_MODELS:
        raise ValueError(f"grains = {grains!r} is not valid; valid values are "
                         f"{', '.join(GRAIN_MODELS)}")
    return GRAIN_MODELS[grains]["size"]


def second_population(grains: str) -> bool:
    """Whether grains of model ``grains`` may have a second population (radius2, fraction2)."""
    return bool(GRAIN_MODELS[grains]["two_populations"])


def check_grain_model(grains: str, used: Iterable[str], free: Iterable[str] = ()) -> None:
    """The grain properties a model takes, as the plugin's constructor checks them; ``used``:
    every property given (free or fixed), ``free``: those to be fitted (a model's crystallite
    ``radius`` that does not enter the albedo cannot be).

    Raises:
        ValueError: a property of another model, a required one missing, a fitted radius
            that is not the grain size, or a second population where the model has one.
    """
    if grains not in GRAIN_MODELS:
        return  # the grain optics name the valid models
    rules, used, free = GRAIN_MODELS[grains], set(used), set(free)
    grain_properties = dict.fromkeys(
        name for r in GRAIN_MODELS.values() for name in r["allowed"])
    extra = [n for n in grain_properties if n in used and n not in rules["allowed"]
             and n not in SECOND_POPULATION]
    if extra:
        owner = next(m for m, r in GRAIN_MODELS.items() if extra[0] in r["allowed"])
        raise ValueError(f"{extra} are used only with grains = {owner!r} (grains = "
                         f"{grains!r}); set grains={owner}")
    missing = [n for n in rules["required"] if n not in used]
    if missing:
        raise ValueError(f"grains = {grains!r} needs {', '.join(missing)} (free or fixed, um)")
    size = rules["size"]
    if size != "radius" and "radius" in free:
        others = [n for n in rules["allowed"] if n not in ("radius", size) and n in RANGES]
        raise ValueError(f"radius is the crystallite radius with grains = {grains!r} and "
                         f"does not enter the albedo: fit {size} (and {' and '.join(others)}) "
                         "instead")
    two = [n for n in POPULATIONS if n in used]
    if two and not rules["two_populations"]:
        raise ValueError(f"{two} cannot be used with grains = {grains!r} (one population)")
