"""Fit the powder plugin's parameters to goniometric BRF measurements.

The loss is the weighted sum of squares ``sum_i ((BRF_model_i - BRF_i) / sigma_i)^2`` (sigma = 1
when the data carry none), accumulated in float64; every row counts, replicated geometries
included. The model is the C++ plugin: :class:`~mitsuba_powder.plugin.brf.BatchBRF` evaluates it at
every geometry and wavelength for a whole batch of parameter sets in one Dr.Jit launch, and its
Jacobian by forward-mode AD (one pass per property over the same traced graph). The grains'
albedo comes from the plugin's Mie theory (:mod:`~mitsuba_powder.plugin.grains`), with its
radius derivatives.

The problem (:class:`~mitsuba_powder.fitting.problem.Problem`, its variables in
:mod:`mitsuba_powder.fitting.variables`) is what the optimiser minimises; this module runs the
fit and reads the result.

Strategy (:mod:`mitsuba_powder.fitting.optimise`): a scrambled Sobol design of starts over the
(log-)bounds; with the radius free, the radius of the starts runs over a log grid of the whole
range (rho(r) from Mie theory has several branches) and is held during the global phase; all
starts take batched Levenberg-Marquardt steps at once; the best few distinct end points are
polished with ``scipy.optimize.least_squares`` (trust region, bounds, the Jacobian) with every
variable free. The result says how many starts reached the best loss within 1 %.

Default free properties: with several wavelengths the paper's six (``amplitude_volume``, ``g``,
``extinction``, ``radius``, ``amplitude_surface``, ``correlation_length``), the radius shared by
all wavelengths through Mie theory. With one wavelength the radius is not determined (the BRF
depends on it only through rho(r), which several radii share), so ``albedo`` is fitted instead
and the radii whose Mie albedo gives the fitted rho are reported (all branches).

Uncertainties come from the Jacobian of the weighted residuals at the optimum:
``C = s^2 (J^T J)^-1``, with ``s^2 = chi^2 / (N - p)`` when the data carry no sigma and
``s^2 = 1`` when they do. The result warns about parameters at a bound, parameters whose
1-sigma exceeds their value, nearly degenerate pairs, fewer than two agreeing starts, and a
chi2/N far from 1.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from .._checks import check_range
from ..io.measurements import Measurements
from ..plugin import registry
from ..plugin.brf import VARIANT, PowderBRF, batch_variant
from ..plugin.grains import GRAIN_VARIABLES, GrainOptics
from ..variants import use_variant
from .optimise import (
    AGREEMENT,
    DEFAULT_STARTS,
    NLOPT_EVALUATIONS_PER_START,
    MultistartResult,
    check_determined,
    check_search,
    multistart,
    nlopt_search,
    sobol_starts,
)
from .problem import DEFAULT_RADIUS, GRAIN_SETTINGS, Problem
from .variables import EBS_KAPPA_OVER_K0, FITTABLE, REGIMES

__all__ = [
    "DEFAULT_FREE",
    "DEFAULT_FREE_ONE_WAVELENGTH",
    "DEFAULT_POLISH",
    "DEFAULT_RADIUS",
    "DEFAULT_STARTS",
    "EBS_KAPPA_OVER_K0",
    "FITTABLE",
    "GRAIN_SETTINGS",
    "REGIMES",
    "FitResult",
    "Problem",
    "default_free",
    "fit",
    "predict",
    "radius_branches",
]

#: Radii of the log grid the global phase holds the radius at (every Mie branch is tried)
PROFILE_RADII = 32

#: Distinct end points of the global phase polished (its starts: optimise.DEFAULT_STARTS)
DEFAULT_POLISH = 4

#: The paper's six (Table 1, with the effective radius): the default for several wavelengths
DEFAULT_FREE = ["amplitude_volume", "g", "extinction", "radius", "amplitude_surface",
                "correlation_length"]

#: One wavelength: the albedo instead of the radius, which rho(r) does not determine
DEFAULT_FREE_ONE_WAVELENGTH = ["amplitude_volume", "g", "extinction", "albedo",
                               "amplitude_surface", "correlation_length"]

#: A parameter this close to a bound (fraction of its search range) is "at the bound"
AT_BOUND = 1e-3

#: |correlation| above which two parameters are reported as nearly degenerate
DEGENERATE = 0.99


def default_free(data: Measurements, fixed: dict | None = None) -> list[str]:
    """The default free properties for ``data`` (see :data:`DEFAULT_FREE`), less those given in
    ``fixed``; at one wavelength with the grains or the albedo given, the albedo is not fitted
    (it comes from them)."""
    fixed = fixed or {}
    if len(data.wavelengths()) > 1:
        size = registry.grain_size(fixed.get("grains", registry.DEFAULTS["grains"]))
        return [size if n == "radius" else n for n in DEFAULT_FREE
                if (size if n == "radius" else n) not in fixed]
    given = any(k in fixed for k in GRAIN_VARIABLES + GRAIN_SETTINGS + ("albedo",))
    return [n for n in DEFAULT_FREE_ONE_WAVELENGTH
            if n not in fixed and not (n == "albedo" and given)]


@dataclass
class FitResult:
    """Outcome of :func:`fit`.

    Attributes:
        parameters: plugin property -> fitted or fixed value (single wavelength: loadable with
            ``mi.load_dict({'type': 'powder', **parameters})``). With several wavelengths and a
            free albedo, ``albedo`` is an ``irregular`` spectrum dict.
        parameters_by_wavelength: wavelength (nm) -> flat property dict for a mono variant.
        uncertainties: free property (``albedo@<nm>`` per wavelength) -> 1-sigma uncertainty
            (``inf`` where the data do not determine it).
        free: the free properties.
        model_brf: fitted BRF at every measured geometry (the plugin with ``parameters``).
        loss: weighted sum of squares at the optimum.
        evaluations: batch evaluations of the global phase plus evaluations of the polish.
        seconds: wall-clock time.
        starts: final loss of every start.
        agreeing: starts whose loss is within 1 % of the best.
        correlation: (names, matrix) of the free variables.
        warnings: what the data cannot decide (parameters at a bound, undetermined, degenerate,
            too few agreeing starts, chi2/N far from 1).
        chi2_per_point: loss / N when the data carry sigma, else None.
        radius_branches: one wavelength with a free albedo: per branch of rho(r), the radius
            (um) whose Mie albedo equals the fitted one and the interval of radii within
            1-sigma (:func:`radius_branches`).
        optics: the grain material, ``eta``/``k`` or ``tau_o`` in use, and tau_o per wavelength.
        stages: a line per stage of the optimisation.
        regime: the regime (``ebs`` or ``free``), the extinction limit it set, and kappa / k0
            at each wavelength with the fitted extinction.
    """

    parameters: dict
    parameters_by_wavelength: dict
    uncertainties: dict
    free: list[str]
    data: Measurements
    model_brf: np.ndarray
    loss: float
    evaluations: int
    seconds: float
    starts: list[float] = field(default_factory=list)
    agreeing: int = 0
    correlation: tuple[list[str], np.ndarray] | None = None
    warnings: list[str] = field(default_factory=list)
    chi2_per_point: float | None = None
    radius_branches: list[dict] = field(default_factory=list)
    optics: dict = field(default_factory=dict)
    stages: list[str] = field(default_factory=list)
    regime: dict = field(default_factory=dict)

    def residuals(self) -> np.ndarray:
        return self.model_brf - self.data.brf

    def rmse(self, mask: np.ndarray | None = None) -> float:
        r = self.residuals() if mask is None else self.residuals()[mask]
        return float(np.sqrt(np.mean(r**2)))

    def relative_rmse_percent(self, mask: np.ndarray | None = None) -> float:
        """100 * RMS of (model - measured) / measured."""
        rel = self.residuals() / self.data.brf
        rel = rel if mask is None else rel[mask]
        return float(100.0 * np.sqrt(np.mean(rel**2)))


def _starts(problem: Problem, count: int, seed: int) -> np.ndarray:
    """Sobol starts (the default start first); with the radius (or the agglomerate radius)
    free, it runs over a log grid of its whole range (:data:`PROFILE_RADII` values, each with
    the same number of starts): every branch of rho(r) is tried."""
    y0 = sobol_starts(problem.lower, problem.upper, count, seed)
    size = next((n for n in registry.GRAIN_SIZES if n in problem.free), None)
    if size is not None:
        j = problem.index(size)
        spec = FITTABLE[size]
        grid = np.linspace(spec.to_y(spec.lower), spec.to_y(spec.upper),
                           min(PROFILE_RADII, count))
        y0[:, j] = grid[np.arange(count) % len(grid)]
    y0[0] = problem.start()  # the default start, its radius included
    return y0


def _uncertainties(problem: Problem, y: np.ndarray, chi2: float
                   ) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """1-sigma per variable, correlation matrix and the names of undetermined variables."""
    x = problem.x_of(y)[0]
    _, jac_y = problem.jacobian(y[None])
    dxdy = np.array([s.dx_dy(v) for s, v in zip(problem.specs, x)])
    jac = jac_y[0] / np.where(dxdy != 0, dxdy, 1.0)[None, :]
    n, p = jac.shape
    s2 = 1.0 if problem.data.sigma is not None else chi2 / max(1, n - p)
    scale = np.linalg.norm(jac, axis=0)
    scale = np.where(scale > 0, scale, 1.0)
    js = jac / scale
    u, sv, vt = np.linalg.svd(js, full_matrices=False)
    tiny = sv < 1e-9 * sv[0] if sv.size and sv[0] > 0 else np.ones_like(sv, dtype=bool)
    inv = np.where(tiny, 0.0, 1.0 / np.where(tiny, 1.0, sv) ** 2)
    cov = s2 * (vt.T * inv) @ vt / np.outer(scale, scale)
    err = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    # directions of (near) zero singular value: their parameters are not determined
    undetermined = set()
    for k in np.nonzero(tiny)[0]:
        for j in np.nonzero(np.abs(vt[k]) > 0.1)[0]:
            undetermined.add(int(j))
    err[list(undetermined)] = np.inf
    with np.errstate(invalid="ignore", divide="ignore"):
        corr = cov / np.outer(err, err)
    corr[~np.isfinite(corr)] = np.nan
    np.fill_diagonal(corr, 1.0)
    return err, corr, [f"{problem.names[j][0]}" + (f"@{problem.names[j][1]:g}"
                                                   if problem.names[j][1] is not None else "")
                       for j in sorted(undetermined)]


def _label(name: str, lam: float | None) -> str:
    return name if lam is None else f"{name}@{lam:g}"


def _diagnose(problem: Problem, y: np.ndarray, err: np.ndarray, corr: np.ndarray,
              undetermined: list[str], agreeing: int, chi2_per_point: float | None
              ) -> list[str]:
    """Warnings: what the data cannot decide."""
    x = problem.x_of(y)[0]
    labels = [_label(n, w) for n, w in problem.names]
    out = []
    for j, (label, spec) in enumerate(zip(labels, problem.specs)):
        span = problem.upper[j] - problem.lower[j]
        ebs_bound = (label == "extinction" and problem.regime == "ebs" and
                     spec.upper == problem.extinction_limit)
        if y[j] - problem.lower[j] <= AT_BOUND * span:
            out.append(f"{label} = {x[j]:.4g} is at its lower bound {spec.lower:g}")
        elif problem.upper[j] - y[j] <= AT_BOUND * span and ebs_bound:
            out.append(f"extinction = {x[j]:.4g} /um sits on the bound of the EBS regime "
                       f"(kappa/k0 <= {EBS_KAPPA_OVER_K0:g} at "
                       f"{float(np.max(problem.wavelengths)):g} nm): the data pull the cone "
                       "broader than enhanced back-scattering theory describes (--regime free "
                       "lifts the bound)")
        elif problem.upper[j] - y[j] <= AT_BOUND * span:
            out.append(f"{label} = {x[j]:.4g} is at its upper bound {spec.upper:g}")
    kappa = problem.fixed.get("extinction")
    if isinstance(kappa, (int, float)) and kappa > problem.extinction_limit * (1 + 1e-9):
        out.append(f"extinction = {kappa:g} /um (fixed) is outside the EBS regime: kappa/k0 = "
                   f"{kappa * 1e-3 * float(np.max(problem.wavelengths)) / (2 * math.pi):.3g}"
                   f" > {EBS_KAPPA_OVER_K0:g} at {float(np.max(problem.wavelengths)):g} nm")
    for label in undetermined:
        out.append(f"{label} is not determined by the data (the Jacobian is singular in its "
                   "direction)")
    for j, label in enumerate(labels):
        if label not in undetermined and np.isfinite(err[j]) and err[j] > abs(x[j]):
            out.append(f"{label} = {x[j]:.4g} +- {err[j]:.3g}: its 1-sigma exceeds its value")
    p = len(labels)
    for a in range(p):
        for b in range(a + 1, p):
            if np.isfinite(corr[a, b]) and abs(corr[a, b]) > DEGENERATE:
                out.append(f"{labels[a]} and {labels[b]} are nearly degenerate "
                           f"(correlation {corr[a, b]:+.4f})")
    if agreeing < 2:
        out.append(f"only {agreeing} start reached the best loss (within "
                   f"{100 * AGREEMENT:g} %): the optimum may not be the global one; try more "
                   "starts")
    if chi2_per_point is not None and not 0.5 <= chi2_per_point <= 2.0:
        out.append(f"chi2/N = {chi2_per_point:.3g}: the model and the data's sigma disagree "
                   "(expected about 1)")
    return out


def _optics(problem: Problem) -> dict:
    """The grain material (or eta/k, or tau_o) in use, and tau_o per wavelength."""
    fixed = problem.fixed
    if "tau_o" in problem.free:
        source = "tau_o fitted"
    elif "tau_o" in fixed:
        source = f"tau_o = {fixed['tau_o']} (given)"
    elif "eta" in fixed or "k" in fixed:
        source = f"eta = {fixed.get('eta')}, k = {fixed.get('k')}"
    elif "material" in fixed:
        source = f"material {fixed['material']}"
    else:
        source = "material hematite (the plugin's default)"
    out: dict = {"source": source}
    out["material"] = problem.grains.source
    if problem.tau_o is not None:
        out["tau_o"] = {f"{w:g}": float(t) for w, t in zip(problem.wavelengths,
                                                           problem.tau_o)}
    default = not any(k in fixed or k in problem.free for k in ("material", "eta", "k",
                                                                "tau_o"))
    material = registry.DEFAULTS["material"]
    if default and material not in " ".join(problem.data.comments).lower():
        out["notice"] = (f"the grain material is the default, {material}: it sets tau_o (and "
                         "the albedo when the radius is used); if the sample is not hematite, "
                         "give material=..., eta=... and k=..., or tau_o=...")
    return out


def radius_branches(wavelength: float, albedo: float, albedo_sigma: float, fixed: dict,
                    grid: int = 800) -> tuple[list[dict], str | None]:
    """The radii (um) whose Mie albedo at ``wavelength`` (nm) is compatible with a fitted
    ``albedo`` +- ``albedo_sigma``: one entry per branch of rho(r) over the fittable radius range.

    Each entry gives ``radius`` (where rho(r) equals the albedo, or comes closest), and
    ``lower``/``upper``: the interval of radii around it whose albedo lies within 1-sigma (for a
    steep branch ``radius +- sigma_albedo / |d rho / d r|``; where rho(r) flattens, e.g. for
    large grains, the whole plateau).

    Returns:
        (branches, note): note explains an empty list (albedo out of the reachable range).
    """
    from scipy.optimize import brentq

    spec = FITTABLE["radius"]
    optics = GrainOptics(fixed)
    lam = np.array([wavelength])
    radii = np.geomspace(spec.lower, spec.upper, grid)
    rho = optics.albedo(lam, radii)[0][:, 0]
    sigma = max(float(albedo_sigma), 0.0) if np.isfinite(albedo_sigma) else 0.0
    diff = rho - albedo
    intervals = []
    for k in np.nonzero(np.sign(diff[:-1]) * np.sign(diff[1:]) < 0)[0]:
        f = lambda r: float(optics.albedo(lam, np.array([r]))[0][0, 0]) - albedo  # noqa: E731
        root = brentq(f, radii[k], radii[k + 1], xtol=1e-9 * radii[k])
        slope = float(optics.albedo(lam, np.array([root]), derivatives=True)[1][0, 0, 0])
        half = sigma / abs(slope) if slope != 0 else 0.0
        intervals.append([max(root - half, spec.lower), min(root + half, spec.upper), root])
    inside = np.abs(diff) <= sigma
    edges = np.diff(np.concatenate([[0], inside.astype(int), [0]]))
    for start, stop in zip(np.nonzero(edges == 1)[0], np.nonzero(edges == -1)[0]):
        best = start + int(np.argmin(np.abs(diff[start:stop])))
        intervals.append([radii[start], radii[stop - 1], None, radii[best]])
    intervals.sort(key=lambda iv: iv[0])
    merged: list[list] = []
    for iv in intervals:
        if merged and iv[0] <= merged[-1][1] * (1.0 + 1e-9):
            last = merged[-1]
            last[1] = max(last[1], iv[1])
            last[2] = last[2] if last[2] is not None else iv[2]
            if len(iv) > 3 and len(last) < 4:
                last.append(iv[3])
        else:
            merged.append(list(iv))
    branches = []
    for iv in merged:
        radius = iv[2] if iv[2] is not None else iv[3]
        branches.append({"radius": float(radius), "lower": float(iv[0]), "upper": float(iv[1]),
                         "exact": iv[2] is not None})
    note = None
    if not branches:
        note = (f"no radius in [{spec.lower:g}, {spec.upper:g}] um gives albedo "
                f"{albedo:.5g} at {wavelength:g} nm (reachable range [{rho.min():.5g}, "
                f"{rho.max():.5g}])")
    return branches, note


def fit(data: Measurements, free: list[str] | None = None, fixed: dict | None = None,
        starts: int = DEFAULT_STARTS, polish: int = DEFAULT_POLISH, seed: int = 0,
        max_iterations: int = 60, progress: Callable[[str], None] | None = None,
        regime: str = "ebs", global_stage: str = "sobol") -> FitResult:
    """Fit the plugin to ``data``.

    Args:
        data: measurements (one or several wavelengths; replicated rows each count).
        free: plugin properties to fit (default: :func:`default_free`).
        fixed: other plugin properties, held fixed (e.g. ``{"material": "magnetite"}``,
            ``{"eta": 1.35, "k": 0.0}``, ``{"tau_o": 0.6667}``).
        starts: starts of the global phase (Sobol design; the radius on a log grid).
        polish: distinct end points of the global phase polished with every variable free.
        seed: seed of the design's scrambling.
        max_iterations: Levenberg-Marquardt iterations of the global phase.
        progress: called with a line of text after each stage.
        regime: ``"ebs"`` bounds the extinction so that kappa / k0 <= 0.25 at every fitted
            wavelength (the narrow-cone regime of enhanced back-scattering theory; a fit on
            that bound says so), ``"free"`` keeps the full range.
        global_stage: ``"sobol"`` (the strategy above) or nlopt's ``"mlsl"`` or ``"crs2"``
            over every free variable with
            :data:`~mitsuba_powder.fitting.optimise.NLOPT_EVALUATIONS_PER_START` single-point
            evaluations per start, then the same Levenberg-Marquardt steps and polish
            (:func:`~mitsuba_powder.fitting.optimise.nlopt_search`; docs/fitting.md).

    Raises:
        ValueError: unknown, repeated or inconsistent parameter names; starts or polish < 1;
            a seed outside [0, 2^32); an unknown regime or global stage, or ``mlsl`` or
            ``crs2`` without nlopt installed
            (:func:`~mitsuba_powder.fitting.optimise.check_search`).
    """
    check_search(global_stage, starts, seed)
    check_range("polish", polish, 1)
    if len(data) == 0:
        raise ValueError("no measurements to fit")
    if not np.any(data.brf > 0):
        raise ValueError(f"{data.source or 'the data'}: every BRF value is 0: a powder that "
                         "reflects nothing has no parameters to fit (check the file's brf "
                         "column)")
    # once for the whole fit: switching variants is slow
    with use_variant(batch_variant(data.wavelength)):
        return _fit(data, list(free or default_free(data, fixed)), dict(fixed or {}), starts,
                    polish, seed, max_iterations, progress, regime, global_stage)


def _search(problem: Problem, global_stage: str, starts: int, polish_count: int, seed: int,
            max_iterations: int, progress: Callable[[str], None] | None) -> MultistartResult:
    """The global stage and the polish: Sobol starts (:func:`_starts`) with the grains held in
    the batched phase, or nlopt's MLSL or CRS2 from the default start over every variable."""
    if global_stage != "sobol":
        return nlopt_search(problem, global_stage, NLOPT_EVALUATIONS_PER_START * starts, seed,
                            problem.start(), polish_count, max_iterations, progress=progress)
    y0 = _starts(problem, starts, seed)
    hold = problem.hold_grains()
    problem.grain_derivatives = False  # the grains are held during the global phase
    return multistart(
        problem, y0, polish_count, hold if hold.any() else None, max_iterations,
        refine_count=max(16, starts // 4), progress=progress,
        before_free=lambda: setattr(problem, "grain_derivatives", True))


def _fit(data, free, fixed, starts, polish_count, seed, max_iterations, progress, regime,
         global_stage) -> FitResult:
    t0 = time.perf_counter()
    problem = Problem(data, free, fixed, regime)
    check_determined(data.geometry_summary()["geometries"], len(problem.names),
                     f"the fit of {data.source or 'the data'}")
    optics = _optics(problem)
    if progress:
        progress(f"optics: {optics['source']}" + (
            f"; tau_o {min(optics['tau_o'].values()):.4g}-{max(optics['tau_o'].values()):.4g}"
            if "tau_o" in optics else ""))
        if "notice" in optics:
            progress(f"notice: {optics['notice']}")
    result = _search(problem, global_stage, starts, polish_count, seed, max_iterations,
                     progress)
    y = result.y
    x = problem.x_of(y)[0]

    by_wavelength = {float(lam): problem.properties(x, float(lam))
                     for lam in problem.wavelengths}
    parameters = dict(by_wavelength[float(problem.wavelengths[0])])
    if any(w is not None for _, w in problem.names):
        albedo = [(w, float(x[j])) for j, (_, w) in enumerate(problem.names) if w is not None]
        parameters["albedo"] = {"type": "irregular",
                                "wavelengths": ", ".join(f"{w:g}" for w, _ in albedo),
                                "values": ", ".join(f"{v:.8g}" for _, v in albedo)}
    residual = problem.residuals(y[None])[0]
    model_brf = data.brf + residual / problem.weights
    chi2 = float(np.sum(residual**2))
    err, corr, undetermined = _uncertainties(problem, y, chi2)
    uncertainties = {_label(n, w): float(err[j]) for j, (n, w) in enumerate(problem.names)}
    chi2_per_point = chi2 / len(data) if data.sigma is not None else None
    warnings = _diagnose(problem, y, err, corr, undetermined, result.agreeing, chi2_per_point)
    branches = []
    if len(problem.wavelengths) == 1 and "albedo" in problem.free:
        lam = float(problem.wavelengths[0])
        branches, note = radius_branches(lam, float(parameters["albedo"]),
                                         uncertainties["albedo"], fixed)
        if note:
            optics["radius_note"] = note
    regime_info = {"name": regime, "kappa_over_k0_max": EBS_KAPPA_OVER_K0 if regime == "ebs"
                   else None, "extinction_limit": problem.extinction_limit
                   if regime == "ebs" else None,
                   "kappa_over_k0": _kappa_over_k0(parameters.get("extinction", 1.0),
                                                   problem.wavelengths)}
    _check_finite(parameters, model_brf, chi2, data)
    return FitResult(parameters, by_wavelength, uncertainties, problem.free, data, model_brf,
                     chi2, problem.evaluations, time.perf_counter() - t0,
                     [float(c) for c in result.start_costs], result.agreeing,
                     ([_label(n, w) for n, w in problem.names], corr), warnings,
                     chi2_per_point, branches, optics, result.stages, regime_info)


def _check_finite(parameters: dict, model_brf: np.ndarray, chi2: float,
                  data: Measurements) -> None:
    """Raise instead of returning a fit whose parameters, model or loss are not finite
    (naming what and, for the model, the first row)."""
    bad = [k for k, v in parameters.items()
           if isinstance(v, float) and not math.isfinite(v) and k != "thickness"]
    if bad:
        raise RuntimeError(f"the fit of {data.source or 'the data'} ended with non-finite "
                           f"parameters {bad}; nothing was written")
    rows = np.nonzero(~np.isfinite(model_brf))[0]
    if rows.size or not math.isfinite(chi2):
        where = (f"at row {int(rows[0])} (theta_i {data.theta_i[rows[0]]:g}, theta_o "
                 f"{data.theta_o[rows[0]]:g}, phi {data.phi[rows[0]]:g})" if rows.size else "")
        raise RuntimeError(f"the fit of {data.source or 'the data'} ended with a non-finite "
                           f"model BRF {where}; nothing was written")


def _kappa_over_k0(extinction: float, wavelengths: np.ndarray) -> dict[str, float]:
    """kappa / k0 (k0 = 2 pi / lambda) at each wavelength (nm)."""
    return {f"{w:g}": float(extinction) * 1e-3 * float(w) / (2.0 * math.pi)
            for w in wavelengths}


def _predict_rows(by_wavelength: dict, data: Measurements) -> np.ndarray:
    out = np.empty(len(data))
    for lam in data.wavelengths():
        props = by_wavelength.get(float(lam))
        if props is None:
            raise ValueError(f"wavelength {lam:g} nm was not fitted; fitted: "
                             f"{sorted(by_wavelength)}")
        sel = data.wavelength == lam
        out[sel] = PowderBRF(data.subset(sel), props).brf()
    return out


def predict(result: FitResult, data: Measurements) -> np.ndarray:
    """BRF of the fitted material at other geometries (each wavelength with its parameters).

    Raises:
        ValueError: ``data`` has a wavelength the fit did not cover.
    """
    with use_variant(VARIANT):
        return _predict_rows(result.parameters_by_wavelength, data)
