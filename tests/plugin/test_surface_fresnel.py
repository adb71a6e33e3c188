"""surface_fresnel = "fresnel": the surface term times F(c) / F(1), the unpolarised Fresnel
reflectance of the grain material at the half vector normalised to normal incidence
(docs/model.md, "Surface reflectance factor").

Against docs/model.md's reference values and the independent complex-arithmetic oracle
(tests/oracles/model.py: fresnel_unpolarized, surface_fresnel_factor) in five variants; the
rest of the BSDF unchanged; sample weights = eval / pdf; gradients against finite
differences; the bad-input errors; the surface term's energy bound."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import (
    Albedo,
    channel_wavelengths,
    evaluate,
    is_scalar,
    random_hemisphere,
    sample,
    use_variant,
)
from oracles.model import Params, brdf_terms, fresnel_unpolarized, surface_fresnel_factor

VARIANTS = ["scalar_rgb", "scalar_spectral", "llvm_ad_rgb", "llvm_ad_mono", "llvm_ad_spectral"]
#: docs/model.md's reference values: index -> {angle (deg): F}
MODEL_F = {1.35: {0.0: 0.022182, 60.0: 0.062869, 80.0: 0.353341},
           3.0 + 0.1j: {0.0: 0.250468, 80.0: 0.433172}}


def mirror_pairs(angles_deg) -> tuple[np.ndarray, np.ndarray]:
    t = np.radians(np.asarray(angles_deg, np.float64))
    wi = np.stack([np.sin(t), np.zeros_like(t), np.cos(t)], axis=1)
    return wi, wi * np.array([-1.0, -1.0, 1.0])


def test_oracle_reproduces_model_md():
    for m, values in MODEL_F.items():
        for angle, f in values.items():
            assert fresnel_unpolarized(np.cos(np.radians(angle)), m) == pytest.approx(f,
                                                                                      abs=6e-7)


@pytest.mark.parametrize("variant", VARIANTS)
@pytest.mark.parametrize("m", list(MODEL_F))
def test_factor_equals_model_md_ratios(variant, m):
    """In the mirror direction c = mu_i: eval(fresnel) / eval(none) = F(mu_i) / F(1)."""
    use_variant(variant)
    angles = list(MODEL_F[m])
    wi, wo = mirror_pairs(angles)
    lam = channel_wavelengths(len(angles), np.random.default_rng(0))
    common = {"type": "powder", "eta": float(np.real(m)), "k": float(np.imag(m)),
              "lobes": "surface", "amplitude_surface": 1e-3, "correlation_length": 1.0}
    got = (evaluate(mi.load_dict({**common, "surface_fresnel": "fresnel"}), wi, wo, lam)
           / evaluate(mi.load_dict(common), wi, wo, lam))
    f = MODEL_F[m]
    want = np.array([f[a] / f[0.0] for a in angles])
    # docs/model.md's F values have 6 digits: their ratios are known to ~3e-6 relative
    np.testing.assert_allclose(got, np.broadcast_to(want[:, None], got.shape), rtol=1e-5)
    oracle = fresnel_unpolarized(np.cos(np.radians(angles)), m) / fresnel_unpolarized(1.0, m)
    np.testing.assert_allclose(got, np.broadcast_to(oracle[:, None], got.shape), rtol=2e-6)


def random_case(rng: np.random.Generator, k: int) -> tuple[Params, Albedo, complex]:
    p = Params(amplitude_volume=rng.uniform(0.3, 1.5), g=rng.uniform(-0.8, 0.8),
               extinction=10 ** rng.uniform(-1.5, 0.5), tau_o=rng.uniform(0.5, 8.0),
               amplitude_surface=10 ** rng.uniform(-5, -2),
               correlation_length=10 ** rng.uniform(-1, 0.7),
               specular="harvey_shack" if k % 2 else "gaussian", sigma=rng.uniform(0.05, 0.4))
    m = complex(rng.uniform(1.1, 3.2), rng.choice([0.0, rng.uniform(0.0, 0.6)]))
    return p, Albedo(rng.uniform(0.1, 0.95, 3)), m


@pytest.mark.parametrize("variant", VARIANTS)
def test_eval_matches_the_oracle(variant):
    """Every term as the reference computes it, the surface term times the oracle's factor:
    1e-4 relative, both surface models, random directions (a third near the mirror)."""
    use_variant(variant)
    rng = np.random.default_rng(26)
    n = 200 if is_scalar() else 4000
    for k in range(8):
        p, albedo, m = random_case(rng, k)
        wi = random_hemisphere(n, rng, min_mu=0.02)
        wo = random_hemisphere(n, rng, min_mu=0.02)
        wo[: n // 3] = wi[: n // 3] * np.array([-1.0, -1.0, 1.0])
        wi, wo = (w.astype(np.float32).astype(np.float64) for w in (wi, wo))
        lam = channel_wavelengths(n, rng)
        p32 = p.as_float32()
        bsdf = mi.load_dict({"type": "powder", "albedo": albedo.as_dict(), **p.properties(),
                             "eta": m.real, "k": m.imag, "surface_fresnel": "fresnel"})
        got = evaluate(bsdf, wi, wo, lam)
        terms = brdf_terms(wi, wo, albedo.at(lam), lam, p32)
        m32 = complex(np.float32(m.real), np.float32(m.imag))
        factor = surface_fresnel_factor(wi, wo, m32)
        want = (terms["single"] + terms["multiple"] + terms["coherent"]
                + terms["surface"] * factor) * wo[:, 2:3]
        floor = 1e-9 * np.max(np.abs(want))
        err = np.abs(got - want) / (np.abs(want) + floor)
        assert err.max() <= 1e-4, (variant, k, p, m, err.max())


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_spectral", "scalar_spectral"])
def test_material_index_per_channel(variant):
    """The factor uses the material's index at each channel's wavelength (hematite here:
    RGB at rgb_wavelengths, spectral at each sample's wavelength from the 1 nm table)."""
    from pathlib import Path

    import mitsuba_powder
    from mitsuba_powder import _optics

    use_variant(variant)
    data = Path(mitsuba_powder.__file__).parent / "data" / "optical_constants"
    n_pairs = 6
    wi, wo = mirror_pairs(np.linspace(10.0, 80.0, n_pairs))
    lam = channel_wavelengths(n_pairs, np.random.default_rng(2))
    common = {"type": "powder", "albedo": 0.5, "lobes": "surface", "amplitude_surface": 1e-3}
    got = (evaluate(mi.load_dict({**common, "surface_fresnel": "fresnel"}), wi, wo, lam)
           / evaluate(mi.load_dict(common), wi, wo, lam))
    wl, n, k = (np.array(v) for v in _optics.hematite_average(
        str(data / "hematite_Querry-o.yml"), str(data / "hematite_Querry-e.yml")))
    m = np.interp(lam * 1e-3, wl, n) + 1j * np.interp(lam * 1e-3, wl, k)
    want = fresnel_unpolarized(wi[:, 2:3], m) / fresnel_unpolarized(1.0, m)
    np.testing.assert_allclose(got, want, rtol=1e-3)
    assert np.ptp(got[-1]) > 1e-3  # a different index per channel


def test_default_is_the_paper_and_other_terms_unchanged():
    use_variant("llvm_ad_rgb")
    rng = np.random.default_rng(3)
    wi = random_hemisphere(500, rng, min_mu=0.05)
    wo = random_hemisphere(500, rng, min_mu=0.05)
    base = {"type": "powder", "eta": 1.5, "k": 0.0, "albedo": 0.7, "amplitude_surface": 1e-3}
    np.testing.assert_array_equal(evaluate(mi.load_dict(base), wi, wo),
                                  evaluate(mi.load_dict({**base, "surface_fresnel": "none"}),
                                           wi, wo))
    volume = {**base, "lobes": "single,multiple,coherent"}
    np.testing.assert_array_equal(
        evaluate(mi.load_dict(volume), wi, wo),
        evaluate(mi.load_dict({**volume, "surface_fresnel": "fresnel"}), wi, wo))
    assert "surface_fresnel = fresnel" in str(mi.load_dict({**base,
                                                            "surface_fresnel": "fresnel"}))


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_spectral", "llvm_ad_mono"])
@pytest.mark.parametrize("specular", ["harvey_shack", "gaussian"])
def test_sample_weights_are_eval_over_pdf(variant, specular):
    use_variant(variant)
    rng = np.random.default_rng(5)
    n = 20000
    props = {"type": "powder", "eta": 1.35, "k": 0.0, "albedo": 0.8, "extinction": 0.5,
             "amplitude_surface": 2e-3, "correlation_length": 2.0, "specular": specular,
             "sigma": 0.1, "surface_fresnel": "fresnel"}
    bsdf = mi.load_dict(props)
    theta = np.radians(rng.uniform(0.0, 85.0, n))
    wi = np.stack([np.sin(theta), np.zeros(n), np.cos(theta)], axis=1)
    lam = channel_wavelengths(n, rng)
    wo, pdf, weight = sample(bsdf, wi, rng.uniform(size=n), rng.uniform(size=(n, 2)), lam)
    ok = pdf > 0
    assert ok.mean() > 0.95
    value, pdf2 = evaluate(bsdf, wi[ok], wo[ok], lam[ok], what="eval_pdf")
    np.testing.assert_allclose(pdf2, pdf[ok], rtol=2e-4)
    np.testing.assert_allclose(weight[ok], value / pdf[ok][:, None], rtol=2e-3, atol=1e-6)


def test_lobe_weights_follow_the_factor_at_grazing_light():
    """The surface lobe's share of the samples grows with F(mu_i) / F(1): at 80 degrees
    more samples land near the mirror direction with the factor than without."""
    use_variant("llvm_ad_rgb")
    rng = np.random.default_rng(7)
    n = 40000
    props = {"type": "powder", "eta": 1.35, "k": 0.0, "albedo": 0.8, "amplitude_surface": 1e-4,
             "correlation_length": 2.0}
    t = np.radians(80.0)
    wi = np.tile([np.sin(t), 0.0, np.cos(t)], (n, 1))
    u1, u2 = rng.uniform(size=n), rng.uniform(size=(n, 2))
    near = []
    for mode in ("none", "fresnel"):
        wo, _, _ = sample(mi.load_dict({**props, "surface_fresnel": mode}), wi, u1, u2)
        near.append(np.mean(np.linalg.norm(wo[:, :2] + wi[:, :2], axis=1) < 0.1))
    assert near[1] > 2.0 * near[0], near


def test_gradients_through_the_factor():
    """d eval / d amplitude_surface and d correlation_length with the factor on, against
    central finite differences."""
    use_variant("llvm_ad_rgb")
    rng = np.random.default_rng(11)
    wi = random_hemisphere(64, rng, min_mu=0.2)
    wo = wi * np.array([-1.0, -1.0, 1.0]) + rng.normal(0, 0.05, (64, 3))
    wo[:, 2] = np.abs(wo[:, 2])
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    props = {"type": "powder", "eta": 1.4, "k": 0.01, "albedo": 0.6, "amplitude_surface": 3e-3,
             "correlation_length": 1.5, "lobes": "surface", "surface_fresnel": "fresnel"}
    bsdf = mi.load_dict(props)
    params = mi.traverse(bsdf)
    si = dr.zeros(mi.SurfaceInteraction3f, 64)
    si.wi = mi.Vector3f(*(wi.T.astype(np.float32)))
    w = mi.Vector3f(*(wo.T.astype(np.float32)))
    for key, step in (("amplitude_surface", 1e-4), ("correlation_length", 1e-3)):
        x = params[key]
        dr.enable_grad(x)
        params.update()
        value = bsdf.eval(mi.BSDFContext(), si, w)
        dr.backward(dr.sum(value[0] + value[1] + value[2]))
        grad = float(dr.grad(x)[0])
        fd = []
        for sgn in (1.0, -1.0):
            b = mi.load_dict({**props, key: props[key] + sgn * step})
            v = b.eval(mi.BSDFContext(), si, w)
            fd.append(float(dr.sum(v[0] + v[1] + v[2])[0]))
        assert grad == pytest.approx((fd[0] - fd[1]) / (2 * step), rel=2e-3), key
        params = mi.traverse(bsdf)


@pytest.mark.parametrize("props, message", [
    ({"surface_fresnel": "yes"}, '"surface_fresnel" = "yes" is not valid; valid values are '
                                 '"none" and "fresnel"'),
    ({"surface_fresnel": "fresnel", "tau_o": 1.5}, 'give "eta" and "k" (or "material")'),
    ({"surface_fresnel": "fresnel", "eta": 1.0, "k": 0.0}, "too close to 1"),
    ({"surface_fresnel": "fresnel", "eta": 1.003, "k": 0.0}, "too close to 1"),
])
def test_bad_input(props, message):
    use_variant("scalar_rgb")
    with pytest.raises(Exception, match=message.replace("(", r"\(").replace(")", r"\)")):
        mi.load_dict({"type": "powder", "albedo": 0.5, **props})


def test_tau_o_with_eta_is_accepted():
    use_variant("scalar_rgb")
    b = mi.load_dict({"type": "powder", "albedo": 0.5, "tau_o": 1.5, "eta": 1.35, "k": 0.0,
                      "surface_fresnel": "fresnel"})
    assert "surface_fresnel = fresnel" in str(b)


def test_surface_energy_bound():
    """The factor F(c) / F(1) lies in [1, 1 / F(1)] for a dielectric (F grows from normal to
    grazing incidence): the surface term's directional albedo with it lies between the albedo
    without it and 1 / F(1) times that (45x for eta = 1.35), whatever the lobe's width. The
    volume terms, and so energy = "conserving"'s bound on them, are untouched (test above).
    Integrated on a fine grid, incidences 0-89 deg (docs/powder.md, "Surface reflectance
    factor", has the values)."""
    use_variant("llvm_ad_rgb")
    m = 1.35
    inv_f1 = 1.0 / fresnel_unpolarized(1.0, m)
    n_t, n_p = 400, 200
    ct = (np.arange(n_t) + 0.5) / n_t  # cos theta_o, midpoint rule
    ph = (np.arange(n_p) + 0.5) / n_p * 2 * np.pi
    C, P = np.meshgrid(ct, ph, indexing="ij")
    s = np.sqrt(1 - C**2)
    wo = np.stack([s * np.cos(P), s * np.sin(P), C], axis=-1).reshape(-1, 3)
    cell = (1.0 / n_t) * (2 * np.pi / n_p)  # d(cos theta) d(phi)
    c = np.linspace(0.0, 1.0, 1001)
    ratio = fresnel_unpolarized(c, m) * inv_f1
    assert np.all(np.diff(ratio) <= 0) and ratio[-1] == pytest.approx(1.0)
    for lc in (0.06, 1.0, 3.0):
        for theta in (0.0, 45.0, 75.0, 85.0, 89.0):
            t = np.radians(theta)
            wi = np.tile([np.sin(t), 0.0, np.cos(t)], (len(wo), 1))
            base = {"type": "powder", "eta": m, "k": 0.0, "albedo": 1.0, "lobes": "surface",
                    "amplitude_surface": 1e-3, "correlation_length": lc,
                    "energy": "conserving"}
            albedo = [float(evaluate(mi.load_dict({**base, "surface_fresnel": f}), wi, wo)
                            [:, 1].sum() * cell) for f in ("none", "fresnel")]
            assert albedo[0] * (1 - 1e-5) <= albedo[1] <= albedo[0] * inv_f1, (lc, theta)


def test_fit_and_render_pass_the_option_on(tmp_path, capsys):
    """fit --set surface_fresnel=fresnel writes it into fit.json; render --params passes it
    (and the index) to the scene's powder."""
    import json
    from pathlib import Path

    from mitsuba_powder.cli import main

    params = tmp_path / "truth.json"
    params.write_text(json.dumps({"albedo": 0.9, "eta": 1.35, "k": 0.0,
                                  "amplitude_surface": 5e-4, "correlation_length": 1.0,
                                  "surface_fresnel": "fresnel"}))
    data = tmp_path / "d.csv"
    assert main(["simulate", "--params", str(params), "--protocol", "shadows",
                 "--noise", "0.01", "--out", str(data)]) == 0
    out = tmp_path / "fit"
    assert main(["fit", str(data), "--free", "albedo,amplitude_surface,correlation_length",
                 "--set", "eta=1.35", "--set", "k=0", "--set", "surface_fresnel=fresnel",
                 "--starts", "4", "--figures", "none", "--out", str(out)]) == 0
    fitted = json.loads((out / "fit.json").read_text())["parameters"]
    assert fitted["surface_fresnel"] == "fresnel"
    assert fitted["amplitude_surface"] == pytest.approx(5e-4, rel=0.2)
    scene = Path(__file__).resolve().parents[2] / "scenes" / "powder_patch.xml"
    capsys.readouterr()
    assert main(["render", str(scene), "-o", str(tmp_path / "r.exr"), "-D", "res_x=16",
                 "-D", "res_y=8", "-D", "spp=1", "--params", str(out / "fit.json")]) == 0
    assert "surface_fresnel = fresnel" in capsys.readouterr().out
