"""Hapke's macroscopic roughness (mean slope angle theta_bar) in the ``hapke`` baseline."""

from __future__ import annotations

import math

import numpy as np
import pytest

from helpers import random_hemisphere
from mitsuba_powder.fitting.baselines import MODELS, hapke, hapke_h, hapke_roughness
from mitsuba_powder.io.measurements import gonio_directions

SMOOTH = {"w": 0.8, "b": 0.3, "c": 0.4, "B_s0": 1.0, "h_s": 0.06, "B_c0": 0.5, "h_c": 0.02}

# Reference BRFs of Eradiate's Hapke plugin tests: repository eradiate/mitsuba3 (BSD-3-Clause,
# the Mitsuba 3 licence), files resources/tests/eradiate_plugins/bsdfs/
# hapke_principal_plane_example.nc and hapke_hemisphere_example.nc (variable `reflectance`,
# a BRF; the plugin's test labels it "Reference (Nguyen, Jacquemoud et al.)"). A handful of
# values reproduced here, not the files. Parameters of Pommerol et al. (2013): w = 0.526,
# theta = 13.3 deg, b = 0.187, their c = 0.6365 = (1 + 0.273) / 2, h = 0.083, B_0 = 1, no
# coherent back-scattering. Eradiate's phase function is (1 - c_E) HG_forward + c_E HG_back, this
# project's (1 - c)/2 HG_forward + (1 + c)/2 HG_back, so c = 2 c_E - 1 = 0.273. theta_i = 30 deg;
# the light at azimuth 0 in both (phi = 0, theta_o > 0 is the back-scattering side).
POMMEROL = {"w": 0.526, "b": 0.187, "c": 2 * 0.6365 - 1, "B_s0": 1.0, "h_s": 0.083,
            "B_c0": 0.0, "h_c": 0.01, "theta_bar": 13.3}
# principal plane: signed view zenith `svza` (deg) -> BRF
PRINCIPAL_PLANE = {-89: 0.15426361416626477, -75: 0.14659899990790362,
                   -60: 0.13963297458525023, -45: 0.13287565113608396,
                   -30: 0.13147544865706384, -15: 0.1366557897601734, 0: 0.14886781186094508,
                   14: 0.17026408848063448, 30: 0.24746653093454496, 31: 0.2387982327937265,
                   45: 0.19755379835408934, 60: 0.19394715831256432, 75: 0.19537031151300527,
                   89: 0.19550839826786418}
# hemisphere: (view azimuth `phi`, view zenith `vza`) in deg -> BRF
HEMISPHERE = {(10, 30): 0.21166285957235148, (45, 20): 0.16501619898078565,
              (90, 60): 0.15492245577553318, (135, 45): 0.13649480574301567,
              (170, 30): 0.13165055627777295, (180, 60): 0.13963297458525023,
              (200, 10): 0.1403029025793395, (270, 85): 0.16449464617621296,
              (353, 30): 0.21962458221939352}


def smooth_hapke(p: dict, wi: np.ndarray, wo: np.ndarray) -> np.ndarray:
    """The baseline before the roughness (theta_bar = 0), frozen here as the reference."""
    mu0, mu = wi[:, 2], wo[:, 2]
    cos_g = np.clip(np.sum(wi * wo, axis=1), -1.0, 1.0)
    b, c, w = p["b"], p["c"], p["w"]
    hg = lambda s: (1 - b * b) / (1 + s * 2 * b * cos_g + b * b) ** 1.5  # noqa: E731
    phase = 0.5 * (1 + c) * hg(-1.0) + 0.5 * (1 - c) * hg(1.0)
    tan_half = np.sqrt(np.maximum(0.0, (1.0 - cos_g) / (1.0 + cos_g)))
    b_s = 1.0 / (1.0 + tan_half / p["h_s"])
    y = tan_half / p["h_c"]
    b_c = (1.0 + np.where(y > 1e-8, -np.expm1(-y) / np.maximum(y, 1e-300), 1.0)) \
        / (2.0 * (1.0 + y) ** 2)
    r = w / (4 * np.pi) * mu0 / (mu0 + mu) * (phase * (1.0 + p["B_s0"] * b_s)
                                              + hapke_h(mu0, w) * hapke_h(mu, w) - 1.0) \
        * (1.0 + p["B_c0"] * b_c)
    return np.pi * r / mu0


def test_hapke_roughness_matches_eradiate_reference_tables():
    svza = np.array(list(PRINCIPAL_PLANE), dtype=float)
    wi, wo = gonio_directions(30.0, svza, 0.0)
    np.testing.assert_allclose(hapke(POMMEROL, wi, wo), list(PRINCIPAL_PLANE.values()),
                               rtol=1e-9)
    phi, vza = np.array(list(HEMISPHERE), dtype=float).T
    wi, wo = gonio_directions(30.0, vza, phi)
    np.testing.assert_allclose(hapke(POMMEROL, wi, wo), list(HEMISPHERE.values()), rtol=1e-9)
    # the roughness matters at these parameters (up to 18 % of the BRF): the agreement is its
    smooth = hapke({**POMMEROL, "theta_bar": 0.0}, wi, wo)
    assert np.max(np.abs(smooth / np.array(list(HEMISPHERE.values())) - 1)) > 0.05


def test_hapke_theta_bar_zero_is_the_smooth_model():
    rng = np.random.default_rng(5)
    wi, wo = random_hemisphere(2000, rng, 0.02), random_hemisphere(2000, rng, 0.02)
    ref = smooth_hapke(SMOOTH, wi, wo)
    np.testing.assert_allclose(hapke({**SMOOTH, "theta_bar": 0.0}, wi, wo), ref, rtol=1e-12)
    np.testing.assert_allclose(hapke(SMOOTH, wi, wo), ref, rtol=1e-12)  # theta_bar left out
    mu0e, mue, s = hapke_roughness(0.0, wi, wo)
    np.testing.assert_array_equal(mu0e, wi[:, 2])
    np.testing.assert_array_equal(mue, wo[:, 2])
    np.testing.assert_array_equal(s, 1.0)


def test_hapke_roughness_is_continuous_at_small_theta_bar():
    rng = np.random.default_rng(6)
    wi, wo = random_hemisphere(2000, rng, 0.02), random_hemisphere(2000, rng, 0.02)
    ref = smooth_hapke(SMOOTH, wi, wo)
    previous = np.inf
    for t in (3.0, 1.0, 0.1, 1e-2, 1e-4):
        dev = np.max(np.abs(hapke({**SMOOTH, "theta_bar": t}, wi, wo) / ref - 1.0))
        assert dev < previous, (t, dev)
        previous = dev
        # once the E1, E2 terms have died out, also at these grazing angles (cos >= 0.02),
        # only chi = 1 / sqrt(1 + pi tan^2 theta_bar) remains: a change of order tan^2
        if t <= 0.1:
            assert dev <= math.tan(math.radians(t)) ** 2, (t, dev)
    assert previous < 1e-11


def test_hapke_roughness_cases_join_at_i_equals_e_and_at_the_normal():
    # the two cases i <= e and i >= e meet continuously at i = e, for every azimuth
    phi = np.linspace(0.0, 180.0, 13)
    for i in (10.0, 40.0, 70.0):
        wi, wo_lo = gonio_directions(i, i - 1e-7, phi)
        _, wo_hi = gonio_directions(i, i + 1e-7, phi)
        p = {**SMOOTH, "theta_bar": 30.0}
        np.testing.assert_allclose(hapke(p, wi, wo_lo), hapke(p, wi, wo_hi), rtol=1e-6)
    # at exact back-scattering (psi = 0, i = e) nothing is shadowed: S = 1
    wi, wo = gonio_directions([10.0, 40.0, 70.0], [10.0, 40.0, 70.0], 0.0)
    np.testing.assert_allclose(hapke_roughness(30.0, wi, wo)[2], 1.0, rtol=1e-12)
    # at normal incidence the azimuth is undefined and must not matter
    wi, wo = gonio_directions(0.0, 50.0, phi)
    v = hapke({**SMOOTH, "theta_bar": 30.0}, wi, wo)
    np.testing.assert_allclose(v, v[0], rtol=1e-12)
    wi, wo = gonio_directions(1e-9, 50.0, phi)
    np.testing.assert_allclose(hapke({**SMOOTH, "theta_bar": 30.0}, wi, wo), v[0], rtol=1e-8)


@pytest.mark.parametrize("theta_bar", [5.0, 25.0, 45.0])
def test_hapke_roughness_is_reciprocal_and_shadows(theta_bar):
    rng = np.random.default_rng(7)
    wi, wo = random_hemisphere(2000, rng, 0.02), random_hemisphere(2000, rng, 0.02)
    p = {**SMOOTH, "theta_bar": theta_bar}
    a, b = hapke(p, wi, wo), hapke(p, wo, wi)
    assert np.all(np.isfinite(a)) and np.all(a > 0)
    np.testing.assert_allclose(a, b, rtol=1e-10)
    mu0e, mue, s = hapke_roughness(theta_bar, wi, wo)
    # S is a shadowing factor; Hapke's approximation lets it pass 1 by a few per cent at
    # grazing forward geometries
    assert np.all(mu0e > 0) and np.all(mue > 0) and np.all((s > 0) & (s < 1.1))
    # rougher surfaces darken grazing views away from the light
    wi, wo = gonio_directions(60.0, -80.0, 0.0)
    assert hapke(p, wi, wo)[0] < hapke({**p, "theta_bar": theta_bar / 2}, wi, wo)[0]


@pytest.mark.parametrize("bad", [-1.0, 45.5, 90.0, float("nan")])
def test_hapke_theta_bar_out_of_range_is_an_error(bad):
    wi, wo = gonio_directions(30.0, 30.0, 0.0)
    with pytest.raises(ValueError, match=r"theta_bar = .* deg is out of range; valid range "
                                         r"is \[0, 45\] deg"):
        hapke({**SMOOTH, "theta_bar": bad}, wi, wo)
    with pytest.raises(ValueError, match=f"theta_bar = {bad:g} deg"):
        hapke_roughness(bad, wi, wo)


def test_hapke_theta_bar_is_a_fitted_parameter():
    spec = MODELS["hapke"][1]["theta_bar"]
    assert (spec.lower, spec.upper, spec.log) == (0.0, 45.0, False)
    assert spec.lower < spec.start < spec.upper
