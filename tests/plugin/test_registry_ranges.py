"""The plugin's valid ranges as Python reads them (mitsuba_powder.plugin.registry.INTERVALS,
exported by _optics.property_intervals from powder_registry.h) are the ranges the plugin
itself refuses values outside of: at each end of every numeric property, mi.load_dict
accepts the value just inside and refuses the value just outside (a closed end is compared
in single precision: just outside is the next float32)."""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest

from mitsuba_powder.plugin import registry
from mitsuba_powder.variants import use_variant

#: What a property needs beside it to load (the other property of a second population, the
#: grain model of the agglomerate properties, the other half of a complex index)
CONTEXT = {
    "radius2": {"fraction2": 0.5}, "fraction2": {"radius2": 0.5},
    # (the other fractions 0, so that each fraction reaches 1)
    "radius3": {"radius2": 0.5, "fraction2": 0.2, "fraction3": 0.2},
    "fraction3": {"radius2": 0.5, "fraction2": 0.0, "radius3": 0.5},
    "radius4": {"radius2": 0.5, "fraction2": 0.2, "radius3": 0.5, "fraction3": 0.2,
                "fraction4": 0.2},
    "fraction4": {"radius2": 0.5, "fraction2": 0.0, "radius3": 0.5, "fraction3": 0.0,
                  "radius4": 0.5},
    "agglomerate_radius": {"grains": "agglomerate"},
    "agglomerate_fill": {"grains": "agglomerate", "agglomerate_radius": 1.0},
    "eta": {"k": 0.01}, "k": {"eta": 1.5},
}

#: Grain sizes just inside their range's lower end 0 are refused by another rule, with its own
#: message (the Mie tables' size parameter 2 pi r / lambda >= 1e-3): their value inside
GRAIN_SIZE_INSIDE = 0.01


def _ends(interval: registry.Interval, name: str) -> list[tuple[str, float, bool]]:
    """(which end, value, accepted) just inside and just outside each end."""
    out = []
    for side, end, closed, toward in (("lower", interval.lower, interval.lower_closed, -1),
                                      ("upper", interval.upper, interval.upper_closed, 1)):
        if side == "lower" and name in ("radius", "radius2", "radius3", "radius4",
                                        "agglomerate_radius"):
            out += [("lower inside", GRAIN_SIZE_INSIDE, True), ("lower outside", end, False)]
            continue
        if math.isinf(end):
            inside = end if closed else math.copysign(10.0, end)
            outside = None if closed else end
        elif closed:
            inside = end
            outside = float(np.nextafter(np.float32(end), np.float32(toward * math.inf)))
        else:
            inside = end - toward * 1e-6 * max(1.0, abs(end))
            outside = end
        out.append((f"{side} inside", inside, True))
        if outside is not None:
            out.append((f"{side} outside", outside, False))
    return out


CASES = [(name, *end) for name, interval in registry.INTERVALS.items()
         for end in _ends(interval, name)]


def test_every_numeric_property_has_an_interval():
    assert set(registry.INTERVALS) == set(registry.RANGES)
    for name, interval in registry.INTERVALS.items():
        assert (interval.lower, interval.upper) == registry.RANGES[name]
        assert str(interval)[0] in "[(" and str(interval)[-1] in ")]"


@pytest.mark.parametrize("name, where, value, accepted", CASES,
                         ids=[f"{c[0]}-{c[1]}" for c in CASES])
def test_exported_ranges_are_the_plugin_s_refusals(name, where, value, accepted):
    interval = registry.INTERVALS[name]
    assert bool(interval.contains(value)) is accepted, (name, where, value, str(interval))
    props = {"type": "powder", **CONTEXT.get(name, {}), name: value}
    with use_variant("scalar_rgb"):
        if accepted:
            mi.load_dict(props)
        else:
            with pytest.raises(Exception, match=f"{name}.* is out of range; valid range is "
                                                f"{_escaped(str(interval))}"):
                mi.load_dict(props)


def _escaped(text: str) -> str:
    import re

    return re.escape(text)


def test_contains_refuses_nan_and_compares_closed_ends_in_single_precision():
    sigma = registry.INTERVALS["sigma"]  # (0, pi/2]
    assert not sigma.contains(float("nan"))
    assert sigma.contains(math.pi / 2 * (1 + 1e-9))  # rounds to the float32 end
    assert not sigma.contains(0.0)
    np.testing.assert_array_equal(registry.INTERVALS["g"].contains([-1.0, 0.0, 1.0]),
                                  [False, True, False])
