"""Colour from the grains: Mie efficiencies against miepython, tau_o from Fresnel, the albedo
the plugin uses, two grain populations, radius gradients and the optical-constants loader."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import (
    SHARED,
    channel_kind,
    gradients_and_differences,
    needs_shared,
    use_variant,
)
from mitsuba_powder import _optics
from oracles.grains import (
    OPTICAL_CONSTANTS,
    hematite_nk,
    mie_albedo,
    mie_efficiencies,
    read_yaml_nk,
    tau_o_trapezoid,
)

SHARED_CONSTANTS = SHARED / "data" / "optical_constants"
X_GRID = np.logspace(-3, np.log10(200.0), 45)


INDICES = [1.33 + 0j, 1.5 + 0j, 3.0 + 0.1j, 2.9 + 1.5j]


@pytest.mark.parametrize("index", INDICES + ["hematite 400", "hematite 550", "hematite 700"])
def test_mie_double_precision_matches_miepython(index):
    if isinstance(index, str):
        index = complex(hematite_nk(np.array([float(index.split()[1])]))[0])
    for x in X_GRID:
        got = _optics.mie_efficiencies(index, float(x))
        want = mie_efficiencies(index, float(x))
        np.testing.assert_allclose(got, want, rtol=1e-6, err_msg=f"m={index}, x={x}")


@pytest.mark.parametrize("index", INDICES)
def test_mie_single_precision_values_of_the_plugin(index):
    """q_ext and q_sca as the plugin stores them (float32), through eval_attribute."""
    use_variant("llvm_ad_mono")
    wl = 700.0
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    for x in X_GRID:
        r = float(x) * wl * 1e-3 / (2 * np.pi)
        bsdf = mi.load_dict({"type": "powder", "eta": index.real, "k": index.imag,
                             "radius": r, "wavelength": wl})
        got = [float(bsdf.eval_attribute(name, si)[0][0]) for name in ("q_ext", "q_sca")]
        np.testing.assert_allclose(got, mie_efficiencies(index, float(x)), rtol=1e-4,
                                   err_msg=f"m={index}, x={x}")


def test_tau_o_reference_values():
    """docs/model.md: n = 1 -> 2/3, n = 1.33 -> 1.676, n = 2.0 -> 5.4161, n = 2.9 -> 14.304 (to
    the digits docs/model.md gives; the next test checks the integral itself)."""
    assert _optics.tau_o_fresnel(1.0) == pytest.approx(2.0 / 3.0, abs=1e-12)
    assert _optics.tau_o_fresnel(1.33) == pytest.approx(1.676, abs=1e-3)
    assert _optics.tau_o_fresnel(2.0) == pytest.approx(5.4161, abs=1e-4)
    assert _optics.tau_o_fresnel(2.9) == pytest.approx(14.304, abs=1e-3)


@pytest.mark.parametrize("n", [1.0, 1.2, 1.33, 1.5, 2.0, 2.5, 2.9, 3.2])
def test_tau_o_matches_an_independent_integration(n):
    assert _optics.tau_o_fresnel(n) == pytest.approx(tau_o_trapezoid(n), rel=1e-6)


@pytest.mark.parametrize("variant", ["scalar_spectral", "llvm_ad_spectral", "llvm_ad_rgb",
                                     "scalar_rgb", "llvm_ad_mono"])
@pytest.mark.parametrize("radius", [0.01, 0.017, 0.1, 0.5, 2.0])
def test_observable_albedo_is_mie(variant, radius):
    """lobes="single", g = 0: 4 pi (mu_i + mu_o) f / A_v = rho (hematite, miepython)."""
    use_variant(variant)
    kind = channel_kind()
    if kind == "spectral":
        lams = np.array([400.0, 455.0, 550.0, 623.0, 700.0, 810.0])
        chans = lams.reshape(-1, 4) if len(lams) % 4 == 0 else np.array([[400, 455, 550, 623],
                                                                           [700, 810, 500, 600]])
    elif kind == "rgb":
        chans = np.array([[611.3, 549.1, 464.3]])
    else:
        chans = np.array([[650.0]])
    av = 1.3
    props = {"type": "powder", "radius": radius, "lobes": "single", "amplitude_volume": av,
             "wavelength": 650.0}
    bsdf = mi.load_dict(props)
    wi = mi.Vector3f(0.3, 0.1, float(np.sqrt(1 - 0.1)))
    wo = mi.Vector3f(-0.5, 0.2, float(np.sqrt(1 - 0.29)))
    for lam in chans:
        si = dr.zeros(mi.SurfaceInteraction3f) if not variant.startswith("scalar") \
            else mi.SurfaceInteraction3f()
        si.wi = wi
        if kind == "spectral":
            si.wavelengths = mi.UnpolarizedSpectrum(*[float(v) for v in lam])
        value = np.array(bsdf.eval(mi.BSDFContext(), si, wo), dtype=np.float64).ravel()
        mu_i, mu_o = float(wi.z if np.ndim(wi.z) == 0 else wi.z[0]), float(
            wo.z if np.ndim(wo.z) == 0 else wo.z[0])
        rho = 4 * np.pi * (mu_i + mu_o) * value / mu_o / av
        want = [mie_albedo(complex(hematite_nk(np.array([w]))[0]), radius, w) for w in lam]
        np.testing.assert_allclose(rho, want, rtol=2e-4, err_msg=f"{variant} r={radius} {lam}")


def test_two_populations_albedo():
    use_variant("scalar_spectral")
    r1, r2, f2 = 0.083, 0.046, 0.4
    bsdf = mi.load_dict({"type": "powder", "radius": r1, "radius2": r2, "fraction2": f2})
    si = mi.SurfaceInteraction3f()
    lams = [420.0, 530.0, 640.0, 770.0]
    si.wavelengths = mi.UnpolarizedSpectrum(*lams)
    got = np.array(bsdf.eval_attribute("albedo", si), dtype=np.float64).ravel()
    want = [mie_albedo(complex(hematite_nk(np.array([w]))[0]), r1, w, r2, f2) for w in lams]
    np.testing.assert_allclose(got, want, rtol=1e-4)
    # efficiencies of each population are observable too
    q2 = np.array(bsdf.eval_attribute("q_ext2", si), dtype=np.float64).ravel()
    want2 = [mie_efficiencies(complex(hematite_nk(np.array([w]))[0]),
                              2 * np.pi * r2 / (w * 1e-3))[0] for w in lams]
    np.testing.assert_allclose(q2, want2, rtol=1e-4)


def test_fresnel_tau_o_is_used_per_wavelength():
    """With no tau_o property, tau_o(lambda) = Fresnel of Re(eta(lambda)) of hematite."""
    use_variant("scalar_spectral")
    bsdf = mi.load_dict({"type": "powder"})
    si = mi.SurfaceInteraction3f()
    lams = [400.0, 500.0, 600.0, 700.0]
    si.wavelengths = mi.UnpolarizedSpectrum(*lams)
    got = np.array(bsdf.eval_attribute("tau_o", si), dtype=np.float64).ravel()
    want = [tau_o_trapezoid(hematite_nk(np.array([w]))[0].real) for w in lams]
    np.testing.assert_allclose(got, want, rtol=1e-5)
    # an explicit tau_o overrides Fresnel and becomes a traversed parameter
    bsdf = mi.load_dict({"type": "powder", "tau_o": 3.0})
    assert np.allclose(np.array(bsdf.eval_attribute("tau_o", si)), 3.0)
    assert "tau_o" in mi.traverse(bsdf).keys()


@pytest.mark.parametrize("variant", ["scalar_spectral", "llvm_ad_spectral"])
def test_multiple_scattering_at_exact_wavelengths(variant):
    """lobes="multiple" with a Mie albedo and Fresnel tau_o (the spectral table of rho, s(c0),
    tau_o on the 1 nm grid) against L2 of docs/model.md Eq. 9b at each lane's exact wavelength
    (miepython, Fresnel by an independent quadrature): 1e-4 relative."""
    use_variant(variant)
    radius, g, av = 0.1, 0.3, 1.1
    bsdf = mi.load_dict({"type": "powder", "radius": radius, "g": g, "lobes": "multiple",
                         "amplitude_volume": av, "energy": "paper"})
    rng = np.random.default_rng(31)
    lams = rng.uniform(360.0, 830.0, (6, 4))
    wi = np.array([0.3, 0.1, np.sqrt(0.9)])
    wo = np.array([-0.5, 0.2, np.sqrt(0.71)])
    mu_i, mu_o = wi[2], wo[2]
    for lam in lams:
        si = dr.zeros(mi.SurfaceInteraction3f) if not variant.startswith("scalar") \
            else mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*[float(v) for v in wi])
        si.wavelengths = mi.UnpolarizedSpectrum(*[float(v) for v in lam])
        got = np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*[float(v) for v in wo])),
                       dtype=np.float64).ravel()
        index = hematite_nk(lam)
        rho = np.array([mie_albedo(complex(m), radius, w) for m, w in zip(index, lam)])
        tau = np.array([tau_o_trapezoid(m.real) for m in index])
        c0 = np.sqrt(3 * (1 - rho) * (1 - rho * g))
        s = (1 - np.exp(-2 * c0 * tau)) / (2 * c0)
        l2 = 3 * rho**2 * (s + mu_i * mu_o / (mu_i + mu_o)) / ((1 + c0 * mu_i) * (1 + c0 * mu_o))
        want = av * l2 / (4 * np.pi) * mu_o
        np.testing.assert_allclose(got, want, rtol=1e-4, err_msg=f"{variant} {lam}")


def test_albedo_property_overrides_mie():
    """A given albedo replaces Mie's (the radius beside it is an error: it would be ignored)."""
    use_variant("scalar_rgb")
    bsdf = mi.load_dict({"type": "powder", "albedo": 0.42})
    assert np.allclose(np.array(bsdf.eval_attribute("albedo", mi.SurfaceInteraction3f())), 0.42)
    keys = mi.traverse(bsdf).keys()
    assert "albedo.value" in keys and "radius" not in keys
    with pytest.raises(RuntimeError, match='"radius" has no effect together with "albedo"'):
        mi.load_dict({"type": "powder", "albedo": 0.42, "radius": 0.5})


def assert_grain_gradient(variant: str, key: str, value: float, extra: dict) -> None:
    """The plugin's derivative of the shared test loss with respect to a grain property
    (through the Mie tables' tangents) equals a central difference within 2 %."""
    use_variant(variant)
    bsdf = mi.load_dict({"type": "powder", key: value, **extra})
    # a small step: near Mie resonances (weakly absorbing hematite in the red) rho(r)
    # curves so fast that a 1 % central difference is off by a factor of 4
    [(_, _, grad, fd, _)] = gradients_and_differences(
        bsdf, mi.traverse(bsdf), [key], spectral=mi.is_spectral, steps={key: 1e-3})
    assert abs(fd) > 0
    assert abs(grad - fd) <= 0.02 * abs(fd), (grad, fd)


@pytest.mark.parametrize("key,value,extra", [
    ("radius", 0.01, {}), ("radius", 0.1, {}), ("radius", 1.0, {}),
    ("radius2", 0.3, {"radius": 0.05, "fraction2": 0.3}),
    ("fraction2", 0.3, {"radius": 0.05, "radius2": 0.3}),
])
def test_radius_gradient_matches_finite_differences(key, value, extra):
    assert_grain_gradient("llvm_ad_rgb", key, value, extra)


@pytest.mark.parametrize("key,value,extra", [
    ("radius", 0.1, {}), ("fraction2", 0.3, {"radius": 0.05, "radius2": 0.3}),
])
def test_radius_gradient_matches_finite_differences_spectral(key, value, extra):
    """Spectral variants read rho through the packed grain table: gradients still flow."""
    assert_grain_gradient("llvm_ad_spectral", key, value, extra)


# ----------------------------------------------------------------- loader

GOOD_ROWS = "        0.4000 2.5 0.5\n        0.5000 2.6 0.3\n        0.6000 2.7 0.1\n"


def yaml(rows: str, kind: str = "tabulated nk") -> str:
    return f"REFERENCES: test\nDATA:\n  - type: {kind}\n    data: |\n{rows}"


@pytest.mark.parametrize("rows,kind,fragments", [
    (GOOD_ROWS + "        0.6000 2.7 0.1\n", "tabulated nk", ["line 8", "does not increase"]),
    (GOOD_ROWS + "        0.5500 2.7 0.1\n", "tabulated nk", ["line 8", "does not increase"]),
    (GOOD_ROWS + "        0.7000 2.7 -0.1\n", "tabulated nk", ["line 8", "k = -0.1"]),
    (GOOD_ROWS + "        0.7000 0 0.1\n", "tabulated nk", ["line 8", "n = 0"]),
    (GOOD_ROWS + "        0.7000 2.7\n", "tabulated nk", ["line 8", "three numbers"]),
    (GOOD_ROWS + "        0.7000 2.7 abc\n", "tabulated nk", ["line 8", "three numbers"]),
    (GOOD_ROWS + "        0.7000 2.7 nan\n", "tabulated nk", ["line 8", "three numbers"]),
    (GOOD_ROWS, "formula 2", ['"formula 2" is not supported']),
    ("", "tabulated nk", ["no \"tabulated nk\" data block"]),
])
def test_loader_rejects_malformed_rows(tmp_path, rows, kind, fragments):
    path = tmp_path / "bad.yml"
    path.write_text(yaml(rows, kind))
    with pytest.raises(RuntimeError) as info:
        _optics.load_optical_constants(str(path))
    for fragment in fragments:
        assert fragment in str(info.value), str(info.value)
    # the plugin uses the same loader (material = path)
    use_variant("scalar_rgb")
    with pytest.raises(RuntimeError) as info:
        mi.load_dict({"type": "powder", "material": str(path)})
    assert fragments[0] in str(info.value)


def test_loader_reads_a_good_file_and_the_plugin_uses_it(tmp_path):
    path = tmp_path / "good.yml"
    path.write_text(yaml(GOOD_ROWS))
    wl, n, k = _optics.load_optical_constants(str(path))
    assert wl == [0.4, 0.5, 0.6] and n == [2.5, 2.6, 2.7] and k == [0.5, 0.3, 0.1]
    use_variant("llvm_ad_mono")
    bsdf = mi.load_dict({"type": "powder", "material": str(path), "wavelength": 450.0,
                         "radius": 0.1})
    got = float(bsdf.eval_attribute("albedo", dr.zeros(mi.SurfaceInteraction3f, 1))[0][0])
    assert got == pytest.approx(mie_albedo(2.55 + 0.4j, 0.1, 450.0), rel=1e-4)


@needs_shared(SHARED_CONSTANTS)
@pytest.mark.parametrize("name,line", [("hematite_Querry-o.yml", 386),
                                       ("hematite_Querry-e.yml", 188),
                                       ("magnetite_Querry.yml", 295)])
def test_original_files_with_known_defects_are_rejected(name, line):
    with pytest.raises(RuntimeError, match=f"line {line}: wavelength"):
        _optics.load_optical_constants(str(SHARED_CONSTANTS / name))


@pytest.mark.parametrize("name", ["hematite_Querry-o.yml", "hematite_Querry-e.yml",
                                  "magnetite_Querry.yml"])
def test_bundled_files_load_and_match_an_independent_reader(name):
    wl, n, k = (np.array(v) for v in _optics.load_optical_constants(str(OPTICAL_CONSTANTS / name)))
    ref = read_yaml_nk(OPTICAL_CONSTANTS / name)
    np.testing.assert_array_equal(np.stack([wl, n, k], 1), ref)
    assert wl[0] <= 0.36 and wl[-1] >= 0.83
