"""Bounded non-linear least squares from many starts: the optimiser of every fit in the package.

A problem is a vector of residuals ``r(y)`` (float64) of ``p`` variables ``y`` inside a box
``[lower, upper]``, evaluated for a *batch* of ``B`` points at once (the powder model evaluates
all of them in one Dr.Jit launch). The strategy:

1. **Space-filling starts**: a scrambled Sobol design over the box (:func:`sobol_starts`); the
   caller may replace columns (e.g. a log grid over a radius so that every Mie branch is tried).
2. **Batched Levenberg-Marquardt** (:func:`batch_levenberg_marquardt`): every start takes damped
   Gauss-Newton steps at the same time, ``(J^T J + lambda diag(J^T J)) dy = -J^T r`` with the
   Jacobian of the problem, projected onto the box; a step is kept where it lowers the cost.
   Variables can be held at their start value (a profile).
3. **Polish** (:func:`polish`): the best few *distinct* end points are refined with
   ``scipy.optimize.least_squares`` (trust-region reflective, bounds, the problem's Jacobian).
4. **Agreement**: how many starts end within 1 % of the best cost. A fit with fewer than two is
   not trusted to be the global optimum (:attr:`MultistartResult.agreeing`).

The global stage of 1-2 may instead be nlopt's (:func:`nlopt_search`, ``GLOBAL_STAGES``
``mlsl`` or ``crs2``; nlopt is an optional dependency): its single-point evaluations are
recorded, and the best distinct points take the batched Levenberg-Marquardt steps, the polish
and the agreement count above. The Sobol stage stays the default: on multimodal unmixing it
reached low costs at least as often for the same evaluations (docs/fitting.md, "The global
stage").

Variables are in the optimiser's space ``y``: :class:`ParamSpec` maps a bounded parameter to
``y = log10(x)`` (positive scale parameters) or ``y = x``.
"""

from __future__ import annotations

import math
import time
import weakref
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Protocol

import numpy as np

from .._checks import check_range, out_of_range

#: Relative cost difference under which two starts "reach the same loss"
AGREEMENT = 0.01

#: The global stages: Sobol starts with batched Levenberg-Marquardt (:func:`multistart`), or
#: nlopt's MLSL or CRS2 followed by the same Levenberg-Marquardt steps and polish
#: (:func:`nlopt_search`; nlopt is an optional dependency)
GLOBAL_STAGES = ("sobol", "mlsl", "crs2")

#: Relative cost change at which an MLSL local search (LD_MMA) stops
MLSL_LOCAL_FTOL = 1e-6

#: Starts of the Sobol stage, and the nlopt stages' budget per start (single-point
#: evaluations; a Sobol start of unmixing with the radii free spends 41-57,
#: benchmarks/bench_unmix_global.py)
DEFAULT_STARTS = 64
NLOPT_EVALUATIONS_PER_START = 40


@dataclass(frozen=True)
class ParamSpec:
    """Bounds (in the parameter's own unit), search scale and default start of a parameter."""

    lower: float
    upper: float
    log: bool
    start: float

    def to_y(self, x: float | np.ndarray) -> float | np.ndarray:
        """Parameter value -> optimiser variable (log10 for log-scaled parameters)."""
        return np.log10(x) if self.log else x

    def to_x(self, y: float | np.ndarray) -> float | np.ndarray:
        """Optimiser variable -> parameter value."""
        return 10.0**y if self.log else y

    def dx_dy(self, x: float | np.ndarray) -> float | np.ndarray:
        """Derivative of the parameter with respect to its optimiser variable."""
        return x * math.log(10.0) if self.log else np.ones_like(x)


class BatchProblem(Protocol):
    """What the optimiser needs of a least-squares problem."""

    lower: np.ndarray  #: (p,) lower bounds of y
    upper: np.ndarray  #: (p,) upper bounds of y

    def residuals(self, y: np.ndarray) -> np.ndarray:
        """(B, p) points -> (B, N) residuals (float64)."""

    def jacobian(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, p) points -> residuals (B, N) and their Jacobian (B, N, p) with respect to y."""


def check_determined(geometries: int, variables: int, what: str) -> None:
    """Refuse a least-squares fit that its data cannot determine: it needs more distinct
    observations (geometries, each wavelength counted) than free variables; with as many or
    fewer, any parameter set fits exactly and nothing (value, uncertainty) would mean anything.

    Args:
        geometries: distinct observations (replicated rows count once).
        variables: free variables of the fit.
        what: the fit, for the message (e.g. ``"the powder fit of data.csv"``).

    Raises:
        ValueError: ``geometries <= variables``.
    """
    if geometries <= variables:
        raise ValueError(f"{what}: {variables} free variable{'s' * (variables != 1)} cannot be "
                         f"determined by {geometries} distinct geometr"
                         f"{'ies' if geometries != 1 else 'y'} (replicated rows count once); it "
                         "needs more geometries than free variables: give more measurements or "
                         "fewer free parameters (--free, or hold some with --set)")


def sobol_starts(lower: np.ndarray, upper: np.ndarray, count: int, seed: int) -> np.ndarray:
    """``count`` scrambled-Sobol points of the box, (count, p)."""
    from scipy.stats import qmc

    check_range("starts", count, 1)
    sampler = qmc.Sobol(d=len(lower), scramble=True, seed=seed)
    m = max(0, math.ceil(math.log2(count)))
    u = sampler.random_base2(m)[:count]
    return lower + u * (upper - lower)


def finite_difference_jacobian(residuals: Callable[[np.ndarray], np.ndarray],
                               lower: np.ndarray, upper: np.ndarray, step: float = 1e-6
                               ) -> Callable[[np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """A batched Jacobian by central differences, steps ``step * max(1, |y|)`` kept inside
    the box (the default for float64 NumPy models; a model computed in float32, such as the
    plugin's, needs a larger step)."""

    def jacobian(y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        r0 = residuals(y)
        jac = np.empty(r0.shape + (y.shape[1],))
        for j in range(y.shape[1]):
            h = step * np.maximum(1.0, np.abs(y[:, j]))
            yp, ym = y.copy(), y.copy()
            yp[:, j] = np.minimum(y[:, j] + h, upper[j])
            ym[:, j] = np.maximum(y[:, j] - h, lower[j])
            span = (yp[:, j] - ym[:, j])[:, None]
            jac[:, :, j] = (residuals(yp) - residuals(ym)) / np.where(span > 0, span, 1.0)
        return r0, jac

    return jacobian


@dataclass
class LMState:
    """End of a batched Levenberg-Marquardt run."""

    y: np.ndarray        #: (B, p) end points
    cost: np.ndarray     #: (B,) sums of squared residuals
    iterations: int
    evaluations: int     #: batch evaluations (one per residual or Jacobian call)
    unfinished: int = 0  #: starts still iterating when max_iterations stopped them


def _normal_equations(jac: np.ndarray, res: np.ndarray, free: np.ndarray
                      ) -> tuple[np.ndarray, np.ndarray]:
    """(J^T J, J^T r) of every start over its free variables: (B, f, f) and (B, f)."""
    jf = jac[:, :, free]
    # (matmul, not einsum: 5x faster for many small systems, same values)
    jt = jf.transpose(0, 2, 1)
    return np.matmul(jt, jf), np.matmul(jt, res[:, :, None])[:, :, 0]


def _solve_damped(a: np.ndarray, g: np.ndarray, damping: np.ndarray, free: np.ndarray
                  ) -> np.ndarray:
    """Levenberg-Marquardt steps of every start from its normal equations (``a`` = J^T J,
    ``g`` = J^T r over the free variables); held variables get 0."""
    f = a.shape[2]
    diag = np.maximum(np.einsum("bii->bi", a), 1e-30)
    a_damped = a + (damping[:, None] * diag)[:, :, None] * np.eye(f)[None]
    a_damped += 1e-12 * np.max(diag, axis=1)[:, None, None] * np.eye(f)[None]
    step = np.zeros((a.shape[0], len(free)))
    try:
        step[:, free] = -np.linalg.solve(a_damped, g[:, :, None])[:, :, 0]
    except np.linalg.LinAlgError:
        step[:, free] = -np.einsum("bij,bj->bi", np.linalg.pinv(a_damped), g)
    return step


def _padded(fn: Callable, y: np.ndarray):
    """Call a batched function on the rows ``y``, padded (by repeating the last row) to a power
    of two, so that a shrinking set of active starts reuses a few batch sizes."""
    k = len(y)
    size = 1 << max(0, (k - 1).bit_length())
    out = fn(np.concatenate([y, np.repeat(y[-1:], size - k, axis=0)]) if size > k else y)
    return tuple(o[:k] for o in out) if isinstance(out, tuple) else out[:k]


def batch_levenberg_marquardt(problem: BatchProblem, y0: np.ndarray, max_iterations: int = 60,
                              hold: np.ndarray | None = None, ftol: float = 1e-7,
                              hopeless: float = 100.0, patience: int = 15) -> LMState:
    """Damped Gauss-Newton from every row of ``y0`` at once.

    Each iteration evaluates the trial points of the active starts in one batch and the
    Jacobian only where a step was kept. A start stops when a step, kept or not, changes its
    cost by less than ``ftol`` (relative), when its damping explodes (no descent left inside
    the box), or, after ``patience`` iterations, when its cost exceeds ``hopeless`` times the
    best (another basin; the polish only takes the best ones).

    Args:
        problem: the batched least-squares problem.
        y0: (B, p) starts inside the box.
        max_iterations: iterations at most.
        hold: (p,) booleans, variables kept at their start value.
    """
    y = np.clip(np.array(y0, dtype=np.float64), problem.lower, problem.upper)
    free = np.ones(y.shape[1], dtype=bool) if hold is None else ~np.asarray(hold, dtype=bool)
    damping = np.full(len(y), 1e-3)
    active = np.ones(len(y), dtype=bool)
    res, jac = _padded(problem.jacobian, y)
    cost = np.sum(res**2, axis=1)
    evaluations, iterations = 1, 0
    if not free.any():
        return LMState(y, cost, 0, evaluations)
    # the normal equations of the current points (a rejected step reuses them; the Jacobians
    # themselves are not kept)
    jtj, jtr = _normal_equations(jac, res, free)
    del jac, res
    for iterations in range(1, max_iterations + 1):  # noqa: B007
        act = np.nonzero(active)[0]
        step = _solve_damped(jtj[act], jtr[act], damping[act], free)
        trial = np.clip(y[act] + step, problem.lower, problem.upper)
        trial_cost = np.sum(_padded(problem.residuals, trial) ** 2, axis=1)
        evaluations += 1
        cost_before = cost[act].copy()
        better = np.isfinite(trial_cost) & (trial_cost < cost_before)
        gain = np.where(better, (cost_before - trial_cost) / np.maximum(cost_before, 1e-300),
                        0.0)
        damping[act] = np.where(better, np.maximum(damping[act] / 3.0, 1e-9),
                                damping[act] * 4.0)
        kept = act[better]
        if len(kept):
            y[kept] = trial[better]
            r_new, j_new = _padded(problem.jacobian, y[kept])
            evaluations += 1
            jtj[kept], jtr[kept] = _normal_equations(j_new, r_new, free)
            cost[kept] = np.sum(r_new**2, axis=1)
        done = np.zeros(len(y), dtype=bool)
        # a step that changes the cost by less than ftol (relative), kept or not: converged
        flat = np.isfinite(trial_cost) & (np.abs(cost_before - trial_cost)
                                          < ftol * np.maximum(cost_before, 1e-300))
        done[act] = (better & (gain < ftol)) | flat | (damping[act] > 1e7)
        if iterations >= patience:
            done |= cost > hopeless * np.min(cost)
        active &= ~done
        if not active.any():
            break
    return LMState(y, cost, iterations, evaluations, int(np.sum(active)))


@dataclass
class PolishResult:
    y: np.ndarray
    cost: float
    evaluations: int


def polish(problem: BatchProblem, y0: np.ndarray, max_evaluations: int = 200,
           hold: np.ndarray | None = None) -> PolishResult:
    """Refine one point with ``scipy.optimize.least_squares`` (method ``trf``, bounds, the
    problem's Jacobian); ``hold`` variables stay at ``y0``."""
    from scipy.optimize import least_squares

    y0 = np.clip(np.asarray(y0, dtype=np.float64), problem.lower, problem.upper)
    free = np.ones(len(y0), dtype=bool) if hold is None else ~np.asarray(hold, dtype=bool)
    cache: dict = {}
    count = [0]

    def full(z: np.ndarray) -> np.ndarray:
        y = y0.copy()
        y[free] = z
        return y

    def evaluate(z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        key = z.tobytes()
        if cache.get("key") != key:
            r, j = problem.jacobian(full(z)[None])
            count[0] += 1
            cache.update(key=key, r=r[0], j=j[0][:, free])
        return cache["r"], cache["j"]

    lo, hi = problem.lower[free], problem.upper[free]
    # least_squares wants a strictly interior start
    span = hi - lo
    z0 = np.clip(y0[free], lo + 1e-10 * span, hi - 1e-10 * span)
    best = {"cost": math.inf, "z": z0}

    def fun(z):
        r = evaluate(z)[0]
        c = float(np.dot(r, r))
        if c < best["cost"]:
            best.update(cost=c, z=z.copy())
        return r

    solution = least_squares(fun, z0, jac=lambda z: evaluate(z)[1], bounds=(lo, hi),
                             method="trf", x_scale="jac", ftol=1e-9, xtol=1e-9, gtol=1e-9,
                             max_nfev=max_evaluations)
    z = solution.x if 2.0 * solution.cost <= best["cost"] else best["z"]
    r = evaluate(z)[0]
    return PolishResult(full(z), float(np.dot(r, r)), count[0])


@dataclass
class MultistartResult:
    """Outcome of :func:`multistart`.

    Attributes:
        y: best point. cost: its sum of squares.
        start_costs: (B,) final cost of every start (polished ones after polishing).
        polished: indices of the polished starts.
        agreeing: starts whose final cost is within :data:`AGREEMENT` of the best.
        evaluations: batch evaluations of the global phase + single-point evaluations of the
            polish.
        seconds: wall-clock time.
    """

    y: np.ndarray
    cost: float
    start_costs: np.ndarray
    polished: list[int]
    agreeing: int
    evaluations: int
    seconds: float
    stages: list[str] = field(default_factory=list)


def distinct_best(y: np.ndarray, cost: np.ndarray, count: int, span: np.ndarray,
                  min_distance: float = 0.02) -> list[int]:
    """Indices of up to ``count`` lowest-cost points that are at least ``min_distance`` apart
    (max norm, relative to the box ``span``)."""
    chosen: list[int] = []
    for i in np.argsort(cost):
        if not np.isfinite(cost[i]):
            continue
        if all(np.max(np.abs(y[i] - y[j]) / span) > min_distance for j in chosen):
            chosen.append(int(i))
        if len(chosen) == count:
            break
    return chosen


def multistart(problem: BatchProblem, starts: np.ndarray, polish_count: int = 4,
               hold_global: np.ndarray | None = None, max_iterations: int = 60,
               max_polish_evaluations: int = 200, refine_count: int = 16,
               progress: Callable[[str], None] | None = None,
               before_free: Callable[[], None] | None = None) -> MultistartResult:
    """Batched Levenberg-Marquardt from every start; with ``hold_global`` variables held in this
    first phase (e.g. a radius on a grid), the best ``refine_count`` distinct end points take a
    second batched phase with every variable free (``before_free`` is called first); then the
    best ``polish_count`` distinct end points are polished."""
    t0 = time.perf_counter()
    lm = batch_levenberg_marquardt(problem, starts, max_iterations, hold_global)
    held = hold_global is not None and bool(np.any(hold_global))
    stages = [f"global: {len(starts)} starts, batched Levenberg-Marquardt"
              f"{' (profile variables held)' if held else ''}, {lm.iterations} iterations "
              f"({lm.evaluations} batch evaluations), best cost {np.min(lm.cost):.6g}"]
    if progress:
        progress(stages[-1])
    span = np.maximum(problem.upper - problem.lower, 1e-30)
    costs, ends = lm.cost.copy(), lm.y.copy()
    evaluations = lm.evaluations
    if before_free is not None:
        before_free()
    if held:
        refine = distinct_best(ends, costs, refine_count, span)
        # starts that ended at the same held point as a chosen one follow it (so that starts
        # sharing a basin can agree), each from its own end point
        near = np.max(np.abs(ends[:, None, :] - ends[None, refine, :]) / span, axis=2)
        refine = sorted(set(refine) | set(np.nonzero(np.min(near, axis=1) <= 0.02)[0].tolist()))
        second = batch_levenberg_marquardt(problem, ends[refine], max_iterations)
        costs[refine], ends[refine] = second.cost, second.y
        evaluations += second.evaluations
        stages.append(f"global, every variable free: the best {len(refine)} end points, "
                      f"{second.iterations} iterations ({second.evaluations} batch "
                      f"evaluations), best cost {np.min(second.cost):.6g}")
        if progress:
            progress(stages[-1])
    return _polish_best(problem, ends, costs, evaluations, t0, stages, polish_count,
                        max_polish_evaluations, progress)


def _polish_best(problem: BatchProblem, ends: np.ndarray, costs: np.ndarray, evaluations: int,
                 t0: float, stages: list[str], polish_count: int, max_polish_evaluations: int,
                 progress: Callable[[str], None] | None) -> MultistartResult:
    """The common end of every global stage: the best ``polish_count`` distinct end points
    (within ten times the best cost) are polished, and the agreement is counted."""
    span = np.maximum(problem.upper - problem.lower, 1e-30)
    # end points in far worse basins (ten times the best cost) are not worth polishing
    chosen = [i for i in distinct_best(ends, costs, polish_count, span)
              if costs[i] <= 10.0 * np.min(costs)]
    for i in chosen:
        result = polish(problem, ends[i], max_polish_evaluations)
        evaluations += result.evaluations
        stages.append(f"polish of start {i}: cost {costs[i]:.6g} -> {result.cost:.6g} "
                      f"({result.evaluations} evaluations)")
        if result.cost <= costs[i]:
            costs[i], ends[i] = result.cost, result.y
        if progress:
            progress(stages[-1])
    best = int(np.argmin(costs))
    agreeing = int(np.sum(costs <= costs[best] * (1.0 + AGREEMENT) + 1e-300))
    return MultistartResult(ends[best], float(costs[best]), costs, chosen, agreeing,
                            evaluations, time.perf_counter() - t0, stages)


def check_global_stage(name: str, option: str = "global_stage") -> str:
    """``name`` if it is one of :data:`GLOBAL_STAGES`; else an error naming ``option``, the
    value and the valid values."""
    if name not in GLOBAL_STAGES:
        raise ValueError(f"{option} = {name!r} is not a global stage; valid values are "
                         f"{', '.join(GLOBAL_STAGES)}")
    return name


#: Seeds of the global stages lie in [0, SEED_LIMIT): nlopt.srand takes an unsigned 32-bit
#: integer on every platform (a C ``unsigned long``), and the Sobol scrambling the same seeds
SEED_LIMIT = 2**32


def check_search(global_stage: str, starts, seed,
                 options: tuple[str, str, str] = ("global_stage", "starts", "seed")) -> None:
    """The options of a global stage, checked before any work: a known stage
    (:func:`check_global_stage`) whose module is installed (nlopt for ``mlsl`` and ``crs2``),
    ``starts >= 1`` and an integer ``seed`` in [0, :data:`SEED_LIMIT`); each error names the
    option (``options``: the names of the three, e.g. ``("--global", "--starts", "--seed")``),
    its value and the valid values.

    Raises:
        ValueError: any of them (also a missing nlopt, which :func:`nlopt_search` reports as
            an ImportError once the work has started).
    """
    check_global_stage(global_stage, options[0])
    if global_stage != "sobol":
        try:
            _nlopt()
        except ImportError as exc:
            raise ValueError(f"{options[0]} = {global_stage!r}: {exc}") from None
    check_range(options[1], starts, 1)
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)):
        raise ValueError(f"{options[2]} = {seed!r} is not an integer")
    if not 0 <= seed < SEED_LIMIT:
        raise ValueError(out_of_range(f"{options[2]} = {seed}", f"[0, {SEED_LIMIT - 1}]"))


def _nlopt():
    """The nlopt module, or an error saying how to get it."""
    try:
        import nlopt
    except ImportError:
        raise ImportError("the global stages mlsl and crs2 use nlopt, which is not installed: "
                          "pip install 'mitsuba-powder[nlopt]' (or pip install nlopt), or use "
                          "the sobol stage") from None
    return nlopt


def _nlopt_optimiser(nlopt, method: str, p: int, problem: BatchProblem):
    """nlopt's ``GN_MLSL_LDS`` (low-discrepancy MLSL, its local searches by ``LD_MMA`` on the
    gradient ``2 J^T r``; ``LD_LBFGS`` stops the whole run with a generic failure on the
    unmixing problems) or ``GN_CRS2_LM`` over the box."""
    algorithm = {"mlsl": nlopt.GN_MLSL_LDS, "crs2": nlopt.GN_CRS2_LM}[method]
    opt = nlopt.opt(algorithm, p)
    opt.set_lower_bounds(problem.lower)
    opt.set_upper_bounds(problem.upper)
    if method == "mlsl":
        local = nlopt.opt(nlopt.LD_MMA, p)
        local.set_ftol_rel(MLSL_LOCAL_FTOL)
        local.set_lower_bounds(problem.lower)
        local.set_upper_bounds(problem.upper)
        opt.set_local_optimizer(local)
    return opt


def _stopper(opt) -> Callable[[], None]:
    """``opt.force_stop`` through a weak reference to ``opt``.

    nlopt's optimiser holds its objective by a reference that Python's garbage collector
    cannot see (a C++ object of the SWIG wrapper), so an objective that holds the optimiser
    (e.g. its bound ``force_stop``) makes a cycle that is never collected: the objective, its
    problem and whatever the problem holds lived as long as the process. For the fit that was
    its :class:`~mitsuba_powder.plugin.brf.BatchBRF` engines, powder plugin instances whose
    parameters have one value per lane (e.g. 198), and Dr.Jit traces every live instance of
    the variant in a render's BSDF call: every later render in that variant failed
    ("jit_var_call(): size of output variable ... is 198 (must be 1)")."""
    optimiser = weakref.ref(opt)

    def stop() -> None:
        alive = optimiser()
        if alive is not None:
            alive.force_stop()

    return stop


def _recording_objective(problem: BatchProblem, points: list[np.ndarray], costs: list[float],
                         failed: list[BaseException], stop: Callable[[], None]
                         ) -> Callable[[np.ndarray, np.ndarray], float]:
    """nlopt's objective ``(y, grad) -> cost`` of ``problem`` (the sum of squared residuals,
    its gradient filled when nlopt asks), appending each point and its cost to ``points`` and
    ``costs``; a non-finite cost (outside the model's domain) is 1e300, never a NaN. An error
    of the problem is not raised through nlopt (its CRS2 goes on evaluating with the error
    pending, and Python then fails with a SystemError): it is kept in ``failed``, nlopt is
    stopped (``stop``) and the cost is 1e300 until it returns; :func:`nlopt_search` raises it.
    ``stop`` must not hold the optimiser (:func:`_stopper`)."""
    def objective(y: np.ndarray, grad: np.ndarray) -> float:
        if failed:
            return 1e300
        try:
            if grad.size:
                r, jac = problem.jacobian(y[None])
                r = r[0]
                grad[:] = 2.0 * (jac[0].T @ r)
            else:
                r = problem.residuals(y[None])[0]
        except BaseException as error:  # (Ctrl-C too) raised by nlopt_search once nlopt returns
            failed.append(error)
            stop()
            return 1e300
        c = float(r @ r)
        if not math.isfinite(c):
            c = 1e300  # outside the model's domain: the worst cost, never a NaN to nlopt
            if grad.size:
                grad[:] = 0.0
        points.append(np.array(y, dtype=np.float64))
        costs.append(c)
        return c

    return objective


def nlopt_search(problem: BatchProblem, method: str, max_evaluations: int, seed: int,
                 start: np.ndarray | None = None, polish_count: int = 4,
                 max_iterations: int = 60, max_polish_evaluations: int = 200,
                 progress: Callable[[str], None] | None = None) -> MultistartResult:
    """A global stage by nlopt (``method`` ``mlsl`` or ``crs2``, :func:`_nlopt_optimiser`) of
    ``max_evaluations`` single-point evaluations of the cost, from ``start`` (default: the
    middle of the box), its random numbers seeded with ``seed`` (nlopt.srand: the same seed,
    the same result). Every point it evaluates is kept; the best ``polish_count`` distinct ones
    take the batched Levenberg-Marquardt steps of :func:`multistart` with every variable free
    and its polish. ``evaluations`` of the result: the nlopt points, then batch evaluations of
    LM and single-point ones of the polish.

    Raises:
        ValueError: an unknown method or max_evaluations < 1.
        ImportError: nlopt is not installed.
    """
    check_global_stage(method)
    if method == "sobol":
        raise ValueError("nlopt_search runs mlsl or crs2; the sobol stage is multistart()")
    check_range("max_evaluations", max_evaluations, 1)
    nlopt = _nlopt()
    t0 = time.perf_counter()
    points: list[np.ndarray] = []
    costs: list[float] = []
    failed: list[BaseException] = []
    opt = _nlopt_optimiser(nlopt, method, len(problem.lower), problem)
    opt.set_min_objective(_recording_objective(problem, points, costs, failed, _stopper(opt)))
    opt.set_maxeval(int(max_evaluations))
    nlopt.srand(int(seed))
    y0 = (problem.lower + problem.upper) / 2.0 if start is None else np.asarray(start, float)
    stopped = ""
    try:
        opt.optimize(np.clip(y0, problem.lower, problem.upper))
    except (nlopt.RoundoffLimited, nlopt.ForcedStop, RuntimeError) as error:
        # nlopt's own failures (not the objective's errors, raised below as they are):
        # the points so far stand, the LM steps and the polish follow
        stopped = f" (nlopt stopped early: {type(error).__name__} {error})"
    if failed:
        # out of the objective's list first: the error's traceback holds the optimiser, which
        # holds the objective (_stopper), so left in the list it would never be collected
        raise failed.pop()
    if not points:
        raise RuntimeError(f"the global stage {method} (nlopt) stopped before evaluating a "
                           f"point{stopped}; try --global sobol")
    stages = [f"global: nlopt {method} ({opt.get_algorithm_name()}), {len(points)} "
              f"evaluations, best cost {min(costs):.6g}{stopped}"]
    if progress:
        progress(stages[-1])
    all_points, all_costs = np.array(points), np.array(costs)
    span = np.maximum(problem.upper - problem.lower, 1e-30)
    best = distinct_best(all_points, all_costs, polish_count, span)
    lm = batch_levenberg_marquardt(problem, all_points[best], max_iterations)
    stages.append(f"Levenberg-Marquardt from the best {len(best)} distinct points: "
                  f"{lm.iterations} iterations ({lm.evaluations} batch evaluations), best "
                  f"cost {np.min(lm.cost):.6g}")
    if progress:
        progress(stages[-1])
    return _polish_best(problem, lm.y.copy(), lm.cost.copy(), len(points) + lm.evaluations,
                        t0, stages, polish_count, max_polish_evaluations, progress)
