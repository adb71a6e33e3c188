"""Baseline models (Lambertian, Oren-Nayar, RTLSR, Hapke) and compare-models."""

from __future__ import annotations

import json

import numpy as np
import pytest

from helpers import random_hemisphere
from mitsuba_powder.cli import main
from mitsuba_powder.fitting.baselines import MODELS, fit_baseline, hapke, oren_nayar, rtlsr_kernels
from mitsuba_powder.fitting.protocols import protocol_geometries, simulate
from mitsuba_powder.io.measurements import Measurements, gonio_directions, save_measurements

HAPKE = {"w": 0.8, "b": 0.3, "c": 0.4, "B_s0": 1.0, "h_s": 0.06, "B_c0": 0.5, "h_c": 0.02,
         "theta_bar": 15.0}


def test_rtlsr_kernels_known_values():
    wi, wo = gonio_directions([0.0, 30.0], [0.0, 30.0], [0.0, 0.0])
    k_vol, k_geo = rtlsr_kernels(wi, wo)
    assert k_vol[0] == pytest.approx(0.0, abs=1e-12) and k_geo[0] == pytest.approx(0.0, abs=1e-12)
    # hot spot at 30 deg: xi = 0, K_vol = (pi/2) / (2 cos 30) - pi/4
    assert k_vol[1] == pytest.approx(np.pi / 2 / (2 * np.cos(np.radians(30))) - np.pi / 4)


@pytest.mark.parametrize("name", sorted(MODELS))
def test_baselines_are_reciprocal_and_finite(name):
    rng = np.random.default_rng(2)
    wi, wo = random_hemisphere(500, rng, 0.05), random_hemisphere(500, rng, 0.05)
    func, specs = MODELS[name]
    params = HAPKE if name == "hapke" else {k: s.start for k, s in specs.items()}
    a, b = func(params, wi, wo), func(params, wo, wi)
    assert np.all(np.isfinite(a))
    np.testing.assert_allclose(a, b, rtol=1e-10)


def test_hapke_limits():
    wi, wo = gonio_directions([20.0, 40.0], [-10.0, 40.0], [0.0, 0.0])
    # small w, isotropic, no opposition: Lommel-Seeliger, BRF = w / (4 (mu0 + mu))
    p = {**HAPKE, "w": 1e-5, "b": 0.0, "B_s0": 0.0, "B_c0": 0.0}
    np.testing.assert_allclose(hapke(p, wi, wo), 1e-5 / (4 * (wi[:, 2] + wo[:, 2])), rtol=1e-4)
    # at exact back-scattering (second pair) both opposition terms are at their maximum:
    # B_S = B_C = 1, so the factors are (1 + B_s0) on p and (1 + B_c0) overall
    base = hapke({**HAPKE, "B_s0": 0.0, "B_c0": 0.0}, wi[1:], wo[1:])
    with_cb = hapke({**HAPKE, "B_s0": 0.0, "B_c0": 0.5}, wi[1:], wo[1:])
    assert with_cb[0] == pytest.approx(1.5 * base[0], rel=1e-5)  # tan(g/2) ~ 1e-8 here


def test_oren_nayar_reduces_to_lambert_and_brightens_towards_retro():
    wi, wo = gonio_directions([40.0, 40.0], [40.0, -40.0], [0.0, 0.0])
    np.testing.assert_allclose(oren_nayar({"rho": 0.6, "sigma": 0.0}, wi, wo), 0.6)
    v = oren_nayar({"rho": 0.6, "sigma": 0.5}, wi, wo)
    assert v[0] > v[1]


def baseline_data(name: str, params: dict) -> Measurements:
    ti, to, ph = protocol_geometries("shadows,backscatter")
    wi, wo = gonio_directions(ti, to, ph)
    brf = MODELS[name][0](params, wi, wo)
    return Measurements(ti, to, ph, np.full(len(ti), 700.0), brf)


@pytest.mark.parametrize("name,params", [
    ("lambertian", {"rho": 0.7}),
    ("oren_nayar", {"rho": 0.7, "sigma": 0.4}),
    ("rtlsr", {"f_iso": 0.6, "f_vol": 0.2, "f_geo": 0.05}),
    ("hapke", HAPKE),
])
def test_fit_baseline_recovers_its_own_data(name, params):
    fitted = fit_baseline(name, baseline_data(name, params), starts=3)[0]
    data = baseline_data(name, params)
    assert np.max(np.abs(fitted.model_brf - data.brf) / data.brf) < 1e-3, fitted.parameters
    if name != "hapke":  # Hapke's 8 parameters trade off; the BRF is what must match
        for k, v in params.items():
            assert fitted.parameters[k] == pytest.approx(v, rel=1e-2, abs=1e-3), k


def test_compare_models_cli(tmp_path, capsys):
    truth = {"amplitude_volume": 1.1, "g": 0.2, "extinction": 0.45, "radius": 0.05,
             "amplitude_surface": 5e-4, "correlation_length": 1.2}
    save_measurements(tmp_path / "d.csv", simulate(truth, "shadows,backscatter", noise=0.02,
                                                   seed=4))
    assert main(["compare-models", str(tmp_path / "d.csv"), "--set", "radius=0.05",
                 "--starts", "1", "--out", str(tmp_path / "cmp")]) == 0
    rows = json.loads((tmp_path / "cmp" / "model_comparison.json").read_text())
    assert {r["model"] for r in rows} == {"powder", "powder + surface Fresnel", "lambertian",
                                          "oren_nayar", "rtlsr", "hapke"}
    best = min(rows, key=lambda r: r["relative_rmse_percent"])
    assert best["model"].startswith("powder")  # the data come from the powder model
    assert "| 700 | powder |" in (tmp_path / "cmp" / "model_comparison.md").read_text()
    with pytest.raises(ValueError, match="unknown model"):
        fit_baseline("phong", baseline_data("lambertian", {"rho": 0.5}))
    with pytest.raises(ValueError, match="starts = 0 is out of range"):
        fit_baseline("lambertian", baseline_data("lambertian", {"rho": 0.5}), starts=0)
    assert main(["compare-models", str(tmp_path / "d.csv"), "--starts", "0"]) == 2
    assert "starts = 0" in capsys.readouterr().err
