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
    ("extinction", -2.0, ['"extinction"', "= -2", "[1e-08, inf)"]),
    ("extinction", 0.0, ['"extinction"', "= 0", "[1e-08, inf)"]),
    ("amplitude_volume", -0.1, ['"amplitude_volume"', "= -0.1", "[0, 1e+16]"]),
    ("tau_o", -1.0, ['"tau_o"', "= -1", "[0, 1e+20]"]),
    ("thickness", -3.0, ['"thickness"', "= -3", "[0, inf]"]),
    ("amplitude_surface", -1e-3, ['"amplitude_surface"', "= -0.001", "[0, 1e+06]"]),
    ("correlation_length", 0.0, ['"correlation_length"', "= 0", "(0, 1e+08]"]),
    ("sigma", 2.0, ['"sigma"', "= 2", "[1e-18, 1.5708]"]),
    ("sigma", -0.1, ['"sigma"', "= -0.1", "[1e-18, 1.5708]"]),
    ("wavelength", -700.0, ['"wavelength"', "= -700", "[1, 1e+06]"]),
    ("specular", "phong", ['"specular"', '"phong"', "harvey_shack", "gaussian"]),
    ("sampling", "uniform", ['"sampling"', '"uniform"', "lobes", "cosine"]),
    ("lobes", "single,glossy", ['"lobes"', '"glossy"', "single, multiple, coherent, surface"]),
    ("lobes", " , ", ['"lobes"', "names no lobe"]),
    ("rgb_wavelengths", "611, 549", ['"rgb_wavelengths"', "exactly 3", "got 2"]),
    ("rgb_wavelengths", "611, 549, 464, 400", ['"rgb_wavelengths"', "exactly 3", "got 4"]),
    ("rgb_wavelengths", "611, red, 464", ['"rgb_wavelengths"', '"red" is not a number']),
    ("rgb_wavelengths", "611, -549, 464", ['"rgb_wavelengths"', "-549", "[1, 1e+06]"]),
    ("albedo", 1.5, ['"albedo"', "1.5", "[0, 1]"]),
    ("albedo", -0.5, ['"albedo"', "minimum of -0.5", "[0, 1]"]),
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


GRAIN_CASES = [
    ({"radius": -0.1}, ['"radius"', "= -0.1", "(0, inf)"]),
    ({"radius": 0.0}, ['"radius"', "= 0", "(0, inf)"]),
    ({"radius": 30.0}, ['"radius" = 30', "size parameter", "[1e-3, 200]"]),
    ({"radius2": 0.5}, ['"radius2"', '"fraction2"', "got only \"radius2\""]),
    ({"fraction2": 0.5}, ['"radius2"', '"fraction2"', "got only \"fraction2\""]),
    ({"radius2": 0.5, "fraction2": 1.5}, ['"fraction2"', "= 1.5", "[0, 1]"]),
    ({"radius2": -1.0, "fraction2": 0.5}, ['"radius2"', "= -1", "(0, inf)"]),
    ({"material": "chalk"}, ['"material"', '"chalk"', "hematite", "magnetite", ".yml"]),
    ({"material": "missing.yml"}, ['cannot find "missing.yml"']),
    ({"eta": 2.5}, ['both "eta" and "k"', 'only "eta"']),
    ({"eta": -2.5, "k": 0.1}, ['"eta"', "= -2.5", "[0.001, 1000]"]),
    ({"eta": 2.5, "k": -0.1}, ['"k"', "= -0.1", "[0, 1000]"]),
    ({"eta": 2.5, "k": 0.1, "material": "hematite"}, ['either "material" or "eta"']),
]


@pytest.mark.parametrize("props,fragments", GRAIN_CASES,
                         ids=[",".join(f"{k}={v}" for k, v in c[0].items()) for c in GRAIN_CASES])
def test_bad_grain_property_is_rejected(props, fragments):
    use_variant("scalar_rgb")
    with pytest.raises(RuntimeError) as info:
        mi.load_dict({"type": "powder", **props})
    for fragment in fragments:
        assert fragment in str(info.value)


@pytest.mark.parametrize("variant", ["scalar_rgb", "llvm_ad_rgb", "llvm_ad_spectral"])
@pytest.mark.parametrize("value,fragment", [(1.5, "maximum of 1.5"), (-0.25, "minimum of -0.25")])
def test_albedo_out_of_range_through_traverse_is_rejected(variant, value, fragment):
    """An albedo edited after loading (mi.traverse, render --params) is checked like one given
    at construction."""
    use_variant(variant)
    params = mi.traverse(mi.load_dict(GOOD))
    params["albedo.value"] = type(params["albedo.value"])(value)
    with pytest.raises(RuntimeError, match=fragment):
        params.update()
    params["albedo.value"] = type(params["albedo.value"])(0.7)
    params.update()  # a valid value is accepted again, str(info.value)


def test_wavelengths_outside_the_optical_constants_are_rejected():
    use_variant("scalar_spectral")
    xml = ('<bsdf version="3.0.0" type="powder">'
           '<spectrum name="eta" value="400:2.5, 700:2.9"/>'
           '<spectrum name="k" value="400:0.5, 700:0.01"/></bsdf>')
    with pytest.raises(RuntimeError, match="wavelength 360 nm lies outside the optical "
                                           "constants of the \"eta\" and \"k\" spectra"):
        mi.load_string(xml)
    use_variant("llvm_ad_mono")  # 700 nm is covered
    assert mi.load_string(xml).class_name() == "Powder"
    with pytest.raises(RuntimeError, match="wavelength 800 nm lies outside"):
        mi.load_string(xml.replace("</bsdf>", '<float name="wavelength" value="800"/></bsdf>'))


def test_unknown_property_is_rejected():
    use_variant("scalar_rgb")
    with pytest.raises(RuntimeError, match="extintion"):
        mi.load_dict({**GOOD, "extintion": 1.0})


@pytest.mark.parametrize("key,value,fragment", [
    ("g", 1.2, '"g" = 1.2'),
    ("radius", -0.5, '"radius" = -0.5'),
    ("radius", 50.0, "size parameter"),
    ("extinction", -1.0, '"extinction" = -1'),
    ("amplitude_volume", -0.5, '"amplitude_volume" = -0.5'),
    ("correlation_length", 0.0, '"correlation_length" = 0'),
])
def test_bad_value_through_traverse_is_rejected(key, value, fragment):
    use_variant("llvm_ad_rgb")
    props = dict(GOOD) if key != "radius" else {"type": "powder"}
    params = mi.traverse(mi.load_dict(props))
    params[key] = mi.Float(value)
    with pytest.raises(RuntimeError) as info:
        params.update()
    assert fragment in str(info.value)
