"""The per-parameter fast paths of eval give the same values as the general path: RGB and mono
variants precompute the volume constants for a spatially uniform albedo and skip the
exponential of the coherent term when 2 c0 tau_o >= 18 in every channel (its series when
2 c0 tau_o >= 0.03); spectral variants precompute them for a one-number albedo and a
one-number tau_o (given, or from a constant index) or for a one-number albedo when the layer
is optically thick at every wavelength (2 c0 tau_o >= 18 ln 2: s(c) = 1 / (2 c), within
2^-18), and tabulate them on the 1 nm grid otherwise (s(c0) interpolated instead of
recomputed; for an optically thick Mie albedo, rho alone); a spatially varying texture (here
a constant bitmap) takes the general path."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import channel_wavelengths, evaluate, perturb, random_hemisphere, use_variant
from oracles.model import Params, brdf


def constant_bitmap(value: float, channels: int):
    """A spatially varying texture type whose every texel is ``value`` (nearest filter)."""
    data = np.full((2, 2, channels), value, dtype=np.float32)
    return {"type": "bitmap", "bitmap": mi.Bitmap(data), "raw": True, "filter_type": "nearest"}


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_mono"])
@pytest.mark.parametrize("extra", [{}, {"tau_o": 1.5}, {"thickness": 3.0, "g": 0.4}],
                         ids=["fresnel_tau", "tau_given", "thin"])
def test_uniform_albedo_matches_general_path(variant, extra):
    use_variant(variant)
    channels = 3 if "rgb" in variant else 1
    props = {"type": "powder", "extinction": 0.7, "amplitude_surface": 1e-3, **extra}
    fast = mi.load_dict({**props, "albedo": 0.8})
    general = mi.load_dict({**props, "albedo": constant_bitmap(0.8, channels)})
    rng = np.random.default_rng(21)
    n = 20_000
    wi, wo = random_hemisphere(n, rng, 1e-3), random_hemisphere(n, rng, 1e-3)
    wo[: n // 4] = wi[: n // 4] * rng.uniform(0.999, 1.0, (n // 4, 1))  # near the cone
    a, b = evaluate(fast, wi, wo), evaluate(general, wi, wo)
    assert np.all(np.isfinite(a)) and np.all(a > 0)
    np.testing.assert_allclose(a, b, rtol=2e-6, atol=0)


TABLE8 = "1 nm table of rho, s(c0), tau_o"
TABLE4 = "1 nm table of s(c0), tau_o"
UNIFORM = "once per parameter change"
THICK = "once per parameter change (optically thick)"
THICK_TABLE = "1 nm table of rho (optically thick)"
#: spectral cases: (properties, how the fast instance gets its volume constants); comments:
#: the branch of C that x0 = 2 c0 tau_o selects (hematite's Fresnel tau_o is 8.38-18.8;
#: g = 0.3; optically thick from x0 = 18 ln 2 = 12.48 on)
SPECTRAL_CASES = {
    "mie_fresnel": ({"radius": 0.1}, TABLE8),  # x0 = 10.9 (its bound over the intervals)
    "mie_tau_given": ({"radius": 0.1, "tau_o": 1.5}, TABLE8),
    "mie_thick": ({"radius": 0.05}, THICK_TABLE),  # x0 = 19.5
    "mie_two_populations": ({"radius": 0.1, "radius2": 0.3, "fraction2": 0.4},
                            THICK_TABLE),  # x0 = 14.0
    "mie_two_populations_tau_given": ({"radius": 0.1, "radius2": 0.3, "fraction2": 0.4,
                                       "tau_o": 1.5}, TABLE8),
    "albedo_fresnel": ({"albedo": 0.8}, TABLE4),  # closed form, x0 = 11.3
    "albedo_fresnel_below_thick": ({"albedo": 0.765}, TABLE4),  # x0 = 12.35
    "albedo_fresnel_thick_edge": ({"albedo": 0.756}, THICK),  # x0 = 12.6, exp(-x0) 3.4e-6
    "albedo_fresnel_thick": ({"albedo": 0.3}, THICK),  # x0 >= 23: rounds to the same
    "near_white_fresnel": ({"albedo": 0.99995}, TABLE4),  # closed form, x0 = 0.16
    "white_fresnel_series": ({"albedo": 0.999999}, TABLE4),  # series, x0 = 0.028
    "albedo_tau_given": ({"albedo": 0.8, "tau_o": 1.5}, UNIFORM),
    "albedo_constant_index": ({"albedo": 0.8, "eta": 1.35, "k": 0.0}, UNIFORM),
    "near_white_series": ({"albedo": 0.9995, "tau_o": 0.01}, UNIFORM),  # series
}


def spectral_pairs(n: int, seed: int):
    """Directions (a quarter near the coherent cone) and 4 wavelengths per lane (nm)."""
    rng = np.random.default_rng(seed)
    wi, wo = random_hemisphere(n, rng, 1e-3), random_hemisphere(n, rng, 1e-3)
    wo[: n // 4] = wi[: n // 4] * rng.uniform(0.999, 1.0, (n // 4, 1))
    return wi, wo, rng.uniform(360.0, 830.0, (n, 4))


def volume_path(bsdf) -> str:
    return next(line.split("=", 1)[1].strip().rstrip(",") for line in str(bsdf).splitlines()
                if "volume constants" in line)


@pytest.mark.parametrize("variant", ["llvm_ad_spectral", "scalar_spectral"])
@pytest.mark.parametrize("lobes", ["all", "multiple"])
@pytest.mark.parametrize("case", list(SPECTRAL_CASES))
def test_spectral_volume_constants_match_general_path(variant, lobes, case):
    """A g given as a constant bitmap sends eval down the general path (albedo and tau_o
    looked up and s(c0) computed per lane); a float g takes the constants computed once per
    parameter change or the 1 nm table (the path is asserted). In the table, s(c0) is
    interpolated in wavelength instead of recomputed: L2 ("multiple") differs by at most
    2.3e-5 for a Mie albedo of 100 nm grains; rho, c0 and tau_o, and so L1 and C, are the
    same. Optically thick: L2 and C differ by at most exp(-x0) <= 2^-18 (3.8e-6) plus
    rounding."""
    use_variant(variant)
    extra, path = SPECTRAL_CASES[case]
    props = {"type": "powder", "extinction": 0.7, "amplitude_surface": 1e-3,
             "energy": "paper", "lobes": lobes, **extra}
    fast = mi.load_dict({**props, "g": 0.3})
    general = mi.load_dict({**props, "g": constant_bitmap(0.3, 1)})
    assert volume_path(fast) == path
    assert volume_path(general) == "per lane"
    wi, wo, lam = spectral_pairs(200 if variant.startswith("scalar") else 20_000, 22)
    a, b = evaluate(fast, wi, wo, lam), evaluate(general, wi, wo, lam)
    assert np.all(np.isfinite(a)) and np.all(a > 0)
    # a mix with 300 nm grains: 7.7e-5 (there the albedo's own 1 nm interpolation is 1e-3
    # from Mie at the exact wavelength, s(c0) 4.9e-4, the same both ways)
    rtol = (1e-4 if case == "mie_two_populations_tau_given" else 3e-5 if path == TABLE8
            else 6e-6 if path in (THICK, THICK_TABLE) else 5e-6)
    np.testing.assert_allclose(a, b, rtol=rtol, atol=0)


@pytest.mark.parametrize("lobes", ["multiple", "coherent"])
def test_mie_thick_table_at_the_limit(lobes):
    """100 nm hematite grains at g = 0: 2 c0 tau_o >= 12.85 over the grid's intervals, just
    above the thick limit (12.48): the table holds rho alone, and L2 and C stay within
    exp(-12.85) = 2.6e-6 (plus rounding) of the general path."""
    use_variant("llvm_ad_spectral")
    props = {"type": "powder", "radius": 0.1, "extinction": 0.7, "energy": "paper",
             "lobes": lobes}
    fast = mi.load_dict({**props, "g": 0.0})
    general = mi.load_dict({**props, "g": constant_bitmap(0.0, 1)})
    assert volume_path(fast) == THICK_TABLE
    wi, wo, lam = spectral_pairs(20_000, 23)
    np.testing.assert_allclose(evaluate(fast, wi, wo, lam), evaluate(general, wi, wo, lam),
                               rtol=4.5e-6, atol=0)


def test_thick_mie_table_reads_the_same_values_with_and_without_gradients():
    """The optically thick Mie table is read as 64-bit words (one gather per wavelength) when
    no gradient flows through it, and as float records when the radius is differentiated:
    the same values, to the bit; and the gradient path still reaches the radius."""
    use_variant("llvm_ad_spectral")
    bsdf = mi.load_dict({"type": "powder", "radius": 0.05, "extinction": 0.7})
    assert volume_path(bsdf) == THICK_TABLE
    wi, wo, lam = spectral_pairs(4_000, 24)
    packed = evaluate(bsdf, wi, wo, lam)
    params = mi.traverse(bsdf)
    dr.enable_grad(params["radius"])
    params.update()
    records = evaluate(bsdf, wi, wo, lam)
    assert np.all(np.isfinite(packed)) and np.all(packed > 0)
    np.testing.assert_array_equal(records, packed)
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    si.wi = mi.Vector3f(0.3, 0.1, float(np.sqrt(0.9)))
    si.wavelengths = mi.UnpolarizedSpectrum(450.0, 550.0, 650.0, 750.0)
    value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(-0.5, 0.2, float(np.sqrt(0.71))))
    dr.backward(dr.sum(dr.sum(mi.unpolarized_spectrum(value))))
    assert abs(float(dr.grad(params["radius"])[0])) > 0


def test_spectral_paths_follow_parameter_edits():
    """The path is chosen again at every update: a Mie powder's g set to one value per lane
    (batched fits) takes the per-lane path, each lane equal to its own instance; one g again
    takes the table, equal to a new instance."""
    use_variant("llvm_ad_spectral")
    base = {"type": "powder", "radius": 0.1, "extinction": 0.7, "energy": "paper"}
    bsdf = mi.load_dict({**base, "g": 0.3})
    assert volume_path(bsdf) == TABLE8
    params = mi.traverse(bsdf)
    g = np.array([-0.4, 0.3, 0.8], dtype=np.float32)
    params["g"] = mi.Float(g)
    params.update()
    assert volume_path(bsdf) == "per lane"
    wi, wo, lam = spectral_pairs(3, 7)
    got = evaluate(bsdf, wi, wo, lam)
    for i, gi in enumerate(g):
        want = evaluate(mi.load_dict({**base, "g": float(gi)}), wi[i:i + 1], wo[i:i + 1],
                        lam[i:i + 1])
        np.testing.assert_allclose(got[i], want[0], rtol=3e-5)
    params["g"] = mi.Float(0.8)
    params.update()
    assert volume_path(bsdf) == TABLE8
    wi, wo, lam = spectral_pairs(1000, 8)
    np.testing.assert_allclose(evaluate(bsdf, wi, wo, lam),
                               evaluate(mi.load_dict({**base, "g": 0.8}), wi, wo, lam),
                               rtol=1e-6)


def test_optically_thick_path_follows_albedo_edits():
    """Editing the albedo across the thick limit switches between the constants computed once
    and the 1 nm table, each time equal to a new instance with that albedo (hematite's Fresnel
    tau_o, g = 0: thick up to albedo 0.815)."""
    use_variant("llvm_ad_spectral")
    base = {"type": "powder", "extinction": 0.7, "amplitude_surface": 1e-3}
    bsdf = mi.load_dict({**base, "albedo": 0.8})
    params = mi.traverse(bsdf)
    key = next(k for k in params.keys() if k.startswith("albedo"))
    wi, wo, lam = spectral_pairs(2000, 9)
    for albedo, path in [(0.8, THICK), (0.9, TABLE4), (0.5, THICK)]:
        params[key] = albedo
        params.update()
        assert volume_path(bsdf) == path, albedo
        np.testing.assert_allclose(
            evaluate(bsdf, wi, wo, lam),
            evaluate(mi.load_dict({**base, "albedo": albedo}), wi, wo, lam), rtol=1e-6)


def test_the_saturated_coherent_path_is_exercised():
    """With hematite's Fresnel tau_o (~14) and albedo 0.8, 2 c0 tau_o >= 18 in every channel."""
    use_variant("llvm_ad_rgb")
    bsdf = mi.load_dict({"type": "powder", "albedo": 0.8})
    si = dr.zeros(mi.SurfaceInteraction3f, 1)
    tau = np.array(bsdf.eval_attribute("tau_o", si)).ravel()
    c0 = np.sqrt(3.0 * (1 - 0.8) * (1 - 0.0))
    assert np.all(2 * c0 * tau >= 18.0), tau


@pytest.mark.parametrize("values,path", [([-0.5, 0.0, 0.3, 0.5], THICK),
                                         ([-0.5, 0.0, 0.8, 0.5], "per lane")],
                         ids=["all_thick", "one_lane_not_thick"])
def test_spectral_thick_only_if_every_lane_is(values, path):
    """g set to one value per lane (batched fits) in llvm_ad_spectral, albedo 0.7: the layer
    is optically thick only if every lane is (2 c0 tau_o >= 12.48 for g <= 0.549; 0.8 is not).
    Each lane equals a separately loaded instance (thick or 1 nm table) within the thick
    path's bound."""
    use_variant("llvm_ad_spectral")
    base = {"type": "powder", "albedo": 0.7, "extinction": 0.7, "amplitude_surface": 1e-3}
    batched = mi.load_dict({**base, "g": 0.1})
    params = mi.traverse(batched)
    params["g"] = mi.Float(np.array(values, dtype=np.float32))
    params.update()
    assert volume_path(batched) == path
    wi, wo, lam = spectral_pairs(len(values), 11)
    wo[:] = wi * np.array([0.9999, 0.9999, 1.0])  # near the coherent cone
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    got = evaluate(batched, wi, wo, lam)
    for i, v in enumerate(values):
        single = mi.load_dict({**base, "g": v})
        assert volume_path(single) == (TABLE4 if v == 0.8 else THICK)
        want = evaluate(single, wi[i:i + 1], wo[i:i + 1], lam[i:i + 1])
        np.testing.assert_allclose(got[i], want[0], rtol=6e-6, atol=0, err_msg=str(v))


@pytest.mark.parametrize("variant,name", [("llvm_ad_rgb", "albedo"), ("llvm_ad_rgb", "tau_o"),
                                          ("llvm_ad_mono", "tau_o")])
def test_one_value_per_lane_takes_every_lane_into_account(variant, name):
    """Parameters set through mi.traverse with one value per lane (batched fits, e.g.
    the RTI fits): the saturated-cone shortcut and the range checks must hold for every lane, not
    only the first. Lane 0 is saturated (2 c0 tau_o >= 18), some others are not; each lane
    must equal a separately loaded instance (the shortcut once took lane 0 for all: 0.1 % off
    near back-scattering for albedo 0.99)."""
    use_variant(variant)
    if name == "albedo":
        values = np.array([0.05, 0.99, 0.9, 0.999, 0.3], dtype=np.float32)
        base = {"type": "powder", "albedo": {"type": "rgb", "value": [0.5] * 3}}
        alone = [dict(base, albedo=float(v)) for v in values]
    else:
        values = np.array([40.0, 0.5, 2.0, 0.05, 8.0], dtype=np.float32)
        base = {"type": "powder", "albedo": 0.95, "tau_o": 1.0}
        alone = [dict(base, tau_o=float(v)) for v in values]
    n = len(values)
    batched = mi.load_dict(base)
    params = mi.traverse(batched)
    lanes = mi.Float(values)
    params[name + (".value" if name == "albedo" else "")] = (
        mi.Color3f(lanes, lanes, lanes) if name == "albedo" else lanes)
    params.update()
    rng = np.random.default_rng(5)
    wi = random_hemisphere(n, rng, 0.2)
    wo = wi * np.array([0.9999, 0.9999, 1.0])  # inside the coherent cone
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    got = evaluate(batched, wi, wo)
    for i, props in enumerate(alone):
        want = evaluate(mi.load_dict(props), wi[i:i + 1], wo[i:i + 1])
        np.testing.assert_allclose(got[i], want[0], rtol=2e-6, atol=0, err_msg=str(props))

    # every lane is range-checked
    values = mi.Float(np.array([0.5, 1.0, -0.2, 0.1], dtype=np.float32))
    params = mi.traverse(mi.load_dict({"type": "powder", "albedo": 0.5}))
    params["amplitude_volume"] = values
    with pytest.raises(RuntimeError, match=r'"amplitude_volume" = -0\.2 is out of range'):
        params.update()
    params = mi.traverse(mi.load_dict({"type": "powder", "albedo": 0.5}))
    params["g"] = mi.Float(np.array([0.1, np.nan], dtype=np.float32))
    with pytest.raises(RuntimeError, match=r'"g" = nan is out of range'):
        params.update()


def test_grain_properties_take_one_value():
    use_variant("llvm_ad_rgb")
    params = mi.traverse(mi.load_dict({"type": "powder", "radius": 0.05}))
    params["radius"] = mi.Float(np.array([0.05, 0.08], dtype=np.float32))
    with pytest.raises(RuntimeError, match=r'"radius" holds 2 values \(one per lane\); a grain '
                                           r'property takes one value, or a texture'):
        params.update()


def test_one_thickness_per_lane_with_infinite_lanes():
    """Lanes of infinite and finite thickness in one call: each equals its own instance, and
    the gradient with respect to the extinction is finite (no 0 x inf) and matches central
    differences."""
    use_variant("llvm_ad_rgb")
    thickness = np.array([np.inf, 2.0, np.inf, 0.5], dtype=np.float32)
    base = {"type": "powder", "albedo": 0.7, "extinction": 1.3, "lobes": "single"}
    bsdf = mi.load_dict(base)
    params = mi.traverse(bsdf)
    params["thickness"] = mi.Float(thickness)
    params.update()
    rng = np.random.default_rng(8)
    wi, wo = random_hemisphere(4, rng, 0.2), random_hemisphere(4, rng, 0.2)
    got = evaluate(bsdf, wi, wo)
    for i, d in enumerate(thickness):
        alone = mi.load_dict({**base, "thickness": float(d)})
        np.testing.assert_allclose(got[i], evaluate(alone, wi[i:i + 1], wo[i:i + 1])[0],
                                   rtol=2e-6)
    kappa = mi.Float(1.3)
    dr.enable_grad(kappa)
    params["extinction"] = kappa
    params.update()
    si = dr.zeros(mi.SurfaceInteraction3f, 4)
    si.wi = mi.Vector3f(*wi.T.astype(np.float32))
    value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wo.T.astype(np.float32)))
    dr.backward(dr.sum(value[0]))
    grad = float(dr.grad(kappa)[0])
    sums = []
    for k in (1.3 + 1e-3, 1.3 - 1e-3):
        params["extinction"] = k
        params.update()
        sums.append(evaluate(bsdf, wi, wo)[:, 0].sum())
    assert np.isfinite(grad) and grad != 0.0
    assert grad == pytest.approx((sums[0] - sums[1]) / 2e-3, rel=0.02)


def test_energy_conserving_takes_one_value_per_parameter():
    use_variant("llvm_ad_rgb")
    params = mi.traverse(mi.load_dict({"type": "powder", "albedo": 0.5,
                                       "energy": "conserving"}))
    params["g"] = mi.Float(np.array([0.1, 0.2], dtype=np.float32))
    with pytest.raises(RuntimeError, match=r'"g" holds 2 values \(one per lane\); with '
                                           r'energy = "conserving" it takes one value .*'
                                           r'use energy = "paper" for one value per lane'):
        params.update()
    # the surface lobe is not in the normalisation: one value per lane is accepted
    base = {"type": "powder", "albedo": 0.5, "energy": "conserving"}
    bsdf = mi.load_dict(base)
    params = mi.traverse(bsdf)
    values = np.array([1e-3, 5e-2], dtype=np.float32)
    params["amplitude_surface"] = mi.Float(values)
    params.update()
    rng = np.random.default_rng(9)
    wi = random_hemisphere(2, rng, 0.3)
    wo = wi * np.array([-1.0, -1.0, 1.0])  # the mirror direction: the surface lobe's peak
    got = evaluate(bsdf, wi, wo)
    for i, a in enumerate(values):
        want = evaluate(mi.load_dict({**base, "amplitude_surface": float(a)}), wi[i:i + 1],
                        wo[i:i + 1])
        np.testing.assert_allclose(got[i], want[0], rtol=2e-6)


def surface_exponent(wi: np.ndarray, wo: np.ndarray, lam_nm: np.ndarray, p) -> np.ndarray:
    """Base-2 exponent t of the surface lobe's exp(-t ln 2) per lane and channel (N, C):
    pi^2 l_c^2 f_s^2 (Harvey-Shack, docs/model.md Eq. 21-22) or theta_s^2 / (2 sigma^2) (Eq. 20)."""
    if p.specular == "harvey_shack":
        s2 = np.sum((wo[:, :2] + wi[:, :2]) ** 2, axis=1, keepdims=True)
        x = np.pi**2 * p.correlation_length**2 * s2 / (lam_nm * 1e-3) ** 2
    else:
        mirror = wi * np.array([-1.0, -1.0, 1.0])
        cos_t = np.sum(mirror * wo, axis=1, keepdims=True) / (
            np.linalg.norm(mirror, axis=1, keepdims=True) * np.linalg.norm(wo, axis=1,
                                                                           keepdims=True))
        x = np.broadcast_to(np.arccos(np.clip(cos_t, -1, 1)) ** 2 / (2 * p.sigma**2),
                            lam_nm.shape)
    return x / np.log(2.0)


@pytest.mark.parametrize("variant", ["llvm_ad_rgb", "llvm_ad_spectral", "scalar_rgb"])
@pytest.mark.parametrize("specular", ["harvey_shack", "gaussian"])
def test_surface_exponential(variant, specular):
    """The surface lobe's exponential (powder_lobes.h, exp2_neg: a degree-6 polynomial of
    2^f in JIT variants, dr::exp2 in scalar ones) against float64 where its base-2 exponent
    t <= 63: within 40 float32 ulp of the argument x = t ln 2, times x (2.4e-6 (1 + x)
    relative; the float32 argument, not the exponential, sets the error: the scalar
    variant's library exp2 is as far off, up to 10 ulp x for Harvey-Shack and 30 ulp x for
    the Gaussian lobe's angle). Exactly 0 beyond t = 64.01 (2^-64 of the prefactor) in every
    variant, and never a denormal float. With a gradient on the exponent (AD) JIT variants
    call dr::exp2 on the same float32 argument (dr::exp for the Gaussian lobe, whose argument
    is then rounded once less): the polynomial within 4e-7 (3 ulp), plus 2 ulp of x."""
    use_variant(variant)
    rng = np.random.default_rng(5)
    n = 600 if variant.startswith("scalar") else 40_000
    p = Params(amplitude_surface=1e-3, correlation_length=1.0, specular=specular, sigma=0.15,
               lobes=("surface",)).as_float32()
    wi = random_hemisphere(n, rng, 0.05)
    mirror = wi * np.array([-1.0, -1.0, 1.0])
    wo = random_hemisphere(n, rng, 0.05)
    half = n // 2  # half near the mirror direction: exponents from 0 up
    wo[:half] = perturb(mirror[:half], rng.uniform(0.0, 1.2, half), rng)
    wi, wo = wi.astype(np.float32).astype(np.float64), wo.astype(np.float32).astype(np.float64)
    lam = channel_wavelengths(n, rng)
    bsdf = mi.load_dict({"type": "powder", "albedo": 0.5, **p.properties()})
    got = evaluate(bsdf, wi, wo, lam)
    want = brdf(wi, wo, np.full(lam.shape, 0.5), lam, p) * wo[:, 2:3]
    t = surface_exponent(wi, wo, lam, p)
    inside, outside = t <= 63.0, t > 64.01
    assert inside.sum() > n // 10 and outside.sum() > n // 10  # both sides covered
    rel = np.abs(got[inside] - want[inside]) / want[inside]
    bound = 2.4e-6 * (1.0 + t[inside] * np.log(2.0))
    assert np.all(rel <= bound), f"worst error / bound {np.max(rel / bound):.3g}"
    assert np.all(got[outside] == 0.0)
    tiny = np.finfo(np.float32).tiny
    assert not np.any((got != 0.0) & (np.abs(got) < tiny)), "denormal values"
    if variant.startswith("llvm"):
        params = mi.traverse(bsdf)
        key = "correlation_length" if specular == "harvey_shack" else "sigma"
        dr.enable_grad(params[key])
        params.update()
        ad = evaluate(bsdf, wi, wo, lam)
        assert np.all((ad == 0.0) == (got == 0.0))
        x, nz = t * np.log(2.0), got != 0.0
        # the Gaussian lobe's exp_neg(x) rounds x / ln 2 once more than dr::exp(-x)
        rel = np.abs(ad[nz] - got[nz]) / got[nz]
        assert np.all(rel <= 4e-7 + 1.2e-7 * x[nz]), f"AD path: worst {rel.max():.3g}"
