"""The colour helper: optical properties from the plugin, reflectance and CIE colour."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from helpers import hemispherical_reflectance, use_variant
from mitsuba_powder.cli import main
from mitsuba_powder.plugin.appearance import colour_of_spectrum, powder_colour
from oracles.grains import hematite_nk, mie_albedo, mie_efficiencies, tau_o_trapezoid

ROOT = Path(__file__).resolve().parents[2]


def test_optical_properties_match_miepython():
    c = powder_colour(0.05, wavelengths_nm=np.arange(400.0, 801.0, 50.0), samples=64)
    for i, w in enumerate(c.wavelengths_nm):
        m = complex(hematite_nk(np.array([w]))[0])
        assert c.albedo[i] == pytest.approx(mie_albedo(m, 0.05, w), rel=2e-4)
        assert c.q_ext[i] == pytest.approx(mie_efficiencies(m, 2 * np.pi * 0.05 / (w * 1e-3))[0],
                                           rel=2e-4)
        assert c.tau_o[i] == pytest.approx(tau_o_trapezoid(m.real), rel=1e-5)
    assert c.q_ext2 is None
    assert np.all(np.isnan(c.lab))  # 50 nm steps: no colour


def test_reflectance_matches_a_2d_hemispherical_integral():
    """The helper's 1D quadrature (normal incidence) against the 2D grid of
    helpers.hemispherical_reflectance."""
    c = powder_colour(0.1, wavelengths_nm=np.array([600.0, 700.0]), extinction=2.0)
    use_variant("llvm_ad_mono")
    bsdf = mi.load_dict({"type": "powder", "radius": 0.1, "extinction": 2.0,
                         "wavelength": 700.0})
    want = hemispherical_reflectance(bsdf, 0.0, n=1024)[0]
    assert c.reflectance[1] == pytest.approx(want, rel=2e-3)


def test_flat_reflectance_is_neutral():
    """Without the coherent term (the only wavelength-dependent one once albedo and tau_o
    are fixed) the spectrum is flat, so the colour is grey: a* = b* = 0."""
    c = powder_colour(albedo=0.8, tau_o=2.0, lobes="single,multiple")
    assert np.ptp(c.reflectance) < 1e-5
    assert abs(c.lab[1]) < 0.05 and abs(c.lab[2]) < 0.05
    y = c.reflectance.mean()
    assert c.xyz[1] == pytest.approx(y, rel=1e-3)
    assert c.lab[0] == pytest.approx(116 * y ** (1 / 3) - 16, rel=1e-3)


def test_colour_needs_a_standard_grid():
    with pytest.raises(ValueError, match="step of 1, 5, 10 or 20 nm covering 380-780"):
        colour_of_spectrum(np.arange(400.0, 701.0, 10.0), np.ones(31))


def test_colour_of_spectrum_of_a_red_spectrum():
    wl = np.arange(360.0, 831.0, 5.0)
    xyz, srgb, lab = colour_of_spectrum(wl, np.where(wl > 600, 0.8, 0.05))
    assert srgb[0] > srgb[1] and srgb[0] > srgb[2] and lab[1] > 20


def test_two_populations_and_variant_restored():
    use_variant("scalar_rgb")
    c = powder_colour(0.083, radius2=0.046, fraction2=0.4,
                      wavelengths_nm=np.array([450.0, 650.0]), samples=32)
    assert mi.variant() == "scalar_rgb"
    want = [mie_albedo(complex(hematite_nk(np.array([w]))[0]), 0.083, w, 0.046, 0.4)
            for w in (450.0, 650.0)]
    np.testing.assert_allclose(c.albedo, want, rtol=2e-4)
    assert c.q_ext2 is not None and len(c.q_ext2) == 2


@pytest.mark.parametrize("kwargs,message", [
    ({"radius2": 0.1}, "both radius2 and fraction2"),
    ({"wavelengths_nm": np.array([300.0, 400.0])}, "valid range is 360-830 nm"),
    ({"wavelengths_nm": np.array([500.0, 400.0])}, "increasing"),
    ({"samples": 4}, "samples = 4"),
])
def test_bad_arguments(kwargs, message):
    with pytest.raises(ValueError, match=message):
        powder_colour(0.05, **kwargs)


def test_cli_colour(capsys):
    assert main(["colour", "--radius", "0.05", "--samples", "64"]) == 0
    out = capsys.readouterr().out
    assert "CIELAB" in out and "sRGB" in out and "albedo" in out
    assert main(["colour", "--radius", "0.05", "--radius2", "0.1"]) == 2
    assert "fraction2" in capsys.readouterr().err


def test_figure_script_runs_in_quick_mode(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / "hematite_colour.py"),
                           "--quick", "--out", str(tmp_path)], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "figures" / "hematite_colour_vs_radius.png").stat().st_size > 10_000
    assert "| one | 0.01 |" in (tmp_path / "hematite_colour_table.md").read_text()
