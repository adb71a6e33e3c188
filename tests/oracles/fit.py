"""Independent multi-start least-squares fit of docs/model.md's BRDF at one wavelength (test-only).

The reference the project's fitter (``mitsuba_powder.fitting.fit``) is judged against: it shares
no code with the product. The model is :func:`oracles.model.brdf` (NumPy float64, docs/model.md's
equations written independently of the C++ plugin), ``tau_o`` comes from the adaptive Fresnel
quadrature :func:`oracles.grains.tau_o_fresnel` (docs/model.md "Extrapolation ratio tau_o"), and
the optimiser is ``scipy.optimize.least_squares`` (trust-region reflective, finite-difference
Jacobian) polishing every point of a scrambled Sobol design over the (log-)bounds.

Free parameters (docs/model.md names): ``amplitude_volume`` A_v, ``g``, ``extinction`` kappa (1/um),
``albedo`` rho, ``amplitude_surface`` A_s' (um^2), ``correlation_length`` l_c (um); Harvey-Shack
specular lobe, infinite thickness. Bounds are those of
``mitsuba_powder.fitting.fit.FITTABLE`` (copied, not imported). Loss: plain sum of squares of BRF
residuals, ``sum((BRF_model - BRF)^2)`` with ``BRF = pi * BRDF``.

Units: angles in degrees, wavelengths in nm, lengths in micrometres, extinction in 1/micrometre.
"""

from __future__ import annotations

import math
import time
from dataclasses import replace

import numpy as np
from scipy.optimize import least_squares
from scipy.stats import qmc

from oracles.grains import tau_o_fresnel
from oracles.model import Params, brdf, gonio_directions

#: Free parameters in fit order: (lower, upper, optimised on a log10 scale). The same bounds as
#: the plugin fitter's ``FITTABLE`` (python/mitsuba_powder/fitting/fit.py).
BOUNDS: dict[str, tuple[float, float, bool]] = {
    "amplitude_volume": (0.05, 5.0, True),
    "g": (-0.95, 0.95, False),
    "extinction": (1e-3, 1e3, True),
    "albedo": (0.0, 1.0, False),
    "amplitude_surface": (1e-9, 0.1, True),
    "correlation_length": (1e-2, 1e2, True),
}
FREE = tuple(BOUNDS)

#: A start whose final loss is within this relative distance of the best "reached the best"
AGREE_RTOL = 0.01
#: ... or within this fraction of sum(brf^2) (noise-free data, where the best loss is ~1e-30)
AGREE_ATOL = 1e-12


def model_brf(theta_i, theta_o, phi, wavelength_nm: float, values: dict[str, float],
              tau_o: float) -> np.ndarray:
    """BRF = pi * BRDF of :func:`oracles.model.brdf` at gonio geometries (docs/model.md convention).

    Args:
        theta_i, theta_o, phi: incidence, signed viewing angle and azimuth (degrees), (N,).
        wavelength_nm: wavelength (nm).
        values: the six free parameters by name (:data:`FREE`).
        tau_o: extrapolation ratio.

    Returns:
        (N,) reflectance factors.
    """
    wi, wo = gonio_directions(theta_i, theta_o, phi)
    p = Params(amplitude_volume=values["amplitude_volume"], g=values["g"],
               extinction=values["extinction"], tau_o=tau_o, thickness=np.inf,
               amplitude_surface=values["amplitude_surface"],
               correlation_length=values["correlation_length"], specular="harvey_shack")
    return np.pi * brdf(wi, wo, np.float64(values["albedo"]), np.float64(wavelength_nm), p)[:, 0]


def _to_y(x: np.ndarray) -> np.ndarray:
    return np.array([math.log10(v) if BOUNDS[k][2] else v for k, v in zip(FREE, x)])


def _to_x(y: np.ndarray) -> np.ndarray:
    return np.array([10.0**v if BOUNDS[k][2] else v for k, v in zip(FREE, y)])


def _check_inputs(theta_i, theta_o, phi, wavelength_nm, brf, eta, starts, seed):
    arrays = {}
    for name, a in (("theta_i", theta_i), ("theta_o", theta_o), ("phi", phi), ("brf", brf)):
        a = np.asarray(a, dtype=np.float64)
        if a.ndim != 1 or a.size == 0:
            raise ValueError(f"{name} must be a non-empty 1-D array, got shape {a.shape}")
        bad = np.flatnonzero(~np.isfinite(a))
        if bad.size:
            raise ValueError(f"{name}[{bad[0]}] = {a[bad[0]]} is not finite")
        arrays[name] = a
    n = arrays["theta_i"].size
    for name, a in arrays.items():
        if a.size != n:
            raise ValueError(f"{name} has {a.size} values, theta_i has {n}")
    for name in ("theta_i", "theta_o"):
        a = arrays[name]
        bad = np.flatnonzero(np.abs(a) >= 90.0 if name == "theta_o" else (a < 0) | (a >= 90))
        if bad.size:
            raise ValueError(f"{name}[{bad[0]}] = {a[bad[0]]} deg is outside the valid range "
                             f"({'-90, 90' if name == 'theta_o' else '[0, 90'}) deg")
    lam = np.unique(np.asarray(wavelength_nm, dtype=np.float64))
    if lam.size != 1 or not (np.isfinite(lam[0]) and lam[0] > 0):
        raise ValueError(f"wavelength_nm must be one positive wavelength (the fit is at one "
                         f"wavelength), got {lam.tolist()[:5]}")
    if not (isinstance(starts, (int, np.integer)) and starts >= 1):
        raise ValueError(f"starts must be an integer >= 1, got {starts!r}")
    if not (isinstance(seed, (int, np.integer)) and seed >= 0):
        raise ValueError(f"seed must be an integer >= 0, got {seed!r}")
    if not (math.isfinite(eta) and eta >= 1.0):
        raise ValueError(f"eta (real refractive index) must be a finite number >= 1, got {eta}")
    return arrays, float(lam[0])


def reference_fit(theta_i, theta_o, phi, wavelength_nm, brf, eta: float = 1.35,
                  starts: int = 60, seed: int = 0, tol: float = 1e-10,
                  max_nfev: int = 1000) -> dict:
    """Multi-start least-squares fit of the six free parameters at one wavelength.

    Every point of a scrambled Sobol design (``starts`` points, ``seed``) over the bounds
    (log10 scale for A_v, kappa, A_s', l_c; linear for g and rho) is polished with
    ``scipy.optimize.least_squares`` (method ``trf``, bounds, forward-difference Jacobian,
    unit variable scale); the best start is then polished again with a central-difference
    Jacobian and tolerances of 1e-14. A start "reaches the best" when its loss is within
    1 % of the best loss (plus 1e-12 of ``sum(brf^2)``, so that exact fits of noise-free data
    count as agreeing).

    Args:
        theta_i, theta_o, phi: incidence, signed viewing angle and azimuth (degrees), (N,).
        wavelength_nm: the wavelength (nm): a number, or an (N,) array with one value.
        brf: measured reflectance factors (N,).
        eta: real refractive index of the grains (sets tau_o; k = 0).
        starts: number of starts (>= 1).
        seed: seed of the scrambled Sobol design.
        tol: ``ftol``, ``xtol`` and ``gtol`` of every start's polish.
        max_nfev: function evaluations per polish (excluding the Jacobian's); a start that
            crawls along a flat valley (e.g. A_s' -> 0, where l_c has no effect) stops there.

    Returns:
        dict with ``loss`` (best sum of squares, BRF^2), ``rmse`` (sqrt(loss / N)),
        ``parameters`` (name -> value), ``start_losses`` (every start's final loss, sorted),
        ``starts_within_1pct`` (starts that reached the best, above), ``seconds``,
        ``evaluations`` (model evaluations, Jacobians included), ``n`` (points), ``tau_o``,
        ``eta``, ``wavelength_nm``, ``starts``, ``seed``, ``best_start`` (its index),
        ``minima`` (the distinct end points, best first: loss, rmse, how many starts ended
        there (within 1e-6 relative), parameters of the best of them) and ``at_bound``
        (parameters within 1e-6 of a bound, in the optimised scale).

    Raises:
        ValueError: on arrays of different lengths, non-finite values, angles out of range,
            several wavelengths, ``starts`` < 1, a negative seed or ``eta`` < 1.
    """
    t0 = time.perf_counter()
    arrays, lam = _check_inputs(theta_i, theta_o, phi, wavelength_nm, brf, eta, starts, seed)
    tau_o = tau_o_fresnel(eta)
    wi, wo = gonio_directions(arrays["theta_i"], arrays["theta_o"], arrays["phi"])
    measured = arrays["brf"]
    base = Params(tau_o=tau_o, thickness=np.inf, specular="harvey_shack")
    lam64 = np.float64(lam)
    counter = [0]

    def residuals(y: np.ndarray) -> np.ndarray:
        counter[0] += 1
        x = _to_x(y)
        p = replace(base, amplitude_volume=x[0], g=x[1], extinction=x[2],
                    amplitude_surface=x[4], correlation_length=x[5])
        return np.pi * brdf(wi, wo, np.float64(x[3]), lam64, p)[:, 0] - measured

    lower = _to_y(np.array([BOUNDS[k][0] for k in FREE]))
    upper = _to_y(np.array([BOUNDS[k][1] for k in FREE]))
    m = max(0, math.ceil(math.log2(starts)))
    design = qmc.Sobol(d=len(FREE), scramble=True, seed=seed).random_base2(m)[:starts]
    y_starts = qmc.scale(design, lower, upper)

    losses, ys = [], []
    for y0 in y_starts:
        sol = least_squares(residuals, y0, jac="2-point", bounds=(lower, upper), method="trf",
                            x_scale=1.0, ftol=tol, xtol=tol, gtol=tol, max_nfev=max_nfev)
        losses.append(float(np.sum(sol.fun**2)))
        ys.append(sol.x)
    best = int(np.argmin(losses))
    # final polish of the best start with a central-difference Jacobian and tighter tolerances
    sol = least_squares(residuals, ys[best], jac="3-point", bounds=(lower, upper), method="trf",
                        x_scale=1.0, ftol=1e-14, xtol=1e-14, gtol=1e-14, max_nfev=max_nfev)
    if float(np.sum(sol.fun**2)) < losses[best]:
        losses[best], ys[best] = float(np.sum(sol.fun**2)), sol.x
    loss = losses[best]
    y_best = ys[best]
    agree = (1.0 + AGREE_RTOL) * loss + AGREE_ATOL * float(np.sum(measured**2))
    x_best = _to_x(y_best)
    # distinct end points: starts sorted by loss, grouped while within 1e-6 of the group's best
    minima: list[dict] = []
    for i in np.argsort(losses, kind="stable"):
        if minima and losses[i] <= (1.0 + 1e-6) * minima[-1]["loss"] + AGREE_ATOL * float(
                np.sum(measured**2)):
            minima[-1]["starts"] += 1
            continue
        minima.append({"loss": losses[i], "rmse": math.sqrt(losses[i] / measured.size),
                       "starts": 1, "parameters": {k: float(v) for k, v in
                                                   zip(FREE, _to_x(ys[i]))}})
    span = upper - lower
    at_bound = [k for k, y, lo, s in zip(FREE, y_best, lower, span)
                if min(y - lo, lo + s - y) <= 1e-6 * s]
    return {
        "loss": loss,
        "rmse": math.sqrt(loss / measured.size),
        "parameters": {k: float(v) for k, v in zip(FREE, x_best)},
        "start_losses": sorted(losses),
        "starts_within_1pct": int(np.sum(np.asarray(losses) <= agree)),
        "best_start": best,
        "minima": minima,
        "at_bound": at_bound,
        "seconds": time.perf_counter() - t0,
        "evaluations": counter[0],
        "n": int(measured.size),
        "tau_o": tau_o,
        "eta": float(eta),
        "wavelength_nm": lam,
        "starts": int(starts),
        "seed": int(seed),
    }
