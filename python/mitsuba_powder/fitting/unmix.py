"""Unmixing: the fractions (and, optionally, the radii) of a pigment mixture from a measured
single-scattering albedo spectrum (docs/fitting.md, "Unmixing").

The albedo spectrum is what a goniometric fit with the albedo free per wavelength gives
(:func:`mitsuba_powder.fitting.fit.fit`, with its uncertainties), or ``mitsuba-powder albedo``
from a reflectance. The model is the plugin's mixture rule (docs/model.md, "Several materials"),
through ``_optics.mixture_albedo`` with its analytic derivatives: the materials are given, the
volume fractions of the solid (and the radii, if freed) are fitted by weighted least squares.

The fractions are parametrised by amounts ``a_j >= 0`` of populations 2..n relative to
population 1, ``f_j = a_j / (1 + sum_k a_k)`` and ``f_1 = 1 / (1 + sum_k a_k)``: every point of
the search is a valid mixture (fractions in [0, 1] summing to 1) and population 1 is present.
Uncertainties: the covariance ``(J^T W J)^-1`` of the fitted variables, propagated to the
fractions through ``d f / d a``; warnings when the data cannot decide (a fraction whose
uncertainty exceeds it, or two variables correlated beyond 0.95).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np
from scipy.optimize import least_squares

from .. import _optics
from ..plugin import registry
from ..plugin.grains import GrainOptics, volume_fractions

#: a fitted radius (um) stays within this factor of its start
RADIUS_FACTOR = 10.0
#: correlation beyond which two variables are reported as not separately determined
CORRELATION_LIMIT = 0.95


@dataclass
class UnmixResult:
    """Outcome of :func:`unmix`.

    Attributes:
        materials: per population.
        fractions: volume fractions of the solid (sum 1); ``fraction_errors`` their standard
            uncertainties.
        mass_fractions: the same by mass (:data:`registry.DENSITIES`; None for a material
            without a density).
        radii: um (fitted or as given); ``radius_errors``: 0 where held.
        chi2: weighted sum of squared residuals; ``dof``: degrees of freedom.
        model: the fitted albedo per wavelength.
        warnings: what the data cannot decide.
    """

    materials: list[str]
    fractions: np.ndarray
    fraction_errors: np.ndarray
    mass_fractions: np.ndarray | None
    radii: np.ndarray
    radius_errors: np.ndarray
    chi2: float
    dof: int
    model: np.ndarray
    warnings: list[str] = field(default_factory=list)


def _fractions(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(f (n,), d f / d a (n, n-1)) of the amounts ``a`` of populations 2..n."""
    s = 1.0 + float(np.sum(a))
    f = np.concatenate([[1.0], a]) / s
    g = np.zeros((len(f), len(a)))
    for k in range(len(a)):
        g[:, k] = -f / s
        g[k + 1, k] += 1.0 / s
    return f, g


def unmix(wavelengths_nm, albedo, sigma, parts: list[tuple[str, float, float]],
          free_radii: bool = False, by: str = "volume") -> UnmixResult:
    """Fit the fractions of a mixture of known materials to an albedo spectrum.

    Args:
        wavelengths_nm: (W,) nm.
        albedo: (W,) measured single-scattering albedo; ``sigma``: (W,) its standard
            uncertainties (> 0).
        parts: ``(material, fraction, radius um)`` per population (two to four): the fractions
            are the start (by ``by``), the radii the fixed values (or the start, with
            ``free_radii``); population 1 (the first) must be present in the result.
        free_radii: fit the radii too (within a factor :data:`RADIUS_FACTOR` of the start).
        by: how the start fractions are given (``mass`` or ``volume``).

    Raises:
        ValueError: fewer than two populations or more than four, arrays of different lengths,
            a non-positive or non-finite sigma, an albedo outside [0, 1], fewer wavelengths
            than free variables, or what :func:`volume_fractions` and the grain optics refuse.
    """
    wl = np.atleast_1d(np.asarray(wavelengths_nm, dtype=float))
    rho = np.atleast_1d(np.asarray(albedo, dtype=float))
    sig = np.atleast_1d(np.asarray(sigma, dtype=float))
    if not 2 <= len(parts) <= registry.MAX_POPULATIONS:
        raise ValueError(f"unmixing {len(parts)} populations; valid range is "
                         f"[2, {registry.MAX_POPULATIONS}]")
    if not (len(wl) == len(rho) == len(sig)):
        raise ValueError(f"wavelengths, albedo and sigma differ in length ({len(wl)}, "
                         f"{len(rho)}, {len(sig)})")
    if not np.all(np.isfinite(sig) & (sig > 0)):
        raise ValueError("sigma must be finite and > 0 at every wavelength")
    if not np.all(np.isfinite(rho) & (rho >= 0) & (rho <= 1)):
        raise ValueError("the albedo must be in [0, 1] at every wavelength")
    start = volume_fractions([(m, f) for m, f, _ in parts], by)
    if start[0] <= 0:
        raise ValueError(f"population 1 ({parts[0][0]}) needs a start fraction > 0")
    n = len(parts)
    free = (n - 1) + (n if free_radii else 0)
    if len(wl) <= free:
        raise ValueError(f"{len(wl)} wavelengths for {free} free variables: the fit is not "
                         "determined; give more wavelengths or fewer free variables")
    indices = [[complex(m) for m in GrainOptics({"material": mat}).index(wl)]
               for mat, _, _ in parts]
    r0 = np.array([float(r) for _, _, r in parts])
    # variables: log amounts (a_j = exp(z_j), a_j > 0) then, with free_radii, log radii
    z0 = np.log(np.maximum(np.array(start[1:]) / start[0], 1e-6))
    if free_radii:
        z0 = np.concatenate([z0, np.log(r0)])

    def model(z):
        a = np.exp(z[:n - 1])
        radii = np.exp(z[n - 1:]) if free_radii else r0
        f, g = _fractions(a)
        pops = [(float(radii[0]), None, indices[0])] + [
            (float(radii[j]), float(f[j]), indices[j]) for j in range(1, n)]
        values, d = _optics.mixture_albedo("sphere", list(map(float, wl)), pops, True)
        d = np.asarray(d)  # (W, [d r1, d r2, d f2, d r3, d f3, ...])
        d_f = d[:, [2 + 2 * (j - 1) for j in range(1, n)]]  # d rho / d f_j, f_1 = 1 - sum
        # the model's fractions f_j (j >= 2) depend on a; f_1 follows them
        jac = d_f @ (g[1:, :] * a[None, :])  # d / d z_k = d / d a_k * a_k
        if free_radii:
            d_r = d[:, [0] + [1 + 2 * (j - 1) for j in range(1, n)]] * radii[None, :]
            jac = np.concatenate([jac, d_r], axis=1)
        return np.asarray(values), jac

    def residuals(z):
        return (model(z)[0] - rho) / sig

    def jacobian(z):
        return model(z)[1] / sig[:, None]

    lo = np.full(len(z0), -math.log(1e6))
    hi = np.full(len(z0), math.log(1e6))
    if free_radii:
        lo[n - 1:] = np.log(r0 / RADIUS_FACTOR)
        hi[n - 1:] = np.log(r0 * RADIUS_FACTOR)
    z0 = np.clip(z0, lo + 1e-9, hi - 1e-9)
    sol = least_squares(residuals, z0, jac=jacobian, bounds=(lo, hi), method="trf",
                        x_scale="jac", ftol=1e-12, xtol=1e-12, gtol=1e-12, max_nfev=500)
    z = sol.x
    values, jac = model(z)
    res = (values - rho) / sig
    jw = jac / sig[:, None]
    warnings: list[str] = []
    try:
        cov_z = np.linalg.inv(jw.T @ jw)
    except np.linalg.LinAlgError:
        cov_z = np.full((len(z), len(z)), np.inf)
        warnings.append("the Jacobian is singular: the data cannot decide the fractions")
    a = np.exp(z[:n - 1])
    f, g = _fractions(a)
    ga = g * a[None, :]  # d f / d z
    cov_f = ga @ cov_z[:n - 1, :n - 1] @ ga.T
    f_err = np.sqrt(np.maximum(np.diag(cov_f), 0.0))
    radii = np.exp(z[n - 1:]) if free_radii else r0
    r_err = np.zeros(n)
    if free_radii:
        r_err = radii * np.sqrt(np.maximum(np.diag(cov_z)[n - 1:], 0.0))
    materials = [m for m, _, _ in parts]
    for j in range(n):
        if not f_err[j] < max(f[j], 1e-3):
            warnings.append(f"the fraction of {materials[j]} ({f[j]:.3g} +/- {f_err[j]:.2g}) is "
                            "not determined by the data")
    d = np.sqrt(np.maximum(np.diag(cov_z), 1e-300))
    corr = cov_z / np.outer(d, d)
    names = [f"fraction of {m}" for m in materials[1:]] + (
        [f"radius of {m}" for m in materials] if free_radii else [])
    for i in range(len(z)):
        for k in range(i + 1, len(z)):
            if abs(corr[i, k]) > CORRELATION_LIMIT:
                warnings.append(f"{names[i]} and {names[k]} are correlated ({corr[i, k]:+.3f}): "
                                "the data constrain a combination of them only")
    mass = None
    if all(m in registry.DENSITIES for m in materials):
        w = f * np.array([registry.DENSITIES[m] for m in materials])
        mass = w / w.sum()
    return UnmixResult(materials, f, f_err, mass, radii, r_err, float(res @ res),
                       len(wl) - len(z), values, warnings)
