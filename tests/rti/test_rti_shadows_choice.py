"""The default cast shadows, shadows="auto" (issue 36): the relief's shadows are kept where
they relight held-out lights better (cross-validated over folds of the lights, the paired
per-pixel difference over the pixels the relief shades above 0 standard errors,
rti.selection.choose_shadows); a capture without cast shadows keeps the ratio test. The
SYNTHETIC relief with real cast shadows that keeps them: test_rti_relief_render.py."""

from __future__ import annotations

import numpy as np
import pytest

from mitsuba_powder.rti import fit_maps
from mitsuba_powder.rti.options import DEFAULTS, SHADOWS, fit_options
from mitsuba_powder.rti.selection import MIN_SHADED, SHADOW_Z, paired_z
from mitsuba_powder.rti.synthetic import synthetic_capture


def test_auto_is_the_default_and_bad_values_are_named():
    assert DEFAULTS["shadows"] == "auto" and fit_options().shadows == "auto"
    assert SHADOWS == ("auto", "relief", "ratio")
    with pytest.raises(ValueError, match=r"shadows = 'yes'; valid values are \('auto', "
                                         r"'relief', 'ratio'\)"):
        fit_options(shadows="yes")
    with pytest.raises(ValueError, match=r"--shadows = 1; valid values"):
        fit_options(names={"shadows": "--shadows"}, shadows=1)


@pytest.mark.parametrize("relief", [0.0, 0.25, 0.5])
def test_a_capture_without_cast_shadows_keeps_the_ratio_test(relief):
    """SYNTHETIC captures rendered per pixel (no cast shadow; 24 lights at 10-80 degrees,
    noise 0.005), flat (0) or with bumps (0.25, 0.5: normals tilted up to about 15 and 30
    degrees, whose integrated relief does shade some of the lights): the relief's shadows
    do not relight better, the fit is the ratio test's (the same maps as shadows="ratio")
    and relight does not shade. Measured: flat, nothing shades (a tie, no second
    cross-validation); 0.25, the relief shades 8 of the 256 pixels, fewer than MIN_SHADED (a
    tie); 0.5, 83 pixels, cross-validated RMS 0.007231 without and 0.007822 with the relief,
    z = -3.3 (the held-out lights contradict the shadows this capture does not have)."""
    cap = synthetic_capture(16, 16, lights=24, noise=0.005, relief=relief, seed=2)
    result = fit_maps(cap["images"], cap["directions"], rounds=1)
    choice = result.fit_settings["shadows_choice"]
    assert result.fit_settings["shadows"] == "ratio" and choice["chosen"] == "ratio"
    assert choice["z"] <= SHADOW_Z, choice
    assert choice["folds"] == 5 and choice["pixels"] == 256
    if relief < 0.5:  # nothing or too little shades: a tie, no second cross-validation
        assert choice["shaded_pixels"] < MIN_SHADED and choice["z"] == 0
        assert choice["cv_rms"]["relief"] == choice["cv_rms"]["ratio"]
    else:
        assert MIN_SHADED <= choice["shaded_pixels"] < 256 and choice["z"] < -2
        assert choice["cv_rms"]["relief"] > choice["cv_rms"]["ratio"]
    assert (choice["shaded_pixels"] > 0) == (relief > 0)
    assert result.relief is not None  # kept, unused
    shades = float(np.min(result.relief.visibility(cap["directions"]))) < 0.5
    assert shades == (relief > 0)
    plain = fit_maps(cap["images"], cap["directions"], rounds=1, shadows="ratio")
    np.testing.assert_array_equal(result.normals, plain.normals)
    d = cap["directions"][:3]
    np.testing.assert_array_equal(result.predict(d), result.predict(d, shadows=False))


def test_paired_z():
    assert paired_z(np.zeros(10)) == 0.0 and paired_z(np.array([])) == 0.0
    assert paired_z(np.full(4, 0.5)) == np.inf and paired_z(np.full(4, -0.5)) == -np.inf
    rng = np.random.default_rng(0)
    d = rng.normal(1.0, 2.0, 400)
    assert paired_z(d) == pytest.approx(d.mean() / (d.std(ddof=1) / 20.0))
