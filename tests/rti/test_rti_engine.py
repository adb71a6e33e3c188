"""The Dr.Jit per-pixel solver (mitsuba_powder.rti.engine) against the NumPy reference.

References: NumPy's linear solver for the unrolled Cholesky factorisation; the normal
equations, costs and gain systems assembled from :class:`PixelProblem`'s NumPy Jacobian
(itself checked against central differences in test_rti_fit.py) and
:func:`mitsuba_powder.rti.gains.gain_system`; the NumPy solver's maps on SYNTHETIC captures
(the issue's bar: region medians within 0.5 %, normals within 0.2 degrees).
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import write_exr_capture
from mitsuba_powder import rti as rf
from mitsuba_powder.fitting.optimise import ParamSpec, batch_levenberg_marquardt
from mitsuba_powder.rti import blocks as blocks_module
from mitsuba_powder.rti.engine import PixelSystem, cholesky_solve
from mitsuba_powder.rti.forward import PixelEvaluator, near_field, slopes_of_normals
from mitsuba_powder.rti.gains import gain_system
from mitsuba_powder.rti.pixels import PixelData
from mitsuba_powder.rti.problem import PixelProblem
from mitsuba_powder.variants import use_variant

NOISE = 0.01
HELD = ("amplitude_volume", "g", "extinction")
SLOPE = ParamSpec(-5.0, 5.0, False, 0.0)


@pytest.mark.parametrize("n", [1, 3, 7, 10])
def test_cholesky_solve_matches_numpy(n):
    rng = np.random.default_rng(n)
    m = rng.normal(size=(50, n + 4, n))
    a = np.einsum("pki,pkj->pij", m, m) + 1e-3 * np.eye(n)
    b = rng.normal(size=(50, n))
    with use_variant("llvm_ad_rgb"):
        tri = [mi.Float64(np.ascontiguousarray(a[:, i, j])) for i in range(n)
               for j in range(i + 1)]
        x, _, ok = cholesky_solve(tri, [mi.Float64(np.ascontiguousarray(b[:, i]))
                                        for i in range(n)])
        got = np.stack([np.array(v) for v in x], axis=1)
        assert np.all(np.array(ok))
    np.testing.assert_allclose(got, np.linalg.solve(a, b[..., None])[..., 0], rtol=1e-8,
                               atol=1e-10)


def test_cholesky_flags_an_indefinite_system():
    with use_variant("llvm_ad_rgb"):
        a = [mi.Float64([1.0, 1.0]), mi.Float64([2.0, 0.0]), mi.Float64([1.0, 1.0])]
        x, _, ok = cholesky_solve(a, [mi.Float64([1.0, 1.0]), mi.Float64([1.0, 1.0])])
        # [[1, 2], [2, 1]] is indefinite: flagged, step 0; [[1, 0], [0, 1]] is solved
        assert list(np.array(ok)) == [False, True]
        assert np.array(x[0])[0] == 0.0 and np.array(x[0])[1] == pytest.approx(1.0)


def _problem(kind: str):
    """A small problem of 12 pixels under 10 lights in both solvers' form: ``default`` (normal,
    albedo, surface lobe), ``grain`` (a free radius), ``near`` (lights at 3 image widths),
    ``held`` (albedo held, A_v free)."""
    maps, _ = rf.synthetic_maps(4, 3)
    shape = maps["normal"].shape[:2]
    d = rf.dome_directions(10)
    p, k = 12, 10
    gains = np.linspace(1.5, 2.5, k)
    layout = [("slope_x", SLOPE), ("slope_y", SLOPE)]
    fixed = {n: maps[n].reshape(p) for n in HELD}
    fixed_albedo, grain, field, varying = None, None, None, ["amplitude_surface",
                                                             "correlation_length"]
    render = dict(maps)
    if kind == "grain":
        grain = rf.GrainAlbedo("radius", {})
        del render["albedo"]
        render["radius"] = np.full(shape, 0.08)
        layout.append(("radius", rf.SPECS["radius"]))
    elif kind == "held":
        fixed_albedo = maps["albedo"].reshape(p, 3)
        varying = ["amplitude_volume", "amplitude_surface"]
        fixed.pop("amplitude_volume")
        fixed["correlation_length"] = maps["correlation_length"].reshape(p)
    else:
        layout += [(f"albedo{c}", rf.SPECS["albedo"]) for c in range(3)]
    layout += [(n, rf.SPECS[n]) for n in varying]
    distance = 3.0 if kind == "near" else np.inf
    obs = rf.render_capture(render, d, gains=gains, light_distance=distance)
    obs = obs.reshape(k, p, 3).transpose(1, 0, 2).astype(np.float64)
    obs += np.random.default_rng(2).normal(scale=NOISE, size=obs.shape)
    if kind == "near":
        field = near_field(d, distance, shape)
    ev = PixelEvaluator(varying + list(fixed), {}, "llvm_ad_rgb")
    weights = np.ones((p, k))
    weights[0, :3] = 0.0  # some observations left out
    dirs = d if field is None else field[0]
    irr = None if field is None else field[1]
    data = PixelData(obs, weights, dirs, gains, layout, fixed, fixed_albedo, grain, irr)
    prob, system = PixelProblem(ev, data), PixelSystem(ev, data)
    y = np.zeros((p, len(layout) + 1))
    y[:, :2] = slopes_of_normals(maps["normal"].reshape(p, 3)) + 0.05
    col = 2
    if kind == "grain":
        y[:, 2] = rf.SPECS["radius"].to_y(0.07)
        col = 3
    elif kind != "held":
        y[:, 2:5] = maps["albedo"].reshape(p, 3) * 0.9
        col = 5
    for name in varying:
        y[:, col] = rf.SPECS[name].to_y(rf.SPECS[name].start)
        col += 1
    y[:, -1] = np.arange(p)
    return prob, system, y


@pytest.mark.parametrize("kind", ["default", "grain", "near", "held"])
def test_normal_equations_match_the_numpy_jacobian(kind):
    prob, system, y = _problem(kind)
    res, jac = prob.jacobian(y)
    jac = jac[:, :, :-1]
    n = jac.shape[2]
    jtj = np.einsum("bki,bkj->bij", jac, jac)
    jtr = np.einsum("bki,bk->bi", jac, res)
    with use_variant("llvm_ad_rgb"):
        rows = [mi.Float64(np.ascontiguousarray(y[:, j])) for j in range(n)]
        cost, a, g = system.normal_equations(rows, dr.arange(mi.UInt32, len(y)))
        cost = np.array(cost)
        a = np.stack([np.array(v) for v in a], axis=1)
        g = np.stack([np.array(v) for v in g], axis=1)
    np.testing.assert_allclose(cost, np.sum(res**2, axis=1), rtol=1e-5)
    tri = np.array([jtj[:, i, j] for i in range(n) for j in range(i + 1)]).T
    scale = np.max(np.abs(tri), axis=1, keepdims=True)
    assert np.max(np.abs(a - tri) / scale) < 1e-4
    assert np.max(np.abs(g - jtr) / np.max(np.abs(jtr), axis=1, keepdims=True)) < 1e-4


@pytest.mark.parametrize("kind", ["default", "grain", "near"])
def test_solver_reaches_the_reference_optimum(kind):
    prob, system, y = _problem(kind)
    hold = np.zeros(y.shape[1], dtype=bool)
    hold[-1] = True
    ref = batch_levenberg_marquardt(prob, y, 30, hold=hold, hopeless=np.inf)
    got = system.solve(y, 30)
    assert got.iterations >= 2
    np.testing.assert_allclose(got.cost, ref.cost, rtol=1e-3)
    # the normal (slopes) and the albedo or grain size at the same optimum
    np.testing.assert_allclose(got.y[:, :3], ref.y[:, :3], atol=2e-3)


@pytest.mark.parametrize("kind", ["default", "near"])
def test_gain_system_matches_the_numpy_reference(kind):
    prob, system, y = _problem(kind)
    res, jac = prob.jacobian(y)
    value, _ = prob.ev(*prob.unpack(y)[1:4], prob.lights(np.arange(len(y))))
    model = value if prob.irradiance is None else value * prob.irradiance[:, :, None]
    s_ref, b_ref = gain_system(res, jac[:, :, :-1], model, prob.sqrt_w)
    got_value, (s, b) = system.model(y[:, :-1], gain_terms=True)
    np.testing.assert_allclose(got_value, value, rtol=1e-5, atol=1e-7)
    assert np.max(np.abs(s - s_ref)) / np.max(np.abs(s_ref)) < 1e-4
    assert np.max(np.abs(b - b_ref)) / np.max(np.abs(b_ref)) < 1e-3


@pytest.fixture(scope="module")
def capture():
    rng = np.random.default_rng(5)
    rel = 1.0 + 0.1 * rng.standard_normal(30)
    return rf.synthetic_capture(24, 24, 30, noise=NOISE, gains=rel / rel.mean())


def _agree(a, b, cap, albedo_only=False):
    """The issue's bar between two fits: region medians within 0.5 %, normals 0.2 deg."""
    ang = np.degrees(np.arccos(np.clip(np.sum(a.normals * b.normals, -1), -1.0, 1.0)))
    assert np.median(ang) < 0.2, np.median(ang)
    for r in range(4):
        sel = cap["region"] == r
        for c in range(3):
            ma, mb = np.median(a.albedo[sel][:, c]), np.median(b.albedo[sel][:, c])
            assert abs(ma / mb - 1) < 0.005, (r, c, ma, mb)
        for name in ([] if albedo_only else [n for n in a.free if n != "albedo"]):
            ma, mb = np.median(a.maps[name][sel]), np.median(b.maps[name][sel])
            assert abs(ma / mb - 1) < 0.005, (r, name, ma, mb)


def test_fit_maps_solvers_agree_with_gains_fitted(capture):
    cap = capture
    fixed = {n: cap["maps"][n] for n in HELD}
    start = np.full(30, cap["gains"].mean())
    fits = {s: rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fit",
                           initial_gains=start, solver=s) for s in rf.SOLVERS}
    a, b = fits["drjit"], fits["numpy"]
    assert a.fit_settings["solver"] == "drjit" and b.fit_settings["solver"] == "numpy"
    _agree(a, b, cap)
    np.testing.assert_allclose(a.gains, b.gains, rtol=1e-4)
    np.testing.assert_allclose(a.residual_rms, b.residual_rms, rtol=1e-3)


def test_fit_maps_solvers_agree_near_field_with_shadows():
    cap = rf.synthetic_capture(16, 16, 24, noise=NOISE, light_distance=4.0)
    images = cap["images"].copy()
    images[3, :6, :6] *= 0.2   # a cast shadow: flagged and left out
    images[7, 8:, 8:] = 1.0    # saturated
    fixed = {n: cap["maps"][n] for n in HELD}
    fits = {s: rf.fit_maps(images, cap["directions"], fixed=fixed, gains="fit",
                           initial_gains=cap["gains"], light_distance=4.0, solver=s)
            for s in rf.SOLVERS}
    a, b = fits["drjit"], fits["numpy"]
    np.testing.assert_allclose(a.gains, b.gains, rtol=1e-4)
    assert a.used[3, :6, :6].mean() < 0.1 and not a.used[7, 8:, 8:].any()
    # shadow flags compare the model with the observation: one at the threshold may differ
    assert np.mean(a.used != b.used) < 1e-3
    _agree(a, b, cap)


def test_gains_on_a_subsample_are_held_for_every_pixel(capture):
    cap = capture
    fixed = {n: cap["maps"][n] for n in HELD}
    lines = []
    sub = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fit",
                      initial_gains=cap["gains"], gain_subsample=200, progress=lines.append)
    assert sub.fit_settings["gains"] == "fit" and sub.fit_settings["gain_pixels"] == 200
    assert any("gains: fitted on 200 of 576 pixels" in line for line in lines)
    np.testing.assert_allclose(sub.gains, cap["gains"], rtol=0.05)
    # the maps are those of a fit of every pixel with these gains held
    held = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fixed",
                       initial_gains=sub.gains)
    np.testing.assert_array_equal(held.normals, sub.normals)
    np.testing.assert_array_equal(held.albedo, sub.albedo)
    # fewer masked pixels than gain_pixels: every pixel, no subsample
    full = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fit",
                       initial_gains=cap["gains"], gain_subsample=10_000)
    assert "gain_pixels" not in full.fit_settings


def test_unchanged_rounds_are_not_repeated(capture):
    cap = capture
    lines = []
    fixed = {n: cap["maps"][n] for n in HELD}
    res = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fixed",
                      initial_gains=cap["gains"], rounds=4, progress=lines.append,
                      shadows="ratio")
    skipped = [line for line in lines if "observation flags unchanged" in line]
    fitted = sum("Levenberg-Marquardt" in ln for ln in lines)
    assert skipped and len(skipped) + fitted == 4
    # a skipped round would have repeated the last one: the maps are those of the rounds run
    ref = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fixed",
                      initial_gains=cap["gains"], rounds=fitted, shadows="ratio")
    for name in ("normals", "albedo", "residual_rms"):
        np.testing.assert_array_equal(getattr(res, name), getattr(ref, name), err_msg=name)


@pytest.mark.parametrize("kwargs, message", [
    ({"solver": "scipy"}, r"solver = 'scipy' is not a solver; choose one of \('drjit', "
                          r"'numpy'\)"),
    ({"gain_pixels": 0}, r"gain_pixels"),
    ({"seed": -1}, r"seed"),
])
def test_bad_solver_options_are_named(capture, kwargs, message):
    with pytest.raises(ValueError, match=message):
        rf.fit_maps(capture["images"], capture["directions"], gains="fit", **kwargs)


def test_cuda_fit_maps_matches_llvm(capture):
    """cuda_ad_rgb end to end where a CUDA device is present."""
    if "cuda_ad_rgb" not in mi.variants() or not dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("no CUDA device on this machine")
    cap = capture
    fixed = {n: cap["maps"][n] for n in HELD}
    fits = [rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fit",
                        initial_gains=cap["gains"], variant=v)
            for v in ("llvm_ad_rgb", "cuda_ad_rgb")]
    _agree(fits[0], fits[1], cap)


def test_blocks_within_a_memory_budget_give_the_same_maps(capture, monkeypatch):
    """With the gains held a pixel's fit depends only on its own observations: a fit in
    blocks (a tiny memory budget) equals the fit in one block."""
    cap = capture
    fixed = {n: cap["maps"][n] for n in HELD}
    one = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fixed",
                      initial_gains=cap["gains"], shadows="ratio")
    lines = []
    # a budget below the fit's smallest, so that 256 pixels need several blocks
    monkeypatch.setattr(blocks_module, "MIN_MEMORY_GB", 1e-4)
    blocks = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fixed",
                         initial_gains=cap["gains"], memory_gb=0.002, progress=lines.append,
                         shadows="ratio")
    assert one.fit_settings["blocks"] == 1 and blocks.fit_settings["blocks"] > 2
    assert sum(line.startswith("block ") for line in lines) == blocks.fit_settings["blocks"]
    assert blocks.fit_settings["peak_memory_mib"] > 0 and blocks.fit_settings["memory_gb"] == 0.002
    for name in ("normals", "albedo", "residual_rms"):
        np.testing.assert_array_equal(getattr(blocks, name), getattr(one, name), err_msg=name)
    for name in one.maps:
        np.testing.assert_array_equal(blocks.maps[name], one.maps[name], err_msg=name)
    np.testing.assert_array_equal(blocks.used, one.used)
    assert np.array_equal(blocks.mask, one.mask)


def test_memory_budget_is_checked(capture):
    with pytest.raises(ValueError, match=r"memory_gb = 0 is out of range; valid range is "
                                         r"\[0\.015625, inf\) GiB"):
        rf.fit_maps(capture["images"], capture["directions"], memory_gb=0)


def test_cli_fit_maps_records_solver_memory_and_gain_pixels(tmp_path):
    import json

    from mitsuba_powder.cli import main

    lp = write_exr_capture(tmp_path, rf.synthetic_capture(12, 12, 10, noise=NOISE, seed=4))
    out = tmp_path / "maps"
    assert main(["fit-maps", str(lp), "--out", str(out), "--encoding",
                 "linear", "--solver", "numpy", "--memory-gb", "0.5", "--gains", "fit",
                 "--gain-pixels", "64", "--rounds", "1"]) == 0
    fit = json.loads((out / "fit.json").read_text())["fit"]
    assert fit["solver"] == "numpy" and fit["memory_gb"] == 0.5
    assert fit["gain_pixels"] == 64 and fit["gains"] == "fit" and fit["blocks"] == 1
    assert fit["peak_memory_mib"] > 0
    assert fit["full_scale"] is None   # EXR records any value: nothing clipped
