"""White furnace: a powder patch under a uniform environment renders to its albedo.

A patch lit by a ``constant`` environment of radiance 1 reflects, towards a viewing direction
``wo``, the radiance ``rho(wo) = int f(wo, w) cos(theta_w) dw``: the directional-hemispherical
reflectance. The render estimates it with BSDF sampling only (``direct`` integrator with
``emitter_samples = 0``: a test of ``sample``) or with MIS (a test of ``sample`` and ``pdf``
together); the reference is a deterministic quadrature of ``eval`` in polar coordinates around
the retro-reflection direction (where the coherent cone sits).
"""

from __future__ import annotations

import time
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from .._checks import check_range, out_of_range
from ..variants import check_variant, use_variant
from .gonio import eval_channels, film_dict, film_weights, patch_dict, sensor_dict

STRATEGIES = {"bsdf": (0, 1), "mis": (1, 1)}


@dataclass
class FurnaceResult:
    """Albedo rendered under a uniform environment and by quadrature.

    Attributes:
        theta_o: viewing angles, degrees (N,).
        rendered, stderr, quadrature: (N, C) albedo, its Monte Carlo standard error and the
            quadrature of ``eval``.
        strategy, variant, spp, resolution, seconds: how it was rendered.
    """

    theta_o: np.ndarray
    rendered: np.ndarray
    stderr: np.ndarray
    quadrature: np.ndarray
    strategy: str
    variant: str
    spp: int
    resolution: int
    seconds: float

    def z(self) -> np.ndarray:
        """(rendered - quadrature) / stderr, (N, C)."""
        return (self.rendered - self.quadrature) / np.maximum(self.stderr, 1e-30)


def albedo_quadrature(bsdf, theta_o: float, n_rho: int = 384, n_psi: int = 384,
                      chunk: int = 16384) -> np.ndarray:
    """``rho(wo)`` of ``bsdf`` (current variant) by Gauss-Legendre in the angle ``rho`` from
    ``wo`` (the retro direction) and the midpoint rule in its azimuth; per channel
    (sRGB film values per unit spectrum in spectral variants)."""
    t = np.radians(theta_o)
    wo = np.array([np.sin(t), 0.0, np.cos(t)])
    x, wx = np.polynomial.legendre.leggauss(n_rho)
    rho = 0.5 * np.pi * (x + 1.0)
    w_rho = 0.5 * np.pi * wx * np.sin(rho)
    psi = (np.arange(n_psi) + 0.5) * 2.0 * np.pi / n_psi
    u = np.array([np.cos(t), 0.0, -np.sin(t)])
    v = np.cross(wo, u)
    r, p = np.meshgrid(rho, psi, indexing="ij")
    d = (np.cos(r)[..., None] * wo + np.sin(r)[..., None] * (
        np.cos(p)[..., None] * u + np.sin(p)[..., None] * v)).reshape(-1, 3)
    w = np.repeat(w_rho, n_psi) * (2.0 * np.pi / n_psi)
    up = d[:, 2] > 0.0
    d, w = d[up], w[up]
    total = 0.0
    for s in range(0, len(d), chunk):
        part = d[s:s + chunk]
        vals = eval_channels(bsdf, np.repeat(wo[None, :], len(part), axis=0), part)
        total = total + (w[s:s + chunk, None] * vals).sum(axis=0)
    return np.asarray(total)


def hemispherical_reflectance(bsdf, theta_i: float, *, n_inner: int = 32, n_outer: int = 64,
                              n_psi: int = 128, rho_split: float = 0.05,
                              rho_min: float = 1e-6) -> np.ndarray:
    """Directional-hemispherical reflectance ``int f(wi, wo) cos(theta_o) dwo`` of ``bsdf``
    (current variant) at incidence ``theta_i`` (degrees, azimuth 0), per channel, resolving
    coherent cones down to ``rho_min`` radians.

    Polar coordinates on the sphere about the back-scattering direction ``wi``: angle ``rho``
    in [0, rho_max(psi)], where ``tan rho_max = mu_i / (sin theta_i cos psi)`` is the horizon
    (so no node falls outside the hemisphere), azimuth ``psi`` by the midpoint rule
    (``n_psi``); ``rho`` by Gauss-Legendre in ``log rho`` on [rho_min, rho_1] (``n_inner``)
    and in ``x`` on [rho_1, rho_max] with ``rho = rho_max - (rho_max - rho_1) x^2``
    (``n_outer``, nodes dense at the horizon), ``rho_1 = min(rho_max, rho_split)``. The
    cap ``rho < rho_min`` is left out (a relative error of about ``rho_min^2``).
    """
    check_range("theta_i", theta_i, 0.0, 90.0, note="degrees")
    t = np.radians(theta_i)
    mu_i, s_i = np.cos(t), np.sin(t)
    wi = np.array([s_i, 0.0, mu_i])
    u = np.array([mu_i, 0.0, -s_i])
    v = np.array([0.0, 1.0, 0.0])
    psi = (np.arange(n_psi) + 0.5) * 2.0 * np.pi / n_psi
    rho_max = np.arctan2(mu_i, s_i * np.cos(psi))[:, None]
    rho_1 = np.minimum(rho_max, rho_split)
    xi, wi_ = np.polynomial.legendre.leggauss(n_inner)
    xi, wi_ = 0.5 * (xi + 1.0), 0.5 * wi_
    xo, wo_ = np.polynomial.legendre.leggauss(n_outer)
    xo, wo_ = 0.5 * (xo + 1.0), 0.5 * wo_
    span = np.log(rho_1 / rho_min)
    rho_in = rho_min * np.exp(xi[None, :] * span)
    w_in = wi_[None, :] * span * rho_in
    d = rho_max - rho_1
    rho_out = rho_max - d * xo[None, :] ** 2
    w_out = 2.0 * wo_[None, :] * xo[None, :] * d
    rho = np.concatenate([rho_in, rho_out], axis=1)
    weight = np.concatenate([w_in, w_out], axis=1) * np.sin(rho) * (2.0 * np.pi / n_psi)
    p = np.broadcast_to(psi[:, None], rho.shape)
    dirs = (np.cos(rho)[..., None] * wi + np.sin(rho)[..., None] * (
        np.cos(p)[..., None] * u + np.sin(p)[..., None] * v)).reshape(-1, 3)
    vals = eval_channels(bsdf, np.repeat(wi[None, :], len(dirs), axis=0), dirs)
    return (weight.reshape(-1, 1) * vals).sum(axis=0)


def white_furnace(properties: dict, theta_o=(0.0, 45.0, 75.0), *,
                  variant: str = "llvm_ad_rgb", strategy: str = "bsdf", spp: int = 256,
                  resolution: int = 32, seed: int = 0) -> FurnaceResult:
    """Render the patch under a uniform environment (radiance 1) from each ``theta_o``
    (degrees, azimuth 0) and compare with :func:`albedo_quadrature`.

    Args:
        properties: ``powder`` plugin properties (without ``type``).
        theta_o: viewing angles, degrees, in [0, 90).
        variant: Mitsuba variant.
        strategy: ``bsdf`` (BSDF sampling only) or ``mis``.
        spp, resolution: samples per pixel; pixels per side (independent estimates).
        seed: sampler seed.
    """
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy = {strategy!r} is not valid; choose one of "
                         f"{tuple(STRATEGIES)}")
    check_variant(variant)
    if spp < 1 or resolution < 2:
        raise ValueError(f"spp = {spp}, resolution = {resolution}: valid ranges are "
                         "spp >= 1, resolution >= 2")
    angles = np.atleast_1d(np.asarray(theta_o, dtype=np.float64))
    if np.any((angles < 0) | (angles >= 90)):
        raise ValueError(out_of_range(f"theta_o = {angles.tolist()}", "[0, 90)"))
    e, b = STRATEGIES[strategy]
    with use_variant(variant):
        views = np.stack([np.sin(np.radians(angles)), np.zeros_like(angles),
                          np.cos(np.radians(angles))], axis=1)
        scene = mi.load_dict({
            "type": "scene",
            "integrator": {"type": "direct", "emitter_samples": e, "bsdf_samples": b},
            "patch": patch_dict(properties),
            "sky": {"type": "constant", "radiance": {"type": "uniform", "value": 1.0}},
            "sensor": {"type": "batch", "film": film_dict(resolution * len(angles), resolution),
                       "sampler": {"type": "independent", "sample_count": spp},
                       **{f"s{j}": sensor_dict(v, resolution, spp) for j, v in enumerate(views)}},
        })
        start = time.perf_counter()
        image = mi.render(scene, seed=seed)
        dr.sync_thread()
        seconds = time.perf_counter() - start
        n_c = 1 if "mono" in variant else 3
        img = np.array(image, dtype=np.float64).reshape(resolution, resolution * len(angles),
                                                        -1)[..., :n_c]
        pix = np.moveaxis(img.reshape(resolution, len(angles), resolution, n_c), 1, 0).reshape(
            len(angles), -1, n_c)
        white = film_weights()[1].sum(axis=1) if mi.is_spectral else np.ones(3)
        pix = pix[..., :n_c] / white[:n_c]
        bsdf = next(s.bsdf() for s in scene.shapes() if s.id() == "patch")
        quad = np.array([albedo_quadrature(bsdf, a) for a in angles])
    return FurnaceResult(angles, pix.mean(axis=1),
                         pix.std(axis=1, ddof=1) / np.sqrt(pix.shape[1]), quad, strategy,
                         variant, spp, resolution, seconds)
