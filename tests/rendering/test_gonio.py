"""Gonio rendering: the BRF measured on renders equals the analytic BRF (deterministic values,
a collimated source in RGB/mono, to a float32 tolerance; Monte Carlo values by their z, below
the Bonferroni bound), the gonio scene file agrees, and a uniform environment renders to the
albedo (white furnace) with BSDF sampling only and with MIS."""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from helpers import use_variant
from mitsuba_powder.cli import main
from mitsuba_powder.fitting.protocols import geometries
from mitsuba_powder.rendering.furnace import white_furnace
from mitsuba_powder.rendering.gonio import FLOAT32_U, GonioResult, render_gonio
from oracles.model import Params, brdf, gonio_directions

SCENE = Path(__file__).resolve().parents[2] / "scenes" / "gonio.xml"
RGB_NM = (611.3, 549.1, 464.3)
PROPS = {"albedo": {"type": "rgb", "value": [0.85, 0.55, 0.3]}, "extinction": 1.0,
         "tau_o": 2.0 / 3.0}


def assert_agrees(r, family=0.01):
    """Deterministic values within the float32 tolerance; Monte Carlo values below the
    Bonferroni bound that any of them exceeds by chance with probability ``family`` (a bound
    of 3 sigma on each of ~100 values would fail by chance for one seed in four: measured on
    the spectral run of :func:`subset`, 32 seeds, std of z 0.95-0.99)."""
    from statistics import NormalDist

    det = r.deterministic()
    bad = det & ~r.agrees()
    assert not bad.any(), (r.relative_difference()[bad], r.relative_tolerance()[bad])
    z = np.abs(r.z()[~det])
    if z.size:
        bound = NormalDist().inv_cdf(1 - family / 2 / z.size)
        assert z.max() < bound, (z.max(), bound)


def subset():
    """A subset of both protocols: every back-scattering geometry of theta_i = 20 (the peak
    and its flanks) and the SHADOWS principal plane and phi = 90 plane at theta_i = 40."""
    ti, to, ph = geometries("backscatter")
    keep = ti == 20.0
    ti2, to2, ph2 = geometries("shadows")
    keep2 = (ti2 == 40.0) & np.isin(ph2, [0.0, 90.0])
    return (np.concatenate([ti[keep], ti2[keep2]]), np.concatenate([to[keep], to2[keep2]]),
            np.concatenate([ph[keep], ph2[keep2]]))


def test_analytic_brf_is_model_md():
    """The analytic column is pi f of docs/model.md (NumPy reference) at the RGB wavelengths, so
    the geometry convention of the virtual goniometer is the measurement convention."""
    ti, to, ph = subset()
    r = render_gonio(PROPS, ti, to, ph, variant="llvm_ad_rgb", spp=1, resolution=2)
    wi, wo = (np.asarray(a) for a in gonio_directions(ti, to, ph))
    rho = np.tile(np.float32([0.85, 0.55, 0.3]).astype(np.float64), (len(ti), 1))
    lam = np.tile(np.float32(RGB_NM).astype(np.float64), (len(ti), 1))
    want = np.pi * brdf(wi, wo, rho, lam, Params().as_float32())
    np.testing.assert_allclose(r.analytic, want, rtol=2e-4)


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_spectral"])
def test_rendered_brf_matches_analytic(variant):
    """Collimated source. In RGB every pixel is the same deterministic value: no z (it would
    only measure rounding), the relative difference within the float32 tolerance. In spectral
    variants the wavelength sampling makes it a real Monte Carlo estimate: the z-test."""
    use_variant(variant)
    ti, to, ph = subset()
    r = render_gonio(PROPS, ti, to, ph, variant=variant, spp=64, resolution=16, seed=1)
    assert r.rendered.shape == (len(ti), 3)
    assert np.all(r.analytic > 0) and np.all(np.isfinite(r.rendered))
    assert_agrees(r)
    peak = (ti == 20) & (to == 20) & (ph == 0)
    assert r.analytic[peak, 0] > 1.3 * r.analytic[(ti == 20) & (to == 10), 0]  # a real peak
    s = r.summary()
    if variant.endswith("spectral"):
        assert not r.deterministic().any()
        assert np.median(r.stderr / r.analytic) > 1e-4  # genuinely noisy
        assert np.abs(r.z()).max() > 0.1
        assert s["monte_carlo"]["values"] == r.stderr.size
        assert s["deterministic"]["values"] == 0
        assert s["deterministic"]["max_relative_difference"] is None
    else:
        det = r.deterministic()
        assert det.all() and np.isnan(r.z()).all()
        # what was the "Monte Carlo error": zero in most values, rounding in the others
        assert (r.stderr == 0).mean() > 0.5 and (r.stderr / r.analytic).max() < 1e-6
        tol = r.relative_tolerance()
        assert np.all(r.relative_difference() <= tol)
        # the tolerance is float32 arithmetic: (64 + 16) u at least, tens of u at most here
        assert 80 * FLOAT32_U <= tol.min() and tol.max() < 1e-4
        assert s["deterministic"]["values"] == det.size and s["monte_carlo"]["values"] == 0
        assert s["deterministic"]["beyond_tolerance"] == 0
        assert 0 < s["deterministic"]["max_relative_difference"] < 5e-6
        assert s["deterministic"]["max_relative_difference"] == s["max_relative_difference"]
        assert s["monte_carlo"]["max_abs_z"] is None


def test_deterministic_check_rejects_a_small_bias():
    """The float32 tolerance is not vacuous: the deterministic values of a collimated RGB
    render reject a 1e-4 relative error of the analytic BRF (a cos theta_i off by one part in
    10^4 would be caught), and a 1e-5 one wherever the tolerance leaves room for it."""
    use_variant("llvm_ad_rgb")
    ti, to, ph = subset()
    r = render_gonio(PROPS, ti, to, ph, variant="llvm_ad_rgb", spp=16, resolution=4, seed=1)
    assert r.agrees().all()
    tol = r.relative_tolerance()
    biased = GonioResult(r.theta_i, r.theta_o, r.phi, r.wavelength, r.channels, r.rendered,
                         r.stderr, r.analytic * (1 + 1e-4), variant=r.variant, spp=r.spp,
                         source_radius=0.0, sensitivity=r.sensitivity)
    assert not biased.agrees().any()
    assert biased.summary()["deterministic"]["beyond_tolerance"] == r.stderr.size
    # |rendered - analytic (1 + b)| >= b - difference > tolerance there (and a margin of 1e-7)
    tight = tol + r.relative_difference() < 1e-5 - 1e-7
    assert tight.mean() > 0.5
    slight = GonioResult(r.theta_i, r.theta_o, r.phi, r.wavelength, r.channels, r.rendered,
                         r.stderr, r.analytic * (1 + 1e-5), variant=r.variant, spp=r.spp,
                         source_radius=0.0, sensitivity=r.sensitivity)
    assert not slight.agrees()[tight].any()


def test_deterministic_tolerance_grows_with_the_samples_per_pixel():
    """A pixel sums its samples in float32: at 1024 spp the rounding of that sum reaches
    1e-5 relative (measured 1.5e-5 over both protocols with a surface term), and the
    tolerance (1024 + 16 + ...) u covers it."""
    use_variant("llvm_ad_rgb")
    ti, to, ph = subset()
    r = render_gonio(dict(PROPS, amplitude_surface=1e-3), ti, to, ph, variant="llvm_ad_rgb",
                     spp=1024, resolution=2, seed=1)
    assert r.deterministic().all() and r.agrees().all()
    assert r.relative_tolerance().min() >= 1040 * FLOAT32_U
    assert r.relative_difference().max() > 1e-6  # the sum's rounding, larger than at 64 spp


def test_zero_standard_error_is_deterministic_in_any_variant():
    """A value whose standard error is exactly 0 has no z (not even in a Monte Carlo
    configuration): it is checked against the float32 tolerance; the others keep the z-test,
    and the summary reports the two kinds separately."""
    a = np.array([[1.0, 2.0, 4.0], [1.0, 1.0, 1.0]])
    rendered = a * np.array([[1 + 1e-6, 1 - 2e-6, 1.0], [1.01, 0.99, 1.0]])
    stderr = np.array([[0.0, 0.0, 0.0], [0.005, 0.005, 0.0]])
    r = GonioResult(np.zeros(2), np.zeros(2), np.zeros(2), np.full(2, np.nan), ["R", "G", "B"],
                    rendered, stderr, a, variant="llvm_ad_spectral", spp=64,
                    source_radius=0.0)
    det = r.deterministic()
    np.testing.assert_array_equal(det, [[True, True, True], [False, False, True]])
    z = r.z()
    assert np.isnan(z[det]).all()
    np.testing.assert_allclose(z[1, :2], [2.0, -2.0], rtol=1e-6)
    assert r.agrees().all()
    s = r.summary()
    assert s["deterministic"]["values"] == 4 and s["monte_carlo"]["values"] == 2
    assert s["deterministic"]["max_relative_difference"] == pytest.approx(2e-6)
    assert s["deterministic"]["relative_tolerance_max"] == pytest.approx(80 * FLOAT32_U)
    assert s["monte_carlo"]["max_abs_z"] == pytest.approx(2.0, rel=1e-6)
    assert s["monte_carlo"]["beyond_3_sigma"] == 0
    # a disk source is Monte Carlo wherever the standard error is not 0
    disk = GonioResult(r.theta_i, r.theta_o, r.phi, r.wavelength, r.channels, rendered,
                       stderr, a, variant="llvm_ad_rgb", spp=64, source_radius=1.0)
    np.testing.assert_array_equal(disk.deterministic(), det)
    collimated = GonioResult(r.theta_i, r.theta_o, r.phi, r.wavelength, r.channels, rendered,
                             stderr, a, variant="llvm_ad_rgb", spp=64, source_radius=0.0)
    assert collimated.deterministic().all()
    assert not collimated.agrees()[1, :2].any()  # a 1 % error is far beyond float32


@pytest.mark.parametrize("strategy", ["emitter", "mis"])
def test_finite_source_matches_source_averaged_brf(strategy):
    """A 1-degree source: the analytic value is the BRF averaged over the source disk by
    quadrature; emitter sampling and MIS estimate it with real Monte Carlo noise."""
    use_variant("llvm_ad_rgb")
    ti, to, ph = subset()
    r = render_gonio(PROPS, ti, to, ph, variant="llvm_ad_rgb", spp=32, resolution=16,
                     source_radius=1.0, strategy=strategy, seed=2)
    assert_agrees(r)
    assert np.median(r.stderr / r.analytic) > 1e-6
    assert not r.deterministic().any() and np.isfinite(r.z()).all()
    point = render_gonio(PROPS, ti, to, ph, variant="llvm_ad_rgb", spp=1, resolution=2)
    peak = (to == 20) & (ph == 0) & (ti == 20)
    # averaging over the source lowers the cusp of the coherent peak, a little
    assert point.analytic[peak, 0] > r.analytic[peak, 0] > 0.98 * point.analytic[peak, 0]


def test_scene_file_is_the_same_goniometer():
    use_variant("llvm_ad_rgb")
    for ti, to, ph in [(30.0, 30.0, 0.0), (20.0, -52.5, 135.0), (60.0, 17.5, 90.0)]:
        scene = mi.load_file(str(SCENE), theta_i=str(ti), theta_o=str(to), phi=str(ph),
                             extinction="2.0")
        img = np.array(mi.render(scene, spp=4), dtype=np.float64).reshape(-1, 3)
        brf = np.pi * img.mean(axis=0) / np.cos(np.radians(ti))
        r = render_gonio({"radius": 0.017, "extinction": 2.0}, [ti], [to], [ph],
                         variant="llvm_ad_rgb", spp=1, resolution=2)
        np.testing.assert_allclose(brf, r.analytic[0], rtol=1e-5)


def test_measurement_mode_renders_each_wavelength(tmp_path):
    """Mono variant at the geometries and wavelengths of a measurement file."""
    from mitsuba_powder.io.measurements import Measurements, save_measurements
    from mitsuba_powder.plugin.brf import PowderBRF

    data = Measurements([0, 20, 40, 40], [10, -20, 40, 0], [0, 30, 0, 90],
                        [532, 532, 633, 633], [0.9, 1.0, 1.1, 0.8], comments=["test rows"])
    path = save_measurements(tmp_path / "m.csv", data)
    assert main(["render-gonio", "--data", str(path), "--set", "albedo=0.95", "--spp", "2",
                 "--resolution", "4", "--out", str(tmp_path / "out")]) == 0
    import csv

    rows = [r for r in csv.reader(open(tmp_path / "out" / "gonio.csv")) if not r[0].startswith("#")]
    header, rows = rows[0], rows[1:]
    rendered = np.array([float(r[header.index("brf_rendered")]) for r in rows])
    measured = np.array([float(r[header.index("brf_measured")]) for r in rows])
    np.testing.assert_allclose(measured, data.brf)
    np.testing.assert_allclose(rendered, PowderBRF(data, {"albedo": 0.95}).brf(), rtol=2e-5)
    assert (tmp_path / "out" / "gonio.png").is_file()


@pytest.mark.parametrize("strategy", ["bsdf", "mis"])
def test_white_furnace(strategy):
    """A uniform environment of radiance 1: the patch renders to its directional albedo, at
    normal, oblique and grazing views, with the coherent cone and a specular lobe on."""
    props = dict(PROPS, amplitude_surface=1e-3)
    r = white_furnace(props, (0.0, 45.0, 75.0), variant="llvm_ad_rgb", strategy=strategy,
                      spp=128, resolution=32, seed=3)
    assert np.all(np.abs(r.z()) < 3.0), r.z()
    assert np.all(r.stderr / r.quadrature < 3e-3)
    assert 0.6 < r.quadrature[0, 0] < 1.0


def test_white_furnace_spectral():
    r = white_furnace(PROPS, (30.0,), variant="llvm_ad_spectral", strategy="mis", spp=64,
                      resolution=32, seed=4)
    assert np.all(np.abs(r.z()) < 3.0), r.z()


def test_bad_input_names_the_parameter():
    with pytest.raises(ValueError, match="strategy = 'bsdf'.*delta light"):
        render_gonio({}, [0], [0], [0], strategy="bsdf")
    with pytest.raises(ValueError, match=r"source_radius = 20.0 degrees.*\[0, 10\]"):
        render_gonio({}, [0], [0], [0], source_radius=20.0)
    with pytest.raises(ValueError, match="spp = 0"):
        render_gonio({}, [0], [0], [0], spp=0)
    with pytest.raises(ValueError, match="wavelength applies to mono"):
        render_gonio({}, [0], [0], [0], wavelength=500.0)
    with pytest.raises(ValueError, match="equal length"):
        render_gonio({}, [0, 10], [0], [0])
    with pytest.raises(ValueError, match=r"theta_o = \[95.0\]"):
        white_furnace({}, (95.0,))
    with pytest.raises(ValueError, match="strategy = 'emitter'"):
        white_furnace({}, (0.0,), strategy="emitter")


def test_cli_render_gonio_protocol(tmp_path, capsys):
    """The printout and gonio.json state both checks: the deterministic values (collimated,
    RGB) against the float32 tolerance, the Monte Carlo ones (a 1-degree source) by z."""
    import json

    assert main(["render-gonio", "--protocol", "backscatter", "--spp", "2", "--resolution",
                 "4", "--set", "extinction=2", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "33 geometries x 3 channels" in out
    assert "deterministic (no Monte Carlo noise): 99 values, max relative difference" in out
    assert "float32 tolerance of" in out and "0 beyond it" in out
    assert "Monte Carlo: 0 values (no z-test)" in out and "sigma" not in out
    s = json.loads((tmp_path / "gonio.json").read_text())
    assert s["deterministic"]["values"] == 99 and s["monte_carlo"]["values"] == 0
    assert s["deterministic"]["max_relative_difference"] < s["deterministic"][
        "relative_tolerance_min"]
    assert "float32" in s["checks"]
    assert main(["render-gonio", "--protocol", "backscatter", "--spp", "2", "--resolution",
                 "4", "--source-radius", "1", "--strategy", "mis",
                 "--out", str(tmp_path / "disk")]) == 0
    out = capsys.readouterr().out
    assert "deterministic (no Monte Carlo noise): 0 values\n" in out
    assert "Monte Carlo: 99 values, max |z|" in out and "beyond 3 sigma (expected" in out
    s = json.loads((tmp_path / "disk" / "gonio.json").read_text())
    assert s["monte_carlo"]["values"] == 99 and s["monte_carlo"]["max_abs_z"] > 0
    assert main(["render-gonio", "--protocol", "backscatter", "--strategy", "mis",
                 "--out", str(tmp_path)]) == 2
    assert "source_radius > 0" in capsys.readouterr().err


@pytest.mark.parametrize("variant", ["scalar_rgb", "scalar_spectral", "llvm_ad_mono_polarized"])
def test_other_variants(variant):
    """Scalar and polarised variants give the same rendered-vs-analytic agreement."""
    use_variant(variant)
    r = render_gonio(PROPS, [20.0, 20.0], [20.0, -40.0], [0.0, 90.0], variant=variant, spp=16,
                     resolution=8, seed=5)
    assert_agrees(r)
    assert r.deterministic().all() == ("spectral" not in variant)
    if variant == "scalar_rgb":
        f = white_furnace(PROPS, (30.0,), variant=variant, spp=16, resolution=8, seed=6)
        assert np.all(np.abs(f.z()) < 3.0), f.z()


@pytest.mark.parametrize("args,fragment", [
    (([95.0], [0.0], [0.0]), r"theta_i = 95 degrees is out of range; valid range is \[0, 90\)"),
    (([30.0], [-90.0], [0.0]), r"theta_o = -90 degrees .* \(-90, 90\)"),
    (([30.0], [10.0], [400.0]), r"phi = 400 degrees .* \[-360, 360\]"),
    (([float("nan")], [10.0], [0.0]), "theta_i = nan"),
])
def test_bad_geometry_is_rejected(args, fragment):
    with pytest.raises(ValueError, match=fragment):
        render_gonio({}, *args)


def test_cli_wavelength_needs_a_mono_variant(tmp_path, capsys):
    assert main(["render-gonio", "--protocol", "backscatter", "--wavelength", "500",
                 "--out", str(tmp_path)]) == 2
    assert "--wavelength 500 applies to mono variants" in capsys.readouterr().err


PTFE_351 = {"eta": 1.35, "k": 0.0, "amplitude_volume": 0.7685, "g": 0.5115,
            "extinction": 0.6319, "albedo": 0.9911, "amplitude_surface": 3.58e-4,
            "correlation_length": 0.0626}


@pytest.mark.parametrize("guard", [1, 0])
def test_batch_images_do_not_leak_into_each_other(guard, monkeypatch):
    """The 305 geometries of the PTFE file at 351 nm and 75 degrees in one batch film (4880
    pixels wide). Without guard columns a few samples at the border of two images were
    traced by one sub-sensor and splatted into the other's border pixel (float32 rounding of
    the film position): relative differences up to 2.6e-5, with a standard error as large,
    so the z-test did not see it; the float32 tolerance does. With the guard columns every
    pixel of a collimated mono render holds the same value (to rounding)."""
    import mitsuba_powder.rendering.gonio as gonio
    from mitsuba_powder.io.measurements import load_measurements

    monkeypatch.setattr(gonio, "GUARD_COLUMNS", guard)
    data = load_measurements(Path(__file__).resolve().parents[2] / "measurements"
                             / "ptfe_germer2017.csv")
    data = data.subset((data.wavelength == 351) & (data.theta_i == 75))
    assert len(data) == 305
    r = gonio.render_measurements(PTFE_351, data, spp=64, resolution=16, seed=0)
    assert r.deterministic().all()
    noise = (r.stderr / r.analytic).max()
    if guard:
        assert noise < 1e-7 and r.agrees().all(), (noise, r.relative_difference().max())
        assert r.summary()["deterministic"]["max_relative_difference"] < 3e-6
    else:  # the negative control: the leak is there, and the float32 check catches it
        assert noise > 1e-6
        assert r.summary()["deterministic"]["beyond_tolerance"] >= 1
