"""RTI fits that cannot give maps say so (issue 33, case 3): a saturated or black capture, too
few lights or lights in one plane, a memory budget too small to run, a tilted object whose
lowest lights fall below its horizon (the gain step holds the gains of lights that see
nothing), and a fit that diverges all give a clear error or finite maps, never NaN maps with
exit 0. The captures are SYNTHETIC (rendered by the plugin)."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from helpers import write_image_capture
from mitsuba_powder.cli import main
from mitsuba_powder.rti import fit_maps
from mitsuba_powder.rti.forward import render_capture
from mitsuba_powder.rti.gains import MIN_INFORMATION, gain_step, uninformed_lights
from mitsuba_powder.rti.plan import check_finite
from mitsuba_powder.rti.result import MapsResult
from mitsuba_powder.rti.synthetic import dome_directions, synthetic_capture, synthetic_maps

TILT = 40.0  # degrees: 7 of the dome's 40 lights fall below the plane's horizon


@pytest.fixture(scope="module")
def small():
    """A SYNTHETIC capture of 8 x 8 pixels under 12 lights."""
    return synthetic_capture(8, 8, lights=12, noise=0.005)


def tilted_capture(tilt: float = TILT, size: int = 24) -> dict:
    """A SYNTHETIC plane tilted by ``tilt`` degrees towards +x (four regions of the fit's held
    properties), 40 dome lights at 10-80 degrees, noise 0.005, clipped at 0 as a camera does:
    the lights below the plane's horizon give black images."""
    maps, _ = synthetic_maps(size, size, relief=0.0)
    n = np.array([math.sin(math.radians(tilt)), 0.0, math.cos(math.radians(tilt))])
    maps["normal"][:] = n
    for name, value in {"amplitude_volume": 1.0, "g": 0.0, "extinction": 1.0}.items():
        maps[name][:] = value
    d = dome_directions(40)
    clean = render_capture(maps, d, np.full(len(d), 2.0))
    rng = np.random.default_rng(1)
    images = np.clip(clean + rng.normal(0.0, 0.005, clean.shape), 0.0, 1.0).astype(np.float32)
    return {"images": images, "directions": d, "normal": n, "below": np.nonzero(d @ n <= 0)[0]}


def angles(result: MapsResult, n: np.ndarray) -> np.ndarray:
    """Angles (degrees) between the fitted normals and ``n``."""
    fitted = result.normals.reshape(-1, 3).astype(np.float64)
    return np.degrees(np.arccos(np.clip(fitted @ n, -1.0, 1.0)))


def test_saturated_capture_refused(small, tmp_path, capsys):
    images = np.ones_like(small["images"])
    with pytest.raises(ValueError, match=r"64 of the 64 masked pixels see fewer than 3 lights"
                       r".*768 are saturated.*saturation = 0\.99.*shorter exposure"):
        fit_maps(images, small["directions"])
    lp = write_image_capture(tmp_path / "cap", images, small["directions"],
                             "linear", 16)
    for command in ("fit-maps", "compare-maps"):
        out = tmp_path / command
        assert main([command, str(lp), "--out", str(out), "--encoding", "linear"]) == 2
        err = capsys.readouterr().err
        assert "saturated" in err and "--saturation = 0.99" in err and "Traceback" not in err
        assert not (out / "fit.json").exists() and not (out / "compare.json").exists()


def test_black_capture_refused(small):
    with pytest.raises(ValueError, match=r"768 are black.*no light reaches"):
        fit_maps(np.zeros_like(small["images"]), small["directions"])


def test_partly_saturated_capture_fits_and_says_so(small):
    images = small["images"].copy()
    images[:, :3] = 1.0  # three of eight rows saturated under every light
    lines: list[str] = []
    result = fit_maps(images, small["directions"], rounds=1, max_iterations=10,
                      progress=lines.append)
    assert any("24 of 64 pixels have fewer used observations" in t for t in lines), lines
    assert np.all(np.isnan(result.residual_rms[:3])) and np.all(np.isfinite(result.albedo))


@pytest.mark.parametrize("count", [1, 2])
def test_too_few_lights_refused(small, count):
    with pytest.raises(ValueError, match=rf"the capture has {count} light\(s\); a per-pixel "
                       "fit needs at least 3"):
        fit_maps(small["images"][:count], small["directions"][:count])


def test_coplanar_lights_refused(small):
    d = np.array([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
    with pytest.raises(ValueError, match="light directions lie in one plane"):
        fit_maps(small["images"][:4], d)


def test_one_light_cli_says_how_many(small, tmp_path, capsys):
    lp = write_image_capture(tmp_path / "cap", small["images"][:1], small["directions"][:1])
    assert main(["fit-maps", str(lp), "--out", str(tmp_path / "o"), "--encoding",
                 "linear"]) == 2
    err = capsys.readouterr().err
    assert "needs at least 3" in err and "Singular" not in err


def test_memory_budget_too_small_refused(small, tmp_path, capsys):
    with pytest.raises(ValueError, match=r"memory_gb = 1e-09 is out of range; valid "
                       r"range is \[0\.015625, inf\) GiB"):
        fit_maps(small["images"], small["directions"], memory_gb=1e-9)
    lp = write_image_capture(tmp_path / "cap", small["images"], small["directions"])
    assert main(["fit-maps", str(lp), "--out", str(tmp_path / "o"), "--memory-gb",
                 "1e-9"]) == 2
    assert "--memory-gb = 1e-09 is out of range" in capsys.readouterr().err


def test_gain_step_holds_lights_that_see_nothing():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(6, 6))
    s = a @ a.T + 6 * np.eye(6)
    s[2, :] = s[:, 2] = 0.0  # light 2 sees nothing: no information on its gain
    s[4, 4] *= MIN_INFORMATION / 10  # light 4 almost nothing
    rhs = rng.normal(size=6)
    assert uninformed_lights(s).tolist() == [False, False, True, False, True, False]
    gains = np.ones(6)
    new = gain_step(gains, s, rhs, 1.0)
    assert np.all(np.isfinite(new)) and np.isclose(np.mean(new), 1.0)
    # held lights move only with the mean's normalisation
    assert np.isclose(new[2], new[4]) and not np.isclose(new[0], new[2])
    # no light informed, or a non-finite system: the gains stay as they are
    assert np.array_equal(gain_step(gains, np.zeros((6, 6)), rhs, 1.0), gains)
    s_nan = s.copy()
    s_nan[0, 1] = np.nan
    assert np.array_equal(gain_step(gains, s_nan, rhs, 1.0), gains)


def test_gain_step_changes_a_gain_by_at_most_a_factor_2():
    s = np.eye(4)
    new = gain_step(np.ones(4), s, np.array([-100.0, 100.0, 0.0, 0.0]), 1.0)
    raw = np.array([2.0, 0.5, 1.0, 1.0])  # clipped steps, before the mean is restored
    assert np.allclose(new, raw / raw.mean())


@pytest.mark.parametrize("gains", ["fit", "fixed"])
def test_tilted_capture_with_lights_below_its_horizon(gains):
    cap = tilted_capture()
    assert len(cap["below"]) == 7
    lines: list[str] = []
    result = fit_maps(cap["images"], cap["directions"], gains=gains, progress=lines.append)
    for m in (result.normals, result.albedo, *result.maps.values()):
        assert np.all(np.isfinite(m))
    assert np.all(np.isfinite(result.gains))
    err = angles(result, cap["normal"])
    assert np.median(err) < 1.2 and np.percentile(err, 95) < 2.0, (np.median(err), err.max())
    if gains == "fit":
        held = [t for t in lines if "see too little to fit their gain" in t]
        assert held, lines
        for k in cap["below"]:
            assert f"{k}" in held[0]


def test_diverged_fit_refused(small):
    result = fit_maps(small["images"], small["directions"], rounds=1, max_iterations=5)
    check_finite(result)  # a finite result passes
    result.albedo[3, 4, 1] = np.nan
    with pytest.raises(RuntimeError, match=r"the albedo map is not finite at 1 of 64 fitted "
                       r"pixels \(first at x = 4, y = 3\)"):
        check_finite(result)
    result.albedo[3, 4, 1] = 0.5
    result.gains[5] = np.inf
    with pytest.raises(RuntimeError, match=r"the gains of lights \[5\] are not finite"):
        check_finite(result)


def test_nan_outside_the_mask_is_not_an_error(small):
    mask = np.zeros((8, 8), dtype=bool)
    mask[2:6, 2:6] = True
    result = fit_maps(small["images"], small["directions"], mask=mask, rounds=1,
                      max_iterations=5)
    assert np.all(np.isnan(result.albedo[0])) and check_finite(result) is result
    assert json.dumps(result.fit_settings["stages"])
