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
  function (b, c), the 2002 approximation of the H function and the macroscopic roughness of
  Hapke (1984) (mean slope angle theta_bar, 0-45 deg); porosity factor K = 1.
  r = w/(4 pi) mu0e/(mu0e + mue) [p(g) (1 + B_S0 B_S) + H(mu0e) H(mue) - 1] (1 + B_C0 B_C)
  S(i, e, psi); BRF = pi r / mu0 (mu0 = cos i, the true incidence). mu0e, mue and S are the
  effective cosines and the shadowing function (:func:`hapke_roughness`); at theta_bar = 0
  they are mu0, mu and 1 and the model is the smooth-surface one.

Each model: name -> (function(params, wi, wo) -> BRF, parameter specs).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from .._checks import check_range, out_of_range
from ..io.measurements import Measurements
from .optimise import (
    ParamSpec,
    check_determined,
    finite_difference_jacobian,
    multistart,
    sobol_starts,
)


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


#: Bounds of Hapke's mean slope angle theta_bar (degrees)
THETA_BAR_RANGE = (0.0, 45.0)


def hapke_roughness(theta_bar: float, wi: np.ndarray, wo: np.ndarray
                    ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Hapke's (1984; 2012, eqs. 12.46-12.55) macroscopic roughness for a mean slope angle
    ``theta_bar`` (degrees): the effective cosines (mu0e, mue) and the shadowing function
    S(i, e, psi), with psi the azimuth between the planes of incidence and emission (0 on the
    light's side). With chi = 1 / sqrt(1 + pi tan^2 theta_bar),
    E1(x) = exp(-(2/pi) cot theta_bar cot x), E2(x) = exp(-(1/pi) cot^2 theta_bar cot^2 x),
    eta(x) = chi [cos x + sin x tan theta_bar E2(x) / (2 - E1(x))], f = exp(-2 tan(psi/2)):

    - i <= e: D = 2 - E1(e) - (psi/pi) E1(i);
      mu0e = chi [cos i + sin i tan theta_bar (cos psi E2(e) + sin^2(psi/2) E2(i)) / D],
      mue = chi [cos e + sin e tan theta_bar (E2(e) - sin^2(psi/2) E2(i)) / D],
      S = mue/eta(e) mu0/eta(i) chi / (1 - f + f chi mu0/eta(i));
    - e <= i: D = 2 - E1(i) - (psi/pi) E1(e);
      mu0e = chi [cos i + sin i tan theta_bar (E2(i) - sin^2(psi/2) E2(e)) / D],
      mue = chi [cos e + sin e tan theta_bar (cos psi E2(i) + sin^2(psi/2) E2(e)) / D],
      S = mue/eta(e) mu0/eta(i) chi / (1 - f + f chi mu/eta(e)).

    Both cases agree at i = e; at theta_bar = 0 the result is exactly (mu0, mu, 1)."""
    theta_bar, (lo, hi) = float(theta_bar), THETA_BAR_RANGE
    if not lo <= theta_bar <= hi:
        raise ValueError(out_of_range(f"theta_bar = {theta_bar:g} deg", f"[{lo:g}, {hi:g}]",
                                      "deg (Hapke's mean slope angle)"))
    mu0, mu = wi[:, 2], wo[:, 2]
    if theta_bar == 0.0:
        return mu0, mu, np.ones_like(mu0)
    tan_t = math.tan(math.radians(theta_bar))
    chi = 1.0 / math.sqrt(1.0 + math.pi * tan_t * tan_t)
    sin_i, sin_e = np.hypot(wi[:, 0], wi[:, 1]), np.hypot(wo[:, 0], wo[:, 1])
    with np.errstate(divide="ignore", invalid="ignore"):
        # cot x = cos x / sin x (inf at the normal, where E1 = E2 = 0)
        cot_i = np.where(sin_i > 0.0, mu0 / sin_i, np.inf)
        cot_e = np.where(sin_e > 0.0, mu / sin_e, np.inf)
        cos_psi = np.where((sin_i > 0.0) & (sin_e > 0.0),
                           np.sum(wi[:, :2] * wo[:, :2], axis=1) / (sin_i * sin_e), 1.0)
    cos_psi = np.clip(cos_psi, -1.0, 1.0)  # psi is irrelevant where i = 0 or e = 0
    psi = np.arccos(cos_psi)
    sin2_half = 0.5 * (1.0 - cos_psi)  # sin^2(psi/2)
    with np.errstate(divide="ignore", over="ignore"):
        f = np.exp(-2.0 * np.sqrt(sin2_half / np.maximum(1.0 - sin2_half, 0.0)))  # tan(psi/2)

    def e1(cot_x):
        return np.exp(-2.0 / math.pi / tan_t * cot_x)

    def e2(cot_x):
        return np.exp(-(cot_x / tan_t) ** 2 / math.pi)

    with np.errstate(over="ignore"):  # cot^2 x / tan^2 theta_bar -> inf: E2 = 0
        e1_i, e1_e, e2_i, e2_e = e1(cot_i), e1(cot_e), e2(cot_i), e2(cot_e)
    eta_i = chi * (mu0 + sin_i * tan_t * e2_i / (2.0 - e1_i))
    eta_e = chi * (mu + sin_e * tan_t * e2_e / (2.0 - e1_e))
    i_le_e = mu0 >= mu  # i <= e
    d = np.where(i_le_e, 2.0 - e1_e - psi / math.pi * e1_i, 2.0 - e1_i - psi / math.pi * e1_e)
    mu0e = chi * (mu0 + sin_i * tan_t * np.where(i_le_e, cos_psi * e2_e + sin2_half * e2_i,
                                                 e2_i - sin2_half * e2_e) / d)
    mue = chi * (mu + sin_e * tan_t * np.where(i_le_e, e2_e - sin2_half * e2_i,
                                               cos_psi * e2_i + sin2_half * e2_e) / d)
    ratio = np.where(i_le_e, mu0 / eta_i, mu / eta_e)
    s = mue / eta_e * mu0 / eta_i * chi / (1.0 - f + f * chi * ratio)
    return mu0e, mue, s


def hapke(p: dict, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """Hapke's BRF; ``p["theta_bar"]`` (degrees, 0-45) may be left out: 0, a smooth surface."""
    mu0, mu, cos_g = _angles(wi, wo)
    mu0e, mue, shadowing = hapke_roughness(p.get("theta_bar", 0.0), wi, wo)
    b, c, w = p["b"], p["c"], p["w"]
    hg = lambda s: (1 - b * b) / (1 + s * 2 * b * cos_g + b * b) ** 1.5  # noqa: E731
    phase = 0.5 * (1 + c) * hg(-1.0) + 0.5 * (1 - c) * hg(1.0)  # back lobe when c > 0
    tan_half = np.sqrt(np.maximum(0.0, (1.0 - cos_g) / (1.0 + cos_g)))
    b_s = 1.0 / (1.0 + tan_half / p["h_s"])
    y = tan_half / p["h_c"]
    one_minus_exp_over_y = np.where(y > 1e-8, -np.expm1(-y) / np.maximum(y, 1e-300), 1.0)
    b_c = (1.0 + one_minus_exp_over_y) / (2.0 * (1.0 + y) ** 2)
    r = w / (4 * np.pi) * mu0e / (mu0e + mue) * (phase * (1.0 + p["B_s0"] * b_s)
                                                 + hapke_h(mu0e, w) * hapke_h(mue, w) - 1.0) \
        * (1.0 + p["B_c0"] * b_c) * shadowing
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
                      "h_c": ParamSpec(1e-4, 1.0, True, 0.01),
                      "theta_bar": ParamSpec(*THETA_BAR_RANGE, False, 10.0)}),
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
    :func:`mitsuba_powder.fitting.optimise.multistart`); the Jacobian by central differences."""

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
    the package's optimiser (:func:`mitsuba_powder.fitting.optimise.multistart`: Sobol starts,
    batched Levenberg-Marquardt, the best ``polish`` end points refined by ``scipy``), Jacobian
    by central differences."""
    if model not in MODELS:
        raise ValueError(f"unknown model {model!r}; models: {', '.join(MODELS)}")
    check_range("starts", starts, 1)
    func, specs = MODELS[model]
    wi_all, wo_all = data.directions()
    weights = 1.0 / data.sigma if data.sigma is not None else np.ones(len(data))
    out = []
    for lam in data.wavelengths():
        t0 = time.perf_counter()
        sel = data.wavelength == lam
        check_determined(data.subset(sel).geometry_summary()["geometries"], len(specs),
                         f"the {model} fit at {lam:g} nm")
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
