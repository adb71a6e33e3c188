"""The plugin's property registry as ``mitsuba_powder._optics`` exposes it (materials, property
defaults and ranges, grain models) against what the plugin itself accepts, refuses and reports:
the two read the same C++ tables (src/bsdfs/powder_registry.h)."""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest

from helpers import use_variant
from mitsuba_powder import _optics

#: a value inside the range of each grain property, for loading
GRAIN_VALUES = {"radius": 0.5, "radius2": 1.0, "fraction2": 0.3, "agglomerate_radius": 0.15,
                "agglomerate_fill": 0.4, "mixing": "maxwell_garnett"}
#: properties a float parameter needs beside it to be in use (and range-checked)
CONTEXT = {
    "tau_o": {},
    "sigma": {"specular": "gaussian"},
    "radius2": {"fraction2": 0.3},
    "fraction2": {"radius2": 0.1},
    "radius3": {"radius2": 0.1, "fraction2": 0.3, "fraction3": 0.3},
    "fraction3": {"radius2": 0.1, "fraction2": 0.0, "radius3": 0.1},
    "radius4": {"radius2": 0.1, "fraction2": 0.3, "radius3": 0.1, "fraction3": 0.3,
                "fraction4": 0.3},
    "fraction4": {"radius2": 0.1, "fraction2": 0.0, "radius3": 0.1, "fraction3": 0.0,
                  "radius4": 0.1},
    "agglomerate_radius": {"grains": "agglomerate"},
    "agglomerate_fill": {"grains": "agglomerate", "agglomerate_radius": 0.15},
    "eta": {"k": 0.1},
    "k": {"eta": 2.5},
}


def load(props: dict):
    return mi.load_dict({"type": "powder", **props})


def load_error(props: dict) -> str:
    with pytest.raises(RuntimeError) as info:
        load(props)
    return str(info.value)


def test_materials_are_the_plugins():
    use_variant("scalar_rgb")
    names = _optics.materials()
    assert {"hematite", "magnetite"} <= set(names)
    assert set(_optics.material_files()) == set(names)
    for name in names:
        assert "optical constants" in str(load({"material": name}))
    text = load_error({"material": "no_such_material"})
    for name in names:
        assert f'"{name}"' in text, text


def test_every_default_is_what_the_plugin_takes_without_the_property():
    """Giving a property its registry default changes nothing the plugin reports."""
    use_variant("scalar_rgb")
    defaults = _optics.property_defaults()
    assert defaults["radius"] == pytest.approx(0.017)
    assert defaults["agglomerate_fill"] == 0.5 and defaults["grains"] == "sphere"
    assert math.isinf(defaults["thickness"])
    for absent in ("tau_o", "radius2", "fraction2", "agglomerate_radius", "eta", "k"):
        assert absent not in defaults
    agglomerate = {"grains": "agglomerate", "agglomerate_radius": 0.15}
    for name, value in defaults.items():
        base = {"specular": "gaussian"} if name == "sigma" else {}
        if name in ("agglomerate_fill", "mixing"):
            base = agglomerate
        if name == "grains":
            base = {}
        assert str(load({**base, name: value})) == str(load(base)), name


@pytest.mark.parametrize("name", ["amplitude_volume", "g", "extinction", "amplitude_surface",
                                  "correlation_length", "thickness", "radius"])
def test_float_defaults_equal_the_traversed_values(name):
    use_variant("llvm_ad_rgb")
    params = mi.traverse(load({}))
    assert float(params[name][0]) == pytest.approx(_optics.property_defaults()[name],
                                                  rel=1e-6)


def test_agglomerate_fill_default_is_traversed():
    use_variant("llvm_ad_rgb")
    params = mi.traverse(load({"grains": "agglomerate", "agglomerate_radius": 0.15}))
    assert float(params["agglomerate_fill"][0]) == _optics.property_defaults()["agglomerate_fill"]


def range_cases():
    ranges, ends = _optics.property_ranges(), _optics.property_range_ends()
    for name, (lo, hi) in sorted(ranges.items()):
        lo_closed, hi_closed = ends[name]
        for end, closed, outside in ((lo, lo_closed, -1.0), (hi, hi_closed, 1.0)):
            if math.isinf(end):
                continue
            yield name, end, closed, end + outside * 0.01 * max(1.0, abs(end))


@pytest.mark.parametrize("name,end,closed,outside", list(range_cases()))
def test_ranges_are_the_plugins(name, end, closed, outside):
    """A value beyond an end is refused naming the property; the end itself is accepted
    exactly when the registry says the end is closed."""
    use_variant("scalar_rgb")
    context = CONTEXT.get(name, {})
    assert name in load_error({**context, name: outside})
    if closed:
        load({**context, name: end})
    else:
        assert name in load_error({**context, name: end})


def test_ranges_cover_the_float_parameters():
    use_variant("llvm_ad_rgb")
    keys = {k for k in mi.traverse(load({"tau_o": 1.0, "radius2": 0.1, "fraction2": 0.3}))
            .keys()}
    assert keys - {"albedo"} <= set(_optics.property_ranges())


MODELS = _optics.grain_models()


def model_props(model: str, names) -> dict:
    props = {"grains": model, **{n: GRAIN_VALUES[n] for n in names}}
    if model == "slab":
        props.setdefault("radius", 0.5)
    return props


def test_grain_models_are_the_plugins_values():
    assert set(MODELS) == {"sphere", "agglomerate", "slab"}
    assert MODELS["sphere"]["size"] == "radius" and MODELS["slab"]["size"] == "radius"
    assert MODELS["agglomerate"]["size"] == "agglomerate_radius"
    assert MODELS["agglomerate"]["required"] == ["agglomerate_radius"]
    assert not MODELS["agglomerate"]["two_populations"]


@pytest.mark.parametrize("model", sorted(MODELS))
def test_each_model_accepts_its_allowed_properties(model):
    use_variant("scalar_rgb")
    rule = MODELS[model]
    load(model_props(model, rule["allowed"]))
    load(model_props(model, rule["required"]))


@pytest.mark.parametrize("model", sorted(MODELS))
def test_each_model_needs_its_required_properties(model):
    use_variant("scalar_rgb")
    rule = MODELS[model]
    for name in rule["required"]:
        rest = [n for n in rule["allowed"] if n != name]
        assert name in load_error(model_props(model, rest))


#: (model, a grain property it does not allow): the plugin's message
REFUSALS = {
    (model, name): f'powder: property "{name}" cannot be used with grains = "{model}"; it is '
                   'used only with grains = "agglomerate"'
    for model in ("sphere", "slab")
    for name in ("agglomerate_radius", "agglomerate_fill", "mixing")
} | {
    ("agglomerate", name): f'powder: property "{name}" cannot be used with grains = '
                           '"agglomerate" (one population); it is used only with grains = '
                           '"sphere" or "slab"'
    for name in ("radius2", "fraction2")
}


def test_refusals_cover_every_model_and_property():
    pairs = {(model, name) for model, rule in MODELS.items()
             for name in {n for m in MODELS.values() for n in m["allowed"]} - set(rule["allowed"])}
    assert pairs == set(REFUSALS)


@pytest.mark.parametrize("model,name", sorted(REFUSALS))
def test_each_model_refuses_the_other_grain_properties(model, name):
    """Each grain property a model does not allow, given alone beside the model's required
    ones, is refused with the message naming it, the model and the models that allow it."""
    use_variant("scalar_rgb")
    text = load_error(model_props(model, MODELS[model]["required"] + [name]))
    assert REFUSALS[model, name] in text, text


@pytest.mark.parametrize("model", sorted(MODELS))
def test_second_population_as_the_registry_says(model):
    use_variant("scalar_rgb")
    rule = MODELS[model]
    props = model_props(model, rule["required"] + ["radius2", "fraction2"])
    if rule["two_populations"]:
        load(props)
    else:
        assert "radius2" in load_error(props)


@pytest.mark.parametrize("model", sorted(MODELS))
def test_size_property_is_the_traversed_grain_size(model):
    use_variant("llvm_ad_rgb")
    rule = MODELS[model]
    keys = set(mi.traverse(load(model_props(model, rule["required"]))).keys())
    assert rule["size"] in keys
    sizes = {m["size"] for m in MODELS.values()}
    assert not (sizes - {rule["size"]}) & keys


@pytest.mark.parametrize("model", sorted(MODELS))
def test_albedo_table_follows_the_same_rules(model):
    """_optics.albedo_table refuses what the plugin refuses."""
    rule = MODELS[model]
    wl, index = [550.0], [complex(2.5, 0.1)]
    kwargs = {"agglomerate_radius": 0.15} if "agglomerate_radius" in rule["required"] else {}
    rho, _ = _optics.albedo_table(model, wl, index, 0.5, **kwargs)
    assert 0.0 < rho[0] < 1.0
    if not rule["two_populations"]:
        with pytest.raises(Exception, match="radius2"):
            _optics.albedo_table(model, wl, index, 0.5, radius2=1.0, fraction2=0.3, **kwargs)
    if "agglomerate_radius" not in rule["allowed"]:
        with pytest.raises(Exception, match="agglomerate_radius"):
            _optics.albedo_table(model, wl, index, 0.5, agglomerate_radius=0.15)
    for name in rule["required"]:
        with pytest.raises(Exception, match=name):
            _optics.albedo_table(model, wl, index, 0.5)
    ranges = _optics.property_ranges()
    with pytest.raises(Exception, match="radius"):
        _optics.albedo_table(model, wl, index, ranges["radius"][0], **kwargs)
    assert np.isfinite(rho).all()
