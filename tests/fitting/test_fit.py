"""Measurements, protocols, simulation and fitting (issue: fit the model to goniometer data)."""

from __future__ import annotations

import json
import re
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import SHARED, needs_shared, use_variant
from mitsuba_powder.cli import main
from mitsuba_powder.fitting.fit import Problem, default_free, fit, predict, radius_branches
from mitsuba_powder.fitting.protocols import geometries, protocol_geometries, simulate
from mitsuba_powder.io.measurements import (
    MeasurementError,
    Measurements,
    gonio_directions,
    load_measurements,
    save_measurements,
)
from mitsuba_powder.io.ptfe import convert_germer_ptfe
from mitsuba_powder.plugin.brf import BatchBRF, PowderBRF
from mitsuba_powder.plugin.grains import GrainOptics

ROOT = Path(__file__).resolve().parents[2]
SHARED_PTFE = SHARED / "data" / "ptfe_germer2017" / "PTFE.data.csv"

# ----------------------------------------------------------------- loader

GOOD = "theta_i,theta_o,phi,wavelength,brf,sigma\n20,-35,0,700,0.95,0.02\n40,10,90,700,1.1,0.03\n"


@pytest.mark.parametrize("text,fragments", [
    ("theta_i,theta_o,phi,brf\n20,10,0,0.9\n", ["line 1", "missing column(s) ['wavelength']"]),
    ("theta_i,theta_o,phi,wavelength,brdf\n20,10,0,700,0.9\n", ["line 1", "unknown", "brdf"]),
    (GOOD + "20,abc,0,700,0.9,0.02\n", ["line 4", "column 'theta_o'", "'abc' is not a number"]),
    (GOOD + "95,10,0,700,0.9,0.02\n", ["line 4", "column 'theta_i'", "95", "[0, 90)"]),
    (GOOD + "20,-90,0,700,0.9,0.02\n", ["line 4", "column 'theta_o'", "(-90, 90)"]),
    (GOOD + "20,10,0,700,nan,0.02\n", ["line 4", "column 'brf'", "not finite"]),
    (GOOD + "20,10,0,700,-0.1,0.02\n", ["line 4", "column 'brf'", "[0, inf)"]),
    (GOOD + "20,10,0,700,0.9,0\n", ["line 4", "column 'sigma'", "(0, inf)"]),
    (GOOD + "20,10,0,700,0.9\n", ["line 4", "5 fields, expected 6"]),
    ("theta_i,theta_o,phi,wavelength,brf\n", ["no data rows"]),
    ("# only a comment\n", ["no header line"]),
])
def test_bad_measurement_files(tmp_path, text, fragments):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(MeasurementError) as info:
        load_measurements(path)
    for fragment in fragments:
        assert fragment in str(info.value), str(info.value)
    assert str(path) in str(info.value)


def test_round_trip_and_comments(tmp_path):
    path = tmp_path / "good.csv"
    path.write_text("# provenance line\n" + GOOD)
    data = load_measurements(path)
    assert len(data) == 2 and data.comments == ["provenance line"]
    np.testing.assert_array_equal(data.sigma, [0.02, 0.03])
    save_measurements(tmp_path / "copy.csv", data)
    again = load_measurements(tmp_path / "copy.csv")
    np.testing.assert_array_equal(again.brf, data.brf)
    assert again.comments == data.comments


def test_gonio_convention():
    wi, wo = gonio_directions([30.0, 30.0], [30.0, -30.0], [0.0, 0.0])
    np.testing.assert_allclose(wo[0], wi[0], atol=1e-15)                    # back-scattering
    np.testing.assert_allclose(wo[1], wi[1] * [-1, -1, 1], atol=1e-15)      # mirror


# ----------------------------------------------------------------- PTFE


@needs_shared(SHARED_PTFE)
def test_ptfe_conversion_is_reproducible(tmp_path):
    data = convert_germer_ptfe(SHARED_PTFE, tmp_path / "ptfe.csv")
    assert (tmp_path / "ptfe.csv").read_text() == (ROOT / "measurements" /
                                                   "ptfe_germer2017.csv").read_text()
    assert len(data) == 7296 and data.wavelengths().tolist() == [351.0, 532.0, 633.0, 1064.0]


def test_ptfe_azimuth_convention():
    """Germer's source sits at azimuth 180 (phir = 0 is the mirror direction). Converted, the
    (theta_i, theta_o) = (30, 30) view at phir = 0 must be the mirror direction of wi."""
    data = load_measurements(ROOT / "measurements" / "ptfe_germer2017.csv")
    assert "Germer" in " ".join(data.comments)
    wi, wo = data.directions()
    sel = (data.wavelength == 532) & (data.theta_i == 30) & np.isclose(data.theta_o, 30.0)
    cos = np.sum(wi[sel] * wo[sel], axis=1)
    mirror = np.argmin(cos)
    assert np.isclose(cos[mirror], np.cos(np.radians(60.0)))       # 2 x 30 deg from wi
    assert np.isclose(abs(data.phi[sel][mirror]), 180.0)
    np.testing.assert_allclose(wo[sel][mirror], wi[sel][mirror] * [-1, -1, 1], atol=1e-6)
    # sintered PTFE scatters forward: brighter at the mirror than nearest to retro
    assert data.brf[sel][mirror] > data.brf[sel][np.argmax(cos)]


# ----------------------------------------------------------------- protocols


def test_protocol_sizes():
    assert len(geometries("shadows")[0]) == 180
    assert len(geometries("backscatter")[0]) == 33
    # theta_o = 0 is one direction at every azimuth; (0, 0) is in both rigs
    assert len(protocol_geometries("shadows,backscatter")[0]) == 196
    ti, to, ph = geometries("backscatter")
    assert np.all(ph == 0) and set(np.unique(ti)) == {0.0, 20.0, 40.0}
    assert np.all(np.isin(ti, to[ph == 0]))  # exact back-scattering measured
    with pytest.raises(ValueError, match="valid protocols: shadows, backscatter"):
        geometries("moon")


def test_simulate_noise_free_matches_the_plugin():
    props = {"radius": 0.05, "extinction": 0.5, "amplitude_surface": 1e-4}
    data = simulate(props, "backscatter", wavelengths=(550.0,))
    assert data.sigma is None and "SYNTHETIC" in data.comments[0]
    use_variant("scalar_spectral")
    bsdf = mi.load_dict({"type": "powder", **props})
    wi, wo = data.directions()
    for k in range(0, len(data), 7):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*wi[k])
        si.wavelengths = mi.UnpolarizedSpectrum(550.0)
        f = float(np.array(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wo[k]))).ravel()[0])
        assert data.brf[k] == pytest.approx(np.pi * f / wo[k, 2], rel=3e-4)


def test_simulate_noise():
    props = {"radius": 0.05}
    clean = simulate(props, "shadows")
    noisy = simulate(props, "shadows", noise=0.02, seed=3)
    np.testing.assert_allclose(noisy.sigma, 0.02 * clean.brf)
    z = (noisy.brf - clean.brf) / noisy.sigma
    assert abs(z.mean()) < 0.3 and 0.8 < z.std() < 1.2


# ----------------------------------------------------------------- fitting

WAVELENGTHS_26 = tuple(np.arange(360.0, 861.0, 20.0))


def with_replicates(truth: dict, wavelengths=(700.0,), every: int = 5, noise: float = 0.015,
                    seed: int = 11) -> Measurements:
    """Synthetic SHADOWS + back-scattering measurements of ``truth`` (relative ``noise``) in
    which every ``every``-th geometry is measured twice (independent noise)."""
    clean = simulate(truth, "shadows,backscatter", wavelengths)
    idx = np.concatenate([np.arange(len(clean)), np.arange(0, len(clean), every)])
    sigma = noise * clean.brf[idx]
    brf = clean.brf[idx] + np.random.default_rng(seed).normal(size=len(idx)) * sigma
    return Measurements(clean.theta_i[idx], clean.theta_o[idx], clean.phi[idx],
                        clean.wavelength[idx], np.maximum(brf, 0.0), sigma,
                        ["SYNTHETIC DATA with replicated geometries"], "synthetic")


def assert_recovered(result, truth: dict, names, k: float = 3.0) -> None:
    """Each named parameter within k sigma of the truth, with a finite, positive sigma."""
    for name in names:
        err = result.uncertainties[name]
        assert np.isfinite(err) and err > 0, (name, err)
        assert abs(result.parameters[name] - truth[name]) <= k * err, (
            name, truth[name], result.parameters[name], err)


TRUTH = {"amplitude_volume": 1.1, "g": 0.2, "extinction": 0.5, "amplitude_surface": 1e-4,
         "correlation_length": 2.0}


@pytest.mark.parametrize("radius", [0.01, 0.05, 0.3, 2.0])
def test_one_wavelength_default_fit_reaches_the_noise_floor(radius):
    """One wavelength, model-generated data with replicates and 1.5 % noise: the default free
    set (albedo instead of the radius) reaches chi2/N <= 1.2 and recovers the other five; the
    true radius is on one of the reported branches."""
    truth = {**TRUTH, "radius": radius}
    data = with_replicates(truth)
    assert data.geometry_summary()["replicated_rows"] > 0
    result = fit(data, seed=1)
    assert result.free == ["amplitude_volume", "g", "extinction", "albedo", "amplitude_surface",
                           "correlation_length"]
    assert len(result.model_brf) == len(data)
    assert result.chi2_per_point <= 1.2
    assert_recovered(result, truth, TRUTH)
    assert result.agreeing >= 2
    # the radii whose Mie albedo is within 3 sigma of the fitted one include the truth
    branches, _ = radius_branches(700.0, result.parameters["albedo"],
                                  3 * result.uncertainties["albedo"], {})
    assert any(b["lower"] <= radius <= b["upper"] for b in branches), branches
    # and every reported branch radius has the fitted albedo
    for b in result.radius_branches:
        if b["exact"]:
            rho = GrainOptics({}).albedo([700.0], [b["radius"]])[0][0, 0]
            assert rho == pytest.approx(result.parameters["albedo"], abs=1e-6)


def test_replicates_count_in_the_loss():
    """A replicated geometry is a separate observation: it counts in N and in the loss, and
    it pulls the optimum."""
    truth = {**TRUTH, "radius": 0.05}
    base = simulate(truth, "shadows,backscatter", noise=0.01, seed=3)
    rows = np.nonzero(base.theta_i == 0)[0]
    # the same normal-incidence geometries measured again, 20 % brighter
    rep = Measurements(*(np.concatenate([getattr(base, k), getattr(base, k)[rows]])
                         for k in ("theta_i", "theta_o", "phi", "wavelength")),
                       np.concatenate([base.brf, 1.2 * base.brf[rows]]),
                       np.concatenate([base.sigma, base.sigma[rows]]))
    summary = rep.geometry_summary()
    assert summary["rows"] == len(base) + len(rows)
    assert summary["replicated_rows"] >= len(rows)
    fixed = {k: v for k, v in truth.items() if k != "amplitude_volume"}
    one = fit(base, free=["amplitude_volume"], fixed=fixed, starts=4)
    two = fit(rep, free=["amplitude_volume"], fixed=fixed, starts=4)
    assert len(two.model_brf) == len(rep)
    explicit = np.sum(((two.model_brf - rep.brf) / rep.sigma) ** 2)
    assert two.loss == pytest.approx(explicit, rel=1e-9)
    assert two.parameters["amplitude_volume"] > one.parameters["amplitude_volume"] + \
        5 * two.uncertainties["amplitude_volume"]


@pytest.mark.parametrize("radius", [0.05, pytest.param(0.01, marks=pytest.mark.slow),
                                    pytest.param(0.3, marks=pytest.mark.slow),
                                    pytest.param(2.0, marks=pytest.mark.slow)])
def test_joint_fit_of_26_wavelengths_recovers_the_radius(radius):
    """The seed's 26 wavelengths, replicates, 1.5 % noise: the default free set (the paper's
    six) recovers every parameter, the radius included, within 3 sigma."""
    truth = {**TRUTH, "radius": radius}
    data = with_replicates(truth, WAVELENGTHS_26, every=7, seed=5)
    result = fit(data, seed=2)
    assert result.free == ["amplitude_volume", "g", "extinction", "radius",
                           "amplitude_surface", "correlation_length"]
    assert result.chi2_per_point <= 1.1
    assert_recovered(result, truth, list(truth))
    assert result.agreeing >= 2


def test_joint_fit_over_wavelengths_shares_the_radius():
    """Three wavelengths, no back-scattering rig and no surface lobe: the radius valley is
    narrow (the loss rises fivefold 6 % away from it) and few starts reach it, so this fit
    needs more starts than the default."""
    truth = {"amplitude_volume": 1.0, "g": 0.1, "extinction": 0.6, "radius": 0.08}
    data = simulate(truth, "shadows", wavelengths=(450.0, 550.0, 650.0), noise=0.02, seed=5)
    result = fit(data, free=["amplitude_volume", "g", "extinction", "radius"],
                 fixed={"lobes": "single,multiple,coherent"}, starts=256)
    assert result.chi2_per_point < 1.2
    assert set(result.parameters_by_wavelength) == {450.0, 550.0, 650.0}
    assert_recovered(result, truth, truth)


def test_two_populations_are_fitted_through_the_chain_rule():
    truth = {"amplitude_volume": 1.0, "g": 0.1, "extinction": 0.6, "radius": 0.05,
             "radius2": 0.5, "fraction2": 0.4}
    data = simulate(truth, "shadows", wavelengths=(400.0, 500.0, 600.0, 700.0, 800.0),
                    noise=0.01, seed=8)
    result = fit(data, free=["amplitude_volume", "g", "extinction", "radius", "fraction2"],
                 fixed={"radius2": 0.5, "lobes": "single,multiple,coherent"}, starts=32)
    assert result.chi2_per_point < 1.3
    assert_recovered(result, truth, ["amplitude_volume", "g", "extinction", "radius",
                                     "fraction2"])


def test_joint_fit_frees_the_agglomerate_radius_and_fill():
    """Hematite agglomerates (docs/model.md "Grain models"), the seed's 26 wavelengths, replicates,
    1.5 % noise: the default free set has the agglomerate radius in place of the radius; with
    the fill freed too, all seven are recovered within 3 sigma, through the chain rule of the
    agglomerate albedo's derivatives."""
    truth = {**TRUTH, "agglomerate_radius": 0.15, "agglomerate_fill": 0.4}
    grains = {"grains": "agglomerate", "radius": 0.017}
    data = with_replicates({**truth, **grains}, WAVELENGTHS_26, every=7, seed=6)
    assert default_free(data, grains) == ["amplitude_volume", "g", "extinction",
                                          "agglomerate_radius", "amplitude_surface",
                                          "correlation_length"]
    result = fit(data, free=default_free(data, grains) + ["agglomerate_fill"], fixed=grains,
                 seed=3)
    assert result.chi2_per_point <= 1.1
    assert_recovered(result, truth, list(truth))
    assert result.parameters["grains"] == "agglomerate"


def test_joint_fit_of_slab_grains_recovers_the_grain_size():
    """Hapke's slab grains of radius 1 um: the default free set (the paper's six, the radius
    now the slab's D / 2) recovers every parameter within 3 sigma."""
    truth = {**TRUTH, "radius": 1.0}
    data = with_replicates({**truth, "grains": "slab"}, WAVELENGTHS_26, every=7, seed=7)
    result = fit(data, fixed={"grains": "slab"}, seed=4)
    assert "radius" in result.free
    assert result.chi2_per_point <= 1.1
    assert_recovered(result, truth, list(truth))


@pytest.mark.parametrize("free,fixed,fragment", [
    (["agglomerate_radius"], {}, "used only with grains = 'agglomerate'"),
    (["extinction"], {"grains": "slab", "agglomerate_fill": 0.3}, "used only with grains"),
    (["extinction"], {"grains": "agglomerate"}, "needs agglomerate_radius"),
    (["radius"], {"grains": "agglomerate", "agglomerate_radius": 0.2},
     "fit agglomerate_radius"),
    (["agglomerate_radius"], {"grains": "agglomerate", "radius2": 0.3, "fraction2": 0.5},
     "one population"),
    (["albedo"], {"grains": "slab"}, "cannot be used together"),
])
def test_fit_rejects_inconsistent_grain_models(free, fixed, fragment):
    data = simulate(TRUTH, "shadows", wavelengths=(500.0, 600.0))
    with pytest.raises(ValueError, match=re.escape(fragment)):
        fit(data, free=free, fixed=fixed, starts=1)


def test_grain_optics_agglomerate_and_slab_equal_the_plugin():
    """GrainOptics (the fit's albedo) equals the plugin's eval_attribute for the new grain
    models, and its derivative columns match central differences."""
    use_variant("llvm_ad_mono")
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    for props in ({"grains": "agglomerate", "agglomerate_radius": 0.2, "agglomerate_fill": 0.35},
                  {"grains": "agglomerate", "agglomerate_radius": 0.08, "mixing":
                   "maxwell_garnett"},
                  {"grains": "slab", "radius": 0.8, "radius2": 2.0, "fraction2": 0.3}):
        optics = GrainOptics(props)
        lam = 555.0
        bsdf = mi.load_dict({"type": "powder", **props, "wavelength": lam})
        args = dict(radius=[props.get("radius", 0.017)], radius2=props.get("radius2"),
                    fraction2=props.get("fraction2"),
                    agglomerate_radius=props.get("agglomerate_radius"),
                    agglomerate_fill=props.get(
                        "agglomerate_fill", 0.5 if props["grains"] == "agglomerate" else None))
        rho, d = optics.albedo([lam], derivatives=True, **args)
        assert rho[0, 0] == pytest.approx(float(bsdf.eval_attribute("albedo", si)[0][0]),
                                          rel=1e-6)
        for k, name in enumerate(("radius", "radius2", "fraction2", "agglomerate_radius",
                                  "agglomerate_fill")):
            value = args[name][0] if name == "radius" else args[name]
            in_use = value is not None and not (name == "radius" and
                                                props["grains"] == "agglomerate")
            if not in_use:
                assert np.all(d[0, :, k] == 0.0), name
                continue
            h = 1e-5 * value
            up, dn = dict(args), dict(args)
            up[name] = [value + h] if name == "radius" else value + h
            dn[name] = [value - h] if name == "radius" else value - h
            fd = (optics.albedo([lam], **up)[0] - optics.albedo([lam], **dn)[0]) / (2 * h)
            np.testing.assert_allclose(d[0, :, k], fd[0], rtol=2e-3, atol=1e-7, err_msg=name)


def test_free_albedo_is_fitted_per_wavelength():
    truth = {"amplitude_volume": 1.0, "g": 0.0, "extinction": 1.0, "tau_o": 0.6667}
    parts = [simulate({**truth, "albedo": a}, "shadows", (w,), noise=0.01, seed=int(w))
             for w, a in [(500.0, 0.6), (700.0, 0.9)]]
    data = Measurements(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                          ("theta_i", "theta_o", "phi", "wavelength", "brf", "sigma")))
    result = fit(data, free=["albedo", "g"], fixed={k: v for k, v in truth.items()
                                                    if k != "g"}, starts=4)
    assert set(result.uncertainties) == {"albedo@500", "albedo@700", "g"}
    assert result.parameters_by_wavelength[500.0]["albedo"] == pytest.approx(0.6, abs=0.02)
    assert result.parameters_by_wavelength[700.0]["albedo"] == pytest.approx(0.9, abs=0.02)
    assert result.parameters["albedo"]["type"] == "irregular"


def test_a_shadows_style_file_with_theta_o_0_in_every_plane_and_replicates_fits(tmp_path,
                                                                                 capsys):
    """The SHADOWS protocol as the instrument runs it: theta_o = 0 in every azimuth plane (one
    direction, measured five times per incidence) and a repeated scan; it loads and fits."""
    truth = {**TRUTH, "radius": 0.05}
    ti, to, ph = geometries("shadows")  # 180 rows, not de-duplicated
    ti, to, ph = (np.concatenate([a, a[:45]]) for a in (ti, to, ph))  # theta_i = 0 scanned twice
    clean = PowderBRF(Measurements(ti, to, ph, np.full(len(ti), 700.0), np.zeros(len(ti))),
                      truth).brf()
    sigma = 0.015 * clean
    brf = clean + np.random.default_rng(2).normal(size=len(ti)) * sigma
    path = tmp_path / "synthetic_shadows_style.csv"
    save_measurements(path, Measurements(ti, to, ph, np.full(len(ti), 700.0), brf, sigma,
                                         ["SYNTHETIC DATA, SHADOWS-style scan"]))
    data = load_measurements(path)
    summary = data.geometry_summary()
    assert summary["rows"] == 225 and summary["replicated_rows"] > 45
    assert main(["fit", str(path), "--out", str(tmp_path / "fit")]) == 0
    printed = capsys.readouterr().out
    assert "225 measurements" in printed and "replicated" in printed
    report = json.loads((tmp_path / "fit" / "fit.json").read_text())
    assert report["n_measurements"] == 225
    assert report["geometry"]["replicated_rows"] == summary["replicated_rows"]
    assert report["chi2_per_point"] < 1.3


PTFE_FREE = ["amplitude_volume", "g", "extinction", "albedo", "amplitude_surface",
             "correlation_length"]


def _ptfe_reference() -> dict[float, float]:
    rows = json.loads((ROOT / "benchmarks" / "results" / "ptfe_reference.json").read_text())
    return {r["wavelength_nm"]: r["loss"] for r in rows["rows"]}


@pytest.mark.parametrize("wavelength,seeds", [
    (532.0, (0,)),
    pytest.param(351.0, (0, 1, 2), marks=pytest.mark.slow),
    pytest.param(532.0, (1, 2), marks=pytest.mark.slow),
    pytest.param(633.0, (0, 1, 2), marks=pytest.mark.slow),
    pytest.param(1064.0, (0, 1, 2), marks=pytest.mark.slow),
])
def test_ptfe_fit_reaches_the_reference_fits_best_loss(wavelength, seeds):
    """Real NIST PTFE data: the loss is within 2 % of the best the independent 60-start
    reference fit found (benchmarks/ptfe_reference_fit.py: tests/oracles/model.py's NumPy model and
    scipy), and seeds agree within 1 %."""
    data = load_measurements(ROOT / "measurements" / "ptfe_germer2017.csv")
    data = data.subset(data.wavelength == wavelength)
    best = _ptfe_reference()[wavelength]
    losses = [fit(data, PTFE_FREE, {"eta": 1.35, "k": 0.0}, seed=seed).loss for seed in seeds]
    for loss in losses:
        assert loss <= 1.02 * best, (loss, best)
    assert max(losses) <= 1.01 * min(losses)


def test_regime_bounds_the_extinction_to_the_narrow_cone():
    """--regime ebs (default) keeps kappa/k0 <= 0.25 at every fitted wavelength and says when
    the optimum sits on that bound; --regime free lifts it."""
    truth = {**TRUTH, "radius": 0.05, "extinction": 5.0}  # kappa/k0 = 0.56 at 700 nm
    data = simulate(truth, "shadows,backscatter", noise=0.01, seed=3)
    limit = 0.25 * 2 * np.pi / 0.7
    ebs = fit(data, starts=16)
    assert ebs.regime["name"] == "ebs"
    assert ebs.regime["extinction_limit"] == pytest.approx(limit)
    assert ebs.parameters["extinction"] == pytest.approx(limit, rel=1e-3)
    assert any("bound of the EBS regime" in w for w in ebs.warnings)
    assert ebs.chi2_per_point > 1.5  # the data want a broader cone
    free = fit(data, starts=16, regime="free")
    assert free.regime["name"] == "free" and free.regime["extinction_limit"] is None
    assert not any("EBS regime" in w for w in free.warnings)
    assert free.chi2_per_point < 1.2
    assert_recovered(free, truth, ["extinction", "amplitude_volume", "g"])
    assert free.regime["kappa_over_k0"]["700"] == pytest.approx(
        free.parameters["extinction"] * 0.7 / (2 * np.pi))
    # inside the regime both give the same optimum
    inside = simulate({**TRUTH, "radius": 0.05}, "shadows,backscatter", noise=0.01, seed=3)
    a, b = fit(inside, starts=16), fit(inside, starts=16, regime="free")
    assert a.loss == pytest.approx(b.loss, rel=1e-6)
    with pytest.raises(ValueError, match="regime = 'loose' is not valid"):
        fit(inside, regime="loose")
    # a fixed extinction outside the regime is reported
    fixed = fit(inside, free=["g"], fixed={"extinction": 5.0}, starts=2)
    assert any("outside the EBS regime" in w for w in fixed.warnings)


# ----------------------------------------------------------------- the fit's model


@pytest.mark.parametrize("props", [
    {"radius": 0.05, "extinction": 0.5, "amplitude_surface": 1e-4, "g": 0.2},
    {"radius": 0.3, "radius2": 1.2, "fraction2": 0.3, "g": -0.3, "thickness": 20.0,
     "lobes": "single,multiple,coherent", "material": "magnetite"},
    {"eta": 1.35, "k": 0.0, "radius": 0.2, "extinction": 2.0, "specular": "gaussian",
     "sigma": 0.2, "amplitude_surface": 0.05},
])
def test_batch_engine_equals_the_plugin_as_users_load_it(props):
    """BatchBRF (one llvm_ad_spectral instance, albedo and tau_o as numbers from
    grain_optics) equals a llvm_ad_mono instance per wavelength with the grains (PowderBRF)."""
    wavelengths = (351.0, 550.0, 1064.0) if "eta" in props else (400.0, 700.0, 860.0)
    if "thickness" in props:
        wavelengths = (633.0,)  # one wavelength: the llvm_ad_mono engine
    data = simulate(props, "shadows,backscatter", wavelengths)
    optics = GrainOptics(props)
    rho, _ = optics.albedo(data.wavelengths(), [props["radius"]], props.get("radius2"),
                           props.get("fraction2"))
    varying = [k for k in ("amplitude_volume", "g", "extinction", "thickness",
                           "amplitude_surface", "correlation_length", "sigma") if k in props]
    fixed = {k: v for k, v in props.items() if k not in varying}
    engine = BatchBRF(data, fixed, 3, varying)
    values = {k: np.array([props[k], props[k], props[k]]) for k in varying}
    brf, _ = engine.evaluate(values, np.repeat(rho, 3, axis=0),
                             optics.tau_o(data.wavelengths()))
    for b in range(3):
        np.testing.assert_allclose(brf[b], data.brf, rtol=2e-6, atol=1e-9)


def test_grain_optics_equals_the_plugin():
    use_variant("llvm_ad_mono")
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    for props in ({"radius": 0.017}, {"radius": 1.3, "material": "magnetite"},
                  {"radius": 0.05, "radius2": 0.8, "fraction2": 0.6},
                  {"radius": 0.4, "eta": 1.6, "k": 0.01}):
        optics = GrainOptics(props)
        for lam in (360.0, 555.5, 860.0):
            bsdf = mi.load_dict({"type": "powder", **props, "wavelength": lam})
            rho, _ = optics.albedo([lam], [props["radius"]], props.get("radius2"),
                                   props.get("fraction2"))
            assert rho[0, 0] == pytest.approx(float(bsdf.eval_attribute("albedo", si)[0][0]),
                                              rel=1e-6)
            assert optics.tau_o([lam])[0] == pytest.approx(
                float(bsdf.eval_attribute("tau_o", si)[0][0]), rel=1e-6)
    with pytest.raises(ValueError, match="outside the optical constants"):
        GrainOptics({}).index([100.0])
    with pytest.raises(ValueError, match="size parameter"):
        GrainOptics({}).albedo([500.0], [100.0])
    with pytest.raises(ValueError, match="material = 'gold'"):
        GrainOptics({"material": "gold"})
    with pytest.raises(ValueError, match="give both eta and k"):
        GrainOptics({"eta": 1.5})


def test_grain_optics_derivatives_match_finite_differences():
    optics = GrainOptics({})
    wl = np.array([400.0, 700.0])
    for r1, r2, f2 in ((0.05, None, None), (0.08, 0.6, 0.3)):
        rho, d = optics.albedo(wl, [r1], r2, f2, derivatives=True)
        for k, (name, x) in enumerate((("radius", r1), ("radius2", r2), ("fraction2", f2))):
            if x is None:
                continue
            h = 1e-5 * x
            args = [[r1], r2, f2]
            up, dn = list(args), list(args)
            if k == 0:
                up[0], dn[0] = [r1 + h], [r1 - h]
            else:
                up[k], dn[k] = x + h, x - h
            fd = (optics.albedo(wl, *up)[0] - optics.albedo(wl, *dn)[0]) / (2 * h)
            np.testing.assert_allclose(d[0, :, k], fd[0], rtol=2e-3, atol=1e-6, err_msg=name)


def test_problem_jacobian_matches_finite_differences():
    """The Jacobian of the weighted residuals (forward-mode AD in the plugin, the chain rule
    through Mie theory for the radius, per-wavelength albedo columns) against central
    differences in the optimiser's variables."""
    data = simulate({**TRUTH, "radius": 0.08}, "shadows", (450.0, 650.0), noise=0.02, seed=2)
    for free in (["amplitude_volume", "g", "extinction", "radius", "amplitude_surface",
                  "correlation_length"], ["g", "albedo", "tau_o"]):
        problem = Problem(data, free, {})
        y = problem.start()[None] + 0.05
        _, jac = problem.jacobian(y)
        for j in range(len(problem.names)):
            h = 1e-3
            yp, ym = y.copy(), y.copy()
            yp[0, j] += h
            ym[0, j] -= h
            fd = (problem.residuals(yp) - problem.residuals(ym))[0] / (2 * h)
            scale = np.max(np.abs(fd)) + 1e-12
            assert np.max(np.abs(jac[0, :, j] - fd)) <= 2e-2 * scale, problem.names[j]


def test_g_derivative_at_zero():
    """d BRF / d g at the default start g = 0 (the plugin's |g| had a zero derivative there)."""
    data = simulate({"radius": 0.05, "lobes": "single"}, "shadows")
    problem = Problem(data, ["g"], {"lobes": "single"})
    y = np.array([[0.0]])
    _, jac = problem.jacobian(y)
    fd = (problem.residuals(y + 1e-3) - problem.residuals(y - 1e-3))[0] / 2e-3
    np.testing.assert_allclose(jac[0, :, 0], fd, rtol=5e-3, atol=1e-3 * np.max(np.abs(fd)))


# ----------------------------------------------------------------- what the data cannot decide


def test_warnings_for_bounds_undetermined_parameters_and_chi2():
    truth = {**TRUTH, "radius": 0.05, "amplitude_volume": 5.0}  # A_v at its upper bound
    data = simulate(truth, "shadows,backscatter", noise=0.01, seed=4)
    data.sigma = data.sigma * 0.2  # understated errors: chi2/N ~ 25
    result = fit(data, free=["amplitude_volume", "g", "thickness"],
                 fixed={k: v for k, v in truth.items() if k not in ("amplitude_volume", "g")},
                 starts=8)
    text = "\n".join(result.warnings)
    assert "amplitude_volume = 5 is at its upper bound 5" in text
    # an optically thick layer: the thickness does not change the BRF
    assert "thickness" in text and ("not determined" in text or "exceeds its value" in text)
    assert "chi2/N" in text and result.chi2_per_point > 5
    names, corr = result.correlation
    assert names == ["amplitude_volume", "g", "thickness"] and corr.shape == (3, 3)
    assert np.allclose(np.diag(corr), 1.0)


def test_one_start_is_flagged():
    data = simulate({**TRUTH, "radius": 0.05}, "backscatter", noise=0.01, seed=4)
    result = fit(data, free=["g"], fixed={k: v for k, v in TRUTH.items() if k != "g"},
                 starts=1, polish=1)
    assert result.agreeing == 1
    assert any("only 1 start" in w for w in result.warnings)


def test_optics_in_use_and_the_hematite_notice():
    data = simulate({"radius": 0.05}, "backscatter", noise=0.01, seed=1)
    result = fit(data, free=["g"], starts=2)
    assert "hematite" in result.optics["source"] and "notice" in result.optics
    assert result.optics["tau_o"]["700"] == pytest.approx(
        GrainOptics({}).tau_o([700.0])[0], rel=1e-12)
    ptfe_like = fit(data, free=["g", "albedo"], fixed={"eta": 1.35, "k": 0.0}, starts=2)
    assert "notice" not in ptfe_like.optics and "eta = 1.35" in ptfe_like.optics["source"]
    # k = 0: no radius gives an albedo below 1
    assert ptfe_like.radius_branches == [] and "reachable range" in \
        ptfe_like.optics["radius_note"]


def test_single_wavelength_radius_is_ambiguous_where_mie_albedo_is_not_monotonic():
    """At one wavelength the BRF depends on the radius only through rho(r). rho(r) of
    hematite at 700 nm peaks near 0.1 um, so two radii give the same BRF: the fit cannot tell
    them apart (docs/fitting.md). Several wavelengths remove the ambiguity (next test)."""
    use_variant("llvm_ad_mono")
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    rho = lambda r: float(mi.load_dict({"type": "powder", "radius": r, "wavelength": 700.0})  # noqa: E731
                          .eval_attribute("albedo", si)[0][0])
    radii = np.linspace(0.06, 0.2, 29)
    values = np.array([rho(r) for r in radii])
    peak = int(np.argmax(values))
    assert 0 < peak < len(radii) - 1  # not monotonic: an interior maximum
    # a value below the peak is reached from both sides
    target = values[peak] - 0.05
    assert values[0] < target and values[-1] < target


def test_fit_rejects_bad_parameter_names():
    data = simulate({"radius": 0.05}, "backscatter")
    with pytest.raises(ValueError, match="cannot fit \\['colour'\\]"):
        fit(data, free=["g", "colour"])
    with pytest.raises(ValueError, match="both free and fixed"):
        fit(data, free=["g"], fixed={"g": 0.1})
    with pytest.raises(ValueError, match="radius2 and fraction2"):
        fit(data, free=["radius2"])
    with pytest.raises(ValueError, match="albedo and \\['radius'\\] cannot be used together"):
        fit(data, free=["albedo"], fixed={"radius": 0.05})
    with pytest.raises(ValueError, match="sigma has no effect with specular = 'harvey_shack'"):
        fit(data, free=["sigma"])
    with pytest.raises(ValueError, match="correlation_length has no effect"):
        fit(data, free=["correlation_length"], fixed={"specular": "gaussian"})
    with pytest.raises(ValueError, match="polish = 0 is out of range"):
        fit(data, free=["g"], polish=0)
    with pytest.raises(ValueError, match="eta = 'x'"):
        fit(data, free=["g"], fixed={"eta": "x", "k": 0.0})


def test_cli_simulate_fit_report_and_prediction(tmp_path, capsys):
    params = {"amplitude_volume": 1.1, "g": 0.2, "extinction": 0.45, "radius": 0.05,
              "amplitude_surface": 5e-4, "correlation_length": 1.2}
    (tmp_path / "p.json").write_text(json.dumps(params))
    data_path = tmp_path / "synthetic_powder.csv"
    assert main(["simulate", "--params", str(tmp_path / "p.json"), "--protocol",
                 "shadows,backscatter", "--noise", "0.02", "--out", str(data_path)]) == 0
    assert "SYNTHETIC" in data_path.read_text().splitlines()[0]
    out = tmp_path / "fit"
    assert main(["fit", str(data_path), "--starts", "16", "--fit-incidences", "0,20,40",
                 "--set", "radius=0.05", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "held-out" in printed and "starts reached the best loss" in printed
    assert "chi2/N" in printed and "material hematite" in printed and "regime ebs" in printed
    report = json.loads((out / "fit.json").read_text())
    for key in ("parameters", "uncertainties", "residuals", "rmse_brf", "chi2_per_point",
                "relative_rmse_percent", "per_incidence", "optimizer", "prediction",
                "warnings", "correlation", "geometry", "optics", "regime"):
        assert key in report, key
    assert report["optimizer"]["agreeing_starts"] >= 2 and report["optimizer"]["trusted"]
    assert report["geometry"]["rows"] == report["n_measurements"]
    assert report["prediction"]["n"] == int(np.sum(load_measurements(data_path).theta_i == 60))
    assert report["prediction"]["relative_rmse_percent"] < 10
    # the default --figures summary: one set for the whole fit, no per-wavelength files
    # (tests/fitting/test_fit_report.py: every mode)
    for png in ("summary_rmse.png", "summary_residuals.png", "summary_principal_plane.png"):
        assert (out / png).stat().st_size > 10_000
    assert not (out / "principal_plane_700nm.png").exists()
    # the reported parameters reproduce the fitted BRF through mi.load_dict
    use_variant("llvm_ad_mono")
    bsdf = mi.load_dict({"type": "powder", **report["parameters"], "wavelength": 700.0})
    row = report["residuals"][5]
    wi, wo = gonio_directions(row["theta_i"], row["theta_o"], row["phi"])
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.wi = mi.Vector3f(*[float(v) for v in wi[0]])
    f = float(bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*[float(v) for v in wo[0]]))[0][0])
    assert np.pi * f / wo[0, 2] == pytest.approx(row["fitted"], rel=1e-4)
    # and simulate accepts a fit.json
    assert main(["simulate", "--params", str(out / "fit.json"), "--protocol", "backscatter",
                 "--out", str(tmp_path / "again.csv")]) == 0


def test_cli_fit_errors(tmp_path, capsys):
    path = tmp_path / "bad.csv"
    path.write_text("theta_i,theta_o,phi,wavelength,brf\n20,x,0,700,1\n")
    assert main(["fit", str(path)]) == 2
    assert "line 2, column 'theta_o'" in capsys.readouterr().err
    data = simulate({"radius": 0.05}, "backscatter")
    save_measurements(tmp_path / "ok.csv", data)
    assert main(["fit", str(tmp_path / "ok.csv"), "--free", "g,nonsense"]) == 2
    assert "cannot fit ['nonsense']" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "ok.csv"), "--wavelength", "500"]) == 2
    assert "not in" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "ok.csv"), "--fit-incidences", "0,abc"]) == 2
    assert "--fit-incidences '0,abc'" in capsys.readouterr().err
    assert main(["fit", str(tmp_path / "ok.csv"), "--starts", "0"]) == 2
    assert "starts = 0" in capsys.readouterr().err


def test_predict_requires_fitted_wavelengths():
    data = simulate({"radius": 0.05}, "backscatter")
    result = fit(data, free=["g"], starts=1)
    other = simulate({"radius": 0.05}, "backscatter", wavelengths=(500.0,))
    with pytest.raises(ValueError, match="500 nm was not fitted"):
        predict(result, other)
    np.testing.assert_allclose(predict(result, data), result.model_brf, rtol=1e-6)
    assert isinstance(PowderBRF(data, {"radius": 0.05}).brf(), np.ndarray)


def test_ptfe_script_runs_in_quick_mode(tmp_path):
    import subprocess
    import sys

    for script in ("docs/scripts/ptfe_fits.py",):
        proc = subprocess.run([sys.executable, str(ROOT / script), "--quick", "--out",
                               str(tmp_path)], capture_output=True, text=True, timeout=600)
        assert proc.returncode == 0, proc.stderr
    assert "| 532 | 1824 |" in (tmp_path / "ptfe_fits.md").read_text()
