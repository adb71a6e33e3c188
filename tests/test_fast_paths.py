"""The per-parameter fast paths of eval give the same values as the general path: RGB and mono
variants precompute the volume constants for a spatially uniform albedo and skip the
exponential of the coherent term when 2 c0 tau_o >= 18 in every channel; a spatially varying
texture (here a constant bitmap) takes the general path."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import evaluate, random_hemisphere, use_variant


def constant_bitmap(value: float, channels: int):
    """A spatially varying texture type whose every texel is ``value`` (nearest filter)."""
    data = np.full((2, 2, channels), value, dtype=np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(data), "raw": True, "filter_type": "nearest"}


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_mono"])
@pytest.mark.parametrize("extra", [{}, {"tau_o": 1.5}, {"thickness": 3.0, "g": 0.4}],
                         ids=["fresnel_tau", "tau_given", "thin"])
def test_uniform_albedo_matches_general_path(variant, extra):
    use_variant(variant)
    channels = 3 if "rgb" in variant else 1
    props = {"type": "powder", "extinction": 0.7, "amplitude_surface": 1e-3, **extra}
    fast = mi.load_dict({**props, "albedo": 0.8})
    general = mi.load_dict({**props, "albedo": constant_bitmap(0.8, channels)})
    rng = np.random.default_rng(21)
    n = 20_000
    wi, wo = random_hemisphere(n, rng, 1e-3), random_hemisphere(n, rng, 1e-3)
    wo[: n // 4] = wi[: n // 4] * rng.uniform(0.999, 1.0, (n // 4, 1))  # near the cone
    a, b = evaluate(fast, wi, wo), evaluate(general, wi, wo)
    assert np.all(np.isfinite(a)) and np.all(a > 0)
    np.testing.assert_allclose(a, b, rtol=2e-6, atol=0)


def test_the_saturated_coherent_path_is_exercised():
    """With hematite's Fresnel tau_o (~14) and albedo 0.8, 2 c0 tau_o >= 18 in every channel."""
    use_variant("llvm_ad_rgb")
    bsdf = mi.load_dict({"type": "powder", "albedo": 0.8})
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    tau = np.array(bsdf.eval_attribute("tau_o", si)).ravel()
    c0 = np.sqrt(3.0 * (1 - 0.8) * (1 - 0.0))
    assert np.all(2 * c0 * tau >= 18.0), tau
