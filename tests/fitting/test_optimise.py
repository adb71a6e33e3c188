"""The shared optimiser (mitsuba_powder.fitting.optimise) on problems with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from mitsuba_powder.fitting.optimise import (
    GLOBAL_STAGES,
    ParamSpec,
    batch_levenberg_marquardt,
    check_global_stage,
    check_search,
    distinct_best,
    finite_difference_jacobian,
    multistart,
    nlopt_search,
    polish,
    sobol_starts,
)


class TwoExponentials:
    """r(y) = a1 exp(-k1 t) + a2 exp(-k2 t) - data: a classic multi-minimum fit (the two terms
    can swap, and a one-term fit is a local minimum), y = (a1, log10 k1, a2, log10 k2)."""

    def __init__(self, truth=(1.0, 0.0, 0.5, 1.0), noise=0.0):
        self.t = np.linspace(0.0, 4.0, 60)
        self.data = self.model(np.array([truth]))[0]
        self.data += noise * np.random.default_rng(1).normal(size=self.t.size)
        self.lower = np.array([0.0, -2.0, 0.0, -2.0])
        self.upper = np.array([2.0, 2.0, 2.0, 2.0])
        self.calls = 0

    def model(self, y):
        a1, k1, a2, k2 = (y[:, j:j + 1] for j in range(4))
        return a1 * np.exp(-(10.0**k1) * self.t) + a2 * np.exp(-(10.0**k2) * self.t)

    def residuals(self, y):
        self.calls += 1
        return self.model(np.atleast_2d(y)) - self.data

    def jacobian(self, y):
        y = np.atleast_2d(y)
        a1, k1, a2, k2 = (y[:, j:j + 1] for j in range(4))
        e1, e2 = np.exp(-(10.0**k1) * self.t), np.exp(-(10.0**k2) * self.t)
        ln = np.log(10.0)
        jac = np.stack([e1, -a1 * self.t * e1 * 10.0**k1 * ln, e2,
                        -a2 * self.t * e2 * 10.0**k2 * ln], axis=2)
        return self.residuals(y), jac


def test_param_spec_transforms():
    spec = ParamSpec(1e-3, 1e3, True, 1.0)
    assert spec.to_y(100.0) == pytest.approx(2.0)
    assert spec.to_x(spec.to_y(0.37)) == pytest.approx(0.37)
    h = 1e-6
    assert spec.dx_dy(5.0) == pytest.approx((spec.to_x(spec.to_y(5.0) + h) - 5.0) / h, rel=1e-5)
    lin = ParamSpec(-1.0, 1.0, False, 0.0)
    assert lin.to_y(0.3) == 0.3 and lin.dx_dy(0.3) == 1.0


def test_sobol_starts_fill_the_box():
    lower, upper = np.array([0.0, -3.0]), np.array([1.0, 3.0])
    y = sobol_starts(lower, upper, 64, seed=0)
    assert y.shape == (64, 2)
    assert np.all(y >= lower) and np.all(y <= upper)
    # space filling: every quarter of each axis holds a quarter of the points
    for j in range(2):
        counts = np.histogram(y[:, j], bins=4, range=(lower[j], upper[j]))[0]
        assert np.all(counts == 16)
    assert not np.allclose(y, sobol_starts(lower, upper, 64, seed=1))
    with pytest.raises(ValueError, match="starts = 0 is out of range"):
        sobol_starts(lower, upper, 0, seed=0)


def test_batched_levenberg_marquardt_reaches_the_minimum_from_many_starts():
    problem = TwoExponentials()
    starts = sobol_starts(problem.lower, problem.upper, 32, seed=3)
    state = batch_levenberg_marquardt(problem, starts, max_iterations=200)
    assert state.y.shape == starts.shape
    best = int(np.argmin(state.cost))
    assert state.cost[best] < 1e-12
    # the two terms may swap: compare the sorted (amplitude, rate) pairs
    pairs = sorted([(state.y[best, 0], state.y[best, 1]), (state.y[best, 2], state.y[best, 3])],
                   key=lambda p: p[1])
    np.testing.assert_allclose(pairs, [(1.0, 0.0), (0.5, 1.0)], atol=1e-5)
    # every start ends no worse than it began and inside the box
    begin = np.sum(problem.residuals(starts) ** 2, axis=1)
    assert np.all(state.cost <= begin + 1e-15)
    assert np.all(state.y >= problem.lower) and np.all(state.y <= problem.upper)


def test_held_variables_stay_at_their_start():
    problem = TwoExponentials()
    starts = sobol_starts(problem.lower, problem.upper, 8, seed=0)
    hold = np.array([False, True, False, True])
    state = batch_levenberg_marquardt(problem, starts, hold=hold)
    np.testing.assert_array_equal(state.y[:, hold], starts[:, hold])
    # the free amplitudes are the linear least-squares solution for the held rates
    for b in range(len(starts)):
        k1, k2 = starts[b, 1], starts[b, 3]
        basis = np.stack([np.exp(-(10.0**k1) * problem.t), np.exp(-(10.0**k2) * problem.t)],
                         axis=1)
        amps = np.linalg.lstsq(basis, problem.data, rcond=None)[0]
        if np.all((amps >= 0) & (amps <= 2)):
            np.testing.assert_allclose(state.y[b, [0, 2]], amps, atol=1e-4)


def test_polish_respects_bounds_and_held_variables():
    problem = TwoExponentials(truth=(1.0, 0.0, 1.8, 1.0))
    problem.upper = np.array([2.0, 2.0, 1.5, 2.0])  # the true a2 = 1.8 lies outside
    result = polish(problem, np.array([0.5, 0.2, 0.5, 0.8]))
    assert result.y[2] == pytest.approx(1.5)  # at its bound
    held = polish(problem, np.array([0.5, 0.2, 0.5, 0.8]),
                  hold=np.array([False, True, False, False]))
    assert held.y[1] == 0.2 and held.cost >= result.cost - 1e-12


def test_multistart_counts_agreeing_starts_and_finds_the_global_minimum():
    problem = TwoExponentials(noise=0.002)
    result = multistart(problem, sobol_starts(problem.lower, problem.upper, 32, seed=2),
                        polish_count=3)
    assert result.agreeing >= 2
    assert len(result.start_costs) == 32 and result.cost == pytest.approx(
        np.min(result.start_costs))
    assert np.sum(result.start_costs <= result.cost * 1.01) == result.agreeing
    # a single start from the one-term valley (a2 = 0) stays there: one agreeing start
    lone = multistart(problem, np.array([[1.2, 0.05, 0.0, -2.0]]), polish_count=1)
    assert lone.agreeing == 1


def test_finite_difference_jacobian_matches_the_analytic_one():
    problem = TwoExponentials()
    fd = finite_difference_jacobian(problem.residuals, problem.lower, problem.upper)
    y = np.array([[0.7, 0.1, 0.4, 0.9], [1.5, -0.5, 0.2, 1.2]])
    np.testing.assert_allclose(fd(y)[1], problem.jacobian(y)[1], rtol=1e-5, atol=1e-8)


def test_distinct_best_skips_near_duplicates():
    y = np.array([[0.0, 0.0], [0.001, 0.0], [0.5, 0.5], [1.0, 1.0]])
    cost = np.array([1.0, 0.9, 2.0, np.nan])
    assert distinct_best(y, cost, 3, np.array([1.0, 1.0])) == [1, 2]


# ------------------------------------------------------------ the nlopt global stages


@pytest.mark.parametrize("method", ["mlsl", "crs2"])
def test_nlopt_stage_finds_the_global_minimum(method):
    """MLSL and CRS2 (then the LM steps and the polish) reach the two-term optimum from the
    one-term valley, where a single LM start stays."""
    problem = TwoExponentials(noise=0.002)
    best = multistart(problem, sobol_starts(problem.lower, problem.upper, 32, seed=2))
    result = nlopt_search(problem, method, 600, seed=1, start=np.array([1.2, 0.05, 0.0, -2.0]))
    assert result.cost == pytest.approx(best.cost, rel=1e-6)
    assert result.evaluations > 600 and "nlopt" in result.stages[0]
    assert np.all(result.y >= problem.lower) and np.all(result.y <= problem.upper)


@pytest.mark.parametrize("method", ["mlsl", "crs2"])
def test_nlopt_stage_is_reproducible_with_a_seed(method):
    """The same seed, the same points (nlopt.srand before each run); CRS2's random population
    differs with another seed."""
    def run(seed):
        problem = TwoExponentials(noise=0.002)
        r = nlopt_search(problem, method, 300, seed=seed)
        return r, problem.calls

    (a, calls_a), (b, calls_b) = run(7), run(7)
    np.testing.assert_array_equal(a.y, b.y)
    np.testing.assert_array_equal(a.start_costs, b.start_costs)
    assert calls_a == calls_b and a.stages == b.stages
    if method == "crs2":
        c, _ = run(8)
        assert c.stages[0] != a.stages[0] or not np.array_equal(c.start_costs, a.start_costs)


def test_unknown_global_stage_names_the_option_and_the_valid_values():
    with pytest.raises(ValueError, match=r"global_stage = 'lbfgs' is not a global stage; "
                                         r"valid values are sobol, mlsl, crs2"):
        check_global_stage("lbfgs")
    with pytest.raises(ValueError, match=r"--global = 'x' is not a global stage"):
        check_global_stage("x", "--global")
    assert GLOBAL_STAGES == ("sobol", "mlsl", "crs2")
    with pytest.raises(ValueError, match="global_stage = 'de'"):
        nlopt_search(TwoExponentials(), "de", 10, seed=0)


def test_without_nlopt_the_stage_says_how_to_install_it(monkeypatch):
    import sys

    monkeypatch.setitem(sys.modules, "nlopt", None)
    with pytest.raises(ImportError, match=r"pip install 'mitsuba-powder\[nlopt\]'.*sobol"):
        nlopt_search(TwoExponentials(), "crs2", 10, seed=0)


def test_check_search_names_the_option_the_value_and_the_range(monkeypatch):
    import sys

    flags = ("--global", "--starts", "--seed")
    with pytest.raises(ValueError, match=r"--seed = 4294967296 is out of range; valid range is "
                                         r"\[0, 4294967295\]"):
        check_search("sobol", 1, 2**32, flags)
    with pytest.raises(ValueError, match=r"seed = -1 is out of range"):
        check_search("sobol", 1, -1)
    with pytest.raises(ValueError, match=r"seed = 1.5 is not an integer"):
        check_search("sobol", 1, 1.5)
    with pytest.raises(ValueError, match=r"--starts = 0 is out of range; valid range is "
                                         r"\[1, inf\)"):
        check_search("sobol", 0, 0, flags)
    check_search("sobol", 1, 2**32 - 1)
    monkeypatch.setitem(sys.modules, "nlopt", None)
    check_search("sobol", 1, 0)  # the Sobol stage needs no nlopt
    with pytest.raises(ValueError, match=r"--global = 'crs2': the global stages mlsl and crs2 "
                                         r"use nlopt, which is not installed"):
        check_search("crs2", 1, 0, flags)


def test_an_nlopt_stage_that_stops_before_any_point_is_a_clear_error(monkeypatch):
    """nlopt failing before its first evaluation (a roundoff failure at the start) was
    ``min() arg is an empty sequence``."""
    import nlopt

    from mitsuba_powder.fitting import optimise

    real = optimise._nlopt_optimiser

    class Stopping:
        def __init__(self, opt):
            self.opt = opt

        def __getattr__(self, name):
            return getattr(self.opt, name)

        def optimize(self, y0):
            raise nlopt.RoundoffLimited("roundoff")

    monkeypatch.setattr(optimise, "_nlopt_optimiser", lambda *a: Stopping(real(*a)))
    with pytest.raises(RuntimeError, match=r"the global stage crs2 \(nlopt\) stopped before "
                                           r"evaluating a point \(nlopt stopped early: "
                                           r"RoundoffLimited roundoff\)"):
        nlopt_search(TwoExponentials(), "crs2", 10, seed=0)


class OutsideItsDomain(TwoExponentials):
    """TwoExponentials whose model refuses a1 > 1.5 (as the plugin refuses a radius outside
    its range): an error, not a cost."""

    def residuals(self, y):
        if np.any(np.atleast_2d(y)[:, 0] > 1.5):
            raise ValueError("a1 outside the model's domain")
        return super().residuals(y)

    def jacobian(self, y):
        if np.any(np.atleast_2d(y)[:, 0] > 1.5):
            raise ValueError("a1 outside the model's domain")
        return super().jacobian(y)


@pytest.mark.parametrize("method", ["crs2", "mlsl"])
def test_an_error_of_the_model_reaches_the_caller_as_it_is(method):
    """CRS2 went on evaluating with the model's error pending, and Python failed with a
    SystemError (a traceback from the command line)."""
    for seed in range(3):
        with pytest.raises(ValueError, match="a1 outside the model's domain"):
            nlopt_search(OutsideItsDomain(), method, 300, seed=seed)


def _nothing_holds_the_problem_after(method: str, problem_type: type) -> bool:
    """Whether ``problem_type()``, searched by ``method`` (and its error, if any, caught and
    dropped), is collected once nlopt_search is done with it."""
    import gc
    import weakref

    problem = problem_type()
    alive = weakref.ref(problem)
    try:
        nlopt_search(problem, method, 300, seed=0)
    except ValueError:
        pass
    del problem
    gc.collect()
    return alive() is None


@pytest.mark.parametrize("method", ["mlsl", "crs2"])
def test_an_nlopt_stage_keeps_nothing_of_its_problem(method):
    """After nlopt_search, normally or by the model's error, nothing holds the problem. The
    objective held nlopt's optimiser (its force_stop), which holds the objective by a
    reference the garbage collector cannot see: the problem lived as long as the process, and
    a fit's plugin instances in it broke every later spectral render
    (test_unmix.py::test_a_spectral_render_after_a_crs2_fit)."""
    with pytest.raises(ValueError, match="a1 outside"):
        nlopt_search(OutsideItsDomain(), method, 300, seed=0)  # (the error path is taken)
    assert _nothing_holds_the_problem_after(method, TwoExponentials)
    assert _nothing_holds_the_problem_after(method, OutsideItsDomain)
