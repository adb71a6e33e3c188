"""Issue 35: a reference card in the frame calibrates the exposure and each light's
irradiance (``--reference x0,y0,x1,y1[:REFLECTANCE]``); compare-maps takes fit-maps' options."""

import json
import math

import numpy as np
import pytest

from helpers import write_exr_capture
from mitsuba_powder.cli import main
from mitsuba_powder.rti.forward import render_capture
from mitsuba_powder.rti.reference import Reference, calibrate, parse_reference
from mitsuba_powder.rti.synthetic import dome_directions, synthetic_maps

EXPOSURE = 1.52
NOISE = 0.005
CARD = (0, 0, 4, 4)  # x0, y0, x1, y1


def card_capture(size: int = 16, lights: int = 30, reflectance: float = 0.8) -> dict:
    """The powder of issue 35's synthetic capture, lights of irradiance 1.52 x (1 +- 15 %),
    and a Lambertian card of ``reflectance`` in the top-left 4 x 4 pixels."""
    maps, region = synthetic_maps(size, size)
    for name in ("amplitude_volume", "g", "extinction"):
        maps.pop(name)
    maps["amplitude_surface"][:] = 2e-4
    maps["correlation_length"][:] = 0.5
    d = dome_directions(lights)
    e = EXPOSURE * (1 + 0.15 * np.sin(np.arange(lights)))
    clean = render_capture(maps, d, e)
    x0, y0, x1, y1 = CARD
    clean[:, y0:y1, x0:x1] = (e * reflectance / math.pi * d[:, 2])[:, None, None, None]
    images = clean + np.random.default_rng(2).normal(0.0, NOISE, clean.shape)
    return {"images": images.astype(np.float32), "directions": d, "maps": maps,
            "region": region, "irradiance": e, "reflectance": reflectance}


@pytest.fixture(scope="module")
def capture():
    return card_capture()


def test_the_card_gives_each_light_s_irradiance(capture):
    cal = calibrate(capture["images"], capture["directions"],
                    Reference(CARD, capture["reflectance"]))
    np.testing.assert_allclose(cal["irradiance"], capture["irradiance"], rtol=0.02)
    assert abs(cal["exposure"] / np.mean(capture["irradiance"]) - 1) < 0.005
    assert cal["estimated"].all() and cal["pixels"] == 16


def test_grazing_lights_get_the_others_median(capture):
    d = capture["directions"].copy()
    d[0] = [1.0, 0.0, 0.01]
    cal = calibrate(capture["images"], d, Reference(CARD, capture["reflectance"]))
    assert not cal["estimated"][0] and cal["estimated"][1:].all()
    assert cal["irradiance"][0] == pytest.approx(np.median(cal["irradiance"][1:]))


@pytest.mark.parametrize("text, message", [
    ("0,0,4", r"--reference = '0,0,4': expected x0,y0,x1,y1\[:REFLECTANCE\]"),
    ("0,0,4,4:1.5", r"--reference reflectance = '1.5' is out of range; valid range is "
                    r"\(0, 1\]"),
    ("a,0,4,4", r"expected x0,y0,x1,y1"),
])
def test_a_bad_reference_is_named(text, message):
    with pytest.raises(ValueError, match=message):
        parse_reference(text)


def test_a_card_outside_the_image_is_named(capture):
    with pytest.raises(ValueError, match=r"--reference = 10,0,40,4 is out of range; valid: "
                                         r"0 <= x0 < x1 <= 16"):
        calibrate(capture["images"], capture["directions"], Reference((10, 0, 40, 4)))


def test_fit_maps_with_a_reference_card(capture, tmp_path, capsys):
    lp = write_exr_capture(tmp_path, capture)
    out = tmp_path / "maps"
    assert main(["fit-maps", str(lp), "--out", str(out), "--encoding", "linear",
                 "--reference", "0,0,4,4:0.8", "--free",
                 "albedo,amplitude_surface,correlation_length"]) == 0
    info = json.loads((out / "fit.json").read_text())
    record = info["fit"]["exposure"]
    assert record["source"] == "reference" and record["reference"]["box"] == [0, 0, 4, 4]
    assert abs(info["exposure"] / np.mean(capture["irradiance"]) - 1) < 0.01
    np.testing.assert_allclose(info["gains"], capture["irradiance"], rtol=0.02)
    printed = capsys.readouterr().out
    assert "reference card: 16 pixels, reflectance 0.8" in printed
    from mitsuba_powder.rti.maps import read_maps

    res, _ = read_maps(out)
    assert not res.mask[:4, :4].any() and res.mask.sum() == 16 * 16 - 16
    for r in range(4):
        sel = (capture["region"] == r) & res.mask
        err = np.median(res.albedo[sel], axis=0) / capture["maps"]["albedo"][sel][0] - 1
        assert np.abs(err).max() < 0.03, (r, err)


def test_exposure_and_reference_together_are_refused(capture, tmp_path, capsys):
    lp = write_exr_capture(tmp_path, capture)
    assert main(["fit-maps", str(lp), "--out", str(tmp_path / "m"), "--encoding", "linear",
                 "--reference", "0,0,4,4", "--exposure", "1.5"]) == 2
    assert "--exposure 1.5 and --reference 0,0,4,4 were both given" in capsys.readouterr().err


def test_compare_maps_takes_the_fit_s_options(capture, tmp_path, capsys):
    lp = write_exr_capture(tmp_path, capture)
    out = tmp_path / "cmp"
    assert main(["compare-maps", str(lp), "--out", str(out), "--encoding", "linear",
                 "--models", "lambertian_clamped,powder", "--reference", "0,0,4,4:0.8",
                 "--free", "albedo,amplitude_surface,correlation_length", "--rounds", "1",
                 "--gains", "fixed", "--no-error-images"]) == 0
    doc = json.loads((out / "compare.json").read_text())
    assert doc["capture"]["pixels_scored"] == 16 * 16 - 16  # the card is not scored
    rows = {(r["protocol"], r["model"]): r for r in doc["rows"]}
    # relit at each held-out light's irradiance from the card: near the noise (lights that
    # differ by +-15 % relit at one gain would be off by several times it)
    for protocol in ("interpolation", "grazing"):
        assert rows[(protocol, "powder")]["rmse_linear_8bit"] < 2 * 255 * NOISE
    assert main(["compare-maps", str(lp), "--out", str(tmp_path / "c2"), "--encoding",
                 "linear", "--models", "powder", "--exposure", "0"]) == 2
    assert "exposure = 0 is out of range" in capsys.readouterr().err
