"""Gonio rendering: the BRF measured on renders equals the analytic BRF (within 3 Monte Carlo
standard errors), the gonio scene file agrees, and a uniform environment renders to the albedo
(white furnace) with BSDF sampling only and with MIS."""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from helpers import use_variant
from mitsuba_powder.cli import main
from mitsuba_powder.furnace import white_furnace
from mitsuba_powder.gonio import render_gonio
from mitsuba_powder.protocols import geometries
from reference import Params, brdf

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "gonio.xml"
RGB_NM = (611.3, 549.1, 464.3)
PROPS = {"albedo": {"type": "rgb", "value": [0.85, 0.55, 0.3]}, "extinction": 1.0,
         "tau_o": 2.0 / 3.0}


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
    """The analytic column is pi f of MODEL.md (NumPy reference) at the RGB wavelengths, so
    the geometry convention of the virtual goniometer is the measurement convention."""
    ti, to, ph = subset()
    r = render_gonio(PROPS, ti, to, ph, variant="llvm_ad_rgb", spp=1, resolution=2)
    wi, wo = (np.asarray(a) for a in __import__("reference").gonio_directions(ti, to, ph))
    rho = np.tile(np.float32([0.85, 0.55, 0.3]).astype(np.float64), (len(ti), 1))
    lam = np.tile(np.float32(RGB_NM).astype(np.float64), (len(ti), 1))
    want = np.pi * brdf(wi, wo, rho, lam, Params().as_float32())
    np.testing.assert_allclose(r.analytic, want, rtol=2e-4)


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_spectral"])
def test_rendered_brf_matches_analytic(variant):
    """Collimated source. In RGB every pixel is the same deterministic value (the Monte
    Carlo error is ~0, the float32 floor applies); in spectral variants the wavelength
    sampling makes it a real Monte Carlo estimate."""
    use_variant(variant)
    ti, to, ph = subset()
    r = render_gonio(PROPS, ti, to, ph, variant=variant, spp=64, resolution=16, seed=1)
    assert r.rendered.shape == (len(ti), 3)
    assert np.all(r.analytic > 0) and np.all(np.isfinite(r.rendered))
    bad = ~r.agrees()
    assert not bad.any(), (r.z()[bad], ti[bad.any(1)], to[bad.any(1)], ph[bad.any(1)])
    peak = (ti == 20) & (to == 20) & (ph == 0)
    assert r.analytic[peak, 0] > 1.3 * r.analytic[(ti == 20) & (to == 10), 0]  # a real peak
    if variant.endswith("spectral"):
        assert np.median(r.stderr / r.analytic) > 1e-4  # genuinely noisy
        assert np.abs(r.z()).max() > 0.1


@pytest.mark.parametrize("strategy", ["emitter", "mis"])
def test_finite_source_matches_source_averaged_brf(strategy):
    """A 1-degree source: the analytic value is the BRF averaged over the source disk by
    quadrature; emitter sampling and MIS estimate it with real Monte Carlo noise."""
    use_variant("llvm_ad_rgb")
    ti, to, ph = subset()
    r = render_gonio(PROPS, ti, to, ph, variant="llvm_ad_rgb", spp=32, resolution=16,
                     source_radius=1.0, strategy=strategy, seed=2)
    bad = ~r.agrees()
    assert not bad.any(), r.z()[bad]
    assert np.median(r.stderr / r.analytic) > 1e-6
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
    from mitsuba_powder.measurements import Measurements, save_measurements
    from mitsuba_powder.model import PowderBRF

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
    assert main(["render-gonio", "--protocol", "backscatter", "--spp", "2", "--resolution",
                 "4", "--set", "extinction=2", "--out", str(tmp_path)]) == 0
    out = capsys.readouterr().out
    assert "33 geometries x 3 channels" in out and "beyond 3 sigma" in out
    assert main(["render-gonio", "--protocol", "backscatter", "--strategy", "mis",
                 "--out", str(tmp_path)]) == 2
    assert "source_radius > 0" in capsys.readouterr().err


@pytest.mark.parametrize("variant", ["scalar_rgb", "scalar_spectral", "llvm_ad_mono_polarized"])
def test_other_variants(variant):
    """Scalar and polarised variants give the same rendered-vs-analytic agreement."""
    use_variant(variant)
    r = render_gonio(PROPS, [20.0, 20.0], [20.0, -40.0], [0.0, 90.0], variant=variant, spp=16,
                     resolution=8, seed=5)
    assert np.all(r.agrees()), r.z()
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
