"""The baselines of unmixing (fitting/mixing_rules.py, fitting/unmix_baselines.py): Hapke's
intimate-mixture rule and two-constant Kubelka-Munk against closed forms and hand values,
round trips of each rule through its own unmixing, and the refusals."""

from __future__ import annotations

import math

import numpy as np
import pytest

from mitsuba_powder.fitting import mixing_rules as rules
from mitsuba_powder.fitting.unmix_baselines import unmix_hapke, unmix_km

WL = np.arange(400.0, 701.0, 20.0)  # 16 wavelengths


def test_km_reflectance_closed_forms():
    # K/S = 1/2: R = 3/2 - sqrt(5)/2 = (3 - sqrt 5) / 2; K/S = 4: R = 5 - sqrt(24); K/S = 0: 1
    np.testing.assert_allclose(rules.km_reflectance([0.5, 4.0, 0.0]),
                               [(3 - math.sqrt(5)) / 2, 5 - math.sqrt(24), 1.0], rtol=1e-14)
    # large K/S: R ~ 1 / (2 K/S), written without cancellation
    assert rules.km_reflectance(1e12) == pytest.approx(0.5e-12, rel=1e-6)


def test_km_ratio_inverts_the_reflectance():
    r = np.linspace(0.01, 1.0, 50)
    np.testing.assert_allclose(rules.km_reflectance(rules.km_ratio(r)), r, rtol=1e-12)
    assert rules.km_ratio(0.5) == pytest.approx(0.25)  # (1 - 0.5)^2 / (2 * 0.5)


def test_km_constants_from_masstone_and_tint_round_trip():
    """K and S of a pigment made up, its masstone and a tint with a grey-white made with
    Kubelka-Munk: the two swatches give K and S back."""
    rng = np.random.default_rng(3)
    k_p, s_p = rng.uniform(0.5, 5.0, 16), rng.uniform(0.2, 3.0, 16)
    k_w = rng.uniform(0.0, 0.05, 16)  # the white: S_w = 1
    c = 0.1
    masstone = rules.km_reflectance(k_p / s_p)
    tint = rules.km_reflectance((c * k_p + (1 - c) * k_w) / (c * s_p + (1 - c)))
    k, s = rules.km_constants(masstone, tint, c, k_w)
    np.testing.assert_allclose(k, k_p, rtol=1e-8)
    np.testing.assert_allclose(s, s_p, rtol=1e-8)


def test_km_constants_where_the_swatches_cannot_separate_them():
    """A pigment that absorbs nothing: its tint equals its masstone; S = 1 is taken."""
    k, s = rules.km_constants(np.ones(3), np.ones(3), 0.1, np.zeros(3))
    np.testing.assert_array_equal(s, 1.0)
    np.testing.assert_array_equal(k, 0.0)


def test_hapke_hemispherical_reflectance_hand_values_and_round_trip():
    # w = 3/4: gamma = 1/2, r_h = (1 - 1/2) / (1 + 1) = 1/4; w = 1: 1; w = 0: 0
    np.testing.assert_allclose(rules.hapke_reflectance([0.75, 1.0, 0.0]), [0.25, 1.0, 0.0],
                               atol=1e-15)
    w = np.linspace(0.0, 1.0, 101)
    np.testing.assert_allclose(rules.hapke_albedo(rules.hapke_reflectance(w)), w, atol=1e-12)


def test_hapke_bidirectional_hand_value_limit_and_round_trip():
    # w = 3/4, normal incidence, 45 degrees: H(1) = 3/2, H(cos 45) = (1 + sqrt 2)/(1 + sqrt 2/2)
    mu = math.cos(math.radians(45))
    want = 0.75 / 4 * 1.5 * (1 + 2 * mu) / (1 + mu) / (1 + mu)
    assert rules.hapke_reflectance(0.75, (0, 45)) == pytest.approx(want, rel=1e-14)
    # small w: Lommel-Seeliger, w / (4 (mu0 + mu))
    assert rules.hapke_reflectance(1e-6, "30:20") == pytest.approx(
        1e-6 / (4 * (math.cos(math.radians(30)) + math.cos(math.radians(20)))), rel=1e-6)
    w = np.linspace(0.0, 1.0, 41)
    np.testing.assert_allclose(rules.hapke_albedo(rules.hapke_reflectance(w, "0:45"), "0:45"),
                               w, atol=1e-12)


def test_hapke_mixture_albedo_weights_by_cross_section():
    # u = f / r = (0.5, 5): w = (0.5 * 0.9 + 5 * 0.1) / 5.5
    w = rules.hapke_mixture_albedo([[0.9], [0.1]], [0.5, 0.5], [1.0, 0.1])
    assert w[0] == pytest.approx(0.95 / 5.5, rel=1e-14)
    ends = np.array([np.linspace(0.2, 0.9, 5), np.linspace(0.9, 0.1, 5)])
    np.testing.assert_allclose(rules.hapke_mixture_albedo(ends, [1.0, 0.0], [1.0, 0.1]), ends[0])


def test_one_material_mixtures_equal_the_endmember():
    ends = np.array([np.linspace(0.2, 0.9, 5), np.linspace(0.9, 0.1, 5)])
    k, s = rules.km_ratio(ends), np.array([np.full(5, 1.0), np.full(5, 2.5)])
    k = k * s
    np.testing.assert_allclose(rules.km_mixture_reflectance([0.0, 1.0], k, s), ends[1],
                               rtol=1e-12)
    w = rules.hapke_albedo(ends)
    np.testing.assert_allclose(rules.hapke_reflectance(rules.hapke_mixture_albedo(
        w, [0.0, 1.0], [1.0, 0.3])), ends[1], rtol=1e-12)


def endmembers() -> np.ndarray:
    """Three made-up pure spectra: a white, a red, a dark grey."""
    x = (WL - 400.0) / 300.0
    return np.array([0.95 - 0.05 * x, 0.08 + 0.6 / (1 + np.exp(-(WL - 590.0) / 15.0)),
                     0.06 + 0.02 * x])


PARTS = [("kaolinite", 0.5, 1.0), ("hematite", 0.25, 0.1), ("magnetite", 0.25, 0.3)]


def test_hapke_unmixing_recovers_a_hapke_mixture():
    e = endmembers()
    truth = np.array([0.8, 0.12, 0.08])  # volume
    r = rules.hapke_reflectance(rules.hapke_mixture_albedo(rules.hapke_albedo(e), truth,
                                                           [1.0, 0.1, 0.3]))
    u = unmix_hapke(WL, r, np.full(len(WL), 1e-3), e, PARTS)
    np.testing.assert_allclose(u.volume_fractions, truth, atol=1e-6)
    assert u.rms < 1e-8 and u.method == "hapke"
    d = np.array([2.63, 5.26, 5.18])
    np.testing.assert_allclose(u.mass_fractions, truth * d / np.sum(truth * d), atol=1e-6)


@pytest.mark.parametrize("tinted", [False, True])
def test_km_unmixing_recovers_a_km_mixture(tinted):
    e = endmembers()
    k, s = rules.km_ratio(e), np.ones_like(e)
    tints = None
    if tinted:  # pigments with S of their own; tints of 10 % by mass in the white
        s = np.array([np.ones(len(WL)), np.full(len(WL), 0.4), np.full(len(WL), 2.0)])
        k = k * s
        tints = [(rules.km_mixture_reflectance([0.9, 0.1 * (j == 1), 0.1 * (j == 2)], k, s),
                  0.1) for j in (1, 2)]
    truth = np.array([0.7, 0.2, 0.1])  # mass
    r = rules.km_mixture_reflectance(truth, k, s)
    u = unmix_km(WL, r, np.full(len(WL), 1e-3), e, PARTS, tints=tints)
    np.testing.assert_allclose(u.mass_fractions, truth, atol=1e-6)
    assert u.method == ("km (masstone + tint)" if tinted else "km (S = 1)")
    assert u.rms < 1e-8
    assert u.mass_fraction_errors.shape == (3,) and np.all(u.mass_fraction_errors > 0)


def test_the_uncertainties_follow_the_noise():
    """1 % reflectance noise on a Hapke mixture: fractions within 3 sigma, chi2/dof near 1."""
    e = endmembers()
    truth = np.array([0.8, 0.12, 0.08])
    r = rules.hapke_reflectance(rules.hapke_mixture_albedo(rules.hapke_albedo(e), truth,
                                                           [1.0, 0.1, 0.3]))
    rng = np.random.default_rng(0)
    sigma = np.full(len(WL), 0.01)
    u = unmix_hapke(WL, r + sigma * rng.standard_normal(len(WL)), sigma, e, PARTS)
    assert np.all(np.abs(u.volume_fractions - truth) < 3 * u.volume_fraction_errors)
    assert 0.2 < u.chi2 / u.dof < 2.5


def test_refusals_name_the_value():
    with pytest.raises(ValueError, match=r"reflectance 1.2 is out of range; valid range is "
                                         r"\[0, 1\]"):
        rules.hapke_albedo([0.5, 1.2])
    with pytest.raises(ValueError, match=r"reflectance 0 is out of range; valid range is "
                                         r"\(0, 1\]"):
        rules.km_ratio([0.0, 0.5])
    with pytest.raises(ValueError, match="tint_fraction = 1.5 is out of range"):
        rules.km_constants([0.5], [0.6], 1.5, [0.0])
    with pytest.raises(ValueError, match="endmembers of shape"):
        unmix_hapke(WL, np.full(len(WL), 0.5), np.full(len(WL), 0.01), endmembers()[:2], PARTS)
    with pytest.raises(ValueError, match="1 tints for 2 pigments"):
        unmix_km(WL, np.full(len(WL), 0.5), np.full(len(WL), 0.01), endmembers(), PARTS,
                 tints=[(np.full(len(WL), 0.5), 0.1)])


@pytest.mark.parametrize("energy", ["paper", "conserving"])
def test_powder_unmixing_of_a_reflectance_recovers_its_mixture(energy):
    """A mixture's 0/d reflectance by the plugin (its albedo from the plugin's mixture rule):
    the reflectance -> albedo inversion and today's unmix give the fractions back (in both
    energy modes: two engines)."""
    from mitsuba_powder.fitting.unmix_baselines import PowderReflectance, unmix_powder
    from mitsuba_powder.plugin.grains import mixture_albedo, mixture_properties

    wl = np.arange(400.0, 801.0, 25.0)
    props = {"energy": energy, "extinction": 1.0, "tau_o": 2.0}
    truth = [("kaolinite", 0.8, 1.0), ("hematite", 0.2, 0.1)]  # volume
    rho = mixture_albedo(mixture_properties(truth, "volume"), wl)[0]
    r = PowderReflectance(wl, "0:d", props)(rho[None])[0]
    u = unmix_powder(wl, r, np.full(len(wl), 1e-3), [("kaolinite", 0.5, 1.0),
                                                     ("hematite", 0.5, 0.1)], properties=props)
    np.testing.assert_allclose(u.volume_fractions, [0.8, 0.2], atol=2e-3)
    assert u.rms < 2e-4 and u.method == "powder"
    with pytest.raises(ValueError, match="needs tau_o given"):
        unmix_powder(wl, r, np.full(len(wl), 1e-3), truth, properties={"extinction": 1.0})


def test_unmix_cli_with_a_baseline(tmp_path, capsys):
    """``unmix --baseline hapke`` on CSVs: a Hapke mixture of two made-up endmembers."""
    import json

    from mitsuba_powder.cli import main

    e = endmembers()[:2]
    truth = np.array([0.7, 0.3])
    r = rules.hapke_reflectance(rules.hapke_mixture_albedo(rules.hapke_albedo(e), truth,
                                                           [1.0, 0.1]))
    np.savetxt(tmp_path / "mix.csv", np.c_[WL, r, np.full(len(WL), 1e-3)], delimiter=",",
               header="wavelength,reflectance,sigma")
    for name, spectrum in zip(("white", "red"), e):
        np.savetxt(tmp_path / f"{name}.csv", np.c_[WL, spectrum], delimiter=",")
    out = tmp_path / "u.json"
    assert main(["unmix", str(tmp_path / "mix.csv"), "--mix",
                 "kaolinite:50%:1um,hematite:50%:0.1um", "--baseline", "hapke", "--endmembers",
                 f"{tmp_path / 'white.csv'},{tmp_path / 'red.csv'}", "--json", str(out)]) == 0
    doc = json.loads(out.read_text())
    np.testing.assert_allclose(doc[0]["volume_fractions"], truth, atol=1e-6)
    assert "hapke" in capsys.readouterr().out
    mix = ["unmix", str(tmp_path / "mix.csv"), "--mix", "kaolinite:50%:1um,hematite:50%:0.1um"]
    assert main(mix + ["--baseline", "km"]) == 2
    assert "--baseline needs --endmembers" in capsys.readouterr().err
    assert main(mix + ["--endmembers", str(tmp_path / "red.csv")]) == 2
    assert "--endmembers needs --baseline" in capsys.readouterr().err


def test_km_constants_of_a_tint_as_white_as_the_white():
    """t = k_w: the pigment adds nothing beside the white: S at its floor, K = m S."""
    k, s = rules.km_constants(np.full(2, 0.3), np.ones(2), 0.1, np.zeros(2))
    np.testing.assert_array_equal(s, rules.S_FLOOR)
    np.testing.assert_allclose(k, rules.km_ratio(0.3) * rules.S_FLOOR)


def test_a_fraction_at_the_edge_is_reported():
    """The red masstone itself, unmixed as white + red: the white's fraction goes to the edge
    of the search, and the result says so."""
    e = endmembers()[:2]
    u = unmix_km(WL, e[1], np.full(len(WL), 1e-3), e,
                 [("kaolinite", 0.5, 1.0), ("hematite", 0.5, 0.1)])
    assert u.mass_fractions[0] < 1e-4
    assert any("the fraction of kaolinite is below 0.0001" in w for w in u.warnings)


def test_a_singular_fit_reports_without_a_numpy_warning():
    """Three identical masstones: the mixture does not depend on the fractions, the Jacobian
    is singular; the result says so (infinite or NaN uncertainties, which the command line
    refuses to report with exit 0), without numpy's RuntimeWarning on the way."""
    import warnings

    e = endmembers()
    parts = [("kaolinite", 0.4, 1.0), ("hematite", 0.3, 0.1), ("magnetite", 0.3, 0.3)]
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        u = unmix_km(WL, 0.9 * e[0], np.full(len(WL), 1e-3), np.array([e[0]] * 3), parts)
    assert "the Jacobian is singular" in u.warnings[0]
    assert not np.all(np.isfinite(u.mass_fraction_errors))


def test_bad_spectra_name_the_wavelength_and_the_value():
    e = endmembers()[:2]
    parts = [("kaolinite", 0.5, 1.0), ("hematite", 0.5, 0.1)]
    sigma = np.full(len(WL), 1e-3)
    with pytest.raises(ValueError, match=r"sigma at 440 nm = -0.001 is out of range; valid "
                                         r"range is \(0, inf\)"):
        unmix_hapke(WL, e[0], np.where(WL == 440, -1e-3, sigma), e, parts)
    with pytest.raises(ValueError, match=r"the reflectance at 400 nm = nan is out of range"):
        unmix_km(WL, np.where(WL == 400, np.nan, e[0]), sigma, e, parts)
