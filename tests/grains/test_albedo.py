"""Albedo from a measured reflectance (appearance.albedo_for_reflectance, `mitsuba-powder
albedo`): round trips through the plugin in a spectral variant, with an independent
quadrature; errors; the spectrum file a scene loads."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import use_variant
from mitsuba_powder.cli import main
from mitsuba_powder.plugin.appearance import (
    albedo_for_reflectance,
    hemispherical_nodes,
    reflectance_of_srgb,
)

PROPS = {"extinction": 0.5, "g": 0.2, "amplitude_surface": 1e-4, "eta": 1.6, "k": 0.0,
         "amplitude_volume": 1.1}
WAVELENGTHS = np.array([400.0, 480.0, 550.0, 620.0, 700.0])


def plugin_brf(albedo: np.ndarray, theta_i: float, theta_o: np.ndarray) -> np.ndarray:
    """BRF (len(theta_o), W) of the plugin in llvm_ad_spectral with an ``irregular`` albedo
    spectrum through the wavelengths (each lane at one wavelength)."""
    use_variant("llvm_ad_spectral")
    spectrum = {"type": "irregular", "wavelengths": ", ".join(f"{w:g}" for w in WAVELENGTHS),
                "values": ", ".join(f"{a:.9g}" for a in albedo)}
    bsdf = mi.load_dict({"type": "powder", **PROPS, "albedo": spectrum})
    n, w = len(theta_o), len(WAVELENGTHS)
    to = np.radians(np.tile(theta_o, w))
    ti = np.radians(theta_i)
    si = dr.zeros(mi.SurfaceInteraction3f, n * w)
    si.wi = mi.Vector3f(float(np.sin(ti)), 0.0, float(np.cos(ti)))
    lam = mi.Float(np.repeat(WAVELENGTHS, n).astype(np.float32))
    si.wavelengths = mi.Spectrum(lam, lam, lam, lam)
    wo = mi.Vector3f(mi.Float(np.sin(to).astype(np.float32)), 0.0,
                     mi.Float(np.cos(to).astype(np.float32)))
    f = np.array(bsdf.eval(mi.BSDFContext(), si, wo)[0], dtype=np.float64)
    return (np.pi * f / np.cos(to)).reshape(w, n).T


def test_round_trip_bidirectional_0_45():
    target = np.array([0.35, 0.5, 0.62, 0.75, 0.8])
    albedo = albedo_for_reflectance(WAVELENGTHS, target, (0, 45), **PROPS)
    assert np.all((albedo >= 0) & (albedo <= 1))
    brf = plugin_brf(albedo, 0.0, np.array([45.0]))[0]
    np.testing.assert_allclose(brf, target, atol=1e-3)
    # the string form is the same geometry
    np.testing.assert_allclose(albedo_for_reflectance(WAVELENGTHS, target, "0:45", **PROPS),
                               albedo, atol=1e-7)


def test_round_trip_directional_hemispherical():
    target = np.array([0.3, 0.45, 0.6, 0.7, 0.75])
    albedo = albedo_for_reflectance(WAVELENGTHS, target, "0:d", **PROPS)
    # an independent quadrature: a dense midpoint rule in theta_o (the cone, about 2.5 deg
    # wide here, spans hundreds of nodes)
    m = 20000
    theta = (np.arange(m) + 0.5) * (np.pi / 2) / m
    brf = plugin_brf(albedo, 0.0, np.degrees(theta))
    weight = 2.0 * np.cos(theta) * np.sin(theta) * (np.pi / 2) / m
    np.testing.assert_allclose((brf * weight[:, None]).sum(axis=0), target, atol=1e-3)


def test_hemispherical_nodes_integrate_exactly():
    theta, weight = hemispherical_nodes()
    assert weight.sum() == pytest.approx(1.0, abs=1e-12)  # a white Lambertian: R = 1
    t = np.radians(theta)
    assert (weight * np.cos(t) ** 2).sum() == pytest.approx(0.5, abs=1e-12)


def test_unreachable_and_bad_input():
    with pytest.raises(ValueError, match=r"reflectance 0.99 at 550 nm cannot be reached: .* "
                                         r"lies in \[0, 0.9\d+\]"):
        albedo_for_reflectance([550.0], [0.99], "0:d", extinction=0.5, tau_o=0.6667)
    with pytest.raises(ValueError, match="reflectance -0.1 at 500 nm cannot be reached"):
        albedo_for_reflectance([500.0, 600.0], [-0.1, 0.5], "0:45", extinction=0.5)
    with pytest.raises(ValueError, match="geometry = 'sideways' is not valid"):
        albedo_for_reflectance([500.0], [0.5], "sideways")
    with pytest.raises(ValueError, match="theta_i must lie in"):
        albedo_for_reflectance([500.0], [0.5], (95, 0))
    with pytest.raises(ValueError, match="same length"):
        albedo_for_reflectance([500.0, 600.0], [0.5])
    with pytest.raises(ValueError, match=r"\['radius'\] cannot be given"):
        albedo_for_reflectance([500.0], [0.5], radius=0.05)
    with pytest.raises(ValueError, match="srgb"):
        reflectance_of_srgb([0.5, 0.5])


def test_srgb_upsampling_keeps_the_colour():
    from mitsuba_powder.plugin.appearance import colour_of_spectrum

    wl, r = reflectance_of_srgb([0.7, 0.35, 0.25])
    _, srgb, _ = colour_of_spectrum(wl, r)
    np.testing.assert_allclose(srgb, [0.7, 0.35, 0.25], atol=0.01)
    np.testing.assert_allclose(reflectance_of_srgb([179, 89, 64])[1],
                               reflectance_of_srgb([179 / 255, 89 / 255, 64 / 255])[1])


def test_cli_writes_a_spectrum_a_scene_loads(tmp_path, capsys):
    out = tmp_path / "albedo.spd"
    assert main(["albedo", "--srgb", "0.7,0.35,0.25", "--set", "extinction=0.5",
                 "--out", str(out)]) == 0
    assert "wrote" in capsys.readouterr().out
    rows = np.loadtxt(out)
    assert rows.shape == (81, 2) and rows[0, 0] == 380 and rows[-1, 0] == 780
    assert np.all((rows[:, 1] >= 0) & (rows[:, 1] <= 1))
    use_variant("llvm_ad_spectral")
    bsdf = mi.load_dict({"type": "powder", "extinction": 0.5,
                         "albedo": {"type": "spectrum", "filename": str(out)}})
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.wavelengths = mi.Spectrum(550.0, 550.0, 550.0, 550.0)
    value = float(bsdf.eval_attribute("albedo", si)[0][0])
    assert value == pytest.approx(np.interp(550.0, rows[:, 0], rows[:, 1]), rel=1e-5)
    # from a reflectance file
    csv = tmp_path / "r.csv"
    csv.write_text("wavelength,reflectance\n450,0.3\n550,0.5\n650,0.6\n")
    assert main(["albedo", "--reflectance", str(csv), "--geometry", "0:45",
                 "--out", str(tmp_path / "b.spd")]) == 0
    assert np.loadtxt(tmp_path / "b.spd").shape == (3, 2)
    capsys.readouterr()
    assert main(["albedo", "--out", str(tmp_path / "c.spd")]) == 2
    assert "exactly one of --reflectance" in capsys.readouterr().err
    (tmp_path / "bad.csv").write_text("450,0.3,9\n")
    assert main(["albedo", "--reflectance", str(tmp_path / "bad.csv"), "--out",
                 str(tmp_path / "d.spd")]) == 2
    assert "line 1: 3 fields" in capsys.readouterr().err
    # a --set without '=': an error line and exit code 2 (was SystemExit 1 naming -D)
    assert main(["albedo", "--srgb", "0.7,0.35,0.25", "--set", "tau_o", "--out",
                 str(tmp_path / "e.spd")]) == 2
    assert "--set 'tau_o': expected NAME=VALUE" in capsys.readouterr().err
