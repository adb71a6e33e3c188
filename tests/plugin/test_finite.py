"""Inputs the plugin took wrongly (found by trying to break it, issue 33): an albedo with a grain
size (silently ignored; now an error, as the grain model is), integers where floats are taken
(an integer ``k`` was refused; now accepted wherever a float is)."""

from __future__ import annotations

import mitsuba as mi
import pytest

from helpers import use_variant
from mitsuba_powder import _optics

VARIANTS = ["scalar_rgb", "llvm_ad_rgb"]
RANGES = _optics.property_ranges()

@pytest.mark.parametrize("name,value", [("radius", 3.0), ("radius2", 0.5), ("fraction2", 0.3)])
def test_albedo_with_a_grain_size_is_an_error(name, value):
    """A given albedo replaces the grains: their size is an error beside it, as the grain
    model is (it was ignored)."""
    use_variant("scalar_rgb")
    with pytest.raises(RuntimeError, match=f'property "{name}" has no effect together with '
                                           '"albedo"'):
        mi.load_dict({"type": "powder", "albedo": 0.5, name: value})


#: an integer inside the range of every numeric property, and what it needs beside it
INTEGERS = {
    "amplitude_volume": (2, {}), "g": (0, {}), "extinction": (3, {}), "tau_o": (1, {}),
    "thickness": (5, {}), "amplitude_surface": (0, {}), "correlation_length": (2, {}),
    "sigma": (1, {"specular": "gaussian"}), "radius": (1, {}),
    "radius2": (1, {"fraction2": 0}), "fraction2": (1, {"radius2": 0.5}),
    "agglomerate_radius": (1, {"grains": "agglomerate"}),
    "agglomerate_fill": (1, {"grains": "agglomerate", "agglomerate_radius": 0.5}),
    "wavelength": (600, {}), "eta": (2, {"k": 0.5}), "k": (0, {"eta": 2.5}),
}


def test_integers_cover_every_numeric_property():
    assert set(INTEGERS) == set(RANGES)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("name", sorted(INTEGERS))
def test_integers_are_accepted_wherever_floats_are(variant, name):
    """An integer is the float of the same value: the powder prints the same (an integer k
    was refused as "must be a float or a spectrum")."""
    use_variant(variant)
    value, context = INTEGERS[name]
    assert isinstance(value, int)
    as_int = mi.load_dict({"type": "powder", **context, name: value})
    as_float = mi.load_dict({"type": "powder", **context, name: float(value)})
    assert str(as_int) == str(as_float)


@pytest.mark.parametrize("variant", VARIANTS)
def test_integers_in_spectra_textures_and_lists(variant):
    use_variant(variant)
    pairs = {"eta": {"type": "spectrum", "value": [(400, 2), (700, 3)]},
             "k": {"type": "spectrum", "value": [(400, 0), (700, 1)]}}
    float_pairs = {n: {"type": "spectrum", "value": [(float(a), float(b)) for a, b in v["value"]]}
                   for n, v in pairs.items()}
    assert str(mi.load_dict({"type": "powder", **pairs})) == \
        str(mi.load_dict({"type": "powder", **float_pairs}))
    for albedo in (1, {"type": "uniform", "value": 1}, {"type": "rgb", "value": [1, 0, 1]}):
        mi.load_dict({"type": "powder", "albedo": albedo, "tau_o": 0})
    assert str(mi.load_dict({"type": "powder", "rgb_wavelengths": [600, 550, 450]})) == \
        str(mi.load_dict({"type": "powder", "rgb_wavelengths": "600, 550, 450"}))
