"""The starts of the per-pixel fit (mitsuba_powder.rti.starts): Lambertian photometric stereo
is exact on Lambertian pixels (distant lights or lights at a distance, gains, observations
left out), the powder albedo of the start is the one whose Lambertian-equivalent
reflectance the pixel shows, and the grain-size search finds a size of the albedo of a
noise-free SYNTHETIC powder capture."""

from __future__ import annotations

import math

import numpy as np

import mitsuba_powder.rti as rf
from helpers import lambertian_capture
from mitsuba_powder.fitting.optimise import ParamSpec
from mitsuba_powder.rti.forward import PixelEvaluator, slopes_of_normals
from mitsuba_powder.rti.properties import SLOPE_LIMIT
from mitsuba_powder.rti.starts import PixelStarts, lambertian_start

SHAPE, LIGHTS = (6, 7), 20
SLOPE = ParamSpec(-SLOPE_LIMIT, SLOPE_LIMIT, False, 0.0)


def _lambertian(r: float = math.inf, gains=None):
    c = lambertian_capture(SHAPE, LIGHTS, r, gains=gains)
    assert c["cos"].min() > 0  # no attached shadow: photometric stereo is exact
    return (c["images"], c["directions"], c["normals"], c["reflectance"], c["dirs"], c["s"],
            c["gains"])


def test_photometric_stereo_is_exact_on_lambertian_pixels():
    gains = np.linspace(0.7, 1.3, LIGHTS)
    images, d, n, refl, _, _, g = _lambertian(gains=gains)
    got_n, got_refl = lambertian_start(images, d, gains=g)
    np.testing.assert_allclose(got_n, n, atol=1e-9)
    np.testing.assert_allclose(got_refl, refl, rtol=1e-9)
    # observations left out (weight 0, e.g. flagged shadows) change nothing on exact data
    weights = np.ones(images.shape[:3])
    weights[::3, 2:, :4] = 0.0
    images_bad = images.copy()
    images_bad[::3, 2:, :4] = 5.0  # what the weights leave out
    got_n, got_refl = lambertian_start(images_bad, d, weights, g)
    np.testing.assert_allclose(got_n, n, atol=1e-9)
    np.testing.assert_allclose(got_refl, refl, rtol=1e-9)


def test_photometric_stereo_with_lights_at_a_distance():
    images, d, n, refl, dirs, s, g = _lambertian(r=3.0)
    got_n, got_refl = lambertian_start(images, dirs, gains=g, irradiance=s)
    np.testing.assert_allclose(got_n, n, atol=1e-9)
    np.testing.assert_allclose(got_refl, refl, rtol=1e-9)
    far_n, _ = lambertian_start(images, d, gains=g)  # the distant model is biased here
    assert np.max(np.abs(far_n - n)) > 1e-3


def _powder_capture(maps: dict, d: np.ndarray) -> np.ndarray:
    obs = rf.render_capture(maps, d)
    return obs.reshape(len(d), -1, 3).transpose(1, 0, 2)


def test_the_albedo_start_is_the_powder_s_albedo_of_the_pixel_s_reflectance():
    """Flat pixels of known albedo, the other properties at the values of the start's table:
    the start gives back the albedo (the table's interpolation and the dome's lights are the
    only differences)."""
    d = rf.dome_directions(LIGHTS)
    albedo = np.linspace(0.3, 0.95, 3 * 4).reshape(4, 3)
    p = len(albedo)
    props = {"amplitude_surface": rf.SPECS["amplitude_surface"].start,
             "correlation_length": rf.SPECS["correlation_length"].start}
    maps = {"normal": np.tile([0.0, 0.0, 1.0], (1, p, 1)), "albedo": albedo[None], **props}
    obs = _powder_capture(maps, d)
    layout = [("slope_x", SLOPE), ("slope_y", SLOPE)] + [
        (f"albedo{c}", rf.SPECS["albedo"]) for c in range(3)] + [
        (n, rf.SPECS[n]) for n in props]
    ev = PixelEvaluator(list(props), {}, rf.VARIANT)
    starts = PixelStarts(ev, obs, d, layout, rf.SPECS, ["albedo", *props], list(props),
                         "radius", {}, None, rf.MAX_LANES)
    y, n0, _ = starts(np.ones(LIGHTS), np.ones((p, LIGHTS)))
    np.testing.assert_allclose(y[:, 2:5], albedo, rtol=0.02)
    np.testing.assert_allclose(y[:, :2], slopes_of_normals(n0), atol=1e-12)
    np.testing.assert_array_equal(y[:, -1], np.arange(p))


def test_the_grain_size_search_finds_the_size():
    d = rf.dome_directions(LIGHTS)
    radii = np.array([0.05, 0.09, 0.3])
    p = len(radii)
    maps = {"normal": np.tile([0.0, 0.0, 1.0], (1, p, 1)), "radius": radii[None]}
    obs = _powder_capture(maps, d)
    grain = rf.GrainAlbedo("radius", {})
    layout = [("slope_x", SLOPE), ("slope_y", SLOPE), ("radius", rf.SPECS["radius"])]
    ev = PixelEvaluator([], {}, rf.VARIANT)
    starts = PixelStarts(ev, obs, d, layout, rf.SPECS, ["radius"], [], "radius", {}, grain,
                         rf.MAX_LANES)
    y, _, _ = starts(np.ones(LIGHTS), np.ones((p, LIGHTS)))
    found = rf.SPECS["radius"].to_x(y[:, 2])
    # rho(r) has several branches: the search finds a size of about the pixel's albedo (one
    # of the 40 sizes of its grid: measured within 9.4 %), not necessarily the pixel's size
    np.testing.assert_allclose(grain(found)[0], grain(radii)[0], rtol=0.1)
    y0, _, _ = starts(np.ones(LIGHTS), np.ones((p, LIGHTS)), search=False)
    np.testing.assert_allclose(rf.SPECS["radius"].to_x(y0[:, 2]), rf.SPECS["radius"].start,
                               rtol=1e-12)
    far = np.array([rf.SPECS["radius"].lower, rf.SPECS["radius"].upper])
    # (not a check that any size passes: the range's ends are far from every pixel's albedo)
    assert np.min(np.max(np.abs(grain(far)[0][:, None] - grain(radii)[0][None]), axis=2)) > 0.05
