"""The relief stage fits again only the pixels the relief shades (issue 36): with the gains
held, a pixel that no light's visibility lowers sees the same data as without the relief and
keeps its maps; the shaded pixels' maps equal those of a stage that fits every pixel again.
The shadows choice compares the two fits on the shaded pixels only (a tie where nothing
shades)."""

from __future__ import annotations

import numpy as np
import pytest

from mitsuba_powder.rti import fit_maps
from mitsuba_powder.rti.inputs import FitInputs
from mitsuba_powder.rti.relief import Relief, horizon_map
from mitsuba_powder.rti.synthetic import synthetic_capture


@pytest.fixture(scope="module")
def capture():
    """SYNTHETIC, 16 x 16 px, 24 lights at 10-80 degrees, gentle bumps whose integrated
    relief shades some pixels under the lowest lights."""
    return synthetic_capture(16, 16, lights=24, noise=0.005, relief=0.25, seed=2)


def _fit(capture, **options):
    lines: list[str] = []
    res = fit_maps(capture["images"], capture["directions"], rounds=1, shadows="relief",
                   progress=lines.append, **options)
    return res, lines


def test_only_the_shaded_pixels_are_fitted_again(capture, monkeypatch):
    res, lines = _fit(capture)
    said = [line for line in lines if "pixels shaded under some light" in line]
    assert len(said) == 1, lines
    shaded = int(said[0].split(" of 256 pixels")[0].split()[-1])
    assert 0 < shaded < 256, said
    plain = fit_maps(capture["images"], capture["directions"], rounds=1, shadows="ratio")
    vis = res.relief.visibility(capture["directions"])  # the final relief's, for the record
    assert vis.shape == (256, 24)
    same = np.all(res.normals == plain.normals, axis=-1)
    assert 256 - shaded <= int(same.sum()) < 256  # the others keep the ratio fit's maps
    monkeypatch.setattr(FitInputs, "shaded",
                        lambda self, relief, sel, light_distance, rows=64: sel.copy())
    full, full_lines = _fit(capture)
    assert any("256 of 256 pixels shaded under some light" in line for line in full_lines)
    # equal up to the solver's stopping rule (in the full stage the unshaded pixels' data go
    # through the per-pixel light path, in float32: measured 3e-5 on one normal's component,
    # 6e-4 relative on three albedos, far below the noise's 0.005)
    np.testing.assert_allclose(res.normals, full.normals, atol=1e-4)
    np.testing.assert_allclose(res.albedo, full.albedo, rtol=1e-3, atol=1e-6)
    np.testing.assert_allclose(res.residual_rms, full.residual_rms, rtol=1e-3, atol=1e-7)


def test_fitted_gains_refit_every_pixel(capture):
    """With the gains fitted with every pixel (they couple them all), every pixel is fitted
    again; gains fitted on a subsample of pixels are held after it: the shaded pixels only."""
    res, lines = _fit(capture, gains="fit", exposure=1.0)
    assert any("every pixel fitted again under its lights' visibility (the gains are "
               "fitted)" in line for line in lines), lines
    assert res.fit_settings["relief_refit"]["pixels"] == 256
    _, lines = _fit(capture, gains="fit", exposure=1.0, gain_subsample=64)
    assert any("pixels shaded under some light, fitted again under their lights' visibility "
               "(the others keep their maps)" in line for line in lines), lines


def test_the_diagnostics_count_both_fits(capture, monkeypatch):
    """fit.json's diagnostics after a partial refit: the underdetermined pixels are those of
    the merged maps (NaN residual), the evaluations both fits', the refit's own apart."""
    res, _ = _fit(capture)
    record = res.fit_settings["relief_refit"]
    assert 0 < record["pixels"] < 256 and record["evaluations"] > 0
    assert res.fit_settings["evaluations"] > record["evaluations"]
    nan = int(np.count_nonzero(~np.isfinite(res.residual_rms[res.mask])))
    assert res.fit_settings["underdetermined_pixels"] == nan
    # a refit whose pixels are all underdetermined (every light left out) is counted
    from mitsuba_powder.rti import inputs as rti_inputs

    picked = np.zeros((16, 16), dtype=bool)
    picked[4:6, 4:6] = True
    monkeypatch.setattr(rti_inputs.FitInputs, "shaded",
                        lambda self, relief, sel, light_distance, rows=64: picked & sel)
    real = rti_inputs.FitData.usable.fget

    def usable(data):  # the refit's 4 pixels see no usable observation
        return np.zeros_like(real(data)) if len(data.obs) == 4 else real(data)

    monkeypatch.setattr(rti_inputs.FitData, "usable", property(usable))
    dark, _ = _fit(capture)
    assert dark.fit_settings["relief_refit"] == {**dark.fit_settings["relief_refit"],
                                                 "pixels": 4, "underdetermined_pixels": 4}
    assert np.all(np.isnan(dark.residual_rms[picked]))
    assert dark.fit_settings["underdetermined_pixels"] == int(
        np.count_nonzero(~np.isfinite(dark.residual_rms[dark.mask])))


def test_shaded_pixels_of_a_flat_and_a_stepped_relief(capture):
    inputs_mask = np.ones((16, 16), dtype=bool)
    d = capture["directions"]
    from mitsuba_powder.rti.inputs import check_inputs
    from mitsuba_powder.rti.options import fit_options

    inputs = check_inputs(capture["images"], d, fit_options(), inputs_mask)
    flat = np.zeros((16, 16))
    assert not inputs.shaded(Relief(flat, horizon_map(flat)), inputs_mask, np.inf).any()
    step = np.zeros((16, 16))
    step[:, 8:] = 6.0  # a wall 6 px high facing -x: the pixels just left of it are shaded
    rel = Relief(step, horizon_map(step))
    got = inputs.shaded(rel, inputs_mask, np.inf, rows=5)
    want = np.any(rel.visibility(d) < 1.0, axis=1).reshape(16, 16)
    np.testing.assert_array_equal(got, want)
    assert got[:, 7].all() and not got[:, 9:].any()  # column 8: the edge's spread
    part = np.zeros((16, 16), dtype=bool)
    part[3:9, 2:12] = True
    np.testing.assert_array_equal(inputs.shaded(rel, part, np.inf), want & part)
