"""Flags and components per `lobes` choice (as Mitsuba's test_diffuse.py checks them), and
what `sample` reports: sampled_type and sampled_component, with and without a component
selected in the BSDFContext."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import evaluate, random_hemisphere, use_variant

VARIANT = "llvm_ad_rgb"
PROPS = {"albedo": 0.9, "extinction": 0.5, "amplitude_surface": 1e-2, "correlation_length": 3.0}

# lobes -> the `lobes` of each component, in component order
COMPONENTS = {
    "all": ["single,multiple", "coherent", "surface"],
    "single": ["single"],
    "multiple": ["multiple"],
    "coherent": ["coherent"],
    "surface": ["surface"],
    "coherent,surface": ["coherent", "surface"],
    "single,multiple,surface": ["single,multiple", "surface"],
    "multiple,coherent": ["multiple", "coherent"],
}


def expected_flags(lobes: str):
    f = mi.BSDFFlags
    out = []
    for comp in COMPONENTS[lobes]:
        kind = f.DiffuseReflection if ("single" in comp or "multiple" in comp) else \
            f.GlossyReflection
        out.append(kind | f.FrontSide)
    return out


@pytest.mark.parametrize("lobes", list(COMPONENTS))
def test_flags_per_component(lobes):
    use_variant(VARIANT)
    bsdf = mi.load_dict({"type": "powder", **PROPS, "lobes": lobes})
    want = expected_flags(lobes)
    assert bsdf.component_count() == len(want)
    union = 0
    for i, flags in enumerate(want):
        assert bsdf.flags(i) == int(flags), (i, bsdf.flags(i), flags)
        union |= int(flags)
    assert bsdf.flags() == union


def _sample(bsdf, ctx, n=20_000, seed=3):
    rng = np.random.default_rng(seed)
    wi = random_hemisphere(n, rng, 0.05)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
    bs, weight = bsdf.sample(ctx, si, mi.Float(rng.random(n)),
                             mi.Point2f(rng.random(n), rng.random(n)))
    return (wi, np.array(bs.wo).T, np.array(bs.pdf), np.array(bs.sampled_type),
            np.array(bs.sampled_component))


@pytest.mark.parametrize("lobes", list(COMPONENTS))
def test_sampled_type_is_the_sampled_components(lobes):
    """Each sample names an existing component and a type among that component's flags.
    Without single and multiple, the cosine fallback is reported as a glossy component (it
    used to report DiffuseReflection with the index of the coherent component)."""
    use_variant(VARIANT)
    bsdf = mi.load_dict({"type": "powder", **PROPS, "lobes": lobes})
    _, _, pdf, types, comps = _sample(bsdf, mi.BSDFContext())
    ok = pdf > 0
    assert np.all(comps[ok] < bsdf.component_count())
    flags = np.array([bsdf.flags(int(c)) for c in range(bsdf.component_count())])
    assert np.all((types[ok] & ~flags[comps[ok]]) == 0)
    assert np.all(types[ok] != 0)
    if "single" not in lobes and "multiple" not in lobes and lobes != "all":
        assert not np.any(types[ok] & int(mi.BSDFFlags.DiffuseReflection))


@pytest.mark.parametrize("lobes", ["all", "coherent,surface", "single,multiple,surface"])
def test_component_selection(lobes):
    """ctx.component = i: every sample is of component i, and eval/pdf equal those of a
    powder whose `lobes` is that component alone."""
    use_variant(VARIANT)
    bsdf = mi.load_dict({"type": "powder", **PROPS, "lobes": lobes})
    for i, comp in enumerate(COMPONENTS[lobes]):
        ctx = mi.BSDFContext()
        ctx.component = i
        wi, wo, pdf, types, comps = _sample(bsdf, ctx)
        ok = pdf > 0
        assert ok.mean() > 0.999
        assert np.all(comps[ok] == i)
        assert np.all((types[ok] & ~np.uint32(bsdf.flags(i))) == 0)
        alone = mi.load_dict({"type": "powder", **PROPS, "lobes": comp})
        rng = np.random.default_rng(4)
        wo2 = random_hemisphere(len(wi), rng)
        np.testing.assert_allclose(evaluate(bsdf, wi, wo2, ctx=ctx), evaluate(alone, wi, wo2),
                                   rtol=1e-6, atol=0)
        np.testing.assert_allclose(evaluate(bsdf, wi, wo2, what="pdf", ctx=ctx),
                                   evaluate(alone, wi, wo2, what="pdf"), rtol=1e-6, atol=0)


def test_type_mask_selects_the_volume_terms():
    use_variant(VARIANT)
    bsdf = mi.load_dict({"type": "powder", **PROPS})
    volume = mi.load_dict({"type": "powder", **PROPS, "lobes": "single,multiple"})
    glossy = mi.load_dict({"type": "powder", **PROPS, "lobes": "coherent,surface"})
    rng = np.random.default_rng(5)
    wi, wo = random_hemisphere(5000, rng, 0.05), random_hemisphere(5000, rng)
    for mask, ref in ((mi.BSDFFlags.DiffuseReflection, volume),
                      (mi.BSDFFlags.GlossyReflection, glossy)):
        ctx = mi.BSDFContext()
        ctx.type_mask = int(mask)
        np.testing.assert_allclose(evaluate(bsdf, wi, wo, ctx=ctx), evaluate(ref, wi, wo),
                                   rtol=1e-6, atol=0)
        _, _, pdf, types, _ = _sample(bsdf, ctx)
        assert np.all(types[pdf > 0] == int(mask))
