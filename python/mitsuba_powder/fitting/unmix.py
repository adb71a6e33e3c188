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

from .. import _optics
from .._checks import check_each, check_range
from ..plugin import registry
from ..plugin.grains import GrainOptics, volume_fractions
from .optimise import (
    DEFAULT_STARTS,
    NLOPT_EVALUATIONS_PER_START,
    MultistartResult,
    check_search,
    multistart,
    nlopt_search,
    sobol_starts,
)
from .variables import FITTABLE

#: a fitted radius (um) stays within this factor of its start, and within the radii a
#: goniometric fit frees (:data:`~mitsuba_powder.fitting.variables.FITTABLE`, inside the
#: plugin's Mie range at 360-1000 nm)
RADIUS_FACTOR = 10.0
#: the amounts of populations 2..n relative to population 1 stay within [1/this, this]
AMOUNT_LIMIT = 1e6
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
        evaluations: model evaluations of the search (points, with or without derivatives);
            ``seconds``: its wall time; ``global_stage``: the search that found it.
        covariance: (n, n) covariance of the volume fractions (``fraction_errors`` is the
            square root of its diagonal).
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
    evaluations: int = 0
    seconds: float = 0.0
    global_stage: str = "sobol"
    covariance: np.ndarray | None = None


def _fractions(a: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(f (n,), d f / d a (n, n-1)) of the amounts ``a`` of populations 2..n."""
    s = 1.0 + float(np.sum(a))
    f = np.concatenate([[1.0], a]) / s
    g = np.zeros((len(f), len(a)))
    for k in range(len(a)):
        g[:, k] = -f / s
        g[k + 1, k] += 1.0 / s
    return f, g


def _check_inputs(wl: np.ndarray, rho: np.ndarray, sig: np.ndarray, parts: list) -> None:
    """The errors of :func:`unmix` about the number of populations and the spectra."""
    if not 2 <= len(parts) <= registry.MAX_POPULATIONS:
        raise ValueError(f"unmixing {len(parts)} populations; valid range is "
                         f"[2, {registry.MAX_POPULATIONS}]")
    if not (len(wl) == len(rho) == len(sig)):
        raise ValueError(f"wavelengths, albedo and sigma differ in length ({len(wl)}, "
                         f"{len(rho)}, {len(sig)})")
    at = [f" at {w:g} nm" for w in wl]
    check_each("sigma", sig, 0.0, math.inf, "()", at)
    check_each("the albedo", rho, 0.0, 1.0, "[]", at)


def _start_amounts(parts: list, by: str, free_radii: bool, wavelengths: int) -> np.ndarray:
    """The start log amounts of populations 2..n (a_j = exp(z_j) > 0); errors for an absent
    population 1 and too few wavelengths."""
    start = volume_fractions([(m, f) for m, f, _ in parts], by)
    if start[0] <= 0:
        raise ValueError(f"population 1 ({parts[0][0]}) needs a start fraction > 0")
    n = len(parts)
    free = (n - 1) + (n if free_radii else 0)
    if wavelengths <= free:
        raise ValueError(f"{wavelengths} wavelengths for {free} free variables: the fit is not "
                         "determined; give more wavelengths or fewer free variables")
    return np.log(np.maximum(np.array(start[1:]) / start[0], 1e-6))


@dataclass
class _Mixture:
    """The model of :func:`unmix`: albedo (W,) and its Jacobian in the variables z."""

    wl: np.ndarray
    indices: list
    r0: np.ndarray
    free_radii: bool

    def radii(self, z: np.ndarray) -> np.ndarray:
        return np.exp(z[len(self.r0) - 1:]) if self.free_radii else self.r0

    def __call__(self, z: np.ndarray, derivatives: bool = True
                 ) -> tuple[np.ndarray, np.ndarray | None]:
        n = len(self.r0)
        a = np.exp(z[:n - 1])
        radii = self.radii(z)
        f, g = _fractions(a)
        pops = [(float(radii[0]), None, self.indices[0])] + [
            (float(radii[j]), float(f[j]), self.indices[j]) for j in range(1, n)]
        values, d = _optics.mixture_albedo("sphere", list(map(float, self.wl)), pops,
                                           derivatives)
        if not derivatives:
            return np.asarray(values), None
        d = np.asarray(d)  # (W, [d r1, d r2, d f2, d r3, d f3, ...])
        d_f = d[:, [2 + 2 * (j - 1) for j in range(1, n)]]  # d rho / d f_j, f_1 = 1 - sum
        # the model's fractions f_j (j >= 2) depend on a; f_1 follows them
        jac = d_f @ (g[1:, :] * a[None, :])  # d / d z_k = d / d a_k * a_k
        if self.free_radii:
            d_r = d[:, [0] + [1 + 2 * (j - 1) for j in range(1, n)]] * radii[None, :]
            jac = np.concatenate([jac, d_r], axis=1)
        return np.asarray(values), jac


class _Residuals:
    """The weighted residuals ``(model(z) - rho) / sigma`` of :class:`_Mixture` and their
    Jacobian, batched over points (the :class:`~mitsuba_powder.fitting.optimise.BatchProblem`
    of the search; one model evaluation per distinct point: the optimiser pads a batch by
    repeating its last row, which is evaluated once). ``evaluations`` counts the points."""

    def __init__(self, model: _Mixture, rho: np.ndarray, sig: np.ndarray):
        self.model, self.rho, self.sig = model, rho, sig
        n = len(model.r0)
        self.lower = np.full(n - 1 + (n if model.free_radii else 0), -math.log(AMOUNT_LIMIT))
        self.upper = -self.lower
        if model.free_radii:
            fittable = FITTABLE["radius"]
            self.lower[n - 1:] = np.log(np.maximum(model.r0 / RADIUS_FACTOR, fittable.lower))
            self.upper[n - 1:] = np.log(np.minimum(model.r0 * RADIUS_FACTOR, fittable.upper))
        self.evaluations = 0

    def _distinct(self, y: np.ndarray) -> int:
        k = len(y)
        while k > 1 and np.array_equal(y[k - 2], y[-1]):
            k -= 1
        self.evaluations += k
        return k

    def residuals(self, y: np.ndarray) -> np.ndarray:
        k = self._distinct(y)
        r = np.array([(self.model(z, False)[0] - self.rho) / self.sig for z in y[:k]])
        return np.concatenate([r, np.repeat(r[-1:], len(y) - k, axis=0)])

    def jacobian(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        k = self._distinct(y)
        out = [self.model(z) for z in y[:k]]
        r = np.array([(v - self.rho) / self.sig for v, _ in out])
        j = np.array([jac / self.sig[:, None] for _, jac in out])
        return (np.concatenate([r, np.repeat(r[-1:], len(y) - k, axis=0)]),
                np.concatenate([j, np.repeat(j[-1:], len(y) - k, axis=0)]))


def _search(problem: _Residuals, z0: np.ndarray, global_stage: str, starts: int, seed: int,
            max_evaluations: int | None) -> MultistartResult:
    """The weighted least-squares variables by the global stage of
    :mod:`~mitsuba_powder.fitting.optimise`: ``sobol``, ``starts`` Sobol starts over the box
    (the ``--mix`` start first) with batched Levenberg-Marquardt; ``mlsl`` or ``crs2``, nlopt
    from the ``--mix`` start with ``max_evaluations`` model evaluations (default
    :data:`~mitsuba_powder.fitting.optimise.NLOPT_EVALUATIONS_PER_START` per start); then the
    polish."""
    z0 = np.clip(z0, problem.lower + 1e-9, problem.upper - 1e-9)
    if global_stage == "sobol":
        y0 = sobol_starts(problem.lower, problem.upper, starts, seed)
        y0[0] = z0
        return multistart(problem, y0, max_polish_evaluations=500)
    budget = NLOPT_EVALUATIONS_PER_START * starts if max_evaluations is None else max_evaluations
    return nlopt_search(problem, global_stage, budget, seed, start=z0,
                        max_polish_evaluations=500)


def _covariance(jw: np.ndarray, warnings: list[str]) -> np.ndarray:
    """``(J^T W J)^-1`` of the weighted Jacobian ``jw``; infinite (with a warning) when singular."""
    try:
        return np.linalg.inv(jw.T @ jw)
    except np.linalg.LinAlgError:
        warnings.append("the Jacobian is singular: the data cannot decide the fractions")
        return np.full((jw.shape[1], jw.shape[1]), np.inf)


def _undetermined(materials: list[str], f: np.ndarray, f_err: np.ndarray, cov_z: np.ndarray,
                  free_radii: bool) -> list[str]:
    """Warnings: fractions whose uncertainty exceeds them, variables correlated beyond
    :data:`CORRELATION_LIMIT`."""
    warnings = []
    for j in range(len(materials)):
        if not f_err[j] < max(f[j], 1e-3):
            warnings.append(f"the fraction of {materials[j]} ({f[j]:.3g} +/- {f_err[j]:.2g}) is "
                            "not determined by the data")
    d = np.sqrt(np.maximum(np.diag(cov_z), 1e-300))
    with np.errstate(over="ignore", invalid="ignore"):  # a singular direction: inf / inf
        corr = cov_z / np.outer(d, d)
    names = [f"fraction of {m}" for m in materials[1:]] + (
        [f"radius of {m}" for m in materials] if free_radii else [])
    for i in range(len(corr)):
        for k in range(i + 1, len(corr)):
            if abs(corr[i, k]) > CORRELATION_LIMIT:
                warnings.append(f"{names[i]} and {names[k]} are correlated ({corr[i, k]:+.3f}): "
                                "the data constrain a combination of them only")
    return warnings


def _mass_fractions(materials: list[str], f: np.ndarray) -> np.ndarray | None:
    """The volume fractions ``f`` by mass; None when a material has no density."""
    if not all(m in registry.DENSITIES for m in materials):
        return None
    w = f * np.array([registry.DENSITIES[m] for m in materials])
    return w / w.sum()


def _propagate(model: _Mixture, z: np.ndarray, cov_z: np.ndarray, n: int, free_radii: bool
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """The volume fractions of the variables ``z`` (log amounts, then log radii), their
    1-sigma and covariance propagated from ``cov_z``, the radii (um) and their 1-sigma (0
    where held)."""
    a = np.exp(z[:n - 1])
    f, g = _fractions(a)
    ga = g * a[None, :]  # d f / d z
    cov_f = ga @ cov_z[:n - 1, :n - 1] @ ga.T
    f_err = np.sqrt(np.maximum(np.diag(cov_f), 0.0))
    radii = model.radii(z)
    r_err = np.zeros(n)
    if free_radii:
        r_err = radii * np.sqrt(np.maximum(np.diag(cov_z)[n - 1:], 0.0))
    return f, f_err, cov_f, radii, r_err


def _log_start_radii(parts: list[tuple[str, float, float]]) -> np.ndarray:
    """The logarithms of the populations' start radii (um), each checked within the radii
    ``fit`` frees."""
    for material, _, radius in parts:
        check_range(f"the start radius of {material}", radius, FITTABLE["radius"].lower,
                    FITTABLE["radius"].upper, "[]", unit="um",
                    note="um (free radii: the radii fit frees)")
    return np.log([float(r) for _, _, r in parts])


def _search_warnings(search) -> list[str]:
    """A warning when fewer than two of the global stage's searches reached the best chi2."""
    if len(search.start_costs) > 1 and search.agreeing < 2:
        return [f"only {search.agreeing} of {len(search.start_costs)} searches reached the best "
                "chi2 (within 1 %): it may not be the global optimum; try more starts"]
    return []


def unmix(wavelengths_nm, albedo, sigma, parts: list[tuple[str, float, float]],
          free_radii: bool = False, by: str = "volume", global_stage: str = "sobol",
          starts: int = DEFAULT_STARTS, seed: int = 0, max_evaluations: int | None = None
          ) -> UnmixResult:
    """Fit the fractions of a mixture of known materials to an albedo spectrum.

    Args:
        wavelengths_nm: (W,) nm.
        albedo: (W,) measured single-scattering albedo; ``sigma``: (W,) its standard
            uncertainties (> 0).
        parts: ``(material, fraction, radius um)`` per population (two to four): the fractions
            are the start (by ``by``), the radii the fixed values (or the start, with
            ``free_radii``); population 1 (the first) must be present in the result.
        free_radii: fit the radii too (within a factor :data:`RADIUS_FACTOR` of the start
            and within the fittable radii, 0.003-3 um; a start outside them is an error).
        by: how the start fractions are given (``mass`` or ``volume``).
        global_stage: the search (:data:`~mitsuba_powder.fitting.optimise.GLOBAL_STAGES`):
            ``sobol`` (``starts`` Sobol starts, ``parts`` the first, batched
            Levenberg-Marquardt), ``mlsl`` or ``crs2`` (nlopt from ``parts``, then the same
            Levenberg-Marquardt steps); docs/fitting.md says which measured better.
        starts: Sobol starts (1: from ``parts`` only); with nlopt, the budget is
            ``max_evaluations`` or :data:`NLOPT_EVALUATIONS_PER_START` per start.
        seed: of the Sobol scrambling or of nlopt's random numbers.
        max_evaluations: the model evaluations of an nlopt stage (default
            :data:`NLOPT_EVALUATIONS_PER_START` x ``starts``), before its Levenberg-Marquardt
            steps and polish.

    Raises:
        ValueError: fewer than two populations or more than four, arrays of different lengths,
            a non-positive or non-finite sigma, an albedo outside [0, 1], fewer wavelengths
            than free variables, an unknown global stage or one without nlopt installed, starts
            or max_evaluations < 1, a seed outside [0, 2^32)
            (:func:`~mitsuba_powder.fitting.optimise.check_search`), or what
            :func:`volume_fractions` and the grain optics refuse.
    """
    check_search(global_stage, starts, seed)
    wl = np.atleast_1d(np.asarray(wavelengths_nm, dtype=float))
    rho = np.atleast_1d(np.asarray(albedo, dtype=float))
    sig = np.atleast_1d(np.asarray(sigma, dtype=float))
    _check_inputs(wl, rho, sig, parts)
    z0 = _start_amounts(parts, by, free_radii, len(wl))
    n = len(parts)
    indices = [[complex(m) for m in GrainOptics({"material": mat}).index(wl)]
               for mat, _, _ in parts]
    r0 = np.array([float(r) for _, _, r in parts])
    if free_radii:
        z0 = np.concatenate([z0, _log_start_radii(parts)])  # log amounts, then log radii
    model = _Mixture(wl, indices, r0, free_radii)
    problem = _Residuals(model, rho, sig)
    search = _search(problem, z0, global_stage, starts, seed, max_evaluations)
    z = search.y
    values, jac = model(z)
    res, warnings = (values - rho) / sig, []
    cov_z = _covariance(jac / sig[:, None], warnings)
    f, f_err, cov_f, radii, r_err = _propagate(model, z, cov_z, n, free_radii)
    materials = [m for m, _, _ in parts]
    warnings += _undetermined(materials, f, f_err, cov_z, free_radii) + _search_warnings(search)
    return UnmixResult(materials, f, f_err, _mass_fractions(materials, f), radii, r_err,
                       float(res @ res), len(wl) - len(z), values, warnings,
                       problem.evaluations, search.seconds, global_stage, cov_f)
