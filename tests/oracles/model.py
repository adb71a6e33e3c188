"""Independent NumPy (float64) implementation of the powder BRDF of ``docs/model.md``.

Test-only code: the product computes the model in C++ (``src/bsdfs/powder.cpp``). This file
follows docs/model.md's formulas literally (Eq. 9a, the corrected 9b, 9c/10, 21-22 and 20), e.g.
the coherent term with ``v = (1/mu_i + 1/mu_o) / 2`` and ``np.expm1``, so that it shares no
algebraic rewriting with the plugin.

Units: wavelengths in nm, lengths in micrometres, extinction in 1/micrometre.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

LOBES = ("single", "multiple", "coherent", "surface")


@dataclass
class Params:
    """Parameters of docs/model.md's table (plugin property names)."""

    amplitude_volume: float = 1.0
    g: float = 0.0
    extinction: float = 1.0
    tau_o: float = 2.0 / 3.0
    thickness: float = np.inf
    amplitude_surface: float = 0.0
    correlation_length: float = 1.0
    specular: str = "harvey_shack"
    sigma: float = 0.1
    lobes: tuple[str, ...] = field(default_factory=lambda: LOBES)

    def as_float32(self) -> Params:
        """The same parameters rounded to float32, as the plugin stores them."""
        f = lambda x: float(np.float32(x))  # noqa: E731
        return Params(
            f(self.amplitude_volume), f(self.g), f(self.extinction), f(self.tau_o),
            f(self.thickness), f(self.amplitude_surface), f(self.correlation_length),
            self.specular, f(self.sigma), tuple(self.lobes),
        )

    def properties(self) -> dict:
        """Plugin properties (without albedo)."""
        props = {
            "amplitude_volume": self.amplitude_volume,
            "g": self.g,
            "extinction": self.extinction,
            "tau_o": self.tau_o,
            "amplitude_surface": self.amplitude_surface,
            "specular": self.specular,
            "lobes": ",".join(self.lobes),
        }
        if np.isfinite(self.thickness):
            props["thickness"] = self.thickness
        if self.specular == "harvey_shack":
            props["correlation_length"] = self.correlation_length
        else:
            props["sigma"] = self.sigma
        return props


def s_func(c: np.ndarray, tau_o: float) -> np.ndarray:
    """s(c) = (1 - exp(-2 c tau_o)) / (2 c), = tau_o at c = 0."""
    c = np.asarray(c, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        out = -np.expm1(-2.0 * c * tau_o) / (2.0 * c)
    return np.where(c == 0.0, tau_o, out)


def hg(cos_theta: np.ndarray, g: float) -> np.ndarray:
    """P(Theta) = 4 pi p_HG(Theta)."""
    return (1.0 - g * g) / (1.0 + g * g - 2.0 * g * cos_theta) ** 1.5


def brdf_terms(wi: np.ndarray, wo: np.ndarray, rho: np.ndarray, lam_nm: np.ndarray,
               p: Params) -> dict[str, np.ndarray]:
    """Each term of the BRDF (1/sr, already including A_v / (4 pi) for the volume terms).

    Args:
        wi, wo: (N, 3) unit vectors (wi towards the light, wo towards the viewer).
        rho: single-scattering albedo, broadcastable to (N, C) (C channels).
        lam_nm: wavelengths in nm, broadcastable to (N, C).
        p: parameters.

    Returns:
        dict lobe name -> (N, C) array; zero where mu_i <= 0 or mu_o <= 0.
    """
    wi = np.asarray(wi, np.float64)
    wo = np.asarray(wo, np.float64)
    mu_i = wi[:, 2:3]
    mu_o = wo[:, 2:3]
    valid = (mu_i > 0) & (mu_o > 0)
    mu_i = np.where(valid, mu_i, 1.0)
    mu_o = np.where(valid, mu_o, 1.0)
    rho = np.asarray(rho, np.float64)
    lam = np.asarray(lam_nm, np.float64) * 1e-3  # micrometres
    k0 = 2.0 * np.pi / lam
    kappa = p.extinction
    shape = np.broadcast_shapes(mu_i.shape, rho.shape, lam.shape)
    scale = p.amplitude_volume / (4.0 * np.pi)

    out: dict[str, np.ndarray] = {}

    # Eq. 9a
    cos_theta = -np.sum(wi * wo, axis=1, keepdims=True)
    bracket = 1.0
    if np.isfinite(p.thickness):
        bracket = -np.expm1(-kappa * p.thickness * (1.0 / mu_i + 1.0 / mu_o))
    L1 = rho * hg(cos_theta, p.g) / (mu_i + mu_o) * bracket
    out["single"] = scale * L1

    # Eq. 9b (corrected, docs/model.md)
    c0 = np.sqrt(3.0 * (1.0 - rho) * (1.0 - rho * p.g))
    L2 = 3.0 * rho**2 * (s_func(c0, p.tau_o) + mu_i * mu_o / (mu_i + mu_o)) / (
        (1.0 + c0 * mu_i) * (1.0 + c0 * mu_o))
    out["multiple"] = scale * L2

    # Eq. 9c with Eq. 10
    dxy = np.linalg.norm(wo[:, :2] - wi[:, :2], axis=1, keepdims=True)
    alpha = (k0 / kappa) * dxy
    u = (k0 / kappa) * (mu_i - mu_o)
    v = 0.5 * (1.0 / mu_i + 1.0 / mu_o)
    c = np.sqrt(c0**2 + alpha**2)
    C = 3.0 * rho**2 * (1.0 / (2.0 * v) + s_func(c, p.tau_o)) / (
        mu_i * mu_o * ((c + v) ** 2 + u**2))
    out["coherent"] = scale * C

    # Eq. 21-22 (Harvey-Shack) or Eq. 20 (Gaussian)
    if p.specular == "harvey_shack":
        fs = np.linalg.norm(wo[:, :2] + wi[:, :2], axis=1, keepdims=True) / lam
        lc = p.correlation_length
        S = (p.amplitude_surface * 4.0 * np.pi**2 / lam**4 * (mu_i + mu_o) ** 2
             * np.pi * lc**2 * np.exp(-np.pi**2 * lc**2 * fs**2))
    else:
        mirror = wi * np.array([-1.0, -1.0, 1.0])
        mirror /= np.linalg.norm(mirror, axis=1, keepdims=True)
        won = wo / np.linalg.norm(wo, axis=1, keepdims=True)
        theta_s = np.arctan2(np.linalg.norm(np.cross(mirror, won), axis=1, keepdims=True),
                             np.sum(mirror * won, axis=1, keepdims=True))
        S = (p.amplitude_surface / (p.sigma * np.sqrt(2.0 * np.pi))
             * np.exp(-theta_s**2 / (2.0 * p.sigma**2)))
    out["surface"] = np.broadcast_to(S, shape)

    return {k: np.where(valid, np.broadcast_to(val, shape), 0.0) for k, val in out.items()}


def brdf(wi: np.ndarray, wo: np.ndarray, rho: np.ndarray, lam_nm: np.ndarray,
         p: Params) -> np.ndarray:
    """The BRDF of docs/model.md (1/sr) summed over ``p.lobes``; shape (N, C)."""
    terms = brdf_terms(wi, wo, rho, lam_nm, p)
    return sum(terms[name] for name in p.lobes)


def gonio_directions(theta_i_deg, theta_o_deg, phi_deg) -> tuple[np.ndarray, np.ndarray]:
    """docs/model.md's gonio convention: wi in the xz plane, signed theta_o, azimuth phi."""
    ti = np.radians(np.atleast_1d(theta_i_deg)).astype(np.float64)
    to = np.radians(np.atleast_1d(theta_o_deg)).astype(np.float64)
    ph = np.radians(np.atleast_1d(phi_deg)).astype(np.float64)
    ti, to, ph = np.broadcast_arrays(ti, to, ph)
    wi = np.stack([np.sin(ti), np.zeros_like(ti), np.cos(ti)], axis=1)
    wo = np.stack([np.sin(to) * np.cos(ph), np.sin(to) * np.sin(ph), np.cos(to)], axis=1)
    return wi, wo


def fresnel_unpolarized(c: np.ndarray, m: complex | np.ndarray) -> np.ndarray:
    """Unpolarised Fresnel reflectance of a smooth interface to a medium of complex index
    ``m = eta + i k`` at the cosine ``c`` (docs/model.md, "Surface reflectance factor"), in
    complex float64 arithmetic (the plugin expands it into real arithmetic)."""
    m = np.asarray(m, dtype=np.complex128)
    c = np.asarray(c, dtype=np.float64)
    r = np.sqrt(m * m - 1.0 + c * c + 0j)
    rs = (c - r) / (c + r)
    rp = (m * m * c - r) / (m * m * c + r)
    return 0.5 * (np.abs(rs) ** 2 + np.abs(rp) ** 2)


def surface_fresnel_factor(wi: np.ndarray, wo: np.ndarray, m: complex | np.ndarray
                           ) -> np.ndarray:
    """F(wi . h) / F(1), h the half vector of ``wi`` and ``wo`` (N, 3): the factor of the
    surface term with ``surface_fresnel = fresnel``; (N, 1), or (N, C) for ``m`` of shape
    (N, C) or (C,)."""
    h = wi + wo
    h /= np.linalg.norm(h, axis=1, keepdims=True)
    c = np.clip(np.sum(wi * h, axis=1, keepdims=True), 0.0, 1.0)
    return fresnel_unpolarized(c, m) / fresnel_unpolarized(1.0, m)
