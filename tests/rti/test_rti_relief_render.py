"""Relighting the relief (issue 36): a SYNTHETIC relief with real cast shadows, path traced by
Mitsuba, is relit at held-out grazing lights within 1.5x the noise floor by fit_maps' and
relight's defaults (shadows="auto" keeps the relief there); the rendered relief equals the
per-pixel relight where nothing shades."""

from __future__ import annotations

import numpy as np
import pytest
from relief_capture import noise_floor, relief_capture

from mitsuba_powder.rti import MapsResult, fit_maps, synthetic_maps
from mitsuba_powder.rti.relief import make_relief
from mitsuba_powder.rti.rendered import render_result
from mitsuba_powder.rti.selection import SHADOW_Z


def test_held_out_grazing_lights_are_relit_with_the_defaults(tmp_path):
    """32 x 32 px, 40 lights at 5-80 degrees of which 6 at 5-15 held out, noise 0.005, the
    lights' irradiance not given (1, the fit's calibration), 64 spp (their Monte Carlo noise
    in the floor). The default shadows="auto" keeps the relief (it relights the held-out
    folds better by more than the margin) and relight's default shades by it. Measured:
    1.15x the floor with the defaults, 2.18x with shadows="ratio" (the fit's ratio test and
    no shadow in the relight); auto's cross-validated RMS 0.00866 without the relief,
    0.00744 with it, z = 17."""
    cap = relief_capture(32, 32, tmp_path, spp=64, noise=0.005)
    d, held = cap["directions"], cap["held"]
    assert np.all(np.degrees(np.arcsin(d[held, 2])) <= 15.0) and len(held) == 6
    keep = np.setdiff1d(np.arange(len(d)), held)
    truth = cap["images"][held]
    floor = noise_floor(cap, held)
    # the capture has real cast shadows: a quarter of the held-out pixels see no direct light
    assert np.mean(cap["clean"][held].mean(axis=-1) < 0.005) > 0.2
    result = fit_maps(cap["images"][keep], d[keep])
    choice = result.fit_settings["shadows_choice"]
    assert result.fit_settings["shadows"] == "relief" and choice["chosen"] == "relief"
    cv = choice["cv_rms"]
    assert cv["relief"] < cv["ratio"] and choice["z"] > SHADOW_Z, choice
    shaded = float(np.sqrt(np.mean((result.predict(d[held]) - truth) ** 2)))
    assert shaded < 1.5 * floor, shaded / floor
    plain = fit_maps(cap["images"][keep], d[keep], shadows="ratio")
    assert plain.fit_settings["shadows"] == "ratio" and plain.relief is None
    flat = float(np.sqrt(np.mean((plain.predict(d[held]) - truth) ** 2)))
    assert flat > 1.5 * shaded, (flat / floor, shaded / floor)


def flat_maps(h: int = 12, w: int = 16) -> MapsResult:
    """SYNTHETIC maps of a flat capture (four regions, n = z) with its (flat) relief."""
    maps, _ = synthetic_maps(h, w, relief=0.0, seed=1)
    props = {k: np.asarray(v, np.float32) for k, v in maps.items()
             if k not in ("normal", "albedo")}
    normals = np.zeros((h, w, 3), np.float32)
    normals[..., 2] = 1.0
    result = MapsResult(normals=normals, albedo=maps["albedo"].astype(np.float32),
                        maps=props, settings={}, residual_rms=np.full((h, w), 0.01, np.float32),
                        gains=np.ones(3), used=np.ones((3, h, w), bool),
                        free=["albedo"] + sorted(props), mask=np.ones((h, w), bool))
    result.relief = make_relief(normals, result.residual_rms, result.mask)
    return result


@pytest.mark.parametrize("variant", ["scalar_rgb", "llvm_ad_rgb"])
def test_rendered_flat_relief_equals_the_per_pixel_relight(variant):
    result = flat_maps()
    d = np.array([[0.5, 0.2, 0.84], [-0.6, 0.3, 0.74], [0.1, -0.95, 0.3]])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    expected = result.predict(d)
    rendered = render_result(result, d, spp=4, variant=variant)
    np.testing.assert_allclose(rendered, expected, rtol=0.01, atol=1e-6)


def test_rendered_lights_must_be_of_the_scene_kind():
    result = flat_maps(6, 8)
    with pytest.raises(ValueError, match="light_distance = 3.0: the scene.xml .* directional"):
        render_result(result, np.array([[0.0, 0.0, 1.0]]), light_distance=3.0, spp=1)
