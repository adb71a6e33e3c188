"""Energy: the white furnace of a white powder in ``energy="conserving"`` mode over
kappa/k0, g, tau_o and incidence; the two modes agree in the narrow-cone regime; the regime
warning at load time; eval_pdf, sample weights, chi-square and gradients in conserving mode."""

from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

from helpers import (
    adapters,
    assert_updates_reuse_kernels,
    direction,
    evaluate,
    gradients_and_differences,
    load_and_capture,
    random_hemisphere,
    sample,
    use_variant,
)

LAMBDA_UM = 0.7
K0 = 2.0 * np.pi / LAMBDA_UM  # 1/um, mono variants at 700 nm

# The furnace grid: kappa/k0 from 1e-3 to 10, g from -0.9 to 0.9, tau_o from 0 to
# 100, incidences 0-85 degrees
KAPPA_OVER_K0 = (1e-3, 1e-2, 0.05, 0.25, 1.0, 10.0)
G_VALUES = (-0.9, 0.0, 0.9)
TAU_VALUES = (0.0, 2.0 / 3.0, 3.0, 100.0)
INCIDENCES = (0.0, 30.0, 60.0, 85.0)
# quadrature tolerance: the plugin's table of N (24 incidences x 3072 nodes) and the
# reference quadrature together (measured: see docs/powder.md, "Energy")
FURNACE_TOL = 2e-3


def white_powder(kappa_over_k0: float, g: float, tau_o: float, energy: str,
                 lobes: str = "single,multiple,coherent") -> dict:
    return {"type": "powder", "albedo": {"type": "uniform", "value": 1.0},
            "amplitude_volume": 1.0, "g": g, "extinction": kappa_over_k0 * K0,
            "tau_o": tau_o, "lobes": lobes, "energy": energy, "wavelength": 700.0}


def reflectance(bsdf, theta_i: float) -> float:
    from mitsuba_powder.rendering.furnace import hemispherical_reflectance

    return float(hemispherical_reflectance(bsdf, theta_i)[0])


def test_reference_quadrature_matches_a_midpoint_grid():
    """The cone-resolving quadrature agrees with the midpoint grid of the projected disc
    (helpers.hemispherical_reflectance, an independent scheme) where the latter is accurate
    (broad cone)."""
    from helpers import hemispherical_reflectance as midpoint

    use_variant("llvm_ad_mono")
    bsdf = mi.load_dict(white_powder(1.0, 0.3, 1.0, "paper"))
    for ti in (0.0, 60.0, 85.0):
        a = reflectance(bsdf, ti)
        b = midpoint(bsdf, ti, n=2048)[0]
        assert abs(a - b) < 1e-3 * b, (ti, a, b)


@pytest.fixture(scope="module")
def ladder_reflectance():
    """R_L(g, tau_o, theta_i): reflectance of L1 + L2 alone (paper mode; independent of
    kappa for an infinite layer)."""
    use_variant("llvm_ad_mono")
    out = {}
    for g in G_VALUES:
        for tau in TAU_VALUES:
            bsdf = mi.load_dict(white_powder(0.01, g, tau, "paper", "single,multiple"))
            for ti in INCIDENCES:
                out[g, tau, ti] = reflectance(bsdf, ti)
    return out


@pytest.mark.parametrize("kappa_over_k0", KAPPA_OVER_K0)
def test_white_furnace_conserving(kappa_over_k0, ladder_reflectance):
    """A white powder (rho = 1, A_v = 1, no surface term) in conserving mode reflects
    min(R_L, 1) <= 1 at every incidence, kappa/k0, g and tau_o of the grid."""
    use_variant("llvm_ad_mono")
    worst = 0.0
    for g in G_VALUES:
        for tau in TAU_VALUES:
            bsdf = mi.load_dict(white_powder(kappa_over_k0, g, tau, "conserving"))
            for ti in INCIDENCES:
                r = reflectance(bsdf, ti)
                expected = min(ladder_reflectance[g, tau, ti], 1.0)
                assert r <= 1.0 + FURNACE_TOL, (kappa_over_k0, g, tau, ti, r)
                assert abs(r - expected) <= FURNACE_TOL, (kappa_over_k0, g, tau, ti, r, expected)
                worst = max(worst, r)
    assert worst > 0.5


@pytest.mark.parametrize("kappa_over_k0,tau", [(1.0, 3.0), (10.0, 2.0 / 3.0), (0.01, 3.0),
                                               (1.0, None)])
def test_white_furnace_conserving_spectral(kappa_over_k0, tau):
    """Spectral variant (N per wavelength of a 10 nm grid, interpolated): the white powder
    reflects min(R_L, 1) in every sRGB channel, in units of the film's response to a unit
    spectrum (R_L, of a uniform albedo and a given tau_o, does not depend on wavelength).
    tau None: hematite's Fresnel tau_o (8.4-18.8, the 1 nm table of the volume constants),
    where R_L > 1 at every wavelength."""
    use_variant("llvm_ad_spectral")
    # kappa/k0 at 830 nm, the longest wavelength (larger at shorter ones)
    props = {**white_powder(kappa_over_k0, 0.3, tau, "conserving"),
             "extinction": kappa_over_k0 * 2.0 * np.pi / 0.83}
    del props["wavelength"]
    if tau is None:
        del props["tau_o"]
    bsdf = mi.load_dict(props)
    from mitsuba_powder.rendering.furnace import hemispherical_reflectance

    # the film's channels for a reflectance of 1 at every wavelength, by the same quadrature
    white = hemispherical_reflectance(
        mi.load_dict({"type": "diffuse", "reflectance": {"type": "uniform", "value": 1.0}}),
        0.0)
    ladder = mi.load_dict({**props, "energy": "paper", "lobes": "single,multiple"})
    for ti in (0.0, 60.0, 85.0):
        r = hemispherical_reflectance(bsdf, ti) / white
        expected = np.minimum(hemispherical_reflectance(ladder, ti) / white, 1.0)
        assert np.all(r <= 1.0 + FURNACE_TOL), (ti, r)
        np.testing.assert_allclose(r, expected, atol=FURNACE_TOL, err_msg=f"{ti} deg")


def test_paper_mode_exceeds_one_where_conserving_does_not():
    """The negative control: the same furnace in paper mode passes 1 (broad cone, and a
    ladder that alone exceeds 1 at large tau_o)."""
    use_variant("llvm_ad_mono")
    assert reflectance(mi.load_dict(white_powder(1.0, 0.0, 2.0 / 3.0, "paper")), 0.0) > 1.1
    assert reflectance(mi.load_dict(white_powder(1e-3, 0.0, 3.0, "paper")), 0.0) > 1.5


@pytest.mark.parametrize("variant", ["llvm_ad_mono", "llvm_ad_rgb", "llvm_ad_spectral",
                                     "scalar_rgb"])
def test_modes_agree_in_the_narrow_cone_regime(variant):
    """kappa/k0 <= 0.05 and a ladder that conserves energy (R_L <= 1): conserving equals
    paper within 1 % for every direction pair."""
    use_variant(variant)
    rng = np.random.default_rng(3)
    n = 200 if variant.startswith("scalar") else 20_000
    wi = random_hemisphere(n, rng, 0.02)
    wo = random_hemisphere(n, rng, 0.02)
    wo[: n // 2] = wi[: n // 2]  # at the peak of the cone, where C is largest
    lam = None
    if "spectral" in variant:
        lam = np.sort(rng.uniform(360.0, 830.0, size=(n, 4)), axis=1)
    for kappa_over_k0 in (1e-3, 0.01, 0.05):
        for rho, g, tau in ((1.0, 0.0, 2.0 / 3.0), (0.9, 0.5, 1.0), (0.5, -0.5, 0.3)):
            # kappa/k0 at the longest wavelength evaluated (830 nm spectral)
            lam_max = 0.83 if "spectral" in variant else 0.7
            props = {"type": "powder", "albedo": rho, "g": g, "tau_o": tau,
                     "extinction": kappa_over_k0 * 2.0 * np.pi / lam_max, "wavelength": 700.0,
                     "rgb_wavelengths": "700, 600, 500"}
            paper = evaluate(mi.load_dict({**props, "energy": "paper"}), wi, wo, lam)
            cons = evaluate(mi.load_dict({**props, "energy": "conserving"}), wi, wo, lam)
            ok = paper > 1e-6
            ratio = cons[ok] / paper[ok]
            assert np.all(ratio <= 1.0 + 1e-3) and np.all(ratio >= 0.99), (
                kappa_over_k0, rho, g, tau, ratio.min(), ratio.max())


@pytest.mark.parametrize("variants", [("scalar_rgb", "llvm_ad_rgb"),
                                      ("scalar_spectral", "llvm_ad_spectral"),
                                      ("scalar_spectral", "llvm_ad_spectral", "mie"),
                                      ("scalar_spectral_polarized", "llvm_ad_spectral_polarized"),
                                      ("llvm_ad_mono", "llvm_ad_mono_polarized")])
def test_scalar_and_llvm_tables_agree(variants):
    """The scalar variants' loop and the vectorised table give the same values (and the
    polarized variants those of the unpolarized ones); N lowers the value here."""
    props = {"type": "powder", "albedo": 0.95, "g": 0.2, "tau_o": 2.0, "extinction": 6.0,
             "rgb_wavelengths": "700, 600, 500"}
    if variants[-1] == "mie":  # the spectral 1 nm table of the volume constants
        variants = variants[:-1]
        props = {"type": "powder", "radius": 0.1, "g": 0.2, "extinction": 6.0}
    rng = np.random.default_rng(4)
    wi = random_hemisphere(300, rng, 0.02)
    wo = random_hemisphere(300, rng, 0.02)
    lam = np.sort(rng.uniform(360.0, 830.0, size=(300, 4)), axis=1)
    out = []
    for variant in variants:
        use_variant(variant)
        lv = lam if "spectral" in variant else None
        out.append(evaluate(mi.load_dict({**props, "energy": "conserving"}), wi, wo, lv))
        paper = evaluate(mi.load_dict(props), wi, wo, lv)
        assert np.all(out[-1] < paper), variant
    np.testing.assert_allclose(out[0], out[1], rtol=2e-4, atol=0.0)


@pytest.mark.parametrize("variant,extra,lam_nm", [
    ("llvm_ad_mono", {"wavelength": 700.0}, 700.0),
    ("llvm_ad_rgb", {"rgb_wavelengths": "611.3, 549.1, 464.3"}, 611.3),
    ("llvm_ad_spectral", {}, 830.0),
    ("scalar_rgb", {"rgb_wavelengths": "500, 650, 450"}, 650.0),
])
def test_regime_warning(variant, extra, lam_nm):
    """kappa/k0 above 0.25 at the longest evaluated wavelength warns, naming the property,
    its value, kappa/k0 and the threshold; just below it does not."""
    use_variant(variant)
    limit = 0.25 * 2.0 * np.pi / (lam_nm * 1e-3)  # extinction at kappa/k0 = 0.25
    base = {"type": "powder", "albedo": 0.8, **extra}
    warnings = load_and_capture({**base, "extinction": 1.02 * limit})
    assert len(warnings) == 1, warnings
    text = warnings[0]
    assert '"extinction"' in text and f"{1.02 * limit:g}"[:5] in text, text
    assert "kappa/k0 = 0.255" in text and "0.25" in text, text
    assert load_and_capture({**base, "extinction": 0.98 * limit}) == []


def test_bad_energy_values():
    use_variant("llvm_ad_rgb")
    with pytest.raises(RuntimeError, match=r'"energy" = "conserve" is not valid; valid '
                                           r'values are "paper" and "conserving"'):
        mi.load_dict({"type": "powder", "albedo": 0.5, "energy": "conserve"})
    with pytest.raises(RuntimeError, match="conserving.*spatially uniform albedo"):
        mi.load_dict({"type": "powder", "energy": "conserving",
                      "albedo": {"type": "checkerboard"}})


# (properties, whether N < 0.9 somewhere: a ladder above 1 or a broad cone)
CONSERVING_SETS = [
    ({"albedo": 0.99, "extinction": 3.0, "tau_o": 2.0, "energy": "conserving"}, True),
    ({"albedo": 0.99, "extinction": 30.0, "g": -0.5, "amplitude_surface": 1e-3,
      "energy": "conserving"}, True),
    ({"radius": 0.05, "extinction": 0.5, "energy": "conserving"}, False),
]


@pytest.mark.parametrize("props,lowered", CONSERVING_SETS)
def test_eval_pdf_and_sample_weights_in_conserving_mode(props, lowered):
    use_variant("llvm_ad_rgb")
    rng = np.random.default_rng(8)
    bsdf = mi.load_dict({"type": "powder", **props})
    n = 20_000
    wi = random_hemisphere(n, rng, 1e-3)
    wo = random_hemisphere(n, rng)
    v, p = evaluate(bsdf, wi, wo, what="eval_pdf")
    np.testing.assert_array_equal(v, evaluate(bsdf, wi, wo))
    np.testing.assert_array_equal(p, evaluate(bsdf, wi, wo, what="pdf"))
    wo_s, pdf, weight = sample(bsdf, wi, rng.random(n), rng.random((n, 2)))
    ok = pdf > 0
    v, p = evaluate(bsdf, wi[ok], wo_s[ok], what="eval_pdf")
    np.testing.assert_allclose(weight[ok], v / p[:, None], rtol=1e-4)
    paper = evaluate(mi.load_dict({"type": "powder", **props, "energy": "paper"}),
                     wi[ok], wo_s[ok])
    assert np.all(v <= paper * (1 + 1e-5) + 1e-12)  # the factor only lowers these sets
    assert np.any(v < 0.9 * paper) == lowered


def test_chi2_in_conserving_mode(tmp_path, monkeypatch):
    from mitsuba.chi2 import ChiSquareTest, SphericalDomain

    monkeypatch.chdir(tmp_path)
    use_variant("llvm_ad_rgb")
    wi = direction(40.0)
    sample_func, pdf_func = adapters({"albedo": 0.99, "extinction": 6.0, "tau_o": 2.0,
                                      "amplitude_surface": 1e-3, "energy": "conserving"}, wi)
    chi2 = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                         sample_dim=3, res=201, ires=8)
    assert chi2.run(), chi2.messages


@pytest.mark.parametrize("case", ["below_cap", "capped", "mie"])
def test_gradients_in_conserving_mode(case):
    """AD through the tabulated N against central finite differences, below the cap
    (A_v R_L < 1), on it (A_v R_L > 1 in some channels, where A_v no longer changes the
    volume part) and with the Mie albedo (gradients of the radius through N)."""
    use_variant("llvm_ad_rgb")
    capped = case == "capped"
    props = {"type": "powder", "albedo": {"type": "rgb", "value": [0.9, 0.7, 0.5]},
             "amplitude_volume": 3.0 if capped else 1.2, "g": 0.3, "extinction": 2.0,
             "tau_o": 4.0 if capped else 1.5, "thickness": 0.3, "amplitude_surface": 1e-3,
             "correlation_length": 1.5, "energy": "conserving"}
    if case == "mie":
        del props["albedo"]
        props["radius"] = 0.08
    bsdf = mi.load_dict(props)
    params = mi.traverse(bsdf)
    for key, comp, grad, fd, (value, x0) in gradients_and_differences(bsdf, params):
        scale = max(abs(fd), 1e-3 * abs(value) / max(abs(x0), 1e-6))
        assert abs(grad - fd) <= 0.02 * scale, f"{key}[{comp}]: AD {grad}, FD {fd}"


def test_conserving_updates_reuse_kernels():
    """The table of N is rebuilt on every update from opaque parameters: after a first
    update no new kernel is compiled (paper mode's property, tested in test_autodiff)."""
    use_variant("llvm_ad_rgb")
    bsdf = mi.load_dict({"type": "powder", "albedo": {"type": "rgb", "value": [0.9, 0.7, 0.5]},
                         "g": 0.3, "extinction": 2.0, "tau_o": 1.5, "thickness": 0.3,
                         "amplitude_surface": 1e-3, "energy": "conserving"})
    params = mi.traverse(bsdf)
    params["g"] = mi.Float(0.2)  # a first update builds the table once
    params.update()
    assert_updates_reuse_kernels(bsdf, [("g", 0.1), ("extinction", 5.0), ("tau_o", 3.0),
                                        ("thickness", 0.5), ("amplitude_volume", 0.8)])
