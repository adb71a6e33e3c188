"""Smooth per-light gain model (mitsuba_powder.rti.gains): a SYNTHETIC elevation trend
recovered from noisy gains and evaluated at held-out directions, the residual gains against a
direct solution of the joint least-squares problem, derivatives against finite differences,
serialisation, and degenerate inputs."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mitsuba_powder.rti.gains import GainModel, fit_gain_model, gain_basis


def _dirs(elevations, azimuths) -> np.ndarray:
    e, a = np.radians(np.asarray(elevations, float)), np.radians(np.asarray(azimuths, float))
    return np.stack([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)], axis=1)


#: a dome of 12 rings at the elevations of the real domes' gains, 4 lights each (SYNTHETIC)
RINGS = np.array([11, 14, 17, 30, 33, 36, 48, 52, 57, 67, 72, 78], dtype=float)
DOME = _dirs(np.repeat(RINGS, 4), np.tile([10.0, 100.0, 190.0, 280.0], 12)
             + np.repeat(np.arange(12) * 7.0, 4))


def _truth(directions: np.ndarray) -> np.ndarray:
    """A smooth, not polynomial, trend: 1.16 at 11 degrees falling to 0.91 at 78 (SYNTHETIC)."""
    e = np.degrees(np.arcsin(directions[:, 2]))
    return 0.9 + 0.28 * np.exp(-(e - 10.0) / 18.0)


def test_basis_columns():
    d = _dirs([20.0, 60.0], [30.0, 200.0])
    lx, ly, lz = d.T
    b = gain_basis(d, degree=3, azimuth_order=2)
    np.testing.assert_allclose(b, np.stack([np.ones(2), lz, lz**2, lz**3, lx, ly,
                                            lx**2 - ly**2, 2 * lx * ly], axis=1))
    assert gain_basis(d).shape == (2, 3)
    clamped = gain_basis(d, degree=1, lz_range=(0.5, 0.8))
    np.testing.assert_allclose(clamped[:, 1], [0.5, 0.8])


def test_trend_recovered_at_held_out_directions():
    sigma = 0.015
    rng = np.random.default_rng(0)
    gains = _truth(DOME) * np.exp(rng.normal(0.0, sigma, len(DOME)))
    held = _dirs(rng.uniform(11.0, 78.0, 300), rng.uniform(0.0, 360.0, 300))
    truth = _truth(held)
    assert np.max(truth) / np.min(truth) > 1.25  # a +-12 % trend
    for degree in (2, 3):
        model = fit_gain_model(DOME, gains, degree=degree)
        err = np.log(model.evaluate(held) / truth)
        # within the noise of one light's gain (the fit averages the noise down)
        assert np.sqrt(np.mean(err**2)) < 0.6 * sigma
        assert np.max(np.abs(err)) < 1.5 * sigma
    # today's relight (gain 1 for a light not fitted) is off by the trend
    assert np.max(np.abs(np.log(truth))) > 6 * sigma


def test_trend_coefficients_equal_weighted_polyfit():
    rng = np.random.default_rng(1)
    gains = _truth(DOME) * np.exp(rng.normal(0.0, 0.01, len(DOME)))
    w = rng.uniform(0.2, 3.0, len(DOME))
    model = fit_gain_model(DOME, gains, weights=w, degree=2)
    ref = np.polyfit(DOME[:, 2], np.log(gains), 2, w=np.sqrt(w))[::-1]
    np.testing.assert_allclose(model.coefficients, ref, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(model.residuals, 0.0)
    np.testing.assert_allclose(model.gains(), model.trend(DOME))


def test_residuals_solve_the_joint_problem():
    """c and delta against a direct least-squares solution of the augmented system
    ``[sqrt(w) B, sqrt(w) I; 0, sqrt(strength) I] [c; delta] = [sqrt(w) ln g; 0]``."""
    rng = np.random.default_rng(2)
    gains = _truth(DOME) * np.exp(rng.normal(0.0, 0.03, len(DOME)))
    w = rng.uniform(0.5, 2.0, len(DOME))
    w[5] = 0.0
    wn = w / w.mean()
    y = np.log(gains)
    k = len(DOME)
    for strength in (0.05, 1.0, 20.0):
        model = fit_gain_model(DOME, gains, weights=w, degree=2, azimuth_order=1,
                               strength=strength)
        b = gain_basis(DOME, 2, 1, model.lz_range)
        sw = np.sqrt(wn)[:, None]
        a = np.block([[sw * b, sw * np.eye(k)],
                      [np.zeros((k, b.shape[1])), math.sqrt(strength) * np.eye(k)]])
        sol = np.linalg.lstsq(a, np.concatenate([np.sqrt(wn) * y, np.zeros(k)]), rcond=None)[0]
        np.testing.assert_allclose(model.coefficients, sol[:b.shape[1]], atol=1e-10)
        np.testing.assert_allclose(model.residuals, sol[b.shape[1]:], atol=1e-10)
        assert model.residuals[5] == 0.0  # a light of weight 0 keeps no residual
    # strength 0: the fitted lights keep their gains exactly
    free = fit_gain_model(DOME, gains, weights=w, strength=0.0)
    np.testing.assert_allclose(free.gains()[w > 0], gains[w > 0], rtol=1e-12)


def test_residuals_shrink_towards_the_truth():
    """Gains = trend x a per-light deviation (spread tau) measured with noise sigma: strength
    sigma^2 / tau^2 gives per-light gains closer to the truth than the trend or the raw gains."""
    rng = np.random.default_rng(3)
    d = _dirs(rng.uniform(10.0, 80.0, 400), rng.uniform(0.0, 360.0, 400))
    sigma = tau = 0.02
    true_gain = _truth(d) * np.exp(rng.normal(0.0, tau, len(d)))
    measured = true_gain * np.exp(rng.normal(0.0, sigma, len(d)))

    def mse(strength: float) -> float:
        model = fit_gain_model(d, measured, strength=strength)
        return float(np.mean(np.log(model.gains() / true_gain) ** 2))

    best = mse(sigma**2 / tau**2)
    assert best < 0.7 * mse(math.inf) and best < 0.7 * mse(0.0)


def test_evaluate_matches_fitted_lights_and_clamps():
    rng = np.random.default_rng(4)
    gains = _truth(DOME) * np.exp(rng.normal(0.0, 0.02, len(DOME)))
    model = fit_gain_model(DOME, gains, strength=0.5)
    np.testing.assert_allclose(model.evaluate(DOME), model.gains())
    idx = model.matches(np.vstack([DOME[7], _dirs([45.0], [45.0])]))
    assert idx.tolist() == [7, -1]
    new = _dirs([45.0], [45.0])
    np.testing.assert_allclose(model.evaluate(new), model.trend(new))
    # below the lowest ring: held at the lowest ring's trend unless extrapolating
    low, lowest = _dirs([3.0], [0.0]), _dirs([11.0], [0.0])
    np.testing.assert_allclose(model.trend(low), model.trend(lowest))
    assert model.trend(low, extrapolate=True)[0] != pytest.approx(model.trend(lowest)[0])
    twice = model.scaled(2.0)
    np.testing.assert_allclose(twice.evaluate(DOME), 2.0 * model.evaluate(DOME))


def test_jacobian_against_finite_differences():
    rng = np.random.default_rng(5)
    gains = _truth(DOME) * np.exp(rng.normal(0.0, 0.02, len(DOME)))
    model = fit_gain_model(DOME, gains, degree=2, azimuth_order=2, strength=1.0)
    at = np.vstack([DOME[:5], _dirs([25.0, 70.0], [15.0, 250.0])])
    jac = model.jacobian(at)
    h = 1e-6
    for j in range(len(model.coefficients)):
        step = np.zeros_like(model.coefficients)
        step[j] = h
        plus, minus = (GainModel(model.coefficients + s, model.degree, model.azimuth_order,
                                 model.lz_range, model.strength, model.directions,
                                 model.residuals) for s in (step, -step))
        fd = (plus.evaluate(at) - minus.evaluate(at)) / (2 * h)
        np.testing.assert_allclose(jac[:, j], fd, rtol=1e-7, atol=1e-10)


def test_dict_round_trip():
    rng = np.random.default_rng(6)
    gains = _truth(DOME) * np.exp(rng.normal(0.0, 0.02, len(DOME)))
    for strength in (math.inf, 0.3):
        model = fit_gain_model(DOME, gains, degree=3, azimuth_order=1, strength=strength)
        text = json.dumps(model.to_dict(), allow_nan=False)  # strict JSON for fit.json
        back = GainModel.from_dict(json.loads(text))
        assert (back.degree, back.azimuth_order, back.strength) == (3, 1, strength)
        new = _dirs([5.0, 40.0, 85.0], [0.0, 120.0, 240.0])
        np.testing.assert_allclose(back.evaluate(new), model.evaluate(new), rtol=1e-15)
        np.testing.assert_allclose(back.gains(), model.gains(), rtol=1e-15)
    data = fit_gain_model(DOME, gains).to_dict()
    with pytest.raises(ValueError, match="kind = 'maps'"):
        GainModel.from_dict({**data, "kind": "maps"})
    with pytest.raises(ValueError, match=r"keys \['residuals'\] are missing"):
        GainModel.from_dict({k: v for k, v in data.items() if k != "residuals"})
    with pytest.raises(ValueError, match="coefficients .* expected 3 finite numbers"):
        GainModel.from_dict({**data, "coefficients": [1.0, 2.0]})
    with pytest.raises(ValueError, match="strength = -1 is out of range"):
        GainModel.from_dict({**data, "strength": -1})


def test_degenerate_inputs():
    ring = _dirs([30.0] * 6, np.arange(6) * 60.0)
    with pytest.raises(ValueError, match=r"degree 2 in lz and azimuth order 0 has 3 "
                                         r"coefficients; 2 lights of weight > 0 are too few"):
        fit_gain_model(DOME[:2], np.ones(2))
    with pytest.raises(ValueError, match=r"degree = 1 in lz needs lights at >= 2 distinct "
                                         r"elevations; the lights of weight > 0 have 1 "
                                         r"\(lz = 0.5\); lower the degree"):
        fit_gain_model(ring, np.ones(6), degree=1)
    fit_gain_model(ring, np.ones(6), degree=0, azimuth_order=2)  # one ring: azimuth only
    # every light in one vertical plane: ly = 0 everywhere cannot fix the ly term
    plane = _dirs(np.linspace(10.0, 80.0, 8), np.zeros(8))
    with pytest.raises(ValueError, match="determine only 3 of the 4 functions"):
        fit_gain_model(plane, np.ones(8), degree=1, azimuth_order=1)
    # weights leave too few lights
    w = np.zeros(len(DOME))
    w[:2] = 1.0
    with pytest.raises(ValueError, match="2 lights of weight > 0 are too few"):
        fit_gain_model(DOME, np.ones(len(DOME)), weights=w)
    with pytest.raises(ValueError, match="not all 0"):
        fit_gain_model(DOME, np.ones(len(DOME)), weights=np.zeros(len(DOME)))
    with pytest.raises(ValueError, match=r"gains\[3\] = -1.0 is out of range; valid range is "
                                         r"\(0, inf\)"):
        fit_gain_model(DOME, np.where(np.arange(len(DOME)) == 3, -1.0, 1.0))
    with pytest.raises(ValueError, match="degree = 7 is out of range; valid range is the whole "
                                         "numbers 0-6"):
        fit_gain_model(DOME, np.ones(len(DOME)), degree=7)
    with pytest.raises(ValueError, match="degree = 1.5 is out of range"):
        gain_basis(DOME, degree=1.5)
    with pytest.raises(ValueError, match=r"strength = -0.1 is out of range; valid range is "
                                         r"\[0, inf\]"):
        fit_gain_model(DOME, np.ones(len(DOME)), strength=-0.1)
