"""Shared test utilities: variants, plugin construction and vectorised evaluation, random
parameter sets, the hemispherical reflectance and log messages of a plugin, chi-square adapters,
gradients against finite differences, and the packaging tests' commands, fresh virtual
environments and value comparisons. Test modules import these from here, never from
each other."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import json
import os
import subprocess
import sys
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from mitsuba_powder._variants import VARIANTS as BUILT_VARIANTS
from oracles.model import Params

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


def extreme_directions(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Random pairs mixed with grazing (mu down to 1e-7), normal, exact back-scattering and
    exact mirror configurations."""
    wi = random_hemisphere(n, rng)
    wo = random_hemisphere(n, rng)
    k = n // 8
    for block, mu in enumerate([1e-7, 1e-6, 1e-4]):
        sl = slice(block * k, (block + 1) * k)
        phi = rng.uniform(0, 2 * np.pi, k)
        s = np.sqrt(1 - mu * mu)
        wi[sl] = np.stack([s * np.cos(phi), s * np.sin(phi), np.full(k, mu)], 1)
    wo[3 * k:4 * k] = wi[3 * k:4 * k]                               # exact back-scattering
    wo[4 * k:5 * k] = wi[4 * k:5 * k] * np.array([-1.0, -1.0, 1.0])  # exact mirror
    wo[5 * k:6 * k] = wi[:k]                                         # grazing back-scattering
    wi[6 * k:7 * k] = wo[6 * k:7 * k] = [0.0, 0.0, 1.0]              # normal
    wo[7 * k:] = wi[:n - 7 * k] * np.array([-1.0, -1.0, 1.0])        # grazing mirror
    return wi, wo


def extreme_samples(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    s1 = rng.random(n)
    s2 = rng.random((n, 2))
    below_one = float(np.nextafter(np.float32(1.0), np.float32(0.0)))
    s2[::5] = 0.0
    s2[1::5] = below_one
    s1[2::7] = 0.0
    s1[3::7] = below_one
    return s1, s2


def perturb(w: np.ndarray, scale: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """Directions near ``w``: projected coordinates moved by ~``scale``, kept above the horizon."""
    xy = w[:, :2] + rng.normal(size=(w.shape[0], 2)) * np.asarray(scale).reshape(-1, 1)
    r = np.linalg.norm(xy, axis=1, keepdims=True)
    xy = np.where(r > 0.999, xy / r * 0.999, xy)
    z = np.sqrt(1.0 - np.sum(xy * xy, axis=1, keepdims=True))
    return np.concatenate([xy, z], axis=1)


# ---------- random parameter sets


def random_params(rng: np.random.Generator, k: int) -> tuple[Params, Albedo]:
    """Parameter set ``k`` drawn from ``rng``: every lobe on, infinite thickness for even ``k``,
    the Gaussian lobe every third ``k``, conservative grains (rho = 1 in the first channel)
    every fifth; extinction in 1/um, lengths in um."""
    p = Params(
        amplitude_volume=rng.uniform(0.2, 2.0),
        g=rng.uniform(-0.95, 0.95),
        extinction=10 ** rng.uniform(-2, 2),
        tau_o=rng.choice([0.0, rng.uniform(0.0, 20.0), 2.0 / 3.0]),
        thickness=np.inf if k % 2 == 0 else 10 ** rng.uniform(-1, 2),
        amplitude_surface=10 ** rng.uniform(-6, -2),
        correlation_length=10 ** rng.uniform(-1, 0.7),
        specular="harvey_shack" if k % 3 else "gaussian",
        sigma=rng.uniform(0.02, 0.5),
    )
    rho = rng.uniform(0.0, 1.0, 3)
    if k % 5 == 0:
        rho[0] = 1.0  # conservative grains: c0 = 0
    return p, Albedo(rho)


# ---------- reflectance and log messages of a loaded plugin


def hemispherical_reflectance(bsdf, theta_i_deg: float, n: int = 2048) -> np.ndarray:
    """Integral of f cos(theta_o) over the hemisphere, on an n x n midpoint grid of the
    projected disc in (r^2, phi) (dA = mu_o domega = d(r^2)/2 dphi)."""
    u = (np.arange(n) + 0.5) / n
    phi = (np.arange(n) + 0.5) / n * 2.0 * np.pi
    U, P = np.meshgrid(u, phi, indexing="ij")
    r = np.sqrt(U)
    wo = np.stack([(r * np.cos(P)).ravel(), (r * np.sin(P)).ravel(), np.sqrt(1.0 - U).ravel()], 1)
    ti = np.radians(theta_i_deg)
    wi = np.tile([np.sin(ti), 0.0, np.cos(ti)], (wo.shape[0], 1))
    f = evaluate(bsdf, wi, wo) / wo[:, 2:3].astype(np.float32)
    return f.sum(axis=0) * 0.5 / n * (2.0 * np.pi / n)


class LogCapture(mi.Appender):
    """A Mitsuba log appender that keeps (level, text) of every message."""

    def __init__(self):
        super().__init__()
        self.messages: list[tuple[mi.LogLevel, str]] = []

    def append(self, level, text):
        self.messages.append((level, text))

    def log_progress(self, *args, **kwargs):
        pass


def load_and_capture(props: dict) -> list[str]:
    """Warnings logged while loading ``props``."""
    logger = mi.logger()
    cap = LogCapture()
    logger.add_appender(cap)
    try:
        mi.load_dict(props)
    finally:
        logger.remove_appender(cap)
    return [t for lvl, t in cap.messages if lvl == mi.LogLevel.Warn]


# ---------- chi-square adapters (mitsuba.chi2)


def adapters(props: dict, wi, domain=None, wavelengths=None, zero_weight_fails=False):
    """(sample_func, pdf_func) for mitsuba.chi2; ``wavelengths`` (nm, 4 values) for
    spectral variants. With ``zero_weight_fails`` a sample of weight 0 (in every channel)
    counts as failed, i.e. is left out of the histogram like one of pdf 0."""
    bsdf = mi.load_dict({"type": "powder", **props})
    ctx = mi.BSDFContext()

    def si_for(n):
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = wi
        if wavelengths is not None:
            si.wavelengths = mi.UnpolarizedSpectrum(*wavelengths)
        return si

    def sample_func(s):
        n = dr.width(s)
        bs, weight = bsdf.sample(ctx, si_for(n), s[0], mi.Point2f(s[1], s[2]))
        # A sample fails when its pdf is 0 (off the disc); a valid sample may still have a
        # zero weight where f underflows. Failed samples are kept inside the domain.
        failed = bs.pdf <= 0.0
        if zero_weight_fails:
            failed |= dr.all(mi.unpolarized_spectrum(weight) == 0.0)
        wo = dr.select(failed, mi.Vector3f(wi), bs.wo)
        return wo, mi.Float(dr.select(failed, 0.0, 1.0))

    def pdf_func(p):
        if domain is None:
            return bsdf.pdf(ctx, si_for(dr.width(p)), p)
        wo, jac = domain.direction(p)
        return bsdf.pdf(ctx, si_for(dr.width(p.x)), wo) * jac

    return sample_func, pdf_func


def direction(theta_deg: float):
    """The unit direction in the xz plane at ``theta_deg`` (degrees) from the normal."""
    t = np.radians(theta_deg)
    return mi.ScalarVector3f(float(np.sin(t)), 0.0, float(np.cos(t)))


# ---------- gradients and kernel reuse


def geometry(n: int = 3000, spectral: bool = False):
    """Direction pairs (a third near back-scattering, a third near the mirror direction) and
    loss weights; spectral: four random wavelengths per lane (nm)."""
    rng = np.random.default_rng(21)
    wi = random_hemisphere(n, rng, 0.1)
    wo = random_hemisphere(n, rng, 0.1)
    wo[: n // 3] = perturb(wi[: n // 3], 0.05, rng)
    wo[n // 3: 2 * n // 3] = perturb(wi[n // 3: 2 * n // 3] * [-1, -1, 1], 0.1, rng)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(*[wi[:, k].astype(np.float32) for k in range(3)])
    wov = mi.Vector3f(*[wo[:, k].astype(np.float32) for k in range(3)])
    weights = mi.Float(np.linspace(0.5, 1.5, n).astype(np.float32))
    if spectral:
        lam = np.random.default_rng(3).uniform(360.0, 830.0, (4, n)).astype(np.float32)
        si.wavelengths = mi.UnpolarizedSpectrum(*[mi.Float(row) for row in lam])
    return si, wov, weights


def loss(bsdf, si, wo, weights):
    """sum of weights x (channel 1 + 2 channel 2 + 3 channel 3 [+ 4 channel 4])"""
    value = bsdf.eval(mi.BSDFContext(), si, wo)
    return dr.sum(weights * sum((c + 1.0) * value[c] for c in range(len(value))))


def loss_value(bsdf, si, wo, weights) -> float:
    """Loss accumulated in float64 (for finite differences)."""
    value = np.array(bsdf.eval(mi.BSDFContext(), si, wo), dtype=np.float64)
    w = np.array(weights, dtype=np.float64)
    return float(np.sum(w * sum((c + 1.0) * value[c] for c in range(len(value)))))


def scalar_keys(params) -> list[tuple[str, int | None]]:
    """(key, component) of every scalar of ``params``: component None for a Float, 0-2 for
    the channels of a Color3f."""
    keys = []
    for key in params.keys():
        v = params[key]
        if isinstance(v, mi.Float):
            keys.append((key, None))
        else:  # Color3f
            keys.extend((key, c) for c in range(3))
    return keys


def get_scalar(params, key: str, comp: int | None) -> float:
    """The value of a Float parameter, or of one component of a Color3f parameter."""
    v = params[key]
    return float(v[comp][0]) if comp is not None else float(v[0])


def set_scalar(params, key: str, comp: int | None, x: float) -> None:
    """Set a Float parameter, or one component of a Color3f parameter, and update."""
    if comp is None:
        params[key] = mi.Float(x)
    else:
        c = [float(params[key][i][0]) for i in range(3)]
        c[comp] = x
        params[key] = mi.Color3f(*c)
    params.update()


def gradients_and_differences(bsdf, params, keys=None, spectral: bool = False,
                              steps: dict[str, float] | None = None):
    """Per scalar parameter (all, or the Float parameters ``keys``): (key, component, AD
    gradient of the loss, central finite difference with a relative step of 1 % or
    ``steps[key]``, (loss at x0 + h, x0))."""
    si, wo, weights = geometry(spectral=spectral)
    steps = steps or {}
    out = []
    for key, comp in (scalar_keys(params) if keys is None else [(k, None) for k in keys]):
        # analytic gradient
        dr.enable_grad(params[key])
        params.update()
        dr.backward(loss(bsdf, si, wo, weights))
        grad = dr.grad(params[key])
        grad = float(grad[comp][0] if comp is not None else grad[0])
        dr.disable_grad(params[key])
        params.update()

        # central finite difference
        x0 = get_scalar(params, key, comp)
        h = steps.get(key, 1e-2) * abs(x0)
        vals = []
        for x in (x0 + h, x0 - h):
            set_scalar(params, key, comp, x)
            vals.append(loss_value(bsdf, si, wo, weights))
        set_scalar(params, key, comp, x0)
        out.append((key, comp, grad, (vals[0] - vals[1]) / (2 * h), (vals[0], x0)))
    return out


def assert_updates_reuse_kernels(bsdf, updates: list[tuple[str, float]]) -> None:
    """After a first evaluation, each update of a parameter through mi.traverse (``updates``:
    key, value) evaluates with cached kernels only."""
    params = mi.traverse(bsdf)
    si, wo, weights = geometry(1000)

    def run():
        dr.eval(loss(bsdf, si, wo, weights))

    run()  # compile once
    dr.kernel_history_clear()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        for key, value in updates:
            params[key] = mi.Float(value)
            params.update()
            run()
        history = [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    assert history, "no kernel ran"
    assert all(h.get("cache_hit", False) for h in history), [
        (h.get("cache_hit"), h.get("operation_count")) for h in history]


def write_exr_capture(folder: Path, capture: dict) -> Path:
    """Write a SYNTHETIC capture (``rti.synthetic_capture``'s dict) into ``folder`` as linear
    float EXR images ``light00.exr``... and ``dirs.lp``; returns the ``.lp`` path."""
    from mitsuba_powder import rti

    names = [f"light{k:02d}.exr" for k in range(len(capture["directions"]))]
    rti.write_lp(folder / "dirs.lp", names, capture["directions"])
    like = rti.Capture(images=capture["images"], directions=capture["directions"], names=names,
                       encoding="linear", file_format="exr", bit_depth=32)
    rti.write_images(like, capture["images"], names, folder)
    return folder / "dirs.lp"


def write_image_capture(folder: Path, images: np.ndarray, directions: np.ndarray,
                        encoding: str = "srgb", bit_depth: int = 8) -> Path:
    """Write a capture's ``images`` (K, H, W, 3) as PNG files ``light00.png``... (8 or 16 bit,
    ``encoding`` srgb or linear) and ``dirs.lp`` into ``folder`` (made if needed); returns the
    ``.lp`` path."""
    from mitsuba_powder import rti

    folder.mkdir(parents=True, exist_ok=True)
    names = [f"light{k:02d}.png" for k in range(len(directions))]
    rti.write_lp(folder / "dirs.lp", names, directions)
    like = rti.Capture(images=images, directions=directions, names=names, encoding=encoding,
                       file_format="png", bit_depth=bit_depth)
    rti.write_images(like, images, names, folder)
    return folder / "dirs.lp"


def png_capture(tmp_path_factory, seed: int) -> Path:
    """A folder with a SYNTHETIC 8 x 8 px capture under 12 lights (``seed``), 8-bit PNG (sRGB)
    and ``dirs.lp``."""
    from mitsuba_powder import rti

    folder = tmp_path_factory.mktemp("capture")
    cap = rti.synthetic_capture(8, 8, lights=12, noise=0.005, seed=seed)
    write_image_capture(folder, cap["images"], cap["directions"])
    return folder


def known_maps_folder(folder: Path) -> Path:
    """Write a maps folder of known SYNTHETIC maps (no fit; 8 x 8 px, for 12 lights) into
    ``folder``; returns it."""
    from mitsuba_powder.rti import MapsResult, synthetic_maps
    from mitsuba_powder.rti.maps import write_maps

    m, _ = synthetic_maps(8, 8, relief=0.3, seed=2)
    props = {k: np.asarray(v, np.float32) for k, v in m.items() if k not in ("normal", "albedo")}
    result = MapsResult(normals=m["normal"].astype(np.float32),
                        albedo=m["albedo"].astype(np.float32), maps=props, settings={},
                        residual_rms=np.zeros((8, 8), np.float32), gains=np.ones(12),
                        used=np.ones((12, 8, 8), bool), free=["albedo"] + sorted(props),
                        mask=np.ones((8, 8), bool))
    write_maps(result, folder)
    return folder


def lambertian_capture(shape: tuple[int, int], lights: int, r: float = float("inf"),
                       tilt: float = 0.03, gains=None, seed: int = 3) -> dict:
    """A SYNTHETIC Lambertian capture (no powder): normals tilted from z by about ``tilt``
    (radians, per component), reflectances in [0.2, 0.9], ``lights`` dome lights at ``r``
    image widths (``rti.dome_directions``), gains ``gains`` (default 1). Returns ``images``
    (K, H, W, 3) ``E_k s_k max(n . d_k, 0) R / pi``, ``directions``, ``normals``,
    ``reflectance``, the per-pixel light directions ``dirs`` (K, H, W, 3), irradiance
    factors ``s`` (K, H, W), ``gains`` and ``cos`` (K, H, W) (n . d_k, unclamped)."""
    import numpy as np

    from mitsuba_powder import rti
    from mitsuba_powder.rti.lights import LightRig, image_light_field

    rng = np.random.default_rng(seed)
    d = rti.dome_directions(lights)
    n = rng.normal(scale=tilt, size=tuple(shape) + (3,))
    n[..., 2] = 1.0
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    refl = rng.uniform(0.2, 0.9, tuple(shape) + (3,))
    g = np.ones(lights) if gains is None else np.asarray(gains, dtype=np.float64)
    dirs, s = image_light_field(LightRig(d, r), shape)
    cos = np.einsum("khwi,hwi->khw", dirs, n)
    images = (np.maximum(cos, 0.0)[..., None] * refl[None] / np.pi
              * (g[:, None, None] * s)[..., None])
    return {"images": images, "directions": d, "normals": n, "reflectance": refl,
            "dirs": dirs, "s": s, "gains": g, "cos": cos}


# Packaging: the wheel, the aarch64 build and builds against another mitsuba release

#: The repository root, and the script that prints the plugin's values at fixed inputs
ROOT = Path(__file__).resolve().parents[1]
POWDER_VALUES = ROOT / "tools" / "powder_values.py"


def run(cmd: list, timeout: float = 3600, **kw) -> subprocess.CompletedProcess:
    """Run ``cmd``; fail the test with its output's tail if it fails."""
    proc = subprocess.run([str(c) for c in cmd], capture_output=True, text=True,
                          timeout=timeout, **kw)
    assert proc.returncode == 0, (f"{' '.join(map(str, cmd))} exited {proc.returncode}:\n"
                                  f"{(proc.stdout + proc.stderr)[-5000:]}")
    return proc


def clean_env(venv: Path) -> dict[str, str]:
    """An environment whose PATH is ``venv``'s bin folder only (no compiler, no CMake), with
    this machine's pip settings (index, certificates) and HOME (pip's cache)."""
    keep = {k: v for k, v in os.environ.items()
            if k.startswith("PIP_") or k in ("HOME", "LANG", "SSL_CERT_FILE", "TMPDIR")}
    return {**keep, "PATH": str(venv / "bin")}


def new_venv(path: Path) -> Path:
    """A fresh virtual environment at ``path`` (this Python's version); its python."""
    run([sys.executable, "-m", "venv", path])
    return path / "bin" / "python"


def powder_values(python: Path | str, variant: str, env: dict | None = None) -> dict:
    """tools/powder_values.py's JSON for the plugin installed in ``python``'s environment."""
    return json.loads(run([python, POWDER_VALUES, "--variant", variant], env=env,
                          cwd="/").stdout)


def load_script(name: str):
    """A Python script of tools/ without a .py suffix (``check-aarch64``) as a module."""
    loader = importlib.machinery.SourceFileLoader(name.replace("-", "_"),
                                                  str(ROOT / "tools" / name))
    module = importlib.util.module_from_spec(importlib.util.spec_from_loader(loader.name,
                                                                             loader))
    loader.exec_module(module)
    return module


def max_relative_difference(a: dict, b: dict) -> float:
    """Largest |x - y| / max(|x|, |y|) over every value of two tools/powder_values.py JSONs
    (which must hold the same powders and quantities, as many values of each)."""
    worst = 0.0
    assert a["powders"].keys() == b["powders"].keys()
    for name, quantities in a["powders"].items():
        for q, xs in quantities.items():
            ys = b["powders"][name][q]
            assert len(xs) == len(ys) > 0, (name, q)
            worst = max([worst] + [abs(x - y) / max(abs(x), abs(y), 1e-30)
                                   for x, y in zip(xs, ys)])
    return worst
