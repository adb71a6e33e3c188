"""Measurements, protocols, simulation and fitting (issue: fit the model to goniometer data)."""

from __future__ import annotations

import json
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import use_variant
from mitsuba_powder.cli import main
from mitsuba_powder.fit import fit, predict
from mitsuba_powder.measurements import (
    MeasurementError,
    Measurements,
    gonio_directions,
    load_measurements,
    save_measurements,
)
from mitsuba_powder.model import PowderBRF
from mitsuba_powder.protocols import geometries, protocol_geometries, simulate
from mitsuba_powder.ptfe import convert_germer_ptfe

ROOT = Path(__file__).resolve().parents[1]
SHARED_PTFE = ROOT.parent / "shared" / "data" / "ptfe_germer2017" / "PTFE.data.csv"

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
    (GOOD + "20,35,180,700,0.9,0.02\n", ["line 4", "duplicate of line 2"]),
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


@pytest.mark.skipif(not SHARED_PTFE.is_file(), reason="shared data not beside the repository")
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

CASES = {
    "paper five, back-scattering cone ~3 deg, visible specular": {
        "amplitude_volume": 1.1, "g": 0.2, "extinction": 0.45, "radius": 0.05,
        "amplitude_surface": 5e-4, "correlation_length": 1.2},
    "forward-scattering grains, broad cone, weak specular": {
        "amplitude_volume": 0.8, "g": -0.3, "extinction": 3.0, "radius": 0.03,
        "amplitude_surface": 5e-5, "correlation_length": 0.5},
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_parameter_recovery(case):
    """One wavelength, the default free set (the paper's five; radius fixed at its value)."""
    truth = CASES[case]
    data = simulate(truth, "shadows,backscatter", noise=0.02, seed=11)
    result = fit(data, fixed={"radius": truth["radius"]}, starts=2, seed=1)
    assert "radius" not in result.free and result.parameters["radius"] == truth["radius"]
    truth = {k: v for k, v in truth.items() if k != "radius"}
    assert result.loss < 1.5 * len(data)  # chi^2 per point ~ 1 at the global optimum
    for name, value in truth.items():
        err = result.uncertainties[name]
        assert 0 < err < np.inf
        assert abs(result.parameters[name] - value) <= 3 * err, (name, value,
                                                                 result.parameters[name], err)


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


def test_joint_fit_over_wavelengths_shares_the_radius():
    truth = {"amplitude_volume": 1.0, "g": 0.1, "extinction": 0.6, "radius": 0.08}
    data = simulate(truth, "shadows", wavelengths=(450.0, 550.0, 650.0), noise=0.02, seed=5)
    result = fit(data, free=["amplitude_volume", "g", "extinction", "radius"],
                 fixed={"lobes": "single,multiple,coherent"}, starts=1)
    assert set(result.parameters_by_wavelength) == {450.0, 550.0, 650.0}
    for name, value in truth.items():
        assert abs(result.parameters[name] - value) <= 3 * result.uncertainties[name], name


def test_free_albedo_is_fitted_per_wavelength():
    truth = {"amplitude_volume": 1.0, "g": 0.0, "extinction": 1.0, "tau_o": 0.6667}
    parts = [simulate({**truth, "albedo": a}, "shadows", (w,), noise=0.01, seed=int(w))
             for w, a in [(500.0, 0.6), (700.0, 0.9)]]
    data = Measurements(*(np.concatenate([getattr(p, k) for p in parts]) for k in
                          ("theta_i", "theta_o", "phi", "wavelength", "brf", "sigma")))
    result = fit(data, free=["albedo", "g"], fixed={k: v for k, v in truth.items()
                                                    if k != "g"}, starts=1)
    assert set(result.uncertainties) == {"albedo@500", "albedo@700", "g"}
    assert result.parameters_by_wavelength[500.0]["albedo"] == pytest.approx(0.6, abs=0.02)
    assert result.parameters_by_wavelength[700.0]["albedo"] == pytest.approx(0.9, abs=0.02)
    assert result.parameters["albedo"]["type"] == "irregular"


def test_fit_rejects_bad_parameter_names():
    data = simulate({"radius": 0.05}, "backscatter")
    with pytest.raises(ValueError, match="cannot fit \\['colour'\\]"):
        fit(data, free=["g", "colour"])
    with pytest.raises(ValueError, match="both free and fixed"):
        fit(data, free=["g"], fixed={"g": 0.1})
    with pytest.raises(ValueError, match="radius2 and fraction2"):
        fit(data, free=["radius2"])


def test_cli_simulate_fit_report_and_prediction(tmp_path, capsys):
    params = {"amplitude_volume": 1.1, "g": 0.2, "extinction": 0.45, "radius": 0.05,
              "amplitude_surface": 5e-4, "correlation_length": 1.2}
    (tmp_path / "p.json").write_text(json.dumps(params))
    data_path = tmp_path / "synthetic_powder.csv"
    assert main(["simulate", "--params", str(tmp_path / "p.json"), "--protocol",
                 "shadows,backscatter", "--noise", "0.02", "--out", str(data_path)]) == 0
    assert "SYNTHETIC" in data_path.read_text().splitlines()[0]
    out = tmp_path / "fit"
    assert main(["fit", str(data_path), "--starts", "1", "--fit-incidences", "0,20,40",
                 "--set", "radius=0.05", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    assert "held-out" in printed and "start 1/" in printed
    report = json.loads((out / "fit.json").read_text())
    for key in ("parameters", "uncertainties", "residuals", "rmse_brf",
                "relative_rmse_percent", "per_incidence", "optimizer", "prediction"):
        assert key in report, key
    assert report["prediction"]["n"] == int(np.sum(load_measurements(data_path).theta_i == 60))
    assert report["prediction"]["relative_rmse_percent"] < 10
    for png in ("principal_plane_700nm.png", "polar_700nm.png"):
        assert (out / png).stat().st_size > 10_000
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
