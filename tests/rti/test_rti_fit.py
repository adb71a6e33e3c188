"""Per-pixel powder maps from RTI captures (mitsuba_powder.rti), on SYNTHETIC captures.

References: the forward model against separately loaded plugin instances evaluated in
``scalar_rgb`` with an independent (NumPy, Gram-Schmidt) tangent frame and docs/model.md's argument
order ``f(wi = light, wo = view)``; the Jacobian against central differences; the fits against
the known maps the synthetic capture was rendered from.
"""

import math
import re

import mitsuba as mi
import numpy as np
import pytest

from mitsuba_powder import rti as rf
from mitsuba_powder.fitting.optimise import ParamSpec
from mitsuba_powder.rti.forward import PixelEvaluator, slopes_of_normals
from mitsuba_powder.rti.pixels import PixelData
from mitsuba_powder.rti.problem import PixelProblem
from mitsuba_powder.variants import use_variant

NOISE = 0.01
NON_IDENTIFIABLE = ("amplitude_volume", "g", "extinction")


def _frame(n):
    """An orthonormal tangent frame of n by Gram-Schmidt from the x axis (not Mitsuba's)."""
    a = np.array([1.0, 0.0, 0.0]) if abs(n[0]) < 0.9 else np.array([0.0, 1.0, 0.0])
    s = a - np.dot(a, n) * n
    s /= np.linalg.norm(s)
    return s, np.cross(n, s), n


def _reference(bsdf, normal, light):
    """f(wi = light, wo = view) (n . l) by a plugin instance of its own (scalar_rgb)."""
    with use_variant("scalar_rgb"):
        s, t, n = _frame(np.asarray(normal, float))
        local = lambda v: mi.Vector3f(float(v @ s), float(v @ t), float(v @ n))  # noqa: E731
        wi, wo = local(light), local(np.array([0.0, 0.0, 1.0]))
        si = mi.SurfaceInteraction3f()
        si.wi = wi
        value = np.array(bsdf.eval(mi.BSDFContext(), si, wo), dtype=np.float64).ravel()
        mu_l, mu_v = float(light @ n), float(n[2])
    if mu_l <= 0:
        return np.zeros(3)
    return value / mu_v * mu_l  # eval gives f cos(wo) = f mu_v: swap the cosine


def test_forward_model_equals_separate_instances():
    rng = np.random.default_rng(3)
    h, w = 2, 3
    normal = np.stack([rng.uniform(-0.6, 0.6, (h, w)), rng.uniform(-0.6, 0.6, (h, w)),
                       np.ones((h, w))], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    normal[0, 0] = (0.0, 0.0, 1.0)
    maps = {"normal": normal,
            "albedo": rng.uniform(0.05, 0.99, (h, w, 3)),
            "amplitude_volume": rng.uniform(0.5, 2.0, (h, w)),
            "g": rng.uniform(-0.5, 0.6, (h, w)),
            "extinction": rng.uniform(0.2, 2.5, (h, w)),
            "tau_o": rng.uniform(0.7, 5.0, (h, w)),
            "thickness": rng.uniform(0.5, 20.0, (h, w)),
            "amplitude_surface": 10 ** rng.uniform(-5.5, -3.5, (h, w)),
            "correlation_length": rng.uniform(0.2, 1.5, (h, w))}
    lights = rf.dome_directions(9, 5.0, 89.0)
    lights = np.vstack([lights, [[0.3, 0.1, 0.95], [0.9, 0.0, 0.1]]])  # near-retro, grazing
    lights /= np.linalg.norm(lights, axis=1, keepdims=True)
    images = rf.render_capture(maps, lights)
    checked_zero = 0
    for i in range(h):
        for j in range(w):
            props = {name: float(maps[name][i, j]) for name in maps
                     if name not in ("normal", "albedo")}
            props["albedo"] = {"type": "rgb", "value": maps["albedo"][i, j].tolist()}
            with use_variant("scalar_rgb"):
                bsdf = mi.load_dict({"type": "powder", **props})
            for k, light in enumerate(lights):
                ref = _reference(bsdf, normal[i, j], light)
                got = images[k, i, j]
                if not ref.any():
                    checked_zero += 1
                    assert np.all(got == 0.0)
                else:
                    np.testing.assert_allclose(got, ref, rtol=1e-5, atol=1e-7 * ref.max())
    assert checked_zero > 0  # some lights below a tilted pixel's tangent plane


def test_forward_model_gains_chunks_and_default_view():
    maps, _ = rf.synthetic_maps(6, 5)
    d = rf.dome_directions(7)
    gains = np.linspace(0.5, 2.0, 7)
    one = rf.render_capture(maps, d)
    chunked = rf.render_capture(maps, d, gains, max_lanes=20)  # 2 pixels per evaluation
    np.testing.assert_allclose(chunked, one * gains[:, None, None, None], rtol=1e-6)
    # a Lambertian-like check: a flat, surface-free powder is brighter under a higher light
    flat = dict(maps, normal=np.broadcast_to([0.0, 0.0, 1.0], (6, 5, 3)), amplitude_surface=0.0)
    img = rf.render_capture(flat, np.array([[0.0, 0.0, 1.0], [0.8, 0.0, 0.6]]))
    assert np.all(img[0] > img[1])


def test_jacobian_matches_finite_differences():
    cap_maps, _ = rf.synthetic_maps(4, 4)
    d = rf.dome_directions(12)
    free = ["albedo", "amplitude_volume", "g", "extinction", "amplitude_surface",
            "correlation_length"]
    ev = PixelEvaluator(free[1:], {}, "llvm_ad_rgb")
    layout = [("slope_x", ParamSpec(-5, 5, False, 0)),
              ("slope_y", ParamSpec(-5, 5, False, 0))]
    layout += [(f"albedo{c}", rf.SPECS["albedo"]) for c in range(3)]
    layout += [(n, rf.SPECS[n]) for n in free[1:]]
    p = 16
    obs = rf.render_capture(cap_maps, d).reshape(12, p, 3).transpose(1, 0, 2).astype(float)
    prob = PixelProblem(ev, PixelData(obs, np.ones((p, 12)), d, np.full(12, 1.5), layout))
    y = np.zeros((p, len(layout) + 1))
    y[:, :2] = slopes_of_normals(cap_maps["normal"].reshape(p, 3)) + 0.05
    y[:, 2:5] = cap_maps["albedo"].reshape(p, 3) * 0.95
    for j, name in enumerate(free[1:]):
        y[:, 5 + j] = rf.SPECS[name].to_y(cap_maps[name].reshape(p)) + 0.02
    y[:, -1] = np.arange(p)
    _, jac = prob.jacobian(y)
    for j in range(len(layout)):
        h = 2e-3
        yp, ym = y.copy(), y.copy()
        yp[:, j] += h
        ym[:, j] -= h
        fd = (prob.residuals(yp) - prob.residuals(ym)) / (2 * h)
        scale = np.max(np.abs(fd)) + 1e-12
        err = np.max(np.abs(jac[:, :, j] - fd)) / scale
        assert err < 0.02, (layout[j][0], err)


@pytest.fixture(scope="module")
def capture():
    rng = np.random.default_rng(5)
    rel = 1.0 + 0.1 * rng.standard_normal(40)
    rel /= rel.mean()
    return rf.synthetic_capture(32, 32, 40, noise=NOISE, gains=rel)


def _normal_error_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def _region_medians(result, cap):
    """Per region: median fitted / true - 1 of the albedo (3) and the free properties."""
    out = {}
    truth = cap["maps"]
    for r in range(4):
        sel = cap["region"] == r
        out[r] = {f"albedo{c}": np.median(result.albedo[sel][:, c]) / truth["albedo"][sel][0, c]
                  - 1 for c in range(3)}
        for name in result.free:
            if name != "albedo":
                out[r][name] = np.median(result.maps[name][sel]) / truth[name][sel][0] - 1
    return out


def test_fit_recovers_synthetic_maps_and_predicts_held_out_lights(capture):
    cap = capture
    truth = cap["maps"]
    held = np.arange(4, 40, 5)  # every fifth light held out
    kept = np.setdiff1d(np.arange(40), held)
    fixed = {n: truth[n] for n in NON_IDENTIFIABLE}
    # the default free set given (the cross-validated choice finds these lobes too weak to
    # earn their place: tests/rti/test_rti_exposure.py)
    result = rf.fit_maps(cap["images"][kept], cap["directions"][kept], fixed=fixed,
                         gains="fixed", initial_gains=cap["gains"][kept],
                         free=rf.MAP_DEFAULT_FREE)
    assert result.free == rf.MAP_DEFAULT_FREE and result.n_parameters == 7
    err = _normal_error_deg(result.normals, truth["normal"])
    assert np.median(err) < 1.0 and np.percentile(err, 95) < 2.0
    medians = _region_medians(result, cap)
    for r, values in medians.items():
        for name, rel in values.items():
            # albedo and normals are identifiable (CRB < 1 % and < 1 degree per pixel at 1 %
            # noise); the surface lobe only to 10-40 % per pixel, weakest in region 2
            # (amplitude_surface 1e-5): measured medians 0.6 %, 4.9 % and 24 % at worst
            bound = {"amplitude_surface": 0.35, "correlation_length": 0.10}.get(name, 0.05)
            assert abs(rel) < bound, (r, name, rel)
    predicted = rf.relight(result, cap["directions"][held], cap["gains"][held])
    rms = np.sqrt(np.mean((predicted - cap["images"][held]) ** 2))
    # 1.0 for a perfect prediction (the held-out images' own noise); measured 1.13
    assert rms / NOISE < 1.2
    fitted_rms = np.sqrt(np.mean(result.residual_rms**2))
    assert 0.9 < fitted_rms / NOISE < 1.1


def test_fit_recovers_perturbed_gains(capture):
    cap = capture
    fixed = {n: cap["maps"][n] for n in NON_IDENTIFIABLE}
    start = np.full(40, cap["gains"].mean())
    result = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fit",
                         initial_gains=start)
    assert np.max(np.abs(cap["gains"] / start - 1)) > 0.15  # the start is far off
    np.testing.assert_allclose(result.gains, cap["gains"], rtol=0.03)
    assert math.isclose(np.mean(result.gains), np.mean(start), rel_tol=1e-9)
    err = _normal_error_deg(result.normals, cap["maps"]["normal"])
    assert np.median(err) < 1.0 and np.percentile(err, 95) < 2.0
    for r, values in _region_medians(result, cap).items():
        for c in range(3):
            assert abs(values[f"albedo{c}"]) < 0.05, (r, c, values)


def test_cast_shadows_and_saturation_are_left_out(capture):
    cap = capture
    images = cap["images"].copy()
    yy, xx = np.mgrid[0:32, 0:32]
    shadow = np.zeros(images.shape[:3], dtype=bool)
    for k in range(0, 40, 3):
        shadow[k] = (xx + 0.5 * yy + k) % 24 < 9  # a band of cast shadow
    images[shadow] = 0.1 * images[shadow] + 0.005
    saturated = np.zeros_like(shadow)
    saturated[1, :8, :8] = True
    saturated[:, 31, 31] = True  # saturated under every light: not determined
    images[saturated] = 1.0
    fixed = {n: cap["maps"][n] for n in NON_IDENTIFIABLE}
    kwargs = dict(fixed=fixed, gains="fixed", initial_gains=cap["gains"],
                  free=rf.MAP_DEFAULT_FREE)
    result = rf.fit_maps(images, cap["directions"], **kwargs)
    assert not result.used[saturated].any()
    assert np.isnan(result.residual_rms[31, 31]) and np.isfinite(result.residual_rms[:31]).all()
    assert result.fit_settings["underdetermined_pixels"] == 1
    assert np.mean(~result.used[shadow]) > 0.85
    assert np.mean(~result.used[~shadow & ~saturated]) < 0.001
    err = _normal_error_deg(result.normals, cap["maps"]["normal"])
    assert np.median(err) < 1.0 and np.percentile(err, 95) < 2.0
    truth = cap["maps"]["albedo"]
    for r in range(4):
        sel = cap["region"] == r
        for c in range(3):
            rel = np.median(result.albedo[sel][:, c]) / truth[sel][0, c] - 1
            assert abs(rel) < 0.05, (r, c, rel)
    # the same capture without shadow detection is biased (the test can fail)
    naive = rf.fit_maps(images, cap["directions"], shadow_floor=math.inf, **kwargs)
    assert np.median(_normal_error_deg(naive.normals, cap["maps"]["normal"])) > 3.0


def test_correlation_length_bound_follows_the_light_spacing():
    d = rf.dome_directions(40)
    bound = rf.max_correlation_length(d)
    cos = np.clip(d @ d.T, -1, 1)
    np.fill_diagonal(cos, -1)
    spacing = np.median(np.arccos(cos.max(axis=1)))
    # lobe 1/e half width (projected plane) at the bound = half the spacing, at 464.3 nm
    assert math.isclose(0.4643 / (math.pi * bound), spacing / 2, rel_tol=1e-9)
    assert rf.max_correlation_length(rf.dome_directions(160)) > 1.5 * bound  # denser dome


def test_synthetic_capture_is_labelled_and_noisy():
    cap = rf.synthetic_capture(8, 8, 10, noise=0.02)
    assert cap["label"] == "SYNTHETIC"
    assert cap["images"].shape == (10, 8, 8, 3) and cap["directions"].shape == (10, 3)
    elevation = np.degrees(np.arcsin(cap["directions"][:, 2]))
    assert elevation.min() >= 10.0 - 1e-9 and elevation.max() <= 80.0 + 1e-9
    assert abs(np.std(cap["images"] - cap["clean"]) / 0.02 - 1) < 0.1
    assert sorted(np.unique(cap["region"])) == [0, 1, 2, 3]


@pytest.mark.parametrize("call, message", [
    (lambda c: rf.fit_maps(c["images"][:, :, :, :2], c["directions"]), "images has shape"),
    (lambda c: rf.fit_maps(c["images"], c["directions"][:-1]), "directions has 9 rows"),
    (lambda c: rf.fit_maps(c["images"], np.zeros((10, 3))), r"directions\[0\]"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], free=["radius2"]),
     "not fittable per pixel"),
    (lambda c: rf.fit_maps(c["images"], c["directions"],
                           free=["albedo", "amplitude_volume", "g", "extinction",
                                 "amplitude_surface", "correlation_length", "tau_o"]),
     "valid range is at most 10"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], gains="auto"), "gain mode"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], mask=np.ones((3, 3), bool)),
     "mask has shape"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], mask=np.zeros((8, 8), bool)),
     "selects no pixel"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], saturation=0.0),
     r"saturation = 0.0 is out of range; valid range is \(0, inf\]"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], max_iterations=0),
     "max_iterations = 0 is out of range"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], shadow_ratio=1.5),
     r"shadow_ratio = 1.5 is out of range; valid range is \(0, 1\]"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], initial_gains=-np.ones(10)),
     r"gains\[0\] = -1.0 is out of range"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], fixed={"g": 1.5}),
     r"g\[0, 0\] = 1.5 is out of range; valid range is \(-1, 1\)"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], fixed={"amplitude_surface": 0.0},
                           free=["albedo", "amplitude_surface"]), "both free and fixed"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], free=["g"]),
     "albedo is neither free nor fixed"),
    (lambda c: rf.fit_maps(np.where(np.ones_like(c["images"], bool), np.nan, 0.0),
                           c["directions"]), "is not finite"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], variant="llvm_ad_mono"),
     "need an RGB variant"),
    (lambda c: rf.render_capture(dict(c["maps"], normal=-c["maps"]["normal"]),
                                 c["directions"]), r"normal\[0, 0\].*n_z > 0"),
    (lambda c: rf.render_capture(dict(c["maps"], extinction=np.zeros((8, 8))),
                                 c["directions"]), r"extinction\[0, 0\] = 0.0"),
    (lambda c: rf.render_capture({"normal": c["maps"]["normal"]}, c["directions"]),
     "needs 'normal'"),
    (lambda c: rf.render_capture(c["maps"], c["directions"], gains=np.ones(3)),
     r"gains has shape \(3,\)"),
    (lambda c: rf.render_capture(dict(c["maps"], radius=0.1), c["directions"]),
     "maps has both 'albedo' and 'radius'"),
    (lambda c: rf.render_capture({k: v for k, v in c["maps"].items() if k != "albedo"}
                                 | {"radius": 5.0}, c["directions"]),
     r"radius\[0, 0\] = 5.0 is out of range"),
    (lambda c: rf.synthetic_capture(8, 8, 10, noise=-0.1), "noise = -0.1 is out of range"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], fixed={"energy": "conserving"}),
     r"energy = 'conserving': per-pixel maps need energy = 'paper'"),
    (lambda c: rf.synthetic_capture(8, 8, lights=10.5),
     r"lights = 10.5 is not a whole number; valid range is \[1, inf\]"),
    (lambda c: rf.synthetic_capture(8, 8, lights=10, near_camera=2.5),
     r"near_camera = 2.5 is not a whole number; valid range is \[0, 10\]"),
    (lambda c: rf.synthetic_capture(8, 8, lights=0), r"lights = 0 is out of range"),
    (lambda c: rf.fit_maps(c["images"], c["directions"], rounds=float("inf")),
     "rounds = inf is not a whole number"),
])
def test_bad_input_is_named(call, message):
    cap = rf.synthetic_capture(8, 8, 10, noise=0.0)
    with pytest.raises(ValueError, match=message):
        call(cap)


def test_per_pixel_grain_radius_is_recovered():
    """SYNTHETIC capture of hematite whose grain radius differs per region (the albedo per
    channel follows from it, GrainAlbedo), 1 % noise, 8 held-out lights: the radius is fitted
    per pixel (1 number instead of 3 albedos) through the chain rule of rho(r), and recovered
    per region; calibrated gains; A_v, g and extinction held (not identifiable, rti.fit module doc).
    Measured: radius medians within 1 %, normal medians 1.0-2.3 degrees, held-out RMS 1.5 x
    the noise."""
    maps, region = rf.synthetic_maps(24, 24, relief=0.25, seed=0)
    radii = np.array([0.045, 0.06, 0.08, 0.4])
    maps = dict(maps)
    del maps["albedo"]
    maps["radius"] = radii[region]
    maps["amplitude_surface"] = np.full(region.shape, 1e-5)
    d = rf.dome_directions(40)
    clean = rf.render_capture(maps, d, gains=np.full(40, 2.0))
    images = clean + np.random.default_rng(1).normal(scale=0.01, size=clean.shape).astype(
        np.float32)
    held = np.arange(4, 40, 5)
    used = np.setdiff1d(np.arange(40), held)
    fixed = {n: maps[n] for n in ("amplitude_volume", "g", "extinction")}
    res = rf.fit_maps(images[used], d[used],
                      free=["radius", "amplitude_surface", "correlation_length"], fixed=fixed,
                      gains="fixed", initial_gains=np.full(len(used), 2.0))
    assert res.n_parameters == 5 and "radius" in res.maps
    err = np.degrees(np.arccos(np.clip(np.sum(res.normals * maps["normal"], -1), -1, 1)))
    for i, r in enumerate(radii):
        sel = region == i
        assert np.median(res.maps["radius"][sel]) == pytest.approx(r, rel=0.03), i
        assert np.median(err[sel]) < 2.5, i
    # the albedo map is the grains' albedo
    rho, _ = rf.GrainAlbedo("radius", {})(res.maps["radius"][region == 2])
    np.testing.assert_allclose(res.albedo[region == 2], rho, rtol=1e-5)
    pred = res.predict(d[held], gains=np.full(len(held), 2.0))
    assert np.sqrt(np.mean((pred - images[held]) ** 2)) / 0.01 < 1.7


def _grain_regions_fit(size: int, tolerance: float, normal_deg: float):
    """SYNTHETIC capture (docs/rti.md): four regions of different hematite grain radius,
    amplitude_volume and extinction, a relief, 40 lights of which 8 lie 2-8 degrees from the
    camera (the coherent cone), 1 % noise (of full scale, the brightest clean value 0.9);
    radius, A_v and extinction fitted per pixel with the normal, every fifth light held out."""
    cap = rf.synthetic_capture(size, size, lights=40, noise=NOISE, exposure=None,
                               regions="grains", near_camera=8, seed=0)
    truth, region = cap["maps"], cap["region"]
    held = np.arange(4, 40, 5)
    kept = np.setdiff1d(np.arange(40), held)
    fixed = {n: truth[n] for n in ("g", "amplitude_surface", "correlation_length")}
    res = rf.fit_maps(cap["images"][kept], cap["directions"][kept],
                      free=["radius", "amplitude_volume", "extinction"], fixed=fixed,
                      gains="fixed", initial_gains=cap["gains"][kept])
    assert res.n_parameters == 5
    err = _normal_error_deg(res.normals, truth["normal"])
    rel = {(i, name): np.median(res.maps[name][region == i]) / props[name] - 1.0
           for i, props in enumerate(rf.SYNTHETIC_GRAIN_REGIONS)
           for name in ("radius", "amplitude_volume", "extinction")}
    normal_medians = [float(np.median(err[region == i])) for i in range(4)]
    predicted = rf.relight(res, cap["directions"][held], cap["gains"][held])
    rms = np.sqrt(np.mean((predicted - cap["images"][held]) ** 2))
    print(f"{size} x {size}: region medians (relative error) "
          + ", ".join(f"{k}: {v:+.4f}" for k, v in rel.items())
          + f"; normal medians {np.round(normal_medians, 2)} degrees; held-out RMS / noise "
          f"{rms / NOISE:.3f}; fit {res.fit_settings['seconds']:.0f} s")
    for key, value in rel.items():
        assert abs(value) < tolerance, (key, value)
    assert max(normal_medians) < normal_deg, normal_medians
    assert rms / NOISE < 1.2
    return res


def test_grain_regions_recovered_with_lights_near_the_camera():
    """The synthetic bar of docs/rti.md at 32 x 32 (the 256 x 256 run is the slow test below).
    Measured: region medians within 4 % (radius 2.4 %, A_v 3.9 %, extinction 2.3 % in the
    darkest region, < 1 % elsewhere), normal medians < 0.5 degrees, held-out RMS 1.03 x the
    noise. The issue's bar: 5 % and 2 degrees."""
    _grain_regions_fit(32, tolerance=0.05, normal_deg=1.0)


@pytest.mark.slow
def test_grain_regions_recovered_256():
    """The same at the issue's 256 x 256 x 40 lights (several minutes on 2 cores). Measured:
    region medians within 0.6 %, normal medians 0.27-0.43 degrees, held-out RMS 1.03 x the
    noise."""
    _grain_regions_fit(256, tolerance=0.01, normal_deg=0.6)


def test_near_camera_lights_and_grain_regions():
    cap = rf.synthetic_capture(4, 4, lights=10, noise=0.0, regions="grains", near_camera=3,
                               exposure=None)
    elevation = np.degrees(np.arcsin(cap["directions"][:, 2]))
    assert np.sum(elevation > 81.9) == 3 and np.all(elevation[:7] <= 80.0 + 1e-9)
    assert np.all((elevation[7:] >= 82.0 - 1e-9) & (elevation[7:] <= 88.0 + 1e-9))
    assert np.max(cap["clean"]) == pytest.approx(0.9, rel=1e-6)
    assert "albedo" not in cap["maps"]
    np.testing.assert_array_equal(
        cap["maps"]["radius"][cap["region"] == 3], rf.SYNTHETIC_GRAIN_REGIONS[3]["radius"])
    with pytest.raises(ValueError, match="near_camera = 11"):
        rf.synthetic_capture(4, 4, lights=10, near_camera=11)
    with pytest.raises(ValueError, match="regions = 'sand' is not a region set"):
        rf.synthetic_maps(4, 4, regions="sand")


@pytest.mark.parametrize("free,fixed,fragment", [
    (["radius", "albedo"], {}, "albedo and radius cannot both be given"),
    (["agglomerate_radius"], {}, "agglomerate_radius cannot be free with grains = 'sphere'"),
    (["radius"], {"albedo": (0.5, 0.5, 0.5)}, "albedo and radius cannot both be given"),
])
def test_per_pixel_grain_errors(free, fixed, fragment):
    cap = rf.synthetic_capture(4, 4, lights=8)
    with pytest.raises(ValueError, match=re.escape(fragment)):
        rf.fit_maps(cap["images"], cap["directions"], free=free, fixed=fixed)


def test_grain_albedo_table_against_direct_theory():
    """GrainAlbedo's interpolation against the plugin's double-precision albedo between nodes."""
    from mitsuba_powder.plugin.grains import GrainOptics

    for name, settings in (("radius", {}), ("radius", {"grains": "slab"}),
                           ("agglomerate_radius", {"grains": "agglomerate",
                                                   "agglomerate_fill": 0.4})):
        table = rf.GrainAlbedo(name, settings)
        assert table.max_error < 1e-5, (name, settings, table.max_error)
        r = np.exp(np.random.default_rng(0).uniform(np.log(0.011), np.log(2.9), 50))
        rho, drho = table(r)
        optics = GrainOptics(settings)
        if name == "radius":
            direct, d = optics.albedo(table.wavelengths, r, derivatives=True)
            col = 0
        else:
            direct, d = optics.albedo(table.wavelengths, np.full(50, 0.017), derivatives=True,
                                      agglomerate_radius=r, agglomerate_fill=0.4)
            col = 3
        np.testing.assert_allclose(rho, direct, rtol=1e-5)
        np.testing.assert_allclose(drho, d[:, :, col], rtol=2e-3, atol=1e-3)
