"""Bad input: a clear error naming the property, its value and the valid range."""

from __future__ import annotations

import math

import mitsuba as mi
import pytest

from helpers import use_variant

GOOD = {"type": "powder", "albedo": 0.5}

CASES = [
    # (property, bad value, fragments the message must contain)
    ("g", 1.0, ['"g"', "= 1", "(-1, 1)"]),
    ("g", -1.5, ['"g"', "= -1.5", "(-1, 1)"]),
    ("g", math.nan, ['"g"', "nan", "(-1, 1)"]),
    ("extinction", -2.0, ['"extinction"', "= -2", "(0, inf)"]),
    ("extinction", 0.0, ['"extinction"', "= 0", "(0, inf)"]),
    ("amplitude_volume", -0.1, ['"amplitude_volume"', "= -0.1", "[0, inf)"]),
    ("tau_o", -1.0, ['"tau_o"', "= -1", "[0, inf)"]),
    ("thickness", -3.0, ['"thickness"', "= -3", "[0, inf]"]),
    ("amplitude_surface", -1e-3, ['"amplitude_surface"', "= -0.001", "[0, inf)"]),
    ("correlation_length", 0.0, ['"correlation_length"', "= 0", "(0, inf)"]),
    ("sigma", 2.0, ['"sigma"', "= 2", "(0, 1.5708]"]),
    ("sigma", -0.1, ['"sigma"', "= -0.1", "(0, 1.5708]"]),
    ("wavelength", -700.0, ['"wavelength"', "= -700", "(0, inf)"]),
    ("specular", "phong", ['"specular"', '"phong"', "harvey_shack", "gaussian"]),
    ("lobes", "single,glossy", ['"lobes"', '"glossy"', "single, multiple, coherent, surface"]),
    ("lobes", " , ", ['"lobes"', "names no lobe"]),
    ("rgb_wavelengths", "611, 549", ['"rgb_wavelengths"', "exactly 3", "got 2"]),
    ("rgb_wavelengths", "611, 549, 464, 400", ['"rgb_wavelengths"', "exactly 3", "got 4"]),
    ("rgb_wavelengths", "611, red, 464", ['"rgb_wavelengths"', '"red" is not a number']),
    ("rgb_wavelengths", "611, -549, 464", ['"rgb_wavelengths"', "-549", "(0, inf)"]),
    ("albedo", 1.5, ['"albedo"', "1.5", "[0, 1]"]),
]


@pytest.mark.parametrize("variant", ["scalar_rgb", "llvm_ad_rgb"])
@pytest.mark.parametrize("prop,value,fragments", CASES,
                         ids=[f"{c[0]}={c[1]!r}" for c in CASES])
def test_bad_property_is_rejected_at_load(variant, prop, value, fragments):
    use_variant(variant)
    with pytest.raises(RuntimeError) as info:
        mi.load_dict({**GOOD, prop: value})
    msg = str(info.value)
    for fragment in fragments:
        assert fragment in msg, msg


def test_rgb_wavelengths_as_list_is_accepted_and_checked():
    use_variant("scalar_rgb")
    bsdf = mi.load_dict({**GOOD, "rgb_wavelengths": [600.0, 550.0, 450.0]})
    assert "600, 550, 450" in str(bsdf)
    with pytest.raises(RuntimeError, match='"rgb_wavelengths".*-550'):
        mi.load_dict({**GOOD, "rgb_wavelengths": [600.0, -550.0, 450.0]})


def test_albedo_is_required_until_mie_lands():
    use_variant("scalar_rgb")
    with pytest.raises(RuntimeError, match='"albedo" is required'):
        mi.load_dict({"type": "powder"})


def test_unknown_property_is_rejected():
    use_variant("scalar_rgb")
    with pytest.raises(RuntimeError, match="extintion"):
        mi.load_dict({**GOOD, "extintion": 1.0})


@pytest.mark.parametrize("key,value,fragment", [
    ("g", 1.2, '"g" = 1.2'),
    ("extinction", -1.0, '"extinction" = -1'),
    ("tau_o", -0.5, '"tau_o" = -0.5'),
    ("correlation_length", 0.0, '"correlation_length" = 0'),
])
def test_bad_value_through_traverse_is_rejected(key, value, fragment):
    use_variant("llvm_ad_rgb")
    params = mi.traverse(mi.load_dict(GOOD))
    params[key] = mi.Float(value)
    with pytest.raises(RuntimeError) as info:
        params.update()
    assert fragment in str(info.value)
