"""The plugin is compiled and registered for every variant of the mitsuba wheel."""

from __future__ import annotations

import mitsuba as mi
import numpy as np
import pytest

from helpers import ALL_VARIANTS, Albedo, channel_wavelengths, evaluate, make_bsdf, use_variant
from oracles.model import Params, brdf


def test_every_wheel_variant_is_covered():
    assert sorted(mi.variants()) == sorted(ALL_VARIANTS)


@pytest.mark.parametrize("variant", ALL_VARIANTS)
def test_loads_and_evaluates(variant):
    """Load in each variant and compare a few values with the reference (cuda: skipped
    when this machine has no GPU)."""
    use_variant(variant)
    rng = np.random.default_rng(3)
    p = Params(g=0.3, extinction=0.5, amplitude_surface=1e-3, correlation_length=0.8)
    albedo = Albedo([0.9, 0.5, 0.2])
    bsdf = make_bsdf(p, albedo)
    assert bsdf.class_name() == "Powder"
    ti = np.radians([0.0, 20.0, 40.0, 60.0, 75.0])
    wi = np.stack([np.sin(ti), 0 * ti, np.cos(ti)], 1)
    wo = np.stack([np.sin(ti + 0.01), 0 * ti, np.cos(ti + 0.01)], 1)
    lam = channel_wavelengths(len(ti), rng)
    got = evaluate(bsdf, wi, wo, lam)
    want = brdf(wi, wo, albedo.at(lam), lam, p.as_float32()) * wo[:, 2:3]
    np.testing.assert_allclose(got, want, rtol=1e-4)
