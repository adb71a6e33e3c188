"""Differentiable parameters: gradients against central finite differences, opaque
parameters (an optimisation step does not recompile kernels), and the BSDF's state traversed
by Dr.Jit (a frozen function sees parameter edits)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import (
    assert_updates_reuse_kernels,
    geometry,
    gradients_and_differences,
    loss,
    use_variant,
)

VARIANT = "llvm_ad_rgb"

BASE = {
    "type": "powder",
    "albedo": {"type": "rgb", "value": [0.9, 0.7, 0.5]},
    "amplitude_volume": 1.2,
    "g": 0.3,
    "extinction": 2.0,
    "tau_o": 1.5,
    "thickness": 0.3,
    "amplitude_surface": 1e-3,
}
CASES = {
    "harvey_shack": {**BASE, "correlation_length": 1.5},
    "gaussian": {**BASE, "specular": "gaussian", "amplitude_surface": 0.5, "sigma": 0.15},
}


@pytest.mark.parametrize("case", sorted(CASES))
def test_gradients_match_finite_differences(case):
    use_variant(VARIANT)
    bsdf = mi.load_dict(CASES[case])
    params = mi.traverse(bsdf)
    expected = {"amplitude_volume", "g", "extinction", "albedo.value", "tau_o", "thickness",
                "amplitude_surface", "correlation_length" if case == "harvey_shack" else "sigma"}
    assert set(params.keys()) == expected
    for key, comp, grad, fd, _ in gradients_and_differences(bsdf, params):
        assert abs(fd) > 0, (key, comp)
        assert abs(grad - fd) <= 0.02 * abs(fd), f"{case} {key}[{comp}]: AD {grad}, FD {fd}"


def invalid_lanes():
    """Direction pairs that eval masks out (value 0): a cosine exactly 0, directions below
    the horizon, wo = -wi, and the zero vectors of an interaction that was never set."""
    wi = np.array([[0.6, 0.0, 0.8], [1.0, 0.0, 0.0], [0.6, 0.0, 0.8], [0.6, 0.0, -0.8],
                   [0.0, 0.0, 0.0], [0.28, 0.96, 0.0], [0.0, 0.6, 0.8]])
    wo = np.array([[1.0, 0.0, 0.0], [0.6, 0.0, 0.8], [-0.6, 0.0, -0.8], [0.6, 0.0, 0.8],
                   [0.0, 0.0, 0.0], [-0.28, -0.96, 0.0], [0.0, 0.8, -0.6]])
    return wi, wo


@pytest.mark.parametrize("g", [0.3, 0.99, -0.99])
@pytest.mark.parametrize("case", sorted(CASES))
def test_masked_lanes_add_no_gradient(case, g):
    """Lanes that eval masks out (value 0) add nothing to any gradient, not even a NaN
    from their discarded values: the gradients over valid and masked lanes together equal
    those over the valid lanes alone, for strongly forward and backward scattering too.
    (It fails if eval lets a masked lane's value through; the gradient half also holds
    without eval's replacement of the masked cosines, because Dr.Jit's derivative of a
    select drops the discarded lanes: it guards that behaviour, not the replacement.)"""
    use_variant(VARIANT)
    bsdf = mi.load_dict({**CASES[case], "g": g})
    params = mi.traverse(bsdf)
    si, wo, weights = geometry(300)
    bad_wi, bad_wo = invalid_lanes()
    n_bad = len(bad_wi)
    wi_all = np.concatenate([np.array(si.wi).T, bad_wi]).astype(np.float32)
    wo_all = np.concatenate([np.array(wo).T, bad_wo]).astype(np.float32)
    si_all = dr.zeros(mi.SurfaceInteraction3f, len(wi_all))
    si_all.wi = mi.Vector3f(*[wi_all[:, k] for k in range(3)])
    wo_all_v = mi.Vector3f(*[wo_all[:, k] for k in range(3)])
    w_all = mi.Float(np.concatenate([np.array(weights), np.ones(n_bad)]).astype(np.float32))
    value = np.array(bsdf.eval(mi.BSDFContext(), si_all, wo_all_v))
    assert np.all(value[:, -n_bad:] == 0.0)
    for key in params.keys():
        grads = []
        for args in ((si, wo, weights), (si_all, wo_all_v, w_all)):
            dr.enable_grad(params[key])
            params.update()
            dr.backward(loss(bsdf, *args))
            grads.append(np.array(dr.grad(params[key]), dtype=np.float64).ravel())
            dr.disable_grad(params[key])
            params.update()
        assert np.all(np.isfinite(grads[1])), (case, g, key, grads[1])
        assert np.allclose(grads[1], grads[0], rtol=1e-5, atol=0.0), (case, g, key, grads)


def test_radius_update_with_gradients_reuses_kernels():
    """An optimiser step on the grain radius (gradients tracked, Mie tangents attached) must
    not compile new kernels either."""
    use_variant(VARIANT)
    bsdf = mi.load_dict({"type": "powder", "radius": 0.05})
    params = mi.traverse(bsdf)
    si, wo, weights = geometry(500)

    def step(r):
        params["radius"] = mi.Float(r)
        dr.enable_grad(params["radius"])
        params.update()
        lo = loss(bsdf, si, wo, weights)
        dr.backward(lo)
        dr.eval(dr.grad(params["radius"]))

    step(0.05)
    step(0.06)
    dr.kernel_history_clear()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for r in (0.07, 0.08, 0.09):
            step(r)
        history = [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert history and all(h.get("cache_hit", False) for h in history)


def test_parameter_update_reuses_kernels():
    """Parameters are opaque: changing their values does not compile a new kernel."""
    use_variant(VARIANT)
    bsdf = mi.load_dict(CASES["harvey_shack"])
    assert_updates_reuse_kernels(bsdf, [("g", 0.1), ("extinction", 5.0), ("tau_o", 3.0),
                                        ("amplitude_surface", 2e-3),
                                        ("correlation_length", 0.7), ("thickness", 0.5),
                                        ("amplitude_volume", 0.8)])


FROZEN_CASES = {
    "albedo": lambda: {"albedo": 0.8, "amplitude_surface": 1e-3},
    "grains": lambda: {"radius": 0.1},
    "conserving": lambda: {"albedo": 0.7, "energy": "conserving"},
    "g texture": lambda: {"albedo": 0.7, "g": {
        "type": "bitmap", "raw": True, "data": mi.TensorXf(np.full((2, 2, 1), 0.2, np.float32))}},
}


@pytest.mark.parametrize("case", sorted(FROZEN_CASES))
def test_frozen_function_sees_parameter_edits(case):
    """dr.freeze finds the BSDF's JIT variables through its traversal (the members of its
    parts: parameters, grain tables, sampling means): a function frozen once evaluates the
    edited parameters exactly as a direct call does, without recording again."""
    use_variant(VARIANT)
    bsdf = mi.load_dict({"type": "powder", **FROZEN_CASES[case]()})
    si, wo, _ = geometry(64)

    @dr.freeze
    def frozen_eval(b, si_, wo_):
        return b.eval(mi.BSDFContext(), si_, wo_)

    params = mi.traverse(bsdf)
    for extinction in (1.0, 2.5, 0.5):
        params["extinction"] = extinction
        if "radius" in params:
            params["radius"] = 0.1 * extinction
        params.update()
        direct = np.array(bsdf.eval(mi.BSDFContext(), si, wo))
        np.testing.assert_array_equal(np.array(frozen_eval(bsdf, si, wo)), direct)
    assert frozen_eval.n_recordings == 1


#: spectral paths of the volume constants (tests/plugin/test_fast_paths.py): computed once per
#: parameter change (one-number albedo, tau_o given; or optically thick, with g = 0.3:
#: 2 c0 tau_o >= 14.1), or tabulated on the 1 nm grid (4 or 8 values per record; albedo 0.8:
#: 2 c0 tau_o >= 11.3; 100 nm grains: >= 10.9; or, optically thick, rho alone: 50 nm grains,
#: >= 19.5)
SPECTRAL_CASES = {
    "uniform": {"albedo": 0.8, "tau_o": 1.5},
    "thick": {"albedo": 0.7},
    "table_albedo": {"albedo": 0.8},
    "table_mie": {"radius": 0.1},
    "thick_table_mie": {"radius": 0.05},
}


@pytest.mark.parametrize("lobes", ["all", "multiple"])
@pytest.mark.parametrize("case", sorted(SPECTRAL_CASES))
def test_spectral_gradients_match_finite_differences(case, lobes):
    """Gradients through the spectral volume constants (one value, or the 1 nm table and its
    packet gathers) against central differences, every fittable parameter the case has; with
    L2 alone ("multiple") the gradients of g, tau_o and the albedo go through s(c0) (the
    table's interpolated entry) and c0 only."""
    use_variant("llvm_ad_spectral")
    bsdf = mi.load_dict({"type": "powder", "amplitude_volume": 1.2, "g": 0.3,
                         "extinction": 1.5, "amplitude_surface": 1e-3, "energy": "paper",
                         "lobes": lobes, **SPECTRAL_CASES[case]})
    assert ("optically thick" in str(bsdf)) == case.startswith("thick")
    params = mi.traverse(bsdf)
    keys = [k for k in ("albedo.value", "g", "tau_o", "radius", "amplitude_volume",
                        "extinction") if k in params.keys()]
    assert {"g", "amplitude_volume", "extinction"} <= set(keys)
    if lobes == "multiple":
        keys.remove("extinction")  # L2 does not depend on it
    tolerance = 0.02 if lobes == "all" else 0.01
    # the Mie albedo curves within 1 % of the radius (2 % FD error there; 0.07 % at 0.1 %)
    for key, _, grad, fd, _ in gradients_and_differences(bsdf, params, keys, spectral=True,
                                                          steps={"radius": 1e-3}):
        assert abs(fd) > 0, (case, key)
        assert abs(grad - fd) <= tolerance * abs(fd), f"{case} {key}: AD {grad}, FD {fd}"
