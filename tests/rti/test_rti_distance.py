"""The dome's light distance (mitsuba_powder.rti.distance): the subsample it is fitted on,
the Lambertian scan of the inverse distance on a SYNTHETIC Lambertian capture lit from a
known distance (exact model: the scan's minimum is the grid point nearest the truth), and the
bounded polish (the fit of the powder model's cost: tests/rti/test_rti_near.py)."""

from __future__ import annotations

import math

import numpy as np

from helpers import lambertian_capture
from mitsuba_powder.rti.distance import (
    POLISH_EVALUATIONS,
    SCAN_POINTS,
    polish_inverse_distance,
    scan_inverse_distance,
    subsample_mask,
)
from mitsuba_powder.rti.lights import half_diagonal


def test_the_subsample_spreads_over_the_whole_mask():
    mask = np.zeros((60, 50), bool)
    mask[5:55, 10:45] = True
    sub = subsample_mask(mask, 100)
    assert 0 < sub.sum() <= 100 and not np.any(sub & ~mask)
    rows = np.flatnonzero(sub.any(axis=1))
    assert rows.min() < 10 and rows.max() > 50  # over the whole mask, not its first rows
    small = np.zeros((4, 4), bool)
    small[1, 1:3] = True
    np.testing.assert_array_equal(subsample_mask(small, 100), small)  # fewer: every pixel


def _lambertian_capture(r: float, shape=(20, 24), lights: int = 30):
    """Lambertian pixels (known normals and reflectances) lit from r image widths, as
    observations (P, K, 3), and the lights' directions."""
    c = lambertian_capture(shape, lights, r, tilt=0.15, seed=1)
    return c["images"].reshape(lights, -1, 3).transpose(1, 0, 2), c["directions"]


def test_the_lambertian_scan_finds_the_distance_of_a_lambertian_capture():
    """r on the scan's grid (2.17 image widths): its grid point has the least cost."""
    shape = (20, 24)
    r = 1.0 / np.linspace(0.0, 0.9 / half_diagonal(shape), SCAN_POINTS)[4]  # on the grid
    obs, d = _lambertian_capture(r, shape)
    mask = np.ones(shape, bool)
    us, costs = scan_inverse_distance(obs, np.ones(obs.shape[:2]), mask, d, np.ones(len(d)))
    assert len(us) == SCAN_POINTS and us[0] == 0.0
    np.testing.assert_allclose(us[-1], 0.9 / half_diagonal(shape))
    best = int(np.argmin(costs))
    assert best == int(np.argmin(np.abs(us - 1.0 / r)))
    assert costs[best] < 1e-2 * costs[0]  # distant lights fit far worse
    # a distant capture: the scan prefers u = 0
    obs_far, _ = _lambertian_capture(math.inf, shape)
    _, far = scan_inverse_distance(obs_far, np.ones(obs.shape[:2]), mask, d, np.ones(len(d)))
    assert int(np.argmin(far)) == 0


def test_the_polish_minimises_within_the_best_bracket():
    us = np.linspace(0.0, 1.2, 13)
    truth = 0.43

    def cost(u):
        return (u - truth) ** 2

    u, seen = polish_inverse_distance(cost, us, cost(us))
    assert len(seen) <= POLISH_EVALUATIONS
    assert us[3] <= u <= us[5] and abs(u - truth) < 0.01
    assert all(us[3] <= v <= us[5] for v, _ in seen)
    # a minimum at u = 0 (distant lights) is kept at 0, never negative
    u0, _ = polish_inverse_distance(lambda v: (v + 0.1) ** 2, us, (us + 0.1) ** 2)
    assert 0.0 <= u0 < 0.02
