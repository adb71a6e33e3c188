"""Every option of an RTI fit is checked once, in one place (mitsuba_powder.rti.options and,
against the capture, mitsuba_powder.rti.inputs): a bad value gives the same message through
the command line (``fit-maps``) and through the Python API (``fit_maps``, ``fit_maps_tiled``),
once, naming the option as the caller gave it; a fit checks its options and its capture once,
whatever its stages (no fit calls ``fit_maps`` again). The capture is SYNTHETIC."""

from __future__ import annotations

import math

import numpy as np
import pytest

import mitsuba_powder.rti as rf
from helpers import write_exr_capture
from mitsuba_powder.cli import main
from mitsuba_powder.rti.gains import GainTrend
from mitsuba_powder.rti.options import fit_options

SIZE, LIGHTS = 8, 10

#: (command-line arguments, the API's call on the capture ``c`` (images, directions, .lp,
#: output folder), the message as the API names the option, the option's name on the
#: command line when it differs)
CASES = {
    "iterations": (["--iterations", "0"], lambda c: _fit(c, max_iterations=0),
                   "max_iterations = 0 is out of range; valid range is [1, inf]", None),
    "iterations_whole": (["--iterations", "2.5"], lambda c: _fit(c, max_iterations=2.5),
                         "max_iterations = 2.5 is not a whole number; valid range is [1, inf]",
                         None),
    "iterations_text": (["--iterations", "many"], lambda c: _fit(c, max_iterations="many"),
                        "max_iterations = 'many' is not a number", None),
    "rounds": (["--rounds", "-2"], lambda c: _fit(c, rounds=-2),
               "rounds = -2 is out of range; valid range is [1, inf]", None),
    "gains": (["--gains", "auto"], lambda c: _fit(c, gains="auto"),
              "gains = 'auto' is not a gain mode; choose one of ('fit', 'fixed')", None),
    "solver": (["--solver", "scipy"], lambda c: _fit(c, solver="scipy"),
               "solver = 'scipy' is not a solver; choose one of ('drjit', 'numpy')", None),
    "gain_model": (["--gain-model", "trend"], lambda c: _fit(c, gain_trend=GainTrend("trend")),
                   "gain_model = 'trend' is not valid; choose one of ('none', 'free', "
                   "'smooth')", None),
    "gain_degree": (["--gain-degree", "9"], lambda c: _fit(c, gain_trend=GainTrend(degree=9)),
                    "gain_degree = 9 is out of range; valid range is the whole numbers 0-6",
                    None),
    "gain_spread": (["--gain-model", "smooth", "--gain-spread", "-0.1"],
                    lambda c: _fit(c, gain_trend=GainTrend("smooth", spread=-0.1)),
                    "gain_spread = -0.1 is out of range; valid range is (0, inf) (a relative "
                    "spread, e.g. 0.02), or None", None),
    "gain_spread_mode": (["--gain-spread", "0.1"],
                         lambda c: _fit(c, gain_trend=GainTrend(spread=0.1)),
                         "gain_spread = 0.1 needs gain_model = 'smooth' (it is 'none')", None),
    "exposure": (["--exposure", "0"], lambda c: _fit(c, exposure=0),
                 "exposure = 0 is out of range; valid range is (0, inf) (the lights' "
                 "irradiance scale), or 'fit'", "--exposure"),
    "memory": (["--memory-gb", "0"], lambda c: _fit(c, memory_gb=0),
               "memory_gb = 0 is out of range; valid range is [0.015625, inf) GiB", "--memory-gb"),
    "memory_text": (["--memory-gb", "lots"], lambda c: _fit(c, memory_gb="lots"),
                    "memory_gb = 'lots' is not a number", "--memory-gb"),
    "gain_pixels": (["--gain-pixels", "0"], lambda c: _fit(c, gain_subsample=0),
                    "gain_subsample = 0 is out of range; valid range is [1, inf]",
                    "--gain-pixels"),
    "light_distance": (["--light-distance", "0.5"], lambda c: _fit(c, light_distance=0.5),
                       "light_distance = 0.5 image widths is out of range; valid range is "
                       "(0.707107, inf]: a light must be farther from the image's centre than "
                       "the corners of the 8 x 8 px image (its half-diagonal), so that it is "
                       "never over the imaged area", "--light-distance"),
    "light_distance_text": (["--light-distance", "near"],
                            lambda c: _fit(c, light_distance="near"),
                            "light_distance = 'near' is not valid; give a distance in image "
                            "widths (> the half-diagonal), inf or 'fit'", "--light-distance"),
    "free": (["--free", "radius2"], lambda c: _fit(c, free=["radius2"]),
             "free property 'radius2' is not fittable per pixel; choose among ['albedo', "
             "'amplitude_volume', 'g', 'extinction', 'tau_o', 'thickness', "
             "'amplitude_surface', 'correlation_length', 'sigma', 'radius', "
             "'agglomerate_radius']", None),
    "free_twice": (["--free", "albedo,albedo"], lambda c: _fit(c, free=["albedo", "albedo"]),
                   "free = ['albedo', 'albedo'] names a property twice", None),
    "set_range": (["--set", "g=1.5"], lambda c: _fit(c, fixed={"g": 1.5}),
                  "g[0, 0] = 1.5 is out of range; valid range is (-1, 1)", None),
    "set_free": (["--free", "albedo,amplitude_surface", "--set", "amplitude_surface=1e-4"],
                 lambda c: _fit(c, free=["albedo", "amplitude_surface"],
                                fixed={"amplitude_surface": 1e-4}),
                 "property 'amplitude_surface' is both free and fixed (free = ['albedo', "
                 "'amplitude_surface'] names it and it is held at 0.0001); leave it out of "
                 "free to hold it", None),
    "set_energy": (["--set", "energy=conserving"],
                   lambda c: _fit(c, fixed={"energy": "conserving"}),
                   "energy = 'conserving': per-pixel maps need energy = 'paper' (the only "
                   "valid value here: 'conserving' tabulates its normalisation for one value "
                   "of each parameter, not one per pixel)", None),
    "tile_size": (["--tile-size", "4"], lambda c: _tiled(c, 4),
                  "tile_size = 4 is out of range; valid range is [8, inf]", "--tile-size"),
    "tiled_distance": (["--tile-size", "16", "--light-distance", "3"],
                       lambda c: _tiled(c, 16, light_distance=3.0),
                       "light_distance = 3.0 is not supported by tiled fits; valid value: inf "
                       "(distant lights); fit near-field lights untiled", "--light-distance"),
    "tiled_distance_fit": (["--tile-size", "16", "--light-distance", "fit"],
                           lambda c: _tiled(c, 16, light_distance="fit"),
                           "light_distance = 'fit' is not supported by tiled fits; valid value: "
                           "inf (distant lights); fit near-field lights untiled",
                           "--light-distance"),
    "workers": (["--tile-size", "16", "--workers", "0"], lambda c: _tiled(c, 16, workers=0),
                "workers = 0 is out of range; valid range is [1, inf]", "--workers"),
    "scheduler": (["--tile-size", "16", "--scheduler", "nowhere"],
                  lambda c: _tiled(c, 16, scheduler="nowhere"),
                  "scheduler = 'nowhere' is not a Dask scheduler address; expected "
                  "tcp://HOST:PORT with a port in 1-65535 (e.g. tcp://10.0.0.5:8786, as "
                  "printed by `dask scheduler`)", "--scheduler"),
}


def _fit(c, **options):
    return rf.fit_maps(c["images"], c["directions"], rounds=options.pop("rounds", 1),
                       max_iterations=options.pop("max_iterations", 2), **options)


def _tiled(c, tile_size, **options):
    from mitsuba_powder.rti.tiles import fit_maps_tiled

    return fit_maps_tiled(c["lp"], c["out"], tile_size, encoding="linear", **options)


@pytest.fixture(scope="module")
def capture(tmp_path_factory):
    folder = tmp_path_factory.mktemp("options")
    cap = rf.synthetic_capture(SIZE, SIZE, LIGHTS, noise=0.005, seed=1)
    return {"images": cap["images"], "directions": cap["directions"],
            "lp": write_exr_capture(folder, cap), "out": folder / "api_out"}


@pytest.mark.parametrize("case", list(CASES))
def test_a_bad_value_gives_one_message_through_the_cli_and_the_api(case, capture, tmp_path,
                                                                   capsys):
    args, api, message, flag = CASES[case]
    with pytest.raises(ValueError) as err:
        api(capture)
    assert str(err.value) == message
    out = tmp_path / "maps"
    assert main(["fit-maps", str(capture["lp"]), "--out", str(out), "--encoding", "linear",
                 "--rounds", "1", "--iterations", "2", *args]) == 2
    expected = message if flag is None else flag + message[message.index(" = "):]
    assert capsys.readouterr().err == f"mitsuba-powder: error: {expected}\n"
    assert not out.exists() and not capture["out"].exists()


def test_an_old_option_name_warns_and_messages_name_it(capture):
    with pytest.warns(DeprecationWarning, match="gain_pixels is renamed gain_subsample"):
        with pytest.raises(ValueError, match=r"^gain_pixels = 0 is out of range"):
            _fit(capture, gain_pixels=0)
    with pytest.raises(ValueError, match="gain_model and gain_trend are the same option"):
        _fit(capture, gain_model=GainTrend(), gain_trend=GainTrend())
    with pytest.warns(DeprecationWarning, match="GainOptions is renamed GainTrend"):
        from mitsuba_powder.rti.gains import GainOptions
    assert GainOptions is GainTrend


def test_the_default_free_set_leaves_out_what_is_held():
    """Not given, the free set is the default less the held properties (``--set
    amplitude_surface=...`` holds the lobe's amplitude: it is not also free); given, a
    property both free and held is an error (CASES["set_free"])."""
    o = fit_options(fixed={"amplitude_surface": 1e-4})
    assert o.free == ("albedo", "correlation_length") and o.chooses_free
    assert fit_options().free == tuple(rf.MAP_DEFAULT_FREE)
    held = fit_options(fixed={"albedo": (0.5, 0.5, 0.5)})
    assert held.free == ("amplitude_surface", "correlation_length") and not held.chooses_free


def test_unknown_options_are_named(capture):
    with pytest.raises(ValueError, match=r"fit option\(s\) \['iterations'\] are not fit_maps "
                                         "options"):
        _fit(capture, iterations=3)


def test_the_parser_shows_the_fit_s_choices():
    """The command line checks no value itself: its help lists the choices the fit checks."""
    from mitsuba_powder.cli import parser
    from mitsuba_powder.rti.gains import GAIN_MODEL_MODES, GAIN_MODES

    def listed(names):
        return "{" + ",".join(names) + "}"

    assert parser.GAIN_MODES == listed(GAIN_MODES)
    assert parser.GAIN_MODEL_MODES == listed(GAIN_MODEL_MODES)
    assert parser.SOLVER_NAMES == listed(rf.SOLVERS)


def test_a_fit_checks_its_options_and_capture_once_whatever_its_stages(monkeypatch):
    """A fit with every stage (the light distance fitted, the gains on a subsample, blocks
    within a small memory budget: 149 pixels a block) builds its options once and checks its
    capture once."""
    from mitsuba_powder.rti import fit as fit_module
    from mitsuba_powder.rti import plan as plan_module

    calls = {"options": 0, "inputs": 0, "fit_maps": 0}
    spies = {"options": (fit_module, "fit_options"), "inputs": (plan_module, "check_inputs")}
    for key, (module, name) in spies.items():
        real = getattr(module, name)
        monkeypatch.setattr(module, name, _counting(real, calls, key))
    monkeypatch.setattr(rf, "fit_maps", _counting(rf.fit_maps, calls, "fit_maps"))
    cap = rf.synthetic_capture(16, 16, 12, noise=0.005, seed=2, light_distance=3.0)
    fixed = {n: cap["maps"][n] for n in ("amplitude_volume", "g", "extinction")}
    # a budget below the fit's smallest, so that 256 pixels need several blocks
    monkeypatch.setattr(rf.blocks, "MIN_MEMORY_GB", 1e-4)
    result = fit_module.fit_maps(cap["images"], cap["directions"], fixed=fixed, rounds=1,
                                 max_iterations=3, light_distance="fit", gain_subsample=100,
                                 memory_gb=0.0005, gains="fit")
    assert calls == {"options": 1, "inputs": 1, "fit_maps": 0}
    settings = result.fit_settings
    assert settings["light_distance_source"] == "fitted" and settings["gain_pixels"] == 100
    assert settings["blocks"] > 1 and math.isfinite(result.light_distance)
    plan = plan_module.make_plan(cap["images"], cap["directions"], rf.fit_options(
        fixed=fixed, light_distance="fit", gain_subsample=100, gains="fit"))
    assert [s.name for s in plan.stages] == ["distance scan", "exposure scan",
                                             "gain subsample", "free choice", "exposure check",
                                             "blocks", "shadows choice", "relief"]
    assert np.array_equal(plan.stages[5].pixels, np.ones((16, 16), bool))
    assert np.array_equal(plan.stages[6].pixels, plan.stages[3].pixels)  # the same subsample
    for shadows, last in (("relief", ["blocks", "relief"]),
                          ("ratio", ["exposure check", "blocks"])):
        other = plan_module.make_plan(cap["images"], cap["directions"], rf.fit_options(
            fixed=fixed, light_distance="fit", gain_subsample=100, gains="fit",
            shadows=shadows))
        assert [s.name for s in other.stages][-2:] == last


def _counting(func, calls: dict, key: str):
    def counted(*args, **kwargs):
        calls[key] += 1
        return func(*args, **kwargs)
    return counted
