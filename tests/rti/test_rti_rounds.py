"""Rounds of the per-pixel fit under held gains: a round after the first fits again only the
pixels whose observation flags changed (every pixel's fit is its own), and its maps are those
of a round that fits every pixel again, bit for bit."""

import numpy as np
import pytest
from test_rti_exposure import uncalibrated

import mitsuba_powder.rti.pixelfit as pixelfit
from mitsuba_powder import rti as rf


@pytest.fixture(scope="module")
def capture():
    return uncalibrated(size=32)


def _fit(capture, **options):
    lines = []
    res = rf.fit_maps(capture["images"], capture["directions"], exposure=1.5,
                      progress=lines.append, **options)
    return res, lines


def test_a_later_round_fits_again_only_the_pixels_whose_flags_changed(capture, monkeypatch):
    res, lines = _fit(capture)
    again = [line for line in lines if "pixels whose observation flags changed" in line]
    assert again and again[0].startswith("round 2/3: Levenberg-Marquardt of the ")
    monkeypatch.setattr(pixelfit, "_changed_pixels", lambda previous, state: None)
    full, full_lines = _fit(capture)
    assert not any("flags changed" in line for line in full_lines)
    np.testing.assert_array_equal(res.normals, full.normals)
    np.testing.assert_array_equal(res.albedo, full.albedo)
    for name in full.maps:
        np.testing.assert_array_equal(res.maps[name], full.maps[name])
    np.testing.assert_array_equal(res.residual_rms, full.residual_rms)


def test_fitted_gains_refit_every_pixel(capture):
    """With the gains fitted, they move between rounds: every pixel is fitted again."""
    res, lines = _fit(capture, gains="fit", free=["albedo"])
    assert res.fit_settings["gains"] == "fit"
    assert not any("flags changed" in line for line in lines)
