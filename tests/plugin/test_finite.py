"""Accepted values evaluate to finite numbers: the plugin accepts each float property and
number over the range in which eval, pdf and sample stay finite, with every other property
anywhere in its own range (docs/model.md, "Valid ranges"), at direction pairs down to
mu = 1e-7 (tests/helpers.py, extreme_directions); just outside the range it refuses the value,
naming the property and the range. And the cases found by trying to break the plugin:
``extinction = 1e-20``, ``correlation_length = 1e20`` with a surface term and
``amplitude_volume = 1e38`` (refused), an albedo with a grain size (an error), integers where
floats are taken (accepted), a powder that reflects more than it receives (a warning)."""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest

from helpers import (
    evaluate,
    extreme_directions,
    extreme_samples,
    is_scalar,
    load_and_capture,
    sample,
    use_variant,
)
from mitsuba_powder import _optics
from oracles.model import Params, brdf

VARIANTS = ["scalar_rgb", "llvm_ad_rgb"]
RANGES = _optics.property_ranges()
ENDS = _optics.property_range_ends()
#: the largest float below 1 and the largest finite float (single precision: what the plugin
#: stores)
BELOW_ONE = float(np.nextafter(np.float32(1.0), np.float32(0.0)))
FLOAT_MAX = float(np.finfo(np.float32).max)
FLOAT_TINY = float(np.finfo(np.float32).tiny)  # the smallest normal float
#: the size parameters Mie theory accepts, and the wavelengths of the RGB variants (nm)
MIE_X = (1e-3, 200.0)
RGB = (611.3, 549.1, 464.3)

#: what each property needs beside it to be in use (and to act on eval)
CONTEXT = {
    "amplitude_volume": {"albedo": 1.0},
    "g": {"albedo": 0.8},
    "extinction": {"albedo": 0.8},
    "tau_o": {"albedo": 1.0},
    "thickness": {"albedo": 0.8},
    "amplitude_surface": {"albedo": 0.8},
    "correlation_length": {"albedo": 0.8, "amplitude_surface": 1e-3},
    "sigma": {"albedo": 0.8, "specular": "gaussian", "amplitude_surface": 1.0},
    "radius": {"grains": "slab"},
    "radius2": {"grains": "slab", "radius": 1.0, "fraction2": 0.3},
    "fraction2": {"grains": "slab", "radius": 1.0, "radius2": 0.1},
    # (the other fractions 0, so that each fraction reaches 1)
    "radius3": {"grains": "slab", "radius": 1.0, "radius2": 0.5, "fraction2": 0.0,
                "fraction3": 0.3, "eta3": 1.6, "k3": 0.001},
    "fraction3": {"grains": "slab", "radius": 1.0, "radius2": 0.5, "fraction2": 0.0,
                  "radius3": 0.1, "eta3": 1.6, "k3": 0.001},
    "radius4": {"grains": "slab", "radius": 1.0, "radius2": 0.5, "fraction2": 0.0,
                "radius3": 0.5, "fraction3": 0.0, "fraction4": 0.3, "material4": "calcite"},
    "fraction4": {"grains": "slab", "radius": 1.0, "radius2": 0.5, "fraction2": 0.0,
                  "radius3": 0.5, "fraction3": 0.0, "radius4": 0.1, "material4": "calcite"},
    "agglomerate_radius": {"grains": "agglomerate"},
    "agglomerate_fill": {"grains": "agglomerate", "agglomerate_radius": 0.15},
    "eta": {"k": 0.0, "surface_fresnel": "fresnel", "amplitude_surface": 1e-3},
    "k": {"eta": 1.5, "surface_fresnel": "fresnel", "amplitude_surface": 1e-3},
    "wavelength": {"albedo": 0.8, "eta": 1.5, "k": 0.0, "amplitude_surface": 1e-3},
}


def accepted_range(name: str) -> tuple[float, float, bool, bool]:
    """(lo, hi, lo closed, hi closed) of a property as the RGB variants accept it: the
    registry's, narrowed by the size parameters of Mie theory for agglomerates."""
    (lo, hi), (lo_closed, hi_closed) = RANGES[name], ENDS[name]
    if name == "agglomerate_radius":
        lo = MIE_X[0] * max(RGB) * 1e-3 / (2 * math.pi) * (1 + 1e-5)
        hi = MIE_X[1] * min(RGB) * 1e-3 / (2 * math.pi) * (1 - 1e-5)
        lo_closed = hi_closed = True
    return lo, hi, lo_closed, hi_closed


def end_values(name: str) -> tuple[list[float], list[float]]:
    """(values inside the range at and next to its ends, values just outside it), in single
    precision as the plugin stores them: a closed end and the next float inwards (outwards:
    the next float beyond it); an open end's next float inwards (the largest finite float for
    an infinite end, the smallest normal float for an end at 0) and, outside, the end itself."""
    lo, hi, lo_closed, hi_closed = accepted_range(name)
    if name == "agglomerate_radius":  # Mie's size parameters, with its relative slack 1e-6
        return [lo, hi], [lo * (1 - 1e-4), hi * (1 + 1e-4)]
    inside, outside = [], []
    for end, closed, inwards, outwards in ((lo, lo_closed, hi, -math.inf),
                                           (hi, hi_closed, lo, math.inf)):
        e = np.float32(end)
        step_in = float(np.nextafter(e, np.float32(inwards)))
        if closed:
            inside += [float(e), step_in]
            if not math.isinf(end):
                outside.append(float(np.nextafter(e, np.float32(outwards))))
        else:
            inside.append(FLOAT_MAX if math.isinf(end) else
                          FLOAT_TINY if end == 0 else step_in)
            outside.append(end)
    return inside, outside


def props_with(name: str, value: float) -> dict:
    props = {"type": "powder", **CONTEXT[name]}
    if name == "wavelength":  # RGB variants evaluate the rgb_wavelengths
        props["rgb_wavelengths"] = f"{value!r}, {value!r}, {value!r}"
    else:
        props[name] = value
    return props


def assert_finite(props: dict, label: str, n: int | None = None) -> None:
    """eval, pdf (and, in JIT variants, sample) of the powder are finite and non-negative at
    the extreme direction pairs of tests/helpers.py."""
    n = n or (96 if is_scalar() else 2000)
    rng = np.random.default_rng(8)
    wi, wo = extreme_directions(n, rng)
    lam = None
    if mi.is_spectral:
        lam = np.sort(rng.uniform(360.0, 830.0, (n, 4)), axis=1)
    bsdf = mi.load_dict(props)
    value, pdf = evaluate(bsdf, wi, wo, lam, what="eval_pdf")
    assert np.all(np.isfinite(value)) and np.all(value >= 0), label
    assert np.all(np.isfinite(pdf)) and np.all(pdf >= 0), label
    if not is_scalar():
        s1, s2 = extreme_samples(n, rng)
        swo, spdf, weight = sample(bsdf, wi, s1, s2, lam)
        assert np.all(np.isfinite(swo)) and np.all(np.isfinite(spdf)), label
        assert np.all(np.isfinite(weight)) and np.all(weight >= 0), label


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("name", sorted(CONTEXT))
def test_each_property_is_finite_at_the_ends_of_its_range(variant, name):
    """At each end of its accepted range and next to it, each property gives finite values;
    just outside, it is refused with the range (the others in their default ranges)."""
    use_variant(variant)
    inside, outside = end_values(name)
    for value in inside:
        assert_finite(props_with(name, value), f"{name} = {value!r}")
    shown = "rgb_wavelengths" if name == "wavelength" else name
    for value in outside:
        with pytest.raises(RuntimeError, match=f'"{shown}".*out of range|{shown}.*valid range'):
            mi.load_dict(props_with(name, value))


def test_the_sweep_covers_every_numeric_property():
    assert set(CONTEXT) == set(RANGES)


def corners() -> dict[str, dict]:
    """Powders with several properties at the ends of their ranges at once, where their
    effects multiply (docs/model.md, "Valid ranges"): the volume terms (A_v, tau_o, albedo,
    g), the cone (extinction and wavelength), the Harvey-Shack and Gaussian surface terms
    (amplitude, correlation length or sigma, wavelength), the optical constants."""
    top = {n: max(end_values(n)[0]) for n in ("amplitude_volume", "tau_o",
                                              "amplitude_surface", "correlation_length")}
    low = {n: min(end_values(n)[0]) for n in ("extinction", "correlation_length", "sigma",
                                              "eta")}
    wl_lo, wl_hi = (f"{v!r}, {v!r}, {v!r}" for v in RANGES["wavelength"])
    index = {"eta": 1.5, "k": 0.0}
    return {
        "volume, g -> -1": {"albedo": 1.0, "amplitude_volume": top["amplitude_volume"],
                            "tau_o": top["tau_o"], "g": -BELOW_ONE},
        "volume, g -> 1": {"albedo": 1.0, "amplitude_volume": top["amplitude_volume"],
                           "tau_o": top["tau_o"], "g": BELOW_ONE, "thickness": 1e-30},
        "narrowest cone, shortest wavelength": {
            "albedo": 1.0, "extinction": low["extinction"], "tau_o": top["tau_o"],
            "amplitude_volume": top["amplitude_volume"], "rgb_wavelengths": wl_lo, **index},
        "widest cone": {"albedo": 0.3, "extinction": FLOAT_MAX, "thickness": FLOAT_TINY,
                        "rgb_wavelengths": wl_hi, **index},
        "sharpest surface lobe, shortest wavelength": {
            "albedo": 0.8, "amplitude_surface": top["amplitude_surface"],
            "correlation_length": top["correlation_length"], "rgb_wavelengths": wl_lo,
            **index},
        "broadest surface lobe, longest wavelength": {
            "albedo": 0.8, "amplitude_surface": top["amplitude_surface"],
            "correlation_length": low["correlation_length"], "rgb_wavelengths": wl_hi,
            **index},
        "sharpest Gaussian lobe": {"albedo": 1.0, "specular": "gaussian",
                                   "amplitude_surface": top["amplitude_surface"],
                                   "sigma": low["sigma"],
                                   "amplitude_volume": top["amplitude_volume"]},
        "extreme index, Fresnel factor": {
            "eta": low["eta"], "k": RANGES["k"][1], "surface_fresnel": "fresnel",
            "amplitude_surface": top["amplitude_surface"], "radius": 0.05,
            "amplitude_volume": top["amplitude_volume"]},
        "largest index, Fresnel tau_o": {"eta": RANGES["eta"][1], "k": 0.0, "albedo": 1.0,
                                         "amplitude_volume": top["amplitude_volume"]},
        "conserving": {"albedo": 1.0, "energy": "conserving", "tau_o": top["tau_o"],
                       "amplitude_volume": top["amplitude_volume"],
                       "extinction": low["extinction"], "g": BELOW_ONE},
    }


@pytest.mark.parametrize("variant", VARIANTS + ["llvm_ad_spectral"])
@pytest.mark.parametrize("corner", sorted(corners()))
def test_extremes_together_are_finite(variant, corner):
    use_variant(variant)
    props = corners()[corner]
    if mi.is_spectral:  # spectral variants evaluate 360-830 nm, not the rgb_wavelengths
        props = {k: v for k, v in props.items() if k != "rgb_wavelengths"}
    assert_finite({"type": "powder", **props}, corner)


# ------------------------------------------------------------ the cases of issue 33

@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("props,name", [
    ({"extinction": 1e-20}, "extinction"),
    ({"correlation_length": 1e20, "amplitude_surface": 1e-4}, "correlation_length"),
    ({"amplitude_volume": 1e38}, "amplitude_volume"),
    ({"tau_o": 1e38}, "tau_o"),
    ({"eta": 1e6, "k": 0.0}, "eta"),
    ({"specular": "gaussian", "sigma": 1e-30, "amplitude_surface": 1.0}, "sigma"),
], ids=["extinction 1e-20", "correlation_length 1e20", "amplitude_volume 1e38", "tau_o 1e38",
        "eta 1e6", "sigma 1e-30"])
def test_values_that_evaluated_to_nan_or_inf_are_refused(variant, props, name):
    """Each of these loaded before and gave NaN or inf in eval (eta: tau_o from Fresnel)."""
    use_variant(variant)
    with pytest.raises(RuntimeError, match=f'property "{name}" = .* is out of range; valid '
                                           r"range is [\[(]"):
        mi.load_dict({"type": "powder", **props})


@pytest.mark.parametrize("name,value", [("radius", 3.0), ("radius2", 0.5), ("fraction2", 0.3),
                                        ("radius3", 0.5), ("fraction4", 0.3)])
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
    "radius3": (1, {"radius2": 0.5, "fraction2": 0.2, "fraction3": 0}),
    "fraction3": (1, {"radius2": 0.5, "fraction2": 0, "radius3": 0.5}),
    "radius4": (1, {"radius2": 0.5, "fraction2": 0.2, "radius3": 0.5, "fraction3": 0.2,
                    "fraction4": 0}),
    "fraction4": (1, {"radius2": 0.5, "fraction2": 0, "radius3": 0.5, "fraction3": 0,
                      "radius4": 0.5}),
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


def normal_reflectance(rho: float, g: float, tau: float, lam_nm: float) -> float:
    """What L1 + L2 reflect at normal incidence (A_v = 1): the midpoint rule on 20000 cosines
    with the NumPy model of tests/oracles/model.py."""
    n = 20000
    mu = (np.arange(n) + 0.5) / n
    wo = np.stack([np.sqrt(1 - mu * mu), np.zeros(n), mu], 1)
    wi = np.tile([0.0, 0.0, 1.0], (n, 1))
    p = Params(g=g, tau_o=tau, lobes=("single", "multiple"))
    f = brdf(wi, wo, np.full((n, 1), rho), np.full((n, 1), lam_nm), p)[:, 0]
    return float(2 * np.pi * np.sum(f * mu) / n)


@pytest.mark.parametrize("variant", VARIANTS + ["llvm_ad_spectral"])
def test_a_white_powder_warns_that_it_reflects_more_than_it_receives(variant):
    """albedo = 1 with the default material (tau_o from hematite's index, about 18) reflects
    about 14 times the light it receives at normal incidence with energy = "paper": a warning
    at load time gives the factor (within 1e-3 of the NumPy model), the wavelength, the
    albedo and tau_o."""
    use_variant(variant)
    warnings = [w for w in load_and_capture({"type": "powder", "albedo": 1.0})
                if "times the light it receives" in w]
    assert len(warnings) == 1, warnings
    text = warnings[0]
    factor = float(text.split("reflects ")[1].split(" times")[0])
    lam = float(text.split(" nm")[0].split(" at ")[-1])
    tau = float(text.split("tau_o ")[1].split(")")[0])
    assert factor > 13, text
    assert factor == pytest.approx(normal_reflectance(1.0, 0.0, tau, lam), rel=1e-3), text
    assert 'energy = "conserving"' in text and "docs/powder.md" in text, text


@pytest.mark.parametrize("props", [
    {}, {"albedo": 0.8}, {"albedo": 1.0, "tau_o": 2.0 / 3.0},
    {"albedo": 1.0, "energy": "conserving"}, {"albedo": 1.0, "lobes": "coherent, surface"},
    {"albedo": 1.0, "amplitude_volume": 0.05},
], ids=["default", "albedo 0.8", "white, tau_o 2/3", "conserving", "no ladder", "A_v 0.05"])
def test_powders_that_reflect_less_than_they_receive_do_not_warn(props):
    use_variant("llvm_ad_rgb")
    assert not [w for w in load_and_capture({"type": "powder", **props})
                if "times the light it receives" in w]
