"""The default cast shadows, shadows="auto" (issue 36): the relief's shadows are kept where
they relight held-out lights better by a clear margin (cross-validated over folds of the
lights, rti.selection.choose_shadows); a capture without relief keeps the ratio test. The
SYNTHETIC relief with real cast shadows that keeps them: test_rti_relief_render.py."""

from __future__ import annotations

import numpy as np
import pytest

from mitsuba_powder.rti import fit_maps
from mitsuba_powder.rti.options import DEFAULTS, SHADOWS, fit_options
from mitsuba_powder.rti.selection import SHADOW_MARGIN
from mitsuba_powder.rti.synthetic import synthetic_capture


def test_auto_is_the_default_and_bad_values_are_named():
    assert DEFAULTS["shadows"] == "auto" and fit_options().shadows == "auto"
    assert SHADOWS == ("auto", "relief", "ratio")
    with pytest.raises(ValueError, match=r"shadows = 'yes'; valid values are \('auto', "
                                         r"'relief', 'ratio'\)"):
        fit_options(shadows="yes")
    with pytest.raises(ValueError, match=r"--shadows = 1; valid values"):
        fit_options(names={"shadows": "--shadows"}, shadows=1)


def test_a_flat_capture_keeps_the_ratio_test():
    """A flat SYNTHETIC capture (no relief, no cast shadow; 24 lights at 10-80 degrees,
    noise 0.005): the relief of its noisy normals does not relight better, the fit is the
    ratio test's (the same maps as shadows="ratio") and relight does not shade."""
    cap = synthetic_capture(16, 16, lights=24, noise=0.005, relief=0.0, seed=2)
    result = fit_maps(cap["images"], cap["directions"], rounds=1)
    choice = result.fit_settings["shadows_choice"]
    assert result.fit_settings["shadows"] == "ratio" and choice["chosen"] == "ratio"
    cv = choice["cv_rms"]
    assert not cv["relief"] < (1 - SHADOW_MARGIN) * cv["ratio"], cv
    assert choice["folds"] == 5 and choice["pixels"] == 256
    assert result.relief is not None  # kept, unused
    plain = fit_maps(cap["images"], cap["directions"], rounds=1, shadows="ratio")
    np.testing.assert_array_equal(result.normals, plain.normals)
    d = cap["directions"][:3]
    np.testing.assert_array_equal(result.predict(d), result.predict(d, shadows=False))
