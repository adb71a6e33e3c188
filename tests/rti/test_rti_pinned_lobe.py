"""A surface lobe that ends at the largest amplitude the fit allows is not determined by the
lights (a needle between them, or on observations left out as saturated): those pixels are
fitted again without the lobe (rti.pixelfit._drop_pinned_lobes). Found on RealRTI item 5 (a
varnished painting), where such pixels relit held-out lights at up to 145x the full scale."""

from __future__ import annotations

import numpy as np
import pytest
from test_rti_exposure import uncalibrated

from mitsuba_powder import rti as rf
from mitsuba_powder.fitting.optimise import ParamSpec
from mitsuba_powder.rti.properties import NO_LOBE, SPECS


@pytest.fixture(scope="module")
def capture():
    """SYNTHETIC, 12 x 12 px, 50 lights, A_s' = 2e-4 everywhere (issue 35's capture)."""
    return uncalibrated(size=12)


def _fit(capture, **options):
    lines: list[str] = []
    res = rf.fit_maps(capture["images"], capture["directions"], exposure=1.52, rounds=1,
                      free=["albedo", "amplitude_surface", "correlation_length"],
                      shadows="ratio", progress=lines.append, **options)
    return res, lines


def test_a_lobe_within_its_bounds_is_kept(capture):
    res, lines = _fit(capture)
    assert res.fit_settings["lobe_dropped_pixels"] == 0
    assert not any("surface lobe:" in line for line in lines)
    assert np.median(res.maps["amplitude_surface"]) == pytest.approx(2e-4, rel=0.25)


def test_pixels_pinned_at_the_largest_amplitude_are_fitted_without_the_lobe(capture,
                                                                             monkeypatch):
    """With the amplitude's upper bound below the truth (1e-4 < 2e-4) every pixel's lobe
    ends at it: each is fitted again without the lobe, and its maps are those of a fit of
    the albedo alone (the same start, the same data)."""
    monkeypatch.setitem(SPECS, "amplitude_surface", ParamSpec(1e-9, 1e-4, True, 1e-5))
    res, lines = _fit(capture)
    n = res.fit_settings["lobe_dropped_pixels"]
    assert n > 100, n
    said = [line for line in lines if line.startswith("surface lobe: ")]
    assert said == [f"surface lobe: {n} of 144 pixels end at the largest amplitude (0.0001 "
                    "um^2), which the lights do not determine: fitted again without the lobe"]
    dropped = res.maps["amplitude_surface"] == NO_LOBE["amplitude_surface"]
    assert int(dropped.sum()) == n
    assert np.all(res.maps["correlation_length"][dropped] == NO_LOBE["correlation_length"])
    plain = rf.fit_maps(capture["images"], capture["directions"], exposure=1.52, rounds=1,
                        free=["albedo"], shadows="ratio")
    np.testing.assert_allclose(res.normals[dropped], plain.normals[dropped], atol=1e-5)
    np.testing.assert_allclose(res.albedo[dropped], plain.albedo[dropped], rtol=1e-5)
    assert res.fit_settings["underdetermined_pixels"] == int(
        np.count_nonzero(~np.isfinite(res.residual_rms[res.mask])))
