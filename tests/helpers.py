"""Shared test utilities: variants, plugin construction and vectorised evaluation."""

from __future__ import annotations

import os
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mitsuba_powder._variants import VARIANTS as BUILT_VARIANTS
from reference import Params

#: The variants the installed plugin was built for (generated from CMakeLists.txt's list)
ALL_VARIANTS = list(BUILT_VARIANTS)

#: The project's shared folder (specification and data), beside the checkout
SHARED = Path(__file__).resolve().parents[2] / "shared"


def needs_shared(path: Path):
    """A skip marker for tests that read ``path`` from the shared folder beside the checkout.

    Outside CI a missing folder skips the test (a clone without ``../shared``); in CI
    (``CI=true``, where ``../shared`` is always laid beside the clone) the test runs and fails
    on the missing file instead of being skipped silently."""
    in_ci = os.environ.get("CI", "").lower() in ("1", "true", "yes")
    return pytest.mark.skipif(not Path(path).exists() and not in_ci,
                              reason=f"{path} is missing: the shared folder is not beside the "
                                     "checkout (in CI this test runs and fails instead)")


#: Regular spectrum grid used for spectral albedos (nm)
SPECTRUM_RANGE = (360.0, 830.0)


def use_variant(variant: str) -> None:
    """Select a Mitsuba variant for the rest of the test (skipping the test when it cannot run
    here) through the library's :func:`mitsuba_powder.variants.set_variant`, which also makes
    the plugin findable."""
    if variant not in mi.variants():
        pytest.skip(f"variant {variant} is not in this mitsuba build")
    if variant not in BUILT_VARIANTS:
        # a build with -DPOWDER_VARIANTS=...; test_variants.py requires all of them
        pytest.skip(f"the plugin was built without variant {variant}")
    if variant.startswith("cuda") and not dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("no CUDA device on this machine")
    if variant.startswith("llvm") and not dr.has_backend(dr.JitBackend.LLVM):
        pytest.skip("no usable LLVM backend")
    from mitsuba_powder.variants import set_variant

    set_variant(variant)


def is_scalar() -> bool:
    return mi.variant().startswith("scalar")


def channel_kind() -> str:
    v = mi.variant()
    if "spectral" in v:
        return "spectral"
    if "mono" in v:
        return "mono"
    return "rgb"


class Albedo:
    """An albedo the plugin gets as a Mitsuba dict and the reference gets per channel."""

    def __init__(self, values):
        self.values = np.asarray(values, dtype=np.float64)  # 3 values in [0, 1]

    def as_dict(self) -> dict:
        kind = channel_kind()
        if kind == "rgb":
            return {"type": "rgb", "value": [float(v) for v in self.values]}
        if kind == "mono":
            return {"type": "uniform", "value": float(self.values[0])}
        return {
            "type": "regular",
            "wavelength_min": SPECTRUM_RANGE[0],
            "wavelength_max": SPECTRUM_RANGE[1],
            "values": ", ".join(repr(float(v)) for v in self.values),
        }

    def at(self, lam_nm: np.ndarray) -> np.ndarray:
        """Per-channel albedo the plugin should see at wavelengths ``lam_nm`` (N, C)."""
        kind = channel_kind()
        v32 = self.values.astype(np.float32).astype(np.float64)
        if kind == "rgb":
            return np.broadcast_to(v32[None, :], lam_nm.shape)
        if kind == "mono":
            return np.full(lam_nm.shape, v32[0])
        grid = np.linspace(*SPECTRUM_RANGE, len(v32))
        return np.interp(lam_nm, grid, v32)


def make_bsdf(params: Params, albedo: Albedo, **extra):
    props = {"type": "powder", "albedo": albedo.as_dict(), **params.properties(), **extra}
    return mi.load_dict(props)


def channel_wavelengths(n: int, rng: np.random.Generator, rgb=(611.3, 549.1, 464.3),
                        mono: float = 700.0) -> np.ndarray:
    """Wavelengths (nm) per lane and channel for the current variant, shape (n, C)."""
    kind = channel_kind()
    if kind == "rgb":
        return np.tile(np.asarray(rgb, np.float32).astype(np.float64), (n, 1))
    if kind == "mono":
        return np.full((n, 1), float(np.float32(mono)))
    return np.sort(rng.uniform(*SPECTRUM_RANGE, size=(n, 4)).astype(np.float32), axis=1).astype(
        np.float64)


def _si(wi: np.ndarray, lam: np.ndarray | None):
    n = wi.shape[0]
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
    if channel_kind() == "spectral" and lam is not None:
        si.wavelengths = mi.UnpolarizedSpectrum(*[lam[:, k] for k in range(lam.shape[1])])
    return si


def _unpolarized(value) -> np.ndarray:
    """(C, N) array of the unpolarised part of a BSDF value (Mueller [0, 0] if polarised)."""
    if mi.is_polarized:
        value = mi.unpolarized_spectrum(value)
    arr = np.array(value, dtype=np.float64)
    if arr.ndim == 1:
        arr = arr[:, None]
    return arr


def evaluate(bsdf, wi: np.ndarray, wo: np.ndarray, lam: np.ndarray | None = None,
             what: str = "eval", ctx=None):
    """Evaluate ``bsdf.eval`` (f * cos), ``pdf`` or ``eval_pdf`` at direction pairs.

    Returns (N, C) for eval, (N,) for pdf, a pair for eval_pdf.
    """
    ctx = ctx or mi.BSDFContext()
    wi = np.asarray(wi, np.float32)
    wo = np.asarray(wo, np.float32)
    if is_scalar():
        vals, pdfs = [], []
        for k in range(wi.shape[0]):
            si = mi.SurfaceInteraction3f()
            si.wi = mi.Vector3f(*wi[k])
            if channel_kind() == "spectral" and lam is not None:
                si.wavelengths = mi.UnpolarizedSpectrum(*lam[k])
            w = mi.Vector3f(*wo[k])
            if what == "eval":
                vals.append(_unpolarized(bsdf.eval(ctx, si, w))[:, 0])
            elif what == "pdf":
                pdfs.append(float(bsdf.pdf(ctx, si, w)))
            else:
                v, p = bsdf.eval_pdf(ctx, si, w)
                vals.append(_unpolarized(v)[:, 0])
                pdfs.append(float(p))
        if what == "eval":
            return np.array(vals)
        if what == "pdf":
            return np.array(pdfs)
        return np.array(vals), np.array(pdfs)
    si = _si(wi, lam)
    w = mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2])
    if what == "eval":
        return _unpolarized(bsdf.eval(ctx, si, w)).T
    if what == "pdf":
        return np.array(bsdf.pdf(ctx, si, w), dtype=np.float64)
    v, p = bsdf.eval_pdf(ctx, si, w)
    return _unpolarized(v).T, np.array(p, dtype=np.float64)


def sample(bsdf, wi: np.ndarray, s1: np.ndarray, s2: np.ndarray, lam: np.ndarray | None = None):
    """Vectorised ``bsdf.sample`` (JIT variants). Returns wo (N,3), pdf (N,), weight (N,C)."""
    si = _si(np.asarray(wi, np.float32), lam)
    bs, weight = bsdf.sample(mi.BSDFContext(), si, mi.Float(s1), mi.Point2f(s2[:, 0], s2[:, 1]))
    wo = np.array(bs.wo, dtype=np.float64).T
    return wo, np.array(bs.pdf, dtype=np.float64), _unpolarized(weight).T


def random_hemisphere(n: int, rng: np.random.Generator, min_mu: float = 0.0) -> np.ndarray:
    """Uniformly distributed directions of the upper hemisphere with cos(theta) >= min_mu."""
    mu = rng.uniform(min_mu, 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    s = np.sqrt(np.maximum(0.0, 1.0 - mu * mu))
    return np.stack([s * np.cos(phi), s * np.sin(phi), mu], axis=1)


def perturb(w: np.ndarray, scale: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Directions near ``w``: projected coordinates moved by ~``scale``, kept above the horizon."""
    xy = w[:, :2] + rng.normal(size=(w.shape[0], 2)) * np.asarray(scale).reshape(-1, 1)
    r = np.linalg.norm(xy, axis=1, keepdims=True)
    xy = np.where(r > 0.999, xy / r * 0.999, xy)
    z = np.sqrt(1.0 - np.sum(xy * xy, axis=1, keepdims=True))
    return np.concatenate([xy, z], axis=1)
