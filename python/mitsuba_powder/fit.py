"""Fit the powder plugin's parameters to goniometric BRF measurements.

Weighted least squares on the BRF, ``sum_i ((BRF_model_i - BRF_i) / sigma_i)^2`` (sigma = 1 when
the data have none), evaluated by the C++ plugin at all geometries of a wavelength in one
vectorised Dr.Jit call, with gradients from ``dr.backward`` through ``mi.traverse`` parameters.
nlopt's L-BFGS with bounds runs from the default start, and from the results of global searches
(ISRES, derivative free, from random points of the bounds; log-uniform for positive scale
parameters); the best optimum wins.
Uncertainties come from the Jacobian of the weighted residuals at the optimum (forward-mode
AD): ``C = s^2 (J^T J)^-1``, with ``s^2 = chi^2 / (N - p)`` when the data carry no sigma and
``s^2 = 1`` when they do.

Several wavelengths are fitted jointly: every parameter is shared (the grains' radius sets the
wavelength dependence through Mie theory) except ``albedo`` when it is free, which is fitted
per wavelength.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .measurements import Measurements
from .model import PowderBRF, variant


@dataclass(frozen=True)
class ParamSpec:
    """Bounds (plugin units), scale of the search and default start of a fittable property."""

    lower: float
    upper: float
    log: bool
    start: float


FITTABLE: dict[str, ParamSpec] = {
    # A_v stays near 1 for real powders (MODEL.md); a wide range opens a degenerate valley
    # where a tiny albedo (small grains) is traded against a huge A_v
    "amplitude_volume": ParamSpec(0.05, 5.0, True, 1.0),
    "g": ParamSpec(-0.95, 0.95, False, 0.0),
    "extinction": ParamSpec(1e-3, 1e3, True, 1.0),
    "radius": ParamSpec(3e-3, 3.0, True, 0.05),
    "radius2": ParamSpec(3e-3, 3.0, True, 0.5),
    "fraction2": ParamSpec(0.0, 1.0, False, 0.5),
    "albedo": ParamSpec(0.0, 1.0, False, 0.8),
    "tau_o": ParamSpec(1e-2, 1e2, True, 2.0 / 3.0),
    "thickness": ParamSpec(1e-2, 1e4, True, 100.0),
    "amplitude_surface": ParamSpec(1e-9, 0.1, True, 1e-5),
    "correlation_length": ParamSpec(1e-2, 1e2, True, 1.0),
    "sigma": ParamSpec(1e-3, 1.5, True, 0.1),
}

#: Radius profile (radius free): grid size, L-BFGS evaluations per radius, points kept
PROFILE_RADII = 60
PROFILE_EVALUATIONS = 30
PROFILE_KEEP = 3

#: The paper's six (Table 1, with the effective radius): the default for several wavelengths
DEFAULT_FREE = ["amplitude_volume", "g", "extinction", "radius", "amplitude_surface",
                "correlation_length"]

#: The paper's five with the radius fixed: the default for one wavelength, where the BRF
#: depends on the radius only through rho(r), which several radii share (docs/fitting.md)
DEFAULT_FREE_ONE_WAVELENGTH = ["amplitude_volume", "g", "extinction", "amplitude_surface",
                               "correlation_length"]


def default_free(data: Measurements) -> list[str]:
    """The default free properties for ``data`` (see :data:`DEFAULT_FREE`)."""
    return list(DEFAULT_FREE if len(data.wavelengths()) > 1 else DEFAULT_FREE_ONE_WAVELENGTH)


def _traverse_key(name: str) -> str:
    return "albedo.value" if name == "albedo" else name


@dataclass
class FitResult:
    """Outcome of :func:`fit`.

    Attributes:
        parameters: plugin property -> fitted or fixed value (single wavelength: loadable with
            ``mi.load_dict({'type': 'powder', **parameters})``). With several wavelengths and a
            free albedo, ``albedo`` is an ``irregular`` spectrum dict.
        parameters_by_wavelength: wavelength (nm) -> flat property dict for a mono variant.
        uncertainties: free property (``albedo@<nm>`` per wavelength) -> 1-sigma uncertainty.
        free: the free properties.
        model_brf: fitted BRF at every measured geometry.
        loss: final weighted sum of squares.
        evaluations: objective evaluations over all starts.
        seconds: wall-clock time.
        starts: per start, (final loss, evaluations).
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
    starts: list[tuple[float, int]] = field(default_factory=list)

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


class Problem:
    """The least-squares problem: variables, transform to plugin values, loss and gradient."""

    def __init__(self, data: Measurements, free: list[str], fixed: dict):
        unknown = [n for n in free if n not in FITTABLE]
        if unknown:
            raise ValueError(f"cannot fit {unknown}: fittable properties are "
                             f"{', '.join(FITTABLE)}")
        if len(set(free)) != len(free) or not free:
            raise ValueError(f"free properties must be distinct and non-empty, got {free}")
        clash = [n for n in free if n in fixed]
        if clash:
            raise ValueError(f"{clash} are both free and fixed (--set)")
        if ("radius2" in free or "fraction2" in free) and not (
                ("radius2" in free or "radius2" in fixed) and
                ("fraction2" in free or "fraction2" in fixed)):
            raise ValueError("a second population needs radius2 and fraction2 (free or fixed)")
        self.data = data
        self.free = list(free)
        self.fixed = dict(fixed)
        self.wavelengths = data.wavelengths()
        # optimisation variables: one per free property, albedo once per wavelength
        self.names: list[tuple[str, float | None]] = []
        for n in self.free:
            if n == "albedo" and len(self.wavelengths) > 1:
                self.names += [(n, float(w)) for w in self.wavelengths]
            else:
                self.names.append((n, None))
        self.specs = [FITTABLE[n] for n, _ in self.names]
        self.lower = np.array([self._to_y(s, s.lower) for s in self.specs])
        self.upper = np.array([self._to_y(s, s.upper) for s in self.specs])
        start_props = {n: FITTABLE[n].start for n in self.free}
        self.model = PowderBRF(data, {**start_props, **self.fixed})
        self.weights = 1.0 / data.sigma if data.sigma is not None else np.ones(len(data))
        self.evaluations = 0

    @staticmethod
    def _to_y(spec: ParamSpec, x: float) -> float:
        return math.log10(x) if spec.log else x

    @staticmethod
    def _to_x(spec: ParamSpec, y: float) -> float:
        return 10.0**y if spec.log else y

    def x_of(self, y: np.ndarray) -> np.ndarray:
        return np.array([self._to_x(s, v) for s, v in zip(self.specs, y)])

    def y_of(self, x: np.ndarray) -> np.ndarray:
        return np.array([self._to_y(s, v) for s, v in zip(self.specs, x)])

    def start(self) -> np.ndarray:
        x = []
        for n, _ in self.names:
            x.append(FITTABLE[n].start)
        return self.y_of(np.array(x))

    def _group_variables(self, lam: float) -> list[tuple[int, str]]:
        """(variable index, property) of the variables that act at wavelength lam."""
        return [(j, n) for j, (n, w) in enumerate(self.names) if w is None or w == lam]

    def set_values(self, x: np.ndarray, grad: bool = False) -> None:
        """Write plugin values x into every wavelength group (optionally tracking grads)."""
        with variant():
            for lam, _, _, params, *_ in self.model.groups:
                for j, n in self._group_variables(lam):
                    key = _traverse_key(n)
                    params[key] = mi.Float(float(x[j]))
                    if grad:
                        dr.enable_grad(params[key])
                params.update()

    def loss_and_grad(self, y: np.ndarray) -> tuple[float, np.ndarray]:
        """Weighted sum of squares and its gradient with respect to y."""
        x = self.x_of(y)
        self.set_values(x, grad=True)
        total, grad_x = 0.0, np.zeros(len(x))
        with variant():
            for group in self.model.groups:
                lam, idx, _, params = group[:4]
                r = (self.model.brf_dr(group) - mi.Float(self.data.brf[idx])) * mi.Float(
                    self.weights[idx])
                loss = dr.sum(r * r)
                dr.backward(loss)
                total += float(loss[0])
                for j, n in self._group_variables(lam):
                    g = dr.grad(params[_traverse_key(n)])
                    grad_x[j] += float(g[0]) if dr.width(g) else 0.0
        self.evaluations += 1
        dx_dy = np.array([x_j * math.log(10.0) if s.log else 1.0
                          for s, x_j in zip(self.specs, x)])
        return total, grad_x * dx_dy

    def jacobian(self, x: np.ndarray) -> np.ndarray:
        """d(weighted residual)/dx at x, (N, p), by forward-mode AD (one pass per variable)."""
        jac = np.zeros((len(self.data), len(x)))
        self.set_values(x)
        with variant():
            for j in range(len(x)):
                name, lam_j = self.names[j]
                for group in self.model.groups:
                    lam, idx, _, params = group[:4]
                    if lam_j is not None and lam_j != lam:
                        continue
                    key = _traverse_key(name)
                    dr.enable_grad(params[key])
                    params.update()
                    brf = self.model.brf_dr(group)
                    dr.forward(params[key])
                    jac[idx, j] = np.array(dr.grad(brf), dtype=np.float64) * self.weights[idx]
                    dr.disable_grad(params[key])
                    params.update()
        return jac


def _run(algorithm: int, problem: Problem, y0: np.ndarray, max_evaluations: int,
         hold: tuple[int, ...] = ()) -> tuple[float, np.ndarray]:
    """One nlopt run from y0 (variables in ``hold`` kept at their y0 value); returns the best
    (loss, y) it evaluated."""
    import nlopt

    best: list = [math.inf, np.clip(y0, problem.lower, problem.upper)]
    failure: list[BaseException] = []

    def objective(y, grad):
        try:
            value, g = problem.loss_and_grad(np.asarray(y))
        except Exception as exc:  # re-raised below: nlopt would hide it
            failure.append(exc)
            raise nlopt.ForcedStop from exc
        if grad.size:
            grad[:] = g
        if value < best[0]:
            best[0], best[1] = value, np.array(y)
        return value

    opt = nlopt.opt(algorithm, len(y0))
    lower, upper = problem.lower.copy(), problem.upper.copy()
    for j in hold:  # equal bounds: nlopt keeps the variable fixed
        lower[j] = upper[j] = best[1][j]
    opt.set_lower_bounds(lower)
    opt.set_upper_bounds(upper)
    opt.set_min_objective(objective)
    opt.set_ftol_rel(1e-9)
    opt.set_xtol_rel(1e-7)
    opt.set_maxeval(max_evaluations)
    try:
        opt.optimize(best[1])
    except Exception:
        # L-BFGS's line search gives up near the optimum of a single-precision objective
        # (nlopt's generic failure or RoundoffLimited): keep the best point seen
        if failure:
            raise failure[0] from None
    return float(best[0]), best[1]


def fit(data: Measurements, free: list[str] | None = None, fixed: dict | None = None,
        starts: int = 4, max_evaluations: int = 400, global_evaluations: int = 1500,
        seed: int = 0, progress: Callable[[str], None] | None = None) -> FitResult:
    """Fit the plugin to ``data``.

    Args:
        data: measurements (one or several wavelengths).
        free: plugin properties to fit (default: :func:`default_free`: the paper's six with
            several wavelengths, the five without the radius with one).
        fixed: other plugin properties, held fixed (e.g. ``{"material": "magnetite"}``,
            ``{"eta": 1.35, "k": 0.0}``, ``{"tau_o": 0.6667}``).
        starts: L-BFGS from the default start (and, with the radius free, from the best
            points of a profile over the radius, see :data:`PROFILE_RADII`), then
            ``starts - 1`` runs of a global search (ISRES, from a random point of the bounds)
            polished by L-BFGS.
        max_evaluations: objective evaluations of each L-BFGS run.
        global_evaluations: objective evaluations of each ISRES run.
        seed: seed of the random starts.
        progress: called with a line of text after each start.

    Raises:
        ValueError: unknown, repeated or inconsistent parameter names.
    """

    if starts < 1:
        raise ValueError(f"starts = {starts} is out of range; valid range is [1, inf)")
    with variant():  # once for the whole fit: switching variants per evaluation is slow
        return _fit(data, free, fixed, starts, max_evaluations, global_evaluations, seed,
                    progress)


def _fit(data, free, fixed, starts, max_evaluations, global_evaluations, seed, progress
         ) -> FitResult:
    import nlopt

    t0 = time.perf_counter()
    problem = Problem(data, list(free or default_free(data)), dict(fixed or {}))
    n = len(problem.names)
    rng = np.random.default_rng(seed)
    best = (math.inf, problem.start())
    history = []
    # local starts: the default start; with the radius free, a profile over the radius
    # (rho(r) from Mie theory is not monotonic, so the loss has a narrow basin per root):
    # the other variables are optimised briefly at each radius of a log grid, and the best
    # few points become full starts; then the global starts
    local = [("default start", problem.start())]
    if "radius" in problem.free:
        j = [n for n, _ in problem.names].index("radius")
        profile = []
        for r in np.geomspace(FITTABLE["radius"].lower, FITTABLE["radius"].upper,
                              PROFILE_RADII):
            y = problem.start()
            y[j] = math.log10(r)
            profile.append(_run(nlopt.LD_LBFGS, problem, y, PROFILE_EVALUATIONS, hold=(j,)))
        profile.sort(key=lambda item: item[0])
        for value, y in profile[:PROFILE_KEEP]:
            local.append((f"radius profile, radius {10 ** y[j]:.4g} um (loss {value:.4g})", y))
        if progress:
            progress(f"radius profile: {PROFILE_RADII} radii, {problem.evaluations} "
                     "evaluations")
    plan = local + [("global", None)] * max(0, starts - 1)
    for k, (stage, y0) in enumerate(plan):
        before = problem.evaluations
        if y0 is None:
            # global stage: ISRES (derivative free) from a random point of the bounds
            nlopt.srand(seed + k)
            y0 = _run(nlopt.GN_ISRES, problem, rng.uniform(problem.lower, problem.upper),
                      global_evaluations)[1]
            stage = "ISRES + L-BFGS"
        value, y = _run(nlopt.LD_LBFGS, problem, y0, max_evaluations)
        history.append((float(value), problem.evaluations - before))
        if value < best[0]:
            best = (value, y)
        if progress:
            progress(f"start {k + 1}/{len(plan)} ({stage}): loss {value:.6g} "
                     f"({problem.evaluations - before} evaluations), best {best[0]:.6g}")

    x = problem.x_of(best[1])
    problem.set_values(x)
    model_brf = problem.model.brf()
    residual = (model_brf - data.brf) * problem.weights
    chi2 = float(np.sum(residual**2))
    jac = problem.jacobian(x)
    dof = max(1, len(data) - n)
    s2 = 1.0 if data.sigma is not None else chi2 / dof
    try:
        cov = s2 * np.linalg.inv(jac.T @ jac)
        err = np.sqrt(np.clip(np.diag(cov), 0.0, None))
    except np.linalg.LinAlgError:
        err = np.full(n, np.inf)

    values = {n_: x[j] for j, (n_, w) in enumerate(problem.names) if w is None}
    uncertainties = {(n_ if w is None else f"{n_}@{w:g}"): float(err[j])
                     for j, (n_, w) in enumerate(problem.names)}
    by_wavelength = {}
    for lam in problem.wavelengths:
        d = {**problem.fixed, **{k: float(v) for k, v in values.items()}}
        for j, (n_, w) in enumerate(problem.names):
            if w == lam:
                d[n_] = float(x[j])
        by_wavelength[float(lam)] = d
    parameters = dict(by_wavelength[float(problem.wavelengths[0])])
    if any(w is not None for _, w in problem.names):
        albedo = [(w, float(x[j])) for j, (n_, w) in enumerate(problem.names) if w is not None]
        parameters["albedo"] = {"type": "irregular",
                                "wavelengths": ", ".join(f"{w:g}" for w, _ in albedo),
                                "values": ", ".join(f"{v:.8g}" for _, v in albedo)}
    return FitResult(parameters, by_wavelength, uncertainties, problem.free, data, model_brf,
                     chi2, problem.evaluations, time.perf_counter() - t0, history)


def predict(result: FitResult, data: Measurements) -> np.ndarray:
    """BRF of the fitted material at other geometries (each wavelength with its parameters).

    Raises:
        ValueError: ``data`` has a wavelength the fit did not cover.
    """
    out = np.empty(len(data))
    with variant():
        for lam in data.wavelengths():
            _predict_one(result, data, lam, out)
    return out


def _predict_one(result: FitResult, data: Measurements, lam: float, out: np.ndarray) -> None:
    """Fill ``out`` at the rows of wavelength ``lam``."""
    props = result.parameters_by_wavelength.get(float(lam))
    if props is None:
        raise ValueError(f"wavelength {lam:g} nm was not fitted; fitted: "
                         f"{sorted(result.parameters_by_wavelength)}")
    sel = data.wavelength == lam
    out[sel] = PowderBRF(data.subset(sel), props).brf()
