"""Fit the powder plugin's parameters to goniometric BRF measurements.

The loss is the weighted sum of squares ``sum_i ((BRF_model_i - BRF_i) / sigma_i)^2`` (sigma = 1
when the data carry none), accumulated in float64; every row counts, replicated geometries
included. The model is the C++ plugin: :class:`~mitsuba_powder.plugin.brf.BatchBRF` evaluates it at
every geometry and wavelength for a whole batch of parameter sets in one Dr.Jit launch, and its
Jacobian by forward-mode AD (one pass per property over the same traced graph). The grains'
albedo comes from the plugin's Mie theory (:mod:`~mitsuba_powder.plugin.grains`), with its
radius derivatives.

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

from ..io.measurements import Measurements
from ..plugin.brf import (
    VARIANT,
    BatchBRF,
    PowderBRF,
    batch_variant,
    engine_properties,
)
from ..plugin.grains import DEFAULT_FILL, GRAIN_VARIABLES, GrainOptics
from ..variants import use_variant
from .optimise import AGREEMENT, MultistartResult, ParamSpec, multistart, sobol_starts

FITTABLE: dict[str, ParamSpec] = {
    # A_v stays near 1 for real powders (docs/model.md); a wide range opens a degenerate valley
    # where a tiny albedo (small grains) is traded against a huge A_v
    "amplitude_volume": ParamSpec(0.05, 5.0, True, 1.0),
    "g": ParamSpec(-0.95, 0.95, False, 0.0),
    "extinction": ParamSpec(1e-3, 1e3, True, 1.0),
    "radius": ParamSpec(3e-3, 3.0, True, 0.05),
    "radius2": ParamSpec(3e-3, 3.0, True, 0.5),
    "fraction2": ParamSpec(0.0, 1.0, False, 0.5),
    "agglomerate_radius": ParamSpec(1e-2, 3.0, True, 0.15),
    "agglomerate_fill": ParamSpec(0.05, 1.0, False, DEFAULT_FILL),
    "albedo": ParamSpec(0.0, 1.0, False, 0.8),
    "tau_o": ParamSpec(1e-2, 1e2, True, 2.0 / 3.0),
    "thickness": ParamSpec(1e-2, 1e4, True, 100.0),
    "amplitude_surface": ParamSpec(1e-9, 0.1, True, 1e-5),
    "correlation_length": ParamSpec(1e-2, 1e2, True, 1.0),
    "sigma": ParamSpec(1e-3, 1.5, True, 0.1),
}

#: The plugin's default radius (um), used when neither fitted nor given
DEFAULT_RADIUS = 0.017

#: Grain properties (:data:`~mitsuba_powder.plugin.grains.GRAIN_VARIABLES`) set the albedo
#: through the grain model; they are held in the global phase

#: Properties that only configure the grain model (not fitted)
GRAIN_SETTINGS = ("grains", "mixing")

#: Radii of the log grid the global phase holds the radius at (every Mie branch is tried)
PROFILE_RADII = 32

#: Starts of the global phase, and distinct end points polished
DEFAULT_STARTS = 64
DEFAULT_POLISH = 4

#: The paper's six (Table 1, with the effective radius): the default for several wavelengths
DEFAULT_FREE = ["amplitude_volume", "g", "extinction", "radius", "amplitude_surface",
                "correlation_length"]

#: One wavelength: the albedo instead of the radius, which rho(r) does not determine
DEFAULT_FREE_ONE_WAVELENGTH = ["amplitude_volume", "g", "extinction", "albedo",
                               "amplitude_surface", "correlation_length"]

#: Enhanced back-scattering theory holds while the cone is narrow: ``--regime ebs`` bounds
#: the extinction so that kappa / k0 stays at most this at every fitted wavelength
EBS_KAPPA_OVER_K0 = 0.25

#: Regimes of :func:`fit`
REGIMES = ("ebs", "free")

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
        size = "agglomerate_radius" if fixed.get("grains") == "agglomerate" else "radius"
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


def _check_free(free: list[str], fixed: dict) -> None:
    unknown = [n for n in free if n not in FITTABLE]
    if unknown:
        raise ValueError(f"cannot fit {unknown}: fittable properties are {', '.join(FITTABLE)}")
    if len(set(free)) != len(free) or not free:
        raise ValueError(f"free properties must be distinct and non-empty, got {free}")
    clash = [n for n in free if n in fixed]
    if clash:
        raise ValueError(f"{clash} are both free and fixed (--set)")
    if ("radius2" in free or "fraction2" in free) and not (
            ("radius2" in free or "radius2" in fixed) and
            ("fraction2" in free or "fraction2" in fixed)):
        raise ValueError("a second population needs radius2 and fraction2 (free or fixed)")
    specular = fixed.get("specular", "harvey_shack")
    unused = {"harvey_shack": "sigma", "gaussian": "correlation_length"}.get(specular)
    if unused in free:
        raise ValueError(f"{unused} has no effect with specular = {specular!r}: fit "
                         f"{'correlation_length' if unused == 'sigma' else 'sigma'} instead, or "
                         f"set specular={'gaussian' if unused == 'sigma' else 'harvey_shack'}")
    grains = [n for n in GRAIN_VARIABLES + GRAIN_SETTINGS if n in free or n in fixed]
    if ("albedo" in free or "albedo" in fixed) and grains:
        raise ValueError(f"albedo and {grains} cannot be used together: a given albedo "
                         "replaces the one Mie theory computes from the grains")
    _check_grain_model(free, fixed)
    if "albedo" in fixed and not isinstance(fixed["albedo"], (int, float)):
        raise ValueError(f"albedo = {fixed['albedo']!r}: a fit takes a fixed albedo as one "
                         "number in [0, 1]")
    for name, value in fixed.items():
        spec = FITTABLE.get(name)
        if spec is not None and isinstance(value, (int, float)) and name != "albedo" and not (
                math.isfinite(value) or name == "thickness"):
            raise ValueError(f"{name} = {value} is not a finite number")


def _check_grain_model(free: list[str], fixed: dict) -> None:
    """The grain properties each model takes (as the plugin's constructor checks them)."""
    model = fixed.get("grains", "sphere")
    used = set(free) | set(fixed)
    agglomerate = ("agglomerate_radius", "agglomerate_fill", "mixing")
    if model != "agglomerate":
        extra = [n for n in agglomerate if n in used]
        if extra:
            raise ValueError(f"{extra} are used only with grains = 'agglomerate' (grains = "
                             f"{model!r}); set grains=agglomerate")
        return
    if "agglomerate_radius" not in used:
        raise ValueError("grains = 'agglomerate' needs agglomerate_radius (free or fixed, um)")
    if "radius" in free:
        raise ValueError("radius is the crystallite radius with grains = 'agglomerate' and "
                         "does not enter the albedo: fit agglomerate_radius (and "
                         "agglomerate_fill) instead")
    two = [n for n in ("radius2", "fraction2") if n in used]
    if two:
        raise ValueError(f"{two} cannot be used with grains = 'agglomerate' (one population)")


class Problem:
    """The least-squares problem in the optimiser's variables ``y`` (log10 for scale
    parameters), batched over parameter sets (see
    :class:`mitsuba_powder.fitting.optimise.BatchProblem`).

    Variables: one per free property; ``albedo`` once per wavelength when several are fitted.
    """

    def __init__(self, data: Measurements, free: list[str], fixed: dict,
                 regime: str = "ebs"):
        _check_free(free, fixed)
        if regime not in REGIMES:
            raise ValueError(f"regime = {regime!r} is not valid; valid values are "
                             f"{', '.join(REGIMES)}")
        self.data = data
        self.free = list(free)
        self.fixed = dict(fixed)
        self.regime = regime
        self.wavelengths = data.wavelengths()
        self.row_wavelength = np.searchsorted(self.wavelengths, data.wavelength)
        self.names: list[tuple[str, float | None]] = []
        for n in self.free:
            if n == "albedo" and len(self.wavelengths) > 1:
                self.names += [(n, float(w)) for w in self.wavelengths]
            else:
                self.names.append((n, None))
        self.specs = [FITTABLE[n] for n, _ in self.names]
        # EBS regime: kappa / k0 <= 0.25 at every wavelength, k0 = 2 pi / lambda; the
        # longest wavelength has the smallest k0
        self.extinction_limit = (EBS_KAPPA_OVER_K0 * 2.0 * math.pi /
                                 (1e-3 * float(np.max(self.wavelengths))))
        if regime == "ebs":
            self.specs = [ParamSpec(s.lower, min(s.upper, self.extinction_limit), s.log,
                                    min(s.start, self.extinction_limit))
                          if n == "extinction" else s
                          for s, (n, _) in zip(self.specs, self.names)]
        self.lower = np.array([s.to_y(s.lower) for s in self.specs], dtype=np.float64)
        self.upper = np.array([s.to_y(s.upper) for s in self.specs], dtype=np.float64)
        self.weights = 1.0 / data.sigma if data.sigma is not None else np.ones(len(data))
        self.target = data.brf
        # float properties the plugin takes per parameter set
        self.varying = [n for n in self.free if n != "albedo" and n not in GRAIN_VARIABLES]
        self.grain_free = [n for n in GRAIN_VARIABLES if n in self.free]
        self.albedo_mode = ("free" if "albedo" in self.free else
                            "fixed" if "albedo" in self.fixed else "grains")
        self.engine_properties = engine_properties(self.fixed)
        self.grains = GrainOptics(self.fixed)
        self.tau_o = (np.full(len(self.wavelengths), float(self.fixed["tau_o"]))
                      if "tau_o" in self.fixed else
                      None if "tau_o" in self.free else self.grains.tau_o(self.wavelengths))
        self.grain_derivatives = True
        self._engines: dict[int, BatchBRF] = {}
        self._rho_cache: dict[tuple, tuple[np.ndarray, np.ndarray | None]] = {}
        self.evaluations = 0

    # ----------------------------------------------------------- variables

    def index(self, name: str) -> int:
        return [n for n, _ in self.names].index(name)

    def x_of(self, y: np.ndarray) -> np.ndarray:
        y = np.atleast_2d(y)
        return np.stack([s.to_x(y[:, j]) for j, s in enumerate(self.specs)], axis=1)

    def y_of(self, x: np.ndarray) -> np.ndarray:
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        return np.stack([s.to_y(x[:, j]) for j, s in enumerate(self.specs)], axis=1)

    def start(self) -> np.ndarray:
        """The default start (each property's :class:`ParamSpec` start), (p,)."""
        return self.y_of(np.array([s.start for s in self.specs]))[0]

    def hold_grains(self) -> np.ndarray:
        """(p,) booleans: the grain variables."""
        return np.array([n in GRAIN_VARIABLES for n, _ in self.names])

    # ----------------------------------------------------------- evaluation

    def _engine(self, batch: int) -> BatchBRF:
        if batch not in self._engines:
            self._engines[batch] = BatchBRF(self.data, self.engine_properties, batch,
                                            self.varying)
        return self._engines[batch]

    def _grain_values(self, x: np.ndarray) -> tuple[np.ndarray, ...]:
        """The :data:`GRAIN_VARIABLES` per parameter set (None where absent)."""
        out = []
        for name in GRAIN_VARIABLES:
            if name in self.free:
                out.append(x[:, self.index(name)])
            elif name in self.fixed:
                out.append(np.full(len(x), float(self.fixed[name])))
            else:
                out.append(None)
        if out[0] is None:  # the plugin's default radius
            out[0] = np.full(len(x), DEFAULT_RADIUS)
        return tuple(out)

    def albedo(self, x: np.ndarray, derivatives: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """rho (B, W) and, for grains, d rho / d(:data:`GRAIN_VARIABLES`) (B, W, 5)."""
        b, w = len(x), len(self.wavelengths)
        if self.albedo_mode == "fixed":
            return np.full((b, w), float(self.fixed["albedo"])), None
        if self.albedo_mode == "free":
            cols = [j for j, (n, _) in enumerate(self.names) if n == "albedo"]
            return x[:, cols].reshape(b, w), None
        grain = self._grain_values(x)
        rho = np.empty((b, w))
        deriv = np.zeros((b, w, len(GRAIN_VARIABLES)))
        need = derivatives and self.grain_derivatives and bool(self.grain_free)
        missing = []
        for i in range(b):
            key = tuple(None if v is None else float(v[i]) for v in grain) + (need,)
            if key in self._rho_cache:
                rho[i], d = self._rho_cache[key]
                if d is not None:
                    deriv[i] = d
            else:
                missing.append((i, key))
        if missing:
            idx = np.array([i for i, _ in missing])
            r1, r2, f2, ra, fill = (None if v is None else v[idx] for v in grain)
            values, d = self.grains.albedo(self.wavelengths, r1, r2, f2, derivatives=need,
                                           agglomerate_radius=ra, agglomerate_fill=fill)
            for k, (i, key) in enumerate(missing):
                rho[i] = values[k]
                if d is not None:
                    deriv[i] = d[k]
                if len(self._rho_cache) < 100000:
                    self._rho_cache[key] = (values[k], None if d is None else d[k])
        return rho, deriv

    def _evaluate(self, y: np.ndarray, derivatives: bool):
        y = np.atleast_2d(np.asarray(y, dtype=np.float64))
        x = self.x_of(y)
        rho, drho = self.albedo(x, derivatives)
        values = {n: x[:, self.index(n)] for n in self.varying}
        brf, grads = self._engine(len(x)).evaluate(values, rho, self.tau_o, derivatives)
        self.evaluations += 1
        res = (brf - self.target[None, :]) * self.weights[None, :]
        if not derivatives:
            return res, None
        jac = np.zeros(res.shape + (len(self.names),))
        for j, ((name, lam), spec) in enumerate(zip(self.names, self.specs)):
            dxdy = spec.dx_dy(x[:, j])[:, None]
            if name in self.varying:
                col = grads[name]
            elif name == "albedo":
                col = grads["albedo"] if lam is None else grads["albedo"] * (
                    self.data.wavelength == lam)[None, :]
            else:  # a grain variable: chain rule through rho at each row's wavelength
                k = GRAIN_VARIABLES.index(name)
                col = grads["albedo"] * drho[:, self.row_wavelength, k]
            jac[:, :, j] = col * dxdy * self.weights[None, :]
        return res, jac

    def residuals(self, y: np.ndarray) -> np.ndarray:
        """Weighted residuals (B, N) of parameter sets y (B, p)."""
        return self._evaluate(y, False)[0]

    def jacobian(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Weighted residuals (B, N) and their Jacobian (B, N, p) with respect to y."""
        return self._evaluate(y, True)

    # ----------------------------------------------------------- results

    def properties(self, x: np.ndarray, lam: float | None = None) -> dict:
        """Plugin properties (mono form at wavelength ``lam``) of variables ``x`` (p,)."""
        d = dict(self.fixed)
        for j, (name, w) in enumerate(self.names):
            if w is None or w == lam:
                d[name] = float(x[j])
        return d


def _starts(problem: Problem, count: int, seed: int) -> np.ndarray:
    """Sobol starts (the default start first); with the radius (or the agglomerate radius)
    free, it runs over a log grid of its whole range (:data:`PROFILE_RADII` values, each with
    the same number of starts): every branch of rho(r) is tried."""
    y0 = sobol_starts(problem.lower, problem.upper, count, seed)
    size = next((n for n in ("radius", "agglomerate_radius") if n in problem.free), None)
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
    if default and "hematite" not in " ".join(problem.data.comments).lower():
        out["notice"] = ("the grain material is the default, hematite: it sets tau_o (and "
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
        regime: str = "ebs") -> FitResult:
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

    Raises:
        ValueError: unknown, repeated or inconsistent parameter names; starts or polish < 1;
            an unknown regime.
    """
    if starts < 1:
        raise ValueError(f"starts = {starts} is out of range; valid range is [1, inf)")
    if polish < 1:
        raise ValueError(f"polish = {polish} is out of range; valid range is [1, inf)")
    if len(data) == 0:
        raise ValueError("no measurements to fit")
    # once for the whole fit: switching variants is slow
    with use_variant(batch_variant(data.wavelength)):
        return _fit(data, list(free or default_free(data, fixed)), dict(fixed or {}), starts,
                    polish, seed, max_iterations, progress, regime)


def _fit(data, free, fixed, starts, polish_count, seed, max_iterations, progress, regime
         ) -> FitResult:
    t0 = time.perf_counter()
    problem = Problem(data, free, fixed, regime)
    optics = _optics(problem)
    if progress:
        progress(f"optics: {optics['source']}" + (
            f"; tau_o {min(optics['tau_o'].values()):.4g}-{max(optics['tau_o'].values()):.4g}"
            if "tau_o" in optics else ""))
        if "notice" in optics:
            progress(f"notice: {optics['notice']}")
    y0 = _starts(problem, starts, seed)
    hold = problem.hold_grains()
    problem.grain_derivatives = False  # the grains are held during the global phase
    result: MultistartResult = multistart(
        problem, y0, polish_count, hold if hold.any() else None, max_iterations,
        refine_count=max(16, starts // 4), progress=progress,
        before_free=lambda: setattr(problem, "grain_derivatives", True))
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
    return FitResult(parameters, by_wavelength, uncertainties, problem.free, data, model_brf,
                     chi2, problem.evaluations, time.perf_counter() - t0,
                     [float(c) for c in result.start_costs], result.agreeing,
                     ([_label(n, w) for n, w in problem.names], corr), warnings,
                     chi2_per_point, branches, optics, result.stages, regime_info)


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
