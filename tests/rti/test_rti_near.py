"""Lights at a finite distance and gains that generalise: the forward model, the fit of the
distance, the gain model in relighting, the baselines, the CLI's options and its outputs.
All captures are SYNTHETIC (rendered by the package)."""

from __future__ import annotations

import hashlib
import json
import math
from pathlib import Path

import numpy as np
import pytest

import mitsuba_powder.rti as rf
from mitsuba_powder.cli import main
from mitsuba_powder.fitting.optimise import ParamSpec
from mitsuba_powder.rti.baselines import fit_baseline
from mitsuba_powder.rti.forward import PixelEvaluator, near_field, slopes_of_normals
from mitsuba_powder.rti.gains import GainTrend
from mitsuba_powder.rti.lights import LightRig, image_light_field, light_field, pixel_coordinates
from mitsuba_powder.rti.maps import read_maps, write_maps
from mitsuba_powder.rti.pixels import PixelData
from mitsuba_powder.rti.properties import SLOPE_LIMIT

NOISE = 0.01
NON_IDENTIFIABLE = ("amplitude_volume", "g", "extinction")


def _normal_error_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=-1), -1.0, 1.0)))


def _albedo_medians(result, cap):
    truth = cap["maps"]["albedo"]
    return np.array([[np.median(result.albedo[cap["region"] == r][:, c])
                      / truth[cap["region"] == r][0, c] - 1 for c in range(3)]
                     for r in range(4)])


def test_distant_lights_are_todays_model_bit_for_bit():
    """r = inf is the distant model exactly, not a near-field model close to it: a distant
    rig's light field is its directions and irradiance factors 1 to the last bit; a fit at
    r = inf (a number or one per light) takes the distant path, with no per-pixel lights; and
    the near-field paths of the evaluator and of both solvers (per-pixel directions,
    irradiance factors), fed those values, give the distant model bit for bit."""
    d = rf.dome_directions(12)
    rig = LightRig(d, math.inf)
    dirs, s = light_field(rig, pixel_coordinates((8, 8)).reshape(-1, 2))
    assert np.array_equal(dirs, np.broadcast_to(rig.directions[:, None], dirs.shape))
    assert np.all(s == 1.0)
    for r in (math.inf, np.full(12, math.inf)):
        assert near_field(d, r, (8, 8)) is None
    cap = rf.synthetic_capture(8, 8, 12, seed=3)
    fixed = {n: cap["maps"][n] for n in NON_IDENTIFIABLE}
    a = rf.fit_maps(cap["images"], d, fixed=fixed, rounds=1, max_iterations=5)
    b = rf.fit_maps(cap["images"], d, fixed=fixed, rounds=1, max_iterations=5,
                    light_distance=np.full(12, math.inf))
    for name in ("normals", "albedo", "gains", "residual_rms"):
        np.testing.assert_array_equal(getattr(a, name), getattr(b, name), err_msg=name)
    assert a.fit_settings["light_distance_source"] == "distant"
    # the near-field paths with the distant field's values: the same model, bit for bit
    p = 64
    ev = PixelEvaluator(["amplitude_surface", "correlation_length"] + list(fixed), {},
                        rf.VARIANT)
    layout = [("slope_x", _SLOPE), ("slope_y", _SLOPE)]
    layout += [(f"albedo{c}", rf.SPECS["albedo"]) for c in range(3)]
    layout += [(n, rf.SPECS[n]) for n in ("amplitude_surface", "correlation_length")]
    obs = cap["images"].reshape(12, p, 3).transpose(1, 0, 2)
    held = {n: np.asarray(v, dtype=np.float64).reshape(p) for n, v in fixed.items()}
    common = (obs, np.ones((p, 12)))
    distant = PixelData(*common, d, cap["gains"], layout, held)
    near = PixelData(*common, np.ascontiguousarray(np.broadcast_to(d, (p, 12, 3)),
                                                   dtype=np.float32),
                     cap["gains"], layout, held, irradiance=np.ones((p, 12)))
    y = np.zeros((p, len(layout) + 1))
    y[:, :2] = slopes_of_normals(cap["maps"]["normal"].reshape(p, 3))
    y[:, 2:5] = cap["maps"]["albedo"].reshape(p, 3)
    y[:, 5:7] = [rf.SPECS[n].to_y(rf.SPECS[n].start) for n in ("amplitude_surface",
                                                                 "correlation_length")]
    for solver in rf.SOLVERS.values():
        far_fit, near_fit = (solver(ev, data).solve(y, 5) for data in (distant, near))
        np.testing.assert_array_equal(far_fit.y, near_fit.y)
        far_model, near_model = (solver(ev, data).model(far_fit.y, True)
                                 for data in (distant, near))
        np.testing.assert_array_equal(far_model[0], near_model[0])
        for x, z in zip(far_model[1], near_model[1]):
            np.testing.assert_array_equal(x, z)


_SLOPE = ParamSpec(-SLOPE_LIMIT, SLOPE_LIMIT, False, 0.0)


def test_near_render_is_the_distant_model_per_pixel():
    """Each pixel of a near-field render is the distant model under that pixel's own light
    direction, times its irradiance factor."""
    maps, _ = rf.synthetic_maps(6, 8, seed=1)
    d = rf.dome_directions(5)
    near = rf.render_capture(maps, d, light_distance=2.5)
    dirs, s = image_light_field(LightRig(d, 2.5), (6, 8))
    for i, j in [(0, 0), (5, 7), (2, 3)]:
        one = {k: (v[i:i + 1, j:j + 1] if np.ndim(v) >= 2 else v) for k, v in maps.items()}
        ref = rf.render_capture(one, dirs[:, i, j], s[:, i, j])
        np.testing.assert_allclose(near[:, i, j], ref[:, 0, 0], rtol=1e-5, atol=1e-7)


@pytest.fixture(scope="module")
def near_capture():
    return rf.synthetic_capture(32, 32, 40, noise=NOISE, light_distance=3.0)


def test_near_capture_distance_fitted_and_maps_recovered(near_capture):
    """r = 3: the fitted distance within 5 % and the maps within the distant fit's bounds
    (tests/rti/test_rti_fit.py); measured r = 2.988, normals 0.42 / 0.97 degrees (median /
    95 %), albedo medians within 0.6 %."""
    cap = near_capture
    fixed = {n: cap["maps"][n] for n in NON_IDENTIFIABLE}
    start = np.full(40, cap["gains"].mean())
    result = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, initial_gains=start,
                         light_distance="fit")
    assert abs(result.light_distance / 3.0 - 1) < 0.05, result.light_distance
    assert result.fit_settings["light_distance_source"] == "fitted"
    err = _normal_error_deg(result.normals, cap["maps"]["normal"])
    assert np.median(err) < 1.0 and np.percentile(err, 95) < 2.0
    assert np.max(np.abs(_albedo_medians(result, cap))) < 0.05
    assert 0.9 < np.sqrt(np.nanmean(result.residual_rms**2)) / NOISE < 1.1


def test_distant_fit_of_a_near_capture_is_biased(near_capture):
    """Without the near-field model the normals tilt by degrees (measured median 10)."""
    cap = near_capture
    fixed = {n: cap["maps"][n] for n in NON_IDENTIFIABLE}
    result = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, rounds=1,
                         initial_gains=np.full(40, cap["gains"].mean()))
    assert np.median(_normal_error_deg(result.normals, cap["maps"]["normal"])) > 3.0


def test_smooth_gains_relight_held_out_lights_within_the_noise():
    """Light intensities falling smoothly with elevation (+15 % at the lowest light, -15 %
    at the highest); every fifth light held out, the lowest among them; relit with the gain
    model's gains (none given): within 1.2 x the noise (measured 1.03; 1.71 with gain 1)."""
    d = rf.dome_directions(40)
    lz = d[:, 2]
    rel = 1.0 + 0.15 * (1 - 2 * (lz - lz.min()) / (lz.max() - lz.min()))
    cap = rf.synthetic_capture(32, 32, 40, noise=NOISE, gains=rel)
    fixed = {n: cap["maps"][n] for n in NON_IDENTIFIABLE}
    held = np.arange(0, 40, 5)
    kept = np.setdiff1d(np.arange(40), held)
    assert np.argmin(lz) in held
    start = np.full(len(kept), cap["gains"][kept].mean())
    for mode in ("free", "smooth"):
        result = rf.fit_maps(cap["images"][kept], d[kept], fixed=fixed, initial_gains=start,
                             gain_trend=GainTrend(mode), gains="fit",
                             free=rf.MAP_DEFAULT_FREE)
        pred = rf.relight(result, d[held])
        per_light = np.sqrt(np.mean((pred - cap["images"][held]) ** 2, axis=(1, 2, 3)))
        assert np.max(per_light) / NOISE < 1.2, (mode, per_light / NOISE)
    flat = rf.relight(result, d[held], np.full(len(held), start.mean()))
    assert np.sqrt(np.mean((flat - cap["images"][held]) ** 2)) / NOISE > 1.5


def test_near_baselines_exact_for_a_lambertian_surface():
    d = rf.dome_directions(30)
    h, w = 16, 20
    rng = np.random.default_rng(0)
    n = rng.normal(size=(h, w, 3))
    n[..., 2] = 5.0
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    alb = rng.uniform(0.2, 0.8, (h, w, 3))
    dirs, s = image_light_field(LightRig(d, 3.0), (h, w))
    img = np.einsum("khwi,hwi->khw", dirs, n)[..., None] * alb[None] * s[..., None]
    near = fit_baseline("lambertian", img, d, light_distance=3.0)
    assert np.max(np.abs(near.predict(d) - img)) < 1e-5
    assert np.max(_normal_error_deg(near.normals, n)) < 0.05
    far = fit_baseline("lambertian", img, d)
    assert np.max(np.abs(far.predict(d) - img)) > 0.05
    assert fit_baseline("hsh", img, d, light_distance=3.0).predict(d[:4]).shape == (4, h, w, 3)


@pytest.mark.parametrize("call, fragment", [
    (lambda cap: rf.fit_maps(cap["images"], cap["directions"], light_distance=0.5),
     "light_distance = 0.5 image widths is out of range; valid range is (0.707107, inf]"),
    (lambda cap: rf.fit_maps(cap["images"], cap["directions"], light_distance="far"),
     "light_distance = 'far' is not valid"),
    (lambda cap: fit_baseline("hsh", cap["images"], cap["directions"], light_distance=0.6),
     "light_distance = 0.6 image widths is out of range"),
    (lambda cap: GainTrend("smooth", spread=-0.1), "gain_spread = -0.1 is out of range"),
    (lambda cap: GainTrend("trend"), "gain_model = 'trend' is not valid"),
])
def test_bad_values_are_named(call, fragment):
    cap = rf.synthetic_capture(8, 8, 12, seed=2)
    with pytest.raises(ValueError) as err:
        call(cap)
    assert fragment in str(err.value)


def _snapshot(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    """A SYNTHETIC near-field capture on disk: 8 x 8 px, 12 lights at r = 3, 16-bit PNG;
    ``dirs.lp`` (unit directions) and ``pos.lp`` (positions in mm, pixel size 0.5 mm)."""
    folder = tmp_path_factory.mktemp("near")
    cap = rf.synthetic_capture(8, 8, lights=12, noise=0.002, seed=4, light_distance=3.0)
    names = [f"light{k:02d}.png" for k in range(12)]
    rf.write_lp(folder / "dirs.lp", names, cap["directions"])
    rf.write_lp(folder / "pos.lp", names, cap["directions"] * 3.0 * 8 * 0.5)
    like = rf.Capture(images=cap["images"], directions=cap["directions"], names=names,
                      encoding="linear", file_format="png", bit_depth=16)
    rf.write_images(like, cap["images"], names, folder)
    return folder


def test_cli_near_field_outputs_stay_under_out(capture_dir, tmp_path):
    """fit-maps, relight and compare-maps with near-field options write only under --out;
    fit.json records the distance and the gain model; scene.xml has a point light."""
    work = tmp_path / "w"
    work.mkdir()
    for p in capture_dir.iterdir():
        (work / p.name).write_bytes(p.read_bytes())
    before = _snapshot(tmp_path)
    out = work / "maps"
    assert main(["fit-maps", str(work / "pos.lp"), "--out", str(out), "--encoding", "linear",
                 "--pixel-size", "0.5", "--rounds", "1", "--iterations", "5",
                 "--gain-model", "free"]) == 0
    info = json.loads((out / "fit.json").read_text())
    assert info["light_rig"]["model"] == "near"
    np.testing.assert_allclose(info["light_rig"]["distance"], 3.0, rtol=1e-6)
    assert info["light_rig"]["pixel_size"] == 0.5
    assert info["gain_model"]["kind"] == "mitsuba-powder gain model"
    assert '<emitter type="point">' in (out / "scene.xml").read_text()
    result, _ = read_maps(out)
    assert np.allclose(result.light_distance, 3.0) and result.gain_model is not None
    relit = work / "relit"
    assert main(["relight", str(out), "--lp", str(work / "pos.lp"), "--out", str(relit)]) == 0
    comp = work / "comp"
    assert main(["compare-maps", str(work / "dirs.lp"), "--out", str(comp), "--encoding",
                 "linear", "--light-distance", "3", "--models", "lambertian,hsh",
                 "--no-error-images"]) == 0
    rows = json.loads((comp / "compare.json").read_text())["rows"]
    assert {r["model"] for r in rows} == {"lambertian", "lambertian_near", "hsh", "hsh_near"}
    after = _snapshot(tmp_path)
    for name, digest in before.items():
        assert after.get(name) == digest, name
    new = set(after) - set(before)
    assert all(n.split("/")[1] in ("maps", "relit", "comp") for n in new), new


@pytest.mark.parametrize("extra, fragment", [
    (["--light-distance", "0.5"], "--light-distance = 0.5 image widths is out of range; "
                                  "valid range is (0.707107, inf]"),
    (["--light-distance", "near"], "--light-distance = 'near' is not valid"),
    (["--pixel-size", "-1"], "--pixel-size = -1.0 is out of range; valid range is (0, inf)"),
])
def test_cli_bad_values_are_named(capture_dir, tmp_path, capsys, extra, fragment):
    assert main(["fit-maps", str(capture_dir / "dirs.lp"), "--out", str(tmp_path / "o"),
                 "--encoding", "linear"] + extra) != 0
    assert fragment in capsys.readouterr().err
    assert not (tmp_path / "o").exists()


def test_cli_mixed_lp_is_refused(capture_dir, tmp_path, capsys):
    """With --pixel-size an .lp is read as positions or as directions, never a mix."""
    lines = (capture_dir / "pos.lp").read_text().splitlines()
    unit = (capture_dir / "dirs.lp").read_text().splitlines()
    mixed = tmp_path / "mixed.lp"
    mixed.write_text("\n".join([lines[0], unit[1]] + [
        f"{capture_dir / ln.split()[0]} {' '.join(ln.split()[1:])}" for ln in lines[2:]])
        .replace(unit[1].split()[0], str(capture_dir / unit[1].split()[0])) + "\n")
    assert main(["fit-maps", str(mixed), "--out", str(tmp_path / "o"), "--encoding",
                 "linear", "--pixel-size", "0.5"]) != 0
    err = capsys.readouterr().err
    assert "is a position" in err and "a unit direction" in err and "mixed.lp, line" in err


def test_fit_json_round_trip_and_old_folders(tmp_path):
    """A near-field result's distance and gain model survive fit.json; a folder without the
    keys reads as distant with no gain model (relit as before)."""
    cap = rf.synthetic_capture(8, 8, 12, seed=5, light_distance=4.0)
    result = rf.fit_maps(cap["images"], cap["directions"], rounds=1, max_iterations=5,
                         light_distance=4.0, gain_trend=GainTrend("free"),
                         fixed={n: cap["maps"][n] for n in NON_IDENTIFIABLE})
    write_maps(result, tmp_path / "m")
    back, info = read_maps(tmp_path / "m")
    assert back.light_distance == 4.0
    np.testing.assert_allclose(back.gain_model.evaluate(cap["directions"]), result.gains,
                               rtol=1e-9)
    np.testing.assert_allclose(back.predict(cap["directions"]),
                               result.predict(cap["directions"]), rtol=1e-4, atol=1e-6)
    del info["light_rig"], info["gain_model"]
    (tmp_path / "m" / "fit.json").write_text(json.dumps(info))
    old, _ = read_maps(tmp_path / "m")
    assert math.isinf(old.light_distance) and old.gain_model is None


def test_default_gain_model_is_none_and_relights_new_lights_with_the_exposure():
    """By default no gain model is fitted: a light not fitted is relit with the exposure, the
    gains' mean (on real captures the gains' trend relit held-out lights worse: docs/rti.md)."""
    cap = rf.synthetic_capture(8, 8, 12, seed=5)
    result = rf.fit_maps(cap["images"], cap["directions"], rounds=1, max_iterations=5,
                         fixed={n: cap["maps"][n] for n in NON_IDENTIFIABLE})
    assert result.gain_model is None
    new = cap["directions"][:3] + np.array([0.01, 0.0, 0.0])
    np.testing.assert_array_equal(rf.relight(result, new),
                                  rf.relight(result, new, np.full(3, result.exposure)))
