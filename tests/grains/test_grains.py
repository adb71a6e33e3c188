"""Grain models (docs/model.md, property `grains`): effective-medium agglomerates and Hapke's
equivalent slab. The C++ functions of ``mitsuba_powder._optics`` and the plugin's albedo are
checked against tests/oracles/grains.py (NumPy + miepython, written from docs/model.md only)."""

from __future__ import annotations

import re

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import load_and_capture, use_variant
from mitsuba_powder import _optics
from oracles import grains as ref
from oracles.grains import hematite_nk

RGB_WAVELENGTHS = (611.3, 549.1, 464.3)
#: integer wavelengths (nm): the spectral plugin interpolates a 1 nm table
SPECTRAL_SETS = ((400.0, 523.0, 611.0, 777.0), (360.0, 455.0, 700.0, 830.0))
#: derivative order of albedo_table's second output
DERIVATIVE_KEYS = ("radius", "radius2", "fraction2", "agglomerate_radius", "agglomerate_fill")
#: constant indices: non-absorbing, weakly, moderately and strongly absorbing
CONSTANT_INDICES = (1.5 + 0j, 2.9 + 0.05j, 3.0 + 0.5j, 2.2 + 2.5j)


def hematite(wl_nm) -> list[complex]:
    """Hematite index n + ik at the wavelengths ``wl_nm`` (nm) as the plugin interpolates it."""
    return [complex(v) for v in hematite_nk(np.asarray(wl_nm, dtype=np.float64))]


# ============================================================ (a) the oracle itself

def test_oracle_reproduces_model_md_mixing_values():
    eps_i = (3.0 + 0.5j) ** 2
    assert abs(np.sqrt(ref.bruggeman_eps(eps_i, 0.5)) - (1.926597 + 0.225593j)) < 1e-6
    assert abs(np.sqrt(ref.maxwell_garnett_eps(eps_i, 0.5)) - (1.660462 + 0.082098j)) < 1e-6
    assert abs(ref.effective_index(3.0 + 0.5j, 0.5) - (1.926597 + 0.225593j)) < 1e-6
    assert abs(ref.effective_index(3.0 + 0.5j, 0.5, "maxwell_garnett")
               - (1.660462 + 0.082098j)) < 1e-6
    for mixing in ref.MIXINGS:
        for m in (3.0 + 0.5j, 1.5 + 0j, 2.2 + 2.5j):
            assert abs(ref.effective_index(m, 1.0, mixing) - m) < 1e-12 * abs(m)


@pytest.mark.parametrize("m", [1.33 + 0j, 3.0 + 0.5j, 2.9 + 1.5j, 0.3 + 3.0j])
@pytest.mark.parametrize("f", [0.01, 0.2, 0.5, 0.9])
def test_oracle_bruggeman_root_solves_the_mixing_equation(m, f):
    """The chosen root solves docs/model.md's first form of the rule, is on the physical branch (the
    one connected to eps_i at f = 1, followed in small steps of f) and is close to Maxwell
    Garnett's (the same first order in f) for a dilute mixture."""
    eps_i = m * m
    eps = ref.bruggeman_eps(eps_i, f)
    residual = f * (eps_i - eps) / (eps_i + 2 * eps) + (1 - f) * (1 - eps) / (1 + 2 * eps)
    assert abs(residual) < 1e-12
    assert eps.imag >= 0.0
    cur = eps_i
    for ff in np.linspace(1.0, f, 400)[1:]:
        b = (3 * ff - 1) * eps_i + (2 - 3 * ff)
        d = np.sqrt(b * b + 8 * eps_i)
        roots = np.array([(b + d) / 4, (b - d) / 4])
        cur = roots[np.argmin(np.abs(roots - cur))]
    assert abs(eps - cur) < 1e-9 * abs(cur)
    if f == 0.01:
        mg = ref.maxwell_garnett_eps(eps_i, f)
        assert abs(eps - mg) < 0.1 * abs(mg - 1)


def test_oracle_slab_reference_value_and_limits():
    assert ref.slab_albedo(2.9 + 0.05j, 1.0, 550.0) == pytest.approx(0.34784, abs=5e-6)
    # no absorption: all the light comes back out (Theta = 1)
    assert ref.slab_albedo(1.8 + 0j, 3.0, 500.0) == pytest.approx(1.0, abs=1e-15)
    # opaque grain: only the external reflection S_e
    r0 = ((2.9 - 1) ** 2 + 0.5**2) / ((2.9 + 1) ** 2 + 0.5**2)
    s_e = 0.0587 + 0.8543 * r0 + 0.0870 * r0**2
    assert ref.slab_albedo(2.9 + 0.5j, 1e4, 500.0) == pytest.approx(s_e, rel=1e-12)
    # two populations: equal radii give the one-population value, f2 = 0 and 1 the ends
    one = ref.slab_albedo(2.9 + 0.05j, 1.0, 550.0)
    assert ref.slab_albedo_two(2.9 + 0.05j, 0.5, 0.5, 0.3, 550.0) == pytest.approx(one)
    assert ref.slab_albedo_two(2.9 + 0.05j, 0.5, 3.0, 0.0, 550.0) == pytest.approx(one)
    assert ref.slab_albedo_two(2.9 + 0.05j, 3.0, 0.5, 1.0, 550.0) == pytest.approx(one)


def test_oracle_agglomerate_of_fill_one_is_the_sphere():
    for mixing in ref.MIXINGS:
        for wl in (400.0, 700.0):
            m = hematite([wl])[0]
            assert ref.agglomerate_albedo(m, 0.3, 1.0, wl, mixing) == pytest.approx(
                ref.mie_albedo(m, 0.3, wl), rel=1e-12)


def test_oracle_size_parameter():
    assert ref.crystallite_size_parameter(3 + 4j, 0.1, 500.0) == pytest.approx(
        2 * np.pi * 0.1 * 5 / 0.5, rel=1e-15)


# ============================================================ (b) the C++ double-precision code

INDEX_CASES = list(CONSTANT_INDICES) + [1.33 + 0j, 0.3 + 3.0j] + hematite([360.0, 550.0, 830.0])


@pytest.mark.parametrize("mixing", ref.MIXINGS)
@pytest.mark.parametrize("index", INDEX_CASES)
def test_effective_index_matches_the_oracle(index, mixing):
    for fill in (0.05, 0.3, 0.5, 0.8, 1.0):
        got = complex(_optics.effective_index(index, fill, mixing))
        want = ref.effective_index(index, fill, mixing)
        assert abs(got - want) <= 1e-6 * abs(want), (index, fill, mixing, got, want)


def test_effective_index_reference_values():
    got = complex(_optics.effective_index(3.0 + 0.5j, 0.5, "bruggeman"))
    assert abs(got - (1.926597 + 0.225593j)) < 1e-6, got
    got = complex(_optics.effective_index(3.0 + 0.5j, 0.5, "maxwell_garnett"))
    assert abs(got - (1.660462 + 0.082098j)) < 1e-6, got


@pytest.mark.parametrize("index", [2.9 + 0.05j, 1.5 + 0j, 1.33 + 1e-4j, 3.0 + 0.5j,
                                   2.2 + 2.5j, 1.02 + 0.01j] + hematite([400.0, 700.0]))
def test_slab_albedo_matches_the_oracle(index):
    for d_um in (0.03, 0.3, 1.0, 10.0, 100.0):
        for wl_um in (0.36, 0.55, 0.83):
            got = _optics.slab_albedo(index, d_um, wl_um)
            want = ref.slab_albedo(index, d_um, wl_um * 1e3)
            assert got == pytest.approx(want, rel=1e-6), (index, d_um, wl_um)
    assert _optics.slab_albedo(2.9 + 0.05j, 1.0, 0.55) == pytest.approx(0.34784, abs=5e-6)


TABLE_WAVELENGTHS = [360.0, 450.0, 550.5, 700.0, 830.0]


def table(grains: str, index: list[complex], **kw):
    """albedo_table at TABLE_WAVELENGTHS: (rho (N,), derivatives (N, 5))."""
    rho, der = _optics.albedo_table(grains, TABLE_WAVELENGTHS, index, **kw)
    return np.asarray(rho, dtype=np.float64), np.asarray(der, dtype=np.float64)


def oracle_table(grains: str, index: list[complex], radius: float, radius2=None,
                 fraction2=None, agglomerate_radius=None, agglomerate_fill=0.5,
                 mixing="bruggeman") -> np.ndarray:
    """The oracle's rho at TABLE_WAVELENGTHS for albedo_table's arguments."""
    out = []
    for wl, m in zip(TABLE_WAVELENGTHS, index):
        if grains == "agglomerate":
            out.append(ref.agglomerate_albedo(m, agglomerate_radius, agglomerate_fill, wl,
                                              mixing))
        elif grains == "slab":
            out.append(ref.slab_albedo(m, 2 * radius, wl) if radius2 is None else
                       ref.slab_albedo_two(m, radius, radius2, fraction2, wl))
        else:
            out.append(ref.mie_albedo(m, radius, wl, radius2, fraction2))
    return np.array(out)


HEMATITE_TABLE = hematite(TABLE_WAVELENGTHS)
INDEX_SETS = {"hematite": HEMATITE_TABLE, "k=0": [1.7 + 0j] * 5, "k=2.5": [2.2 + 2.5j] * 5,
              "k=0.05": [2.9 + 0.05j] * 5}

AGGLOMERATE_CASES = [(ra, fill) for ra in (0.05, 0.15, 0.6, 3.0) for fill in (0.1, 0.4, 0.75, 1.0)]


@pytest.mark.parametrize("mixing", ref.MIXINGS)
@pytest.mark.parametrize("indices", INDEX_SETS.keys())
def test_albedo_table_agglomerate_matches_the_oracle(indices, mixing):
    index = INDEX_SETS[indices]
    for ra, fill in AGGLOMERATE_CASES:
        got, _ = table("agglomerate", index, radius=0.017, agglomerate_radius=ra,
                       agglomerate_fill=fill, mixing=mixing)
        want = oracle_table("agglomerate", index, 0.017, agglomerate_radius=ra,
                            agglomerate_fill=fill, mixing=mixing)
        np.testing.assert_allclose(got, want, rtol=1e-6, err_msg=f"R_a={ra}, f={fill}")


def test_albedo_table_agglomerate_default_fill_and_mixing():
    got, _ = table("agglomerate", HEMATITE_TABLE, radius=0.017, agglomerate_radius=0.2)
    want = oracle_table("agglomerate", HEMATITE_TABLE, 0.017, agglomerate_radius=0.2,
                        agglomerate_fill=0.5, mixing="bruggeman")
    np.testing.assert_allclose(got, want, rtol=1e-6)


@pytest.mark.parametrize("indices", INDEX_SETS.keys())
def test_albedo_table_slab_matches_the_oracle(indices):
    index = INDEX_SETS[indices]
    for r in (0.05, 0.5, 5.0, 40.0):
        got, _ = table("slab", index, radius=r)
        np.testing.assert_allclose(got, oracle_table("slab", index, r), rtol=1e-6,
                                   err_msg=f"r={r}")
    for r1, r2, f2 in ((0.5, 0.05, 0.3), (2.0, 20.0, 0.7), (1.0, 0.1, 0.05)):
        got, _ = table("slab", index, radius=r1, radius2=r2, fraction2=f2)
        want = oracle_table("slab", index, r1, radius2=r2, fraction2=f2)
        np.testing.assert_allclose(got, want, rtol=1e-6, err_msg=f"{r1}, {r2}, {f2}")


@pytest.mark.parametrize("indices", INDEX_SETS.keys())
def test_albedo_table_sphere_matches_the_oracle(indices):
    index = INDEX_SETS[indices]
    for r in (0.017, 0.1, 1.0):
        got, _ = table("sphere", index, radius=r)
        np.testing.assert_allclose(got, oracle_table("sphere", index, r), rtol=1e-6)
    got, _ = table("sphere", index, radius=0.083, radius2=0.046, fraction2=0.4)
    want = oracle_table("sphere", index, 0.083, radius2=0.046, fraction2=0.4)
    np.testing.assert_allclose(got, want, rtol=1e-6)


# (grains, keyword arguments, parameters in use)
DERIVATIVE_CASES = [
    ("agglomerate", {"radius": 0.017, "agglomerate_radius": 0.15, "agglomerate_fill": 0.4,
                     "mixing": "bruggeman"}, ("agglomerate_radius", "agglomerate_fill")),
    ("agglomerate", {"radius": 0.017, "agglomerate_radius": 0.5, "agglomerate_fill": 0.7,
                     "mixing": "maxwell_garnett"}, ("agglomerate_radius", "agglomerate_fill")),
    ("agglomerate", {"radius": 0.03, "agglomerate_radius": 0.08, "agglomerate_fill": 0.25,
                     "mixing": "maxwell_garnett"}, ("agglomerate_radius", "agglomerate_fill")),
    ("slab", {"radius": 0.5}, ("radius",)),
    ("slab", {"radius": 0.03}, ("radius",)),
    ("slab", {"radius": 2.0, "radius2": 0.2, "fraction2": 0.3},
     ("radius", "radius2", "fraction2")),
    ("sphere", {"radius": 0.1}, ("radius",)),
    ("sphere", {"radius": 0.083, "radius2": 0.046, "fraction2": 0.4},
     ("radius", "radius2", "fraction2")),
]


def oracle_from_kwargs(grains: str, index: list[complex], kw: dict) -> np.ndarray:
    args = {"agglomerate_fill": 0.5, "mixing": "bruggeman", **kw}
    return oracle_table(grains, index, args.pop("radius"), **args)


@pytest.mark.parametrize("indices", ["hematite", "k=0.05", "k=2.5"])
@pytest.mark.parametrize("grains,kw,used", DERIVATIVE_CASES,
                         ids=[f"{c[0]}-{i}" for i, c in enumerate(DERIVATIVE_CASES)])
def test_albedo_table_derivatives_match_finite_differences_of_the_oracle(grains, kw, used,
                                                                         indices):
    index = INDEX_SETS[indices]
    rho, der = table(grains, index, derivatives=True, **kw)
    assert der.shape == (len(TABLE_WAVELENGTHS), 5), der.shape
    np.testing.assert_allclose(rho, oracle_from_kwargs(grains, index, kw), rtol=1e-6)
    for key in used:
        j = DERIVATIVE_KEYS.index(key)
        h = 1e-5 * kw[key]
        up = oracle_from_kwargs(grains, index, {**kw, key: kw[key] + h})
        down = oracle_from_kwargs(grains, index, {**kw, key: kw[key] - h})
        fd = (up - down) / (2 * h)
        if indices == "hematite":  # never a vacuous comparison of zeros
            assert np.max(np.abs(fd)) > 1e-3, (key, fd)
        # atol: an opaque slab (hematite in the blue) has d rho / d r ~ 1e-11
        np.testing.assert_allclose(der[:, j], fd, rtol=0.02, atol=1e-8,
                                   err_msg=f"d rho / d {key}")
    unused = {key: der[:, j] for j, key in enumerate(DERIVATIVE_KEYS) if key not in used}
    assert all(np.all(v == 0.0) for v in unused.values()), unused  # the interface: exact zeros


def test_albedo_table_values_do_not_depend_on_the_derivatives_flag():
    for grains, kw, _ in DERIVATIVE_CASES:
        rho, _ = table(grains, HEMATITE_TABLE, **kw)
        rho2, _ = table(grains, HEMATITE_TABLE, derivatives=True, **kw)
        np.testing.assert_allclose(rho, rho2, rtol=1e-12, err_msg=grains)


# ============================================================ (c) the plugin's albedo

# (plugin properties beyond type, oracle per (index, wl_nm))
PLUGIN_CASES = {
    "agglomerate-bruggeman": (
        {"grains": "agglomerate", "radius": 0.017, "agglomerate_radius": 0.15,
         "agglomerate_fill": 0.4, "mixing": "bruggeman"},
        lambda m, wl: ref.agglomerate_albedo(m, 0.15, 0.4, wl, "bruggeman")),
    "agglomerate-maxwell_garnett": (
        {"grains": "agglomerate", "radius": 0.017, "agglomerate_radius": 0.5,
         "agglomerate_fill": 0.7, "mixing": "maxwell_garnett"},
        lambda m, wl: ref.agglomerate_albedo(m, 0.5, 0.7, wl, "maxwell_garnett")),
    "agglomerate-defaults": (  # fill 0.5 and Bruggeman by default
        {"grains": "agglomerate", "radius": 0.017, "agglomerate_radius": 0.08},
        lambda m, wl: ref.agglomerate_albedo(m, 0.08, 0.5, wl, "bruggeman")),
    "slab": (
        {"grains": "slab", "radius": 0.5},
        lambda m, wl: ref.slab_albedo(m, 1.0, wl)),
    "slab-two": (
        {"grains": "slab", "radius": 2.0, "radius2": 0.2, "fraction2": 0.3},
        lambda m, wl: ref.slab_albedo_two(m, 2.0, 0.2, 0.3, wl)),
}
# constant optical constants: the index is known exactly at every wavelength
CONSTANT_CASES = {
    "slab-eta-k": (
        {"grains": "slab", "radius": 0.5, "eta": 2.9, "k": 0.05},
        lambda m, wl: ref.slab_albedo(2.9 + 0.05j, 1.0, wl)),
    "slab-two-eta-k": (
        {"grains": "slab", "radius": 5.0, "radius2": 0.3, "fraction2": 0.6, "eta": 1.8,
         "k": 0.002},
        lambda m, wl: ref.slab_albedo_two(1.8 + 0.002j, 5.0, 0.3, 0.6, wl)),
    "agglomerate-eta-k": (
        {"grains": "agglomerate", "radius": 0.01, "agglomerate_radius": 0.3,
         "agglomerate_fill": 0.5, "eta": 3.0, "k": 0.5},
        lambda m, wl: ref.agglomerate_albedo(3.0 + 0.5j, 0.3, 0.5, wl, "bruggeman")),
    "agglomerate-strongly-absorbing": (
        {"grains": "agglomerate", "radius": 0.01, "agglomerate_radius": 0.2,
         "agglomerate_fill": 0.6, "mixing": "maxwell_garnett", "eta": 2.2, "k": 2.5},
        lambda m, wl: ref.agglomerate_albedo(2.2 + 2.5j, 0.2, 0.6, wl, "maxwell_garnett")),
    "agglomerate-k0": (  # no absorption: rho = 1
        {"grains": "agglomerate", "radius": 0.01, "agglomerate_radius": 0.3,
         "agglomerate_fill": 0.35, "eta": 1.6, "k": 0.0},
        lambda m, wl: ref.agglomerate_albedo(1.6 + 0j, 0.3, 0.35, wl, "bruggeman")),
}
ALL_PLUGIN_CASES = {**PLUGIN_CASES, **CONSTANT_CASES}


def plugin_albedo(bsdf, wavelengths=None) -> np.ndarray:
    """The plugin's albedo per channel (float64 copy) for the current variant."""
    if mi.variant().startswith("scalar"):
        si = mi.SurfaceInteraction3f()
    else:
        si = dr.zeros(mi.SurfaceInteraction3f, 1)
    if wavelengths is not None:
        si.wavelengths = mi.UnpolarizedSpectrum(*[float(w) for w in wavelengths])
    return np.array(bsdf.eval_attribute("albedo", si), dtype=np.float64).ravel()


@pytest.mark.parametrize("case", ALL_PLUGIN_CASES.keys())
def test_plugin_albedo_scalar_spectral(case):
    use_variant("scalar_spectral")
    props, oracle = ALL_PLUGIN_CASES[case]
    bsdf = mi.load_dict({"type": "powder", **props})
    for lams in SPECTRAL_SETS:
        got = plugin_albedo(bsdf, lams)
        want = [oracle(m, wl) for m, wl in zip(hematite(lams), lams)]
        np.testing.assert_allclose(got, want, rtol=1e-4, err_msg=f"{case} at {lams} nm")


@pytest.mark.parametrize("case", ALL_PLUGIN_CASES.keys())
def test_plugin_albedo_llvm_ad_rgb(case):
    use_variant("llvm_ad_rgb")
    props, oracle = ALL_PLUGIN_CASES[case]
    got = plugin_albedo(mi.load_dict({"type": "powder", **props}))
    want = [oracle(m, wl) for m, wl in zip(hematite(RGB_WAVELENGTHS), RGB_WAVELENGTHS)]
    np.testing.assert_allclose(got, want, rtol=1e-4, err_msg=case)
    # other rgb_wavelengths are honoured too
    lams = (650.0, 520.0, 430.0)
    got = plugin_albedo(mi.load_dict({"type": "powder", **props,
                                      "rgb_wavelengths": "650, 520, 430"}))
    want = [oracle(m, wl) for m, wl in zip(hematite(lams), lams)]
    np.testing.assert_allclose(got, want, rtol=1e-4, err_msg=case)


@pytest.mark.parametrize("case", ALL_PLUGIN_CASES.keys())
def test_plugin_albedo_llvm_ad_mono(case):
    use_variant("llvm_ad_mono")
    props, oracle = ALL_PLUGIN_CASES[case]
    for wl in (450.0, 700.0):
        got = plugin_albedo(mi.load_dict({"type": "powder", **props, "wavelength": wl}))
        np.testing.assert_allclose(got, [oracle(hematite([wl])[0], wl)], rtol=1e-4,
                                   err_msg=f"{case} at {wl} nm")


def test_plugin_slab_reference_value():
    """docs/model.md: n = 2.9, k = 0.05, D = 1 um, lam = 0.55 um -> rho = 0.34784."""
    use_variant("llvm_ad_mono")
    bsdf = mi.load_dict({"type": "powder", "grains": "slab", "radius": 0.5, "eta": 2.9,
                         "k": 0.05, "wavelength": 550.0})
    assert plugin_albedo(bsdf)[0] == pytest.approx(0.34784, rel=1e-4)


def test_plugin_grains_sphere_is_the_default():
    use_variant("scalar_spectral")
    lams = SPECTRAL_SETS[0]
    a = plugin_albedo(mi.load_dict({"type": "powder", "radius": 0.1}), lams)
    b = plugin_albedo(mi.load_dict({"type": "powder", "radius": 0.1, "grains": "sphere"}), lams)
    np.testing.assert_array_equal(a, b)
    want = [ref.mie_albedo(m, 0.1, wl) for m, wl in zip(hematite(lams), lams)]
    np.testing.assert_allclose(b, want, rtol=1e-4)


@pytest.mark.parametrize("props", [{"grains": "agglomerate", "agglomerate_radius": 0.3},
                                   {"grains": "slab", "radius": 2.0}], ids=["agglomerate", "slab"])
def test_tau_o_still_comes_from_the_grain_material(props):
    """docs/model.md: tau_o comes from the material's Re(eta) whatever the grain model."""
    use_variant("scalar_spectral")
    si = mi.SurfaceInteraction3f()
    si.wavelengths = mi.UnpolarizedSpectrum(*SPECTRAL_SETS[0])
    want = np.array(mi.load_dict({"type": "powder"}).eval_attribute("tau_o", si))
    got = np.array(mi.load_dict({"type": "powder", **props}).eval_attribute("tau_o", si))
    np.testing.assert_array_equal(got, want)
    assert np.all(want > 5.0)  # hematite, n ~ 2.7-3.2


# ============================================================ (d) fill 1 is the sphere

@pytest.mark.parametrize("mixing", ref.MIXINGS)
def test_agglomerate_of_fill_one_is_the_sphere(mixing):
    for ra in (0.05, 0.3, 2.0):
        for index in (HEMATITE_TABLE, INDEX_SETS["k=2.5"], INDEX_SETS["k=0.05"]):
            agg, _ = table("agglomerate", index, radius=0.017, agglomerate_radius=ra,
                           agglomerate_fill=1.0, mixing=mixing)
            sph, _ = table("sphere", index, radius=ra)
            np.testing.assert_allclose(agg, sph, rtol=1e-6, err_msg=f"R_a={ra}")
    use_variant("scalar_spectral")
    agg = mi.load_dict({"type": "powder", "grains": "agglomerate", "agglomerate_radius": 0.3,
                        "agglomerate_fill": 1.0, "mixing": mixing})
    sph = mi.load_dict({"type": "powder", "radius": 0.3})
    for lams in SPECTRAL_SETS:
        np.testing.assert_allclose(plugin_albedo(agg, lams), plugin_albedo(sph, lams),
                                   rtol=1e-5)


# ============================================================ (e) derivatives in the plugin

def traverse_keys(props: dict) -> set[str]:
    return set(mi.traverse(mi.load_dict({"type": "powder", **props})).keys())


def test_traversed_grain_parameters():
    use_variant("llvm_ad_rgb")
    keys = traverse_keys({"grains": "agglomerate", "agglomerate_radius": 0.15})
    assert {"agglomerate_radius", "agglomerate_fill"} <= keys, keys
    assert "radius" not in keys, keys
    keys = traverse_keys({"grains": "slab", "radius": 0.5})
    assert "radius" in keys and "radius2" not in keys and "agglomerate_radius" not in keys, keys
    keys = traverse_keys({"grains": "slab", "radius": 0.5, "radius2": 0.1, "fraction2": 0.2})
    assert {"radius", "radius2", "fraction2"} <= keys, keys


SLAB_TWO = {"grains": "slab", "radius": 5.0, "radius2": 0.3, "fraction2": 0.6, "eta": 1.8,
            "k": 0.002}
PLUGIN_DERIVATIVE_CASES = [
    ({"grains": "agglomerate", "agglomerate_radius": 0.15, "agglomerate_fill": 0.4,
      "mixing": "bruggeman"}, "agglomerate_radius"),
    ({"grains": "agglomerate", "agglomerate_radius": 0.15, "agglomerate_fill": 0.4,
      "mixing": "maxwell_garnett"}, "agglomerate_radius"),
    ({"grains": "agglomerate", "agglomerate_radius": 0.15, "agglomerate_fill": 0.4,
      "mixing": "bruggeman"}, "agglomerate_fill"),
    ({"grains": "agglomerate", "agglomerate_radius": 0.6, "agglomerate_fill": 0.7,
      "mixing": "maxwell_garnett"}, "agglomerate_fill"),
    # hematite is opaque in the blue for D = 1 um: a small grain keeps all three channels live
    ({"grains": "slab", "radius": 0.05}, "radius"),
    (SLAB_TWO, "radius"),
    (SLAB_TWO, "radius2"),
    (SLAB_TWO, "fraction2"),
]
DERIVATIVE_IDS = [f"{p['grains']}-{p.get('mixing', p.get('eta', 'hematite'))}-{k}"
                  for p, k in PLUGIN_DERIVATIVE_CASES]


def single_scattering_albedo(bsdf):
    """rho from ``bsdf.eval`` with lobes = "single", g = 0, A_v = 1 at normal incidence and
    view (L1 = rho / 2, BRDF = L1 / (4 pi), times cos = 1): differentiable Color3f."""
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.wi = mi.Vector3f(0.0, 0.0, 1.0)
    if mi.is_spectral:
        si.wavelengths = mi.UnpolarizedSpectrum(*SPECTRAL_SETS[0])
    return 8.0 * dr.pi * bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(0.0, 0.0, 1.0))


def forward_and_finite_difference(props: dict, key: str, observable,
                                  variant: str = "llvm_ad_rgb"):
    """(forward-mode derivative, central difference of the plugin's own values) per channel
    of ``observable(bsdf)`` with respect to the traversed parameter ``key``."""
    use_variant(variant)
    bsdf = mi.load_dict({"type": "powder", **props})
    params = mi.traverse(bsdf)
    value = float(np.array(params[key]).ravel()[0])
    dr.enable_grad(params[key])
    params.update()
    out = observable(bsdf)
    dr.forward(params[key])
    grad = np.array(dr.grad(out), dtype=np.float64).ravel()
    dr.disable_grad(params[key])
    vals, xs = [], []
    for x in (value * (1 + 1e-3), value * (1 - 1e-3)):
        params[key] = mi.Float(x)
        params.update()
        xs.append(float(np.array(params[key]).ravel()[0]))  # the float32 value really used
        vals.append(np.array(observable(bsdf), dtype=np.float64).ravel())
    return grad, (vals[0] - vals[1]) / (xs[0] - xs[1])


@pytest.mark.parametrize("props,key", PLUGIN_DERIVATIVE_CASES, ids=DERIVATIVE_IDS)
def test_plugin_albedo_derivatives_match_finite_differences(props, key):
    """Through bsdf.eval (what a fit or a render differentiates)."""
    grad, fd = forward_and_finite_difference({**props, "lobes": "single"}, key,
                                             single_scattering_albedo)
    value = props[key]
    assert np.all(np.abs(fd) * value > 1e-3), fd  # d rho / d ln p well above float32 noise
    np.testing.assert_allclose(grad, fd, rtol=0.02, err_msg=f"d albedo / d {key}")


@pytest.mark.parametrize("props,key", PLUGIN_DERIVATIVE_CASES[:4], ids=DERIVATIVE_IDS[:4])
def test_plugin_albedo_derivatives_spectral(props, key):
    """Spectral variants read rho from the 1 nm grain table: derivatives flow through it too."""
    grad, fd = forward_and_finite_difference({**props, "lobes": "single"}, key,
                                             single_scattering_albedo, "llvm_ad_spectral")
    assert np.all(np.abs(fd) * props[key] > 1e-3), fd
    np.testing.assert_allclose(grad, fd, rtol=0.02, err_msg=f"d albedo / d {key}")


@pytest.mark.parametrize("props,key", PLUGIN_DERIVATIVE_CASES[:1] + PLUGIN_DERIVATIVE_CASES[4:5]
                         + [({"radius": 0.1}, "radius")], ids=["agglomerate", "slab", "sphere"])
def test_plugin_albedo_attribute_carries_derivatives(props, key):
    """eval_attribute("albedo") is differentiable too, in reverse mode. (Forward mode leaves
    no gradient on it: in RGB the attribute is the stored per-channel albedo, an interior node
    of the graph that Dr.Jit's default forward propagation clears; reverse mode, what a loss
    uses, reaches the parameter.)"""
    use_variant("llvm_ad_rgb")
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    bsdf = mi.load_dict({"type": "powder", **props})
    params = mi.traverse(bsdf)
    value = float(np.array(params[key]).ravel()[0])
    grad = []
    for c in range(3):
        x = mi.Float(value)
        dr.enable_grad(x)
        params[key] = x
        params.update()
        dr.backward(bsdf.eval_attribute("albedo", si)[c])
        grad.append(float(dr.grad(x)[0]))
    vals, xs = [], []
    for v in (value * (1 + 1e-3), value * (1 - 1e-3)):
        params[key] = mi.Float(v)
        params.update()
        xs.append(float(np.array(params[key]).ravel()[0]))
        vals.append(np.array(bsdf.eval_attribute("albedo", si), dtype=np.float64).ravel())
    fd = (vals[0] - vals[1]) / (xs[0] - xs[1])
    assert np.all(np.abs(fd) * props[key] > 1e-3), fd
    np.testing.assert_allclose(grad, fd, rtol=0.02, err_msg=f"d albedo / d {key}")


# ============================================================ (f) errors

def load_error(props: dict) -> str:
    with pytest.raises(RuntimeError) as info:
        mi.load_dict({"type": "powder", **props})
    return str(info.value)


def assert_mentions(text: str, *fragments: str) -> None:
    for fragment in fragments:
        assert fragment in text, f"{fragment!r} not in: {text}"


AGG = {"grains": "agglomerate", "agglomerate_radius": 0.15}


@pytest.mark.parametrize("fill", [0.0, 1.5, -0.1])
def test_agglomerate_fill_out_of_range(fill):
    use_variant("scalar_rgb")
    text = load_error({**AGG, "agglomerate_fill": fill})
    assert_mentions(text, '"agglomerate_fill"', f"{fill:g}", "valid")


@pytest.mark.parametrize("value", [0.0, -0.2])
def test_agglomerate_radius_out_of_range(value):
    use_variant("scalar_rgb")
    assert_mentions(load_error({**AGG, "agglomerate_radius": value}), '"agglomerate_radius"',
                    "valid")


def test_agglomerate_needs_its_radius():
    use_variant("scalar_rgb")
    assert_mentions(load_error({"grains": "agglomerate"}), "agglomerate_radius")


@pytest.mark.parametrize("extra,name", [
    ({"radius2": 0.05, "fraction2": 0.3}, "radius2"),
    ({"radius2": 0.05}, "radius2"),
    ({"fraction2": 0.3}, "fraction2"),
])
def test_agglomerate_has_one_population(extra, name):
    use_variant("scalar_rgb")
    assert_mentions(load_error({**AGG, **extra}), name, "agglomerate")


@pytest.mark.parametrize("eta", [0.9, 1.0])
def test_slab_needs_eta_above_one(eta):
    use_variant("scalar_rgb")
    assert_mentions(load_error({"grains": "slab", "radius": 0.5, "eta": eta, "k": 0.1}), "eta",
                    "slab")


def test_unknown_grains_lists_the_valid_values():
    use_variant("scalar_rgb")
    text = load_error({"grains": "foo"})
    assert_mentions(text, '"grains"', "foo", "valid", "sphere", "agglomerate", "slab")


def test_unknown_mixing_lists_the_valid_values():
    use_variant("scalar_rgb")
    text = load_error({**AGG, "mixing": "foo"})
    assert_mentions(text, '"mixing"', "foo", "valid", "bruggeman", "maxwell_garnett")


@pytest.mark.parametrize("grains", [None, "sphere", "slab"])
@pytest.mark.parametrize("extra,name", [({"agglomerate_radius": 0.15}, "agglomerate_radius"),
                                        ({"agglomerate_fill": 0.4}, "agglomerate_fill")])
def test_agglomerate_properties_need_grains_agglomerate(grains, extra, name):
    use_variant("scalar_rgb")
    props = {"radius": 0.5, **extra}
    if grains is not None:
        props["grains"] = grains
    assert_mentions(load_error(props), name, "agglomerate")


@pytest.mark.parametrize("grains", [{"grains": "slab", "radius": 0.5}, AGG])
def test_albedo_only_with_sphere_grains(grains):
    use_variant("scalar_rgb")
    assert_mentions(load_error({**grains, "albedo": 0.5}), "albedo", "grains")


@pytest.mark.parametrize("key,value", [("agglomerate_fill", 1.5), ("agglomerate_fill", 0.0),
                                       ("agglomerate_radius", -0.1)])
def test_invalid_parameter_edit_raises_on_update(key, value):
    use_variant("llvm_ad_rgb")
    bsdf = mi.load_dict({"type": "powder", **AGG, "agglomerate_fill": 0.4})
    params = mi.traverse(bsdf)
    params[key] = mi.Float(value)
    with pytest.raises(RuntimeError, match=key):
        params.update()


# ============================================================ (g) validity warning

WARN_VARIANTS = ["llvm_ad_rgb", "scalar_spectral"]


@pytest.mark.parametrize("variant", WARN_VARIANTS)
def test_large_crystallites_warn_about_the_mixing_rule(variant):
    use_variant(variant)
    # hematite, r = 0.1 um: 2 pi r |n + ik| / lam is 3.2 to 4.4 at the rgb wavelengths
    x = [ref.crystallite_size_parameter(m, 0.1, wl) for m, wl in
         zip(hematite(RGB_WAVELENGTHS), RGB_WAVELENGTHS)]
    assert min(x) > 3.0
    warnings = load_and_capture({"type": "powder", **AGG, "radius": 0.1})
    assert len(warnings) == 1, warnings
    assert "size parameter" in warnings[0].lower(), warnings[0]
    assert "radius" in warnings[0], warnings[0]
    # the largest size parameter over the wavelengths the variant evaluates is reported
    lams = RGB_WAVELENGTHS if variant == "llvm_ad_rgb" else np.arange(360.0, 831.0)
    x_max = max(ref.crystallite_size_parameter(m, 0.1, wl) for m, wl in zip(hematite(lams), lams))
    numbers = [float(v) for v in re.findall(r"\d+\.\d+", warnings[0])]
    assert any(abs(v - x_max) <= 0.01 * x_max for v in numbers), (x_max, warnings[0])


@pytest.mark.parametrize("variant", WARN_VARIANTS)
def test_small_crystallites_do_not_warn(variant):
    """r = 0.01 um: size parameter below 0.47 at every wavelength from 360 to 830 nm."""
    use_variant(variant)
    lams = np.arange(360.0, 831.0)
    assert max(ref.crystallite_size_parameter(m, 0.01, wl)
               for m, wl in zip(hematite(lams), lams)) < 0.5
    assert load_and_capture({"type": "powder", **AGG, "radius": 0.01}) == []


@pytest.mark.parametrize("variant", WARN_VARIANTS)
def test_paper_crystallites_warn_where_they_exceed_the_limit(variant):
    """The paper's r = 0.017 um: its size parameter is 0.35-0.79 over 360-830 nm (0.54-0.74 at
    the rgb wavelengths), above docs/model.md's 0.5 at the short wavelengths: the warning says so
    and names the longest wavelength concerned."""
    use_variant(variant)
    lams = RGB_WAVELENGTHS if variant == "llvm_ad_rgb" else np.arange(360.0, 831.0)
    x = np.array([ref.crystallite_size_parameter(m, 0.017, wl)
                  for m, wl in zip(hematite(lams), lams)])
    warnings = load_and_capture({"type": "powder", **AGG, "radius": 0.017})
    assert len(warnings) == 1, warnings
    longest = float(np.max(np.asarray(lams)[x > 0.5]))
    assert f"the longest {longest:g} nm" in warnings[0], (longest, warnings[0])
    assert f"at {int((x > 0.5).sum())} of the {len(lams)} wavelengths" in warnings[0]
