"""Numerical stability: no NaN or Inf from eval, pdf or sample over ~10^6 inputs that
include the extremes of every parameter and of the geometry."""

from __future__ import annotations

import itertools

import mitsuba as mi
import numpy as np
import pytest

from helpers import evaluate, extreme_directions, extreme_samples, sample, use_variant

RHOS = [0.0, 1e-6, 1.0 - 1e-6, 1.0]
GS = [-0.99, 0.99]
KAPPAS = [1e-4, 1.0, 1e4]
TAUS = [0.0, 2.0 / 3.0, 1e3]
N_PER_SET = 14_000  # x 72 parameter sets ~ 1.0e6 inputs


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_spectral"])
def test_no_nan_or_inf_at_extremes(variant):
    use_variant(variant)
    rng = np.random.default_rng(99)
    total = 0
    for k, (rho, g, kappa, tau) in enumerate(itertools.product(RHOS, GS, KAPPAS, TAUS)):
        props = {"type": "powder", "albedo": rho, "g": g, "extinction": kappa, "tau_o": tau}
        if k % 2:
            props.update(specular="gaussian", amplitude_surface=1.0,
                         sigma=[1e-3, 0.5 * np.pi][k % 4 == 1])
        else:
            props.update(amplitude_surface=[1e-2, 1e-6][k % 4 == 0],
                         correlation_length=[10.0, 1e-2][k % 4 == 0])
        if k % 3 == 0:
            props["thickness"] = [1e-3, 1e3][k % 2]
        bsdf = mi.load_dict(props)
        n = N_PER_SET if variant == "llvm_ad_rgb" else N_PER_SET // 4
        wi, wo = extreme_directions(n, rng)
        lam = None
        if "spectral" in variant:
            lam = np.sort(rng.uniform(360.0, 830.0, (n, 4)), axis=1)
        value, pdf = evaluate(bsdf, wi, wo, lam, what="eval_pdf")
        label = f"set {k}: {props}"
        assert np.all(np.isfinite(value)) and np.all(value >= 0), label
        assert np.all(np.isfinite(pdf)) and np.all(pdf >= 0), label
        s1, s2 = extreme_samples(n, rng)
        swo, spdf, weight = sample(bsdf, wi, s1, s2, lam)
        assert np.all(np.isfinite(swo)) and np.all(np.isfinite(spdf)), label
        assert np.all(np.isfinite(weight)) and np.all(weight >= 0), label
        assert np.all(spdf >= 0), label
        total += n
    if variant == "llvm_ad_rgb":
        assert total >= 1_000_000
