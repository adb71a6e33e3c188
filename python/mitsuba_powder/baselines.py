"""Baseline reflectance models, fitted like the powder model for a comparison table.

These are other people's models, written here from their published formulas as NumPy
functions of the gonio geometry; they return the BRF (pi x BRDF). They are not part of the
powder plugin (its model lives in C++ only).

- ``lambertian``: BRF = rho.
- ``oren_nayar``: the qualitative Oren-Nayar model (1994): rho (A + B max(0, cos dphi)
  sin(alpha) tan(beta)), A = 1 - 0.5 s^2 / (s^2 + 0.33), B = 0.45 s^2 / (s^2 + 0.09).
- ``rtlsr``: the Ross-Thick Li-Sparse-Reciprocal kernel model (Lucht et al. 2000, MODIS
  BRDF): f_iso + f_vol K_vol + f_geo K_geo, with b/r = 1 and h/b = 2.
- ``hapke``: Hapke's model with both opposition effects (Hapke 2002, 2012): shadow hiding
  (B_S0, h_S) and coherent back-scattering (B_C0, h_C), a two-term Henyey-Greenstein phase
  function (b, c) and the 2002 approximation of the H function; no macroscopic roughness,
  porosity factor K = 1. r = w/(4 pi) mu0/(mu0 + mu) [p(g) (1 + B_S0 B_S) + H(mu0) H(mu) - 1]
  (1 + B_C0 B_C); BRF = pi r / mu0.

Each model: name -> (function(params, wi, wo) -> BRF, parameter specs).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .measurements import Measurements
from .optimise import ParamSpec, finite_difference_jacobian, multistart, sobol_starts


def _angles(wi: np.ndarray, wo: np.ndarray):
    mu0, mu = wi[:, 2], wo[:, 2]
    cos_g = np.clip(np.sum(wi * wo, axis=1), -1.0, 1.0)  # phase angle g: 0 at retro
    return mu0, mu, cos_g


def lambertian(p: dict, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    return np.full(len(wi), p["rho"])


def oren_nayar(p: dict, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    s2 = p["sigma"] ** 2
    a = 1.0 - 0.5 * s2 / (s2 + 0.33)
    b = 0.45 * s2 / (s2 + 0.09)
    ti, to = np.arccos(np.clip(wi[:, 2], -1, 1)), np.arccos(np.clip(wo[:, 2], -1, 1))
    ni, no = np.linalg.norm(wi[:, :2], axis=1), np.linalg.norm(wo[:, :2], axis=1)
    with np.errstate(invalid="ignore", divide="ignore"):
        cos_dphi = np.where((ni > 1e-12) & (no > 1e-12),
                            np.sum(wi[:, :2] * wo[:, :2], axis=1) / (ni * no), 0.0)
    alpha, beta = np.maximum(ti, to), np.minimum(ti, to)
    return p["rho"] * (a + b * np.maximum(0.0, cos_dphi) * np.sin(alpha) * np.tan(beta))


def rtlsr_kernels(wi: np.ndarray, wo: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(K_vol, K_geo) of Lucht et al. (2000), relative azimuth 0 = hot spot."""
    mu0, mu, cos_xi = _angles(wi, wo)
    xi = np.arccos(cos_xi)
    k_vol = ((np.pi / 2 - xi) * cos_xi + np.sin(xi)) / (mu0 + mu) - np.pi / 4
    sec_i, sec_v = 1.0 / mu0, 1.0 / mu
    # tan(ti) tan(tv) cos(phi) and sin(phi) parts from the projected directions
    tt_cos = np.sum(wi[:, :2] * wo[:, :2], axis=1) / (mu0 * mu)
    tt_sin = np.abs(wi[:, 0] * wo[:, 1] - wi[:, 1] * wo[:, 0]) / (mu0 * mu)
    tan2_i, tan2_v = sec_i**2 - 1.0, sec_v**2 - 1.0
    d2 = np.maximum(tan2_i + tan2_v - 2.0 * tt_cos, 0.0)
    cos_t = np.clip(2.0 * np.sqrt(d2 + tt_sin**2) / (sec_i + sec_v), -1.0, 1.0)  # h/b = 2
    t = np.arccos(cos_t)
    overlap = (t - np.sin(t) * cos_t) * (sec_i + sec_v) / np.pi
    k_geo = overlap - sec_i - sec_v + 0.5 * (1.0 + cos_xi) * sec_i * sec_v
    return k_vol, k_geo


def rtlsr(p: dict, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    k_vol, k_geo = rtlsr_kernels(wi, wo)
    return p["f_iso"] + p["f_vol"] * k_vol + p["f_geo"] * k_geo


def hapke_h(x: np.ndarray, w: float) -> np.ndarray:
    """Hapke's (2002) approximation of Chandrasekhar's H function."""
    gamma = math.sqrt(1.0 - w)
    r0 = (1.0 - gamma) / (1.0 + gamma)
    x = np.maximum(x, 1e-9)
    return 1.0 / (1.0 - w * x * (r0 + (1.0 - 2.0 * r0 * x) / 2.0 * np.log((1.0 + x) / x)))


def hapke(p: dict, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    mu0, mu, cos_g = _angles(wi, wo)
    b, c, w = p["b"], p["c"], p["w"]
    hg = lambda s: (1 - b * b) / (1 + s * 2 * b * cos_g + b * b) ** 1.5  # noqa: E731
    phase = 0.5 * (1 + c) * hg(-1.0) + 0.5 * (1 - c) * hg(1.0)  # back lobe when c > 0
    tan_half = np.sqrt(np.maximum(0.0, (1.0 - cos_g) / (1.0 + cos_g)))
    b_s = 1.0 / (1.0 + tan_half / p["h_s"])
    y = tan_half / p["h_c"]
    one_minus_exp_over_y = np.where(y > 1e-8, -np.expm1(-y) / np.maximum(y, 1e-300), 1.0)
    b_c = (1.0 + one_minus_exp_over_y) / (2.0 * (1.0 + y) ** 2)
    r = w / (4 * np.pi) * mu0 / (mu0 + mu) * (phase * (1.0 + p["B_s0"] * b_s)
                                              + hapke_h(mu0, w) * hapke_h(mu, w) - 1.0) \
        * (1.0 + p["B_c0"] * b_c)
    return np.pi * r / mu0


MODELS: dict[str, tuple[Callable, dict[str, ParamSpec]]] = {
    "lambertian": (lambertian, {"rho": ParamSpec(0.0, 2.0, False, 0.8)}),
    "oren_nayar": (oren_nayar, {"rho": ParamSpec(0.0, 2.0, False, 0.8),
                                "sigma": ParamSpec(0.0, 1.5, False, 0.3)}),
    "rtlsr": (rtlsr, {"f_iso": ParamSpec(0.0, 2.0, False, 0.8),
                      "f_vol": ParamSpec(-1.0, 2.0, False, 0.1),
                      "f_geo": ParamSpec(-1.0, 1.0, False, 0.05)}),
    "hapke": (hapke, {"w": ParamSpec(0.01, 0.9999, False, 0.8),
                      "b": ParamSpec(0.0, 0.95, False, 0.3),
                      "c": ParamSpec(-1.0, 1.0, False, 0.0),
                      "B_s0": ParamSpec(0.0, 5.0, False, 1.0),
                      "h_s": ParamSpec(1e-3, 1.0, True, 0.05),
                      "B_c0": ParamSpec(0.0, 1.0, False, 0.5),
                      "h_c": ParamSpec(1e-4, 1.0, True, 0.01)}),
}


@dataclass
class BaselineFit:
    """A baseline fitted at one wavelength: parameters, model BRF, loss and cost."""

    model: str
    wavelength: float
    parameters: dict
    model_brf: np.ndarray
    loss: float
    evaluations: int
    seconds: float
    agreeing: int = 0


class _BaselineProblem:
    """Weighted BRF residuals of a NumPy baseline, batched over parameter sets (for
    :func:`mitsuba_powder.optimise.multistart`); the Jacobian by central differences."""

    def __init__(self, func: Callable, specs: dict[str, ParamSpec], wi: np.ndarray,
                 wo: np.ndarray, brf: np.ndarray, weights: np.ndarray):
        self.func, self.specs, self.names = func, list(specs.values()), list(specs)
        self.wi, self.wo, self.brf, self.weights = wi, wo, brf, weights
        self.lower = np.array([s.to_y(s.lower) for s in self.specs], dtype=np.float64)
        self.upper = np.array([s.to_y(s.upper) for s in self.specs], dtype=np.float64)
        self.jacobian = finite_difference_jacobian(self.residuals, self.lower, self.upper)

    def parameters(self, y: np.ndarray) -> dict:
        return {n: float(s.to_x(v)) for n, s, v in zip(self.names, self.specs, y)}

    def residuals(self, y: np.ndarray) -> np.ndarray:
        out = np.empty((len(y), len(self.brf)))
        with np.errstate(all="ignore"):
            for b, row in enumerate(np.atleast_2d(y)):
                out[b] = (self.func(self.parameters(row), self.wi, self.wo) - self.brf) \
                    * self.weights
        # a parameter set where the model is undefined gets a huge, finite cost
        return np.where(np.isfinite(out), out, 1e10)


def fit_baseline(model: str, data: Measurements, starts: int = 32, seed: int = 0,
                 polish: int = 2) -> list[BaselineFit]:
    """Fit a baseline at each wavelength of ``data``: weighted least squares on the BRF with
    the package's optimiser (:func:`mitsuba_powder.optimise.multistart`: Sobol starts, batched
    Levenberg-Marquardt, the best ``polish`` end points refined by ``scipy``), Jacobian by
    central differences."""
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; models: {', '.join(MODELS)}")
    if starts < 1:
        raise ValueError(f"starts = {starts} is out of range; valid range is [1, inf)")
    func, specs = MODELS[model]
    wi_all, wo_all = data.directions()
    weights = 1.0 / data.sigma if data.sigma is not None else np.ones(len(data))
    out = []
    for lam in data.wavelengths():
        t0 = time.perf_counter()
        sel = data.wavelength == lam
        problem = _BaselineProblem(func, specs, wi_all[sel], wo_all[sel], data.brf[sel],
                                   weights[sel])
        y0 = sobol_starts(problem.lower, problem.upper, starts, seed)
        y0[0] = [s.to_y(s.start) for s in problem.specs]
        result = multistart(problem, y0, polish_count=polish)
        params = problem.parameters(result.y)
        out.append(BaselineFit(model, float(lam), params, func(params, wi_all[sel], wo_all[sel]),
                               result.cost, result.evaluations, time.perf_counter() - t0,
                               result.agreeing))
    return out
