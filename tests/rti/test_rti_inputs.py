"""The checked inputs of a fit (mitsuba_powder.rti.inputs): each check of the capture against
the options, once, naming what is wrong; the data of a set of pixels gathered without
checking again, as a solver takes it; the observation flags (saturated, shadowed). The
captures are SYNTHETIC."""

from __future__ import annotations

import math

import numpy as np
import pytest

import mitsuba_powder.rti as rf
from mitsuba_powder.rti.forward import near_field
from mitsuba_powder.rti.inputs import check_inputs
from mitsuba_powder.rti.options import fit_options

SHAPE, LIGHTS = (5, 6), 8


@pytest.fixture(scope="module")
def capture():
    return rf.synthetic_capture(*SHAPE, LIGHTS, noise=0.0, seed=4)


@pytest.mark.parametrize("change, message", [
    (lambda c: {"images": c["images"][..., :2]}, r"images has shape \(8, 5, 6, 2\)"),
    (lambda c: {"images": np.where(c["images"] > 0.5, np.inf, c["images"])}, "is not finite"),
    (lambda c: {"directions": c["directions"][:-1]}, "directions has 7 rows for 8 images"),
    (lambda c: {"mask": np.ones((6, 5), bool)}, r"mask has shape \(6, 5\); expected \(5, 6\)"),
    (lambda c: {"mask": np.zeros(SHAPE, bool)}, "mask selects no pixel"),
    (lambda c: {"initial_gains": np.ones(3)}, r"gains has shape \(3,\); expected \(8,\)"),
    (lambda c: {"fixed": {"g": np.zeros((2, 2))}}, r"g has shape \(2, 2\); expected a scalar"),
    (lambda c: {"free": ["amplitude_surface"], "fixed": {"albedo": np.ones((2, 3))}},
     r"fixed albedo has shape \(2, 3\); expected \(3,\) or \(5, 6, 3\)"),
    (lambda c: {"free": ["amplitude_surface"], "fixed": {"albedo": [0.5, 1.5, 0.5]}},
     r"albedo\[0, 0\] = 1.5 is out of range; valid range is \[0, 1\]"),
    (lambda c: {"light_distance": 0.6}, r"light_distance = 0.6 image widths is out of range"),
])
def test_each_input_is_checked_against_the_capture(capture, change, message):
    given = change(capture)
    images = given.pop("images", capture["images"])
    directions = given.pop("directions", capture["directions"])
    mask = given.pop("mask", None)
    with pytest.raises(ValueError, match=message):
        check_inputs(images, directions, fit_options(**given), mask)


def test_a_light_distance_is_named_as_the_caller_names_it(capture):
    options = fit_options(light_distance=0.6, names={"light_distance": "--light-distance"})
    with pytest.raises(ValueError, match=r"^--light-distance = 0.6 image widths"):
        check_inputs(capture["images"], capture["directions"], options)


def test_the_data_of_a_set_of_pixels(capture):
    """A block's observations, held maps, held albedo and lights are those of its pixels, in
    C order (what a fit of only those pixels would gather)."""
    rng = np.random.default_rng(0)
    mask = rng.random(SHAPE) < 0.7
    sel = mask & (rng.random(SHAPE) < 0.5)
    held_g = rng.uniform(-0.5, 0.5, SHAPE)
    albedo = rng.uniform(0.2, 0.9, SHAPE + (3,))
    options = fit_options(free=["amplitude_surface"], fixed={"g": held_g, "albedo": albedo},
                          initial_gains=np.linspace(0.8, 1.2, LIGHTS))
    inputs = check_inputs(capture["images"], capture["directions"], options, mask)
    gains = np.full(LIGHTS, 1.1)
    data = inputs.pixels(sel, gains, math.inf, options)
    np.testing.assert_array_equal(data.obs, capture["images"][:, sel].transpose(1, 0, 2))
    np.testing.assert_array_equal(data.fixed_maps["g"], held_g[sel])
    np.testing.assert_array_equal(data.fixed_albedo, albedo[sel])
    assert data.field is None and data.gains is gains and data.scale == pytest.approx(1.1)
    np.testing.assert_allclose(inputs.gains, np.linspace(0.8, 1.2, LIGHTS))
    near = inputs.pixels(sel, gains, 3.0, options)
    expected = near_field(inputs.d, 3.0, SHAPE, sel)
    np.testing.assert_array_equal(near.field[0], expected[0])
    np.testing.assert_array_equal(near.field[1], expected[1])
    weights = np.ones(data.obs.shape[:2])
    part = near.pixel_data(slice(1, 3), weights, gains, [])
    np.testing.assert_array_equal(part.observed, near.obs[1:3])
    np.testing.assert_array_equal(part.directions, near.field[0][1:3])
    np.testing.assert_array_equal(part.irradiance, near.field[1][1:3])
    np.testing.assert_array_equal(part.fixed["g"], held_g[sel][1:3])


def test_a_held_grain_size_sets_the_albedo_of_its_pixels(capture):
    options = fit_options(free=["amplitude_surface"], fixed={"radius": 0.08})
    inputs = check_inputs(capture["images"], capture["directions"], options)
    data = inputs.pixels(inputs.mask, inputs.gains, math.inf, options)
    rho, _ = inputs.grain(np.full(1, 0.08))
    np.testing.assert_allclose(data.fixed_albedo, np.broadcast_to(rho, (30, 3)), rtol=1e-12)


def test_observations_flagged_saturated_or_shadowed(capture):
    options = fit_options(saturation=0.9, shadow_ratio=0.5, shadow_floor=0.01)
    inputs = check_inputs(capture["images"], capture["directions"], options)
    data = inputs.pixels(inputs.mask, inputs.gains, math.inf, options)
    data.obs[0, 0] = [0.95, 0.1, 0.1]       # one channel saturated
    data.obs[1, 0] = [0.1, 0.1, 0.1]        # far below the prediction: shadowed
    data.obs[2, 0] = [0.2, 0.2, 0.2]        # below, within the ratio
    predicted = np.full(data.obs.shape, 0.3)
    weights = data.flags(predicted)
    assert weights[0, 0] == 0 and weights[1, 0] == 0 and weights[2, 0] == 1
    assert data.saturated[0, 0] and not data.saturated[1, 0]
