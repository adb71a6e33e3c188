"""Render-vs-photo comparison: image reading, exposure and white-balance recovery, ColorChecker
calibration against colour-science's reference chart, CIEDE2000 and the CLI."""

from __future__ import annotations

import json

import colour
import mitsuba as mi
import numpy as np
import pytest

from mitsuba_powder.cli import main
from mitsuba_powder.rendering import photo as P
from mitsuba_powder.variants import use_variant


def smooth_image(h: int = 48, w: int = 64, seed: int = 0) -> np.ndarray:
    """A linear RGB image with smooth colour gradients and a few flat patches."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    img = np.stack([0.2 + 0.6 * x, 0.1 + 0.5 * y, 0.3 + 0.3 * x * y], axis=-1)
    for _ in range(4):
        y0, x0 = rng.integers(0, h - 10), rng.integers(0, w - 10)
        img[y0:y0 + 10, x0:x0 + 10] = rng.uniform(0.05, 0.9, 3)
    return img


def write_png(path, linear: np.ndarray, bits: int) -> None:
    enc = colour.cctf_encoding(np.clip(linear, 0, 1), function="sRGB")
    top = 2**bits - 1
    dtype = np.uint8 if bits == 8 else np.uint16
    with use_variant("scalar_rgb"):
        mi.Bitmap((enc * top + 0.5).astype(dtype),
                  pixel_format=mi.Bitmap.PixelFormat.RGB).write(str(path))


def test_read_exr_and_png(tmp_path):
    img = smooth_image()
    P.write_exr(tmp_path / "a.exr", img * 3.0)
    np.testing.assert_allclose(P.read_image(tmp_path / "a.exr"), img * 3.0, rtol=1e-6)
    write_png(tmp_path / "a16.png", img, 16)
    np.testing.assert_allclose(P.read_image(tmp_path / "a16.png"), img, atol=5e-5)
    write_png(tmp_path / "a8.png", img, 8)
    np.testing.assert_allclose(P.read_image(tmp_path / "a8.png"), img, atol=5e-3)
    # the same PNG read as if it were linear is the encoded values
    raw = P.read_image(tmp_path / "a16.png", "linear")
    np.testing.assert_allclose(raw, colour.cctf_encoding(img, function="sRGB"), atol=5e-5)
    # an EXR declared sRGB-encoded is decoded
    np.testing.assert_allclose(P.read_image(tmp_path / "a.exr", "srgb"),
                               colour.cctf_decoding(img * 3.0, function="sRGB"), rtol=1e-5)


def test_recovers_exposure_and_white_balance(tmp_path):
    """photo = render scaled by a known exposure (-1.3 stops) and white balance, saved as a
    16-bit sRGB PNG: the alignment recovers the inverse gains and Delta E goes to ~0."""
    render = smooth_image()
    gains = np.array([1.25, 1.0, 0.7]) * 2.0**-1.3
    write_png(tmp_path / "photo.png", render * gains, 16)
    P.write_exr(tmp_path / "render.exr", render)
    r = P.read_image(tmp_path / "render.exr")
    p = P.read_image(tmp_path / "photo.png")
    stats, aligned, de = P.compare_images(r, p, align_mode="white-balance", white=1.0)
    np.testing.assert_allclose(stats.gains, 1.0 / gains, rtol=2e-3)
    assert abs(stats.exposure_stops - 1.3) < 3e-3
    np.testing.assert_allclose(stats.white_balance, [0.8, 1.0, 1 / 0.7], rtol=2e-3)
    assert stats.mean < 0.05 and stats.max < 0.5
    # exposure only cannot undo the white balance: the error is large and reported
    st2, _, _ = P.compare_images(r, p, align_mode="exposure", white=1.0)
    assert st2.mean > 3.0
    # and no alignment at all is worse still
    st3, _, _ = P.compare_images(r, p, align_mode="none", white=1.0)
    assert st3.mean > st2.mean


def chart_image(transform: np.ndarray, size=(300, 420), corners=((60, 50), (360, 70),
                                                                  (350, 250), (50, 230))):
    """A photo of the ColorChecker: each patch the reference linear sRGB seen through a
    camera ``transform`` (camera RGB = transform @ sRGB), drawn at the patch centres from
    ``corners`` (a slightly rotated chart), on a grey background, with noise."""
    h, w = size
    img = np.full((h, w, 3), 0.18) @ transform.T
    ref = P.chart_reference_rgb()
    centres = P.chart_patch_centres(corners)
    for (x, y), rgb in zip(centres, ref, strict=True):
        xi, yi = int(round(x)), int(round(y))
        img[yi - 12:yi + 13, xi - 12:xi + 13] = transform @ rgb
    rng = np.random.default_rng(5)
    return np.clip(img * (1 + 0.004 * rng.normal(size=img.shape)), 0, None), corners


def test_colorchecker_calibration_recovers_a_known_transform(tmp_path):
    camera = np.array([[0.70, 0.25, 0.05], [0.10, 0.80, 0.10], [0.02, 0.18, 0.60]]) * 0.8
    img, corners = chart_image(camera)
    write_png(tmp_path / "chart.png", img, 8)
    photo = P.read_image(tmp_path / "chart.png")
    calibrated, matrix, de = P.calibrate_with_chart(photo, corners, half=4)
    assert de.mean() < 1.0 and de.max() < 2.5
    np.testing.assert_allclose(matrix @ camera, np.eye(3), atol=0.03)
    # every patch, measured again on the calibrated image, is the reference to < 1 DE mean
    patches = P.sample_patches(calibrated, P.chart_patch_centres(corners), 4)
    assert P.delta_e_2000(patches[None], P.chart_reference_rgb()[None], 1.0).mean() < 1.0
    # without calibration the chart is far off
    raw = P.sample_patches(photo, P.chart_patch_centres(corners), 4)
    assert P.delta_e_2000(raw[None], P.chart_reference_rgb()[None], 1.0).mean() > 5.0


def test_delta_e_2000_is_colour_science():
    a = np.array([[[0.2, 0.3, 0.4]]])
    b = np.array([[[0.22, 0.3, 0.38]]])
    lab = [colour.XYZ_to_Lab(colour.sRGB_to_XYZ(colour.cctf_encoding(x, function="sRGB")))
           for x in (a, b)]
    np.testing.assert_allclose(P.delta_e_2000(a, b, 1.0),
                               colour.delta_E(lab[0], lab[1], method="CIE 2000"), rtol=1e-6)
    assert P.delta_e_2000(a, a, 1.0)[0, 0] == 0.0


def test_bad_input(tmp_path):
    with pytest.raises(FileNotFoundError, match="does not exist"):
        P.read_image(tmp_path / "nope.exr")
    (tmp_path / "x.bmp").write_bytes(b"0")
    with pytest.raises(ValueError, match="'.bmp' is not supported"):
        P.read_image(tmp_path / "x.bmp")
    P.write_exr(tmp_path / "a.exr", smooth_image())
    with pytest.raises(ValueError, match="encoding = 'gamma'"):
        P.read_image(tmp_path / "a.exr", "gamma")
    a, b = smooth_image(), smooth_image(40, 64)
    with pytest.raises(ValueError, match="64 x 48 px and the photo 64 x 40 px"):
        P.compare_images(a, b)
    with pytest.raises(ValueError, match="region = "):
        P.compare_images(a, a, region=(0, 0, 100, 10))
    with pytest.raises(ValueError, match="align = 'auto'"):
        P.compare_images(a, a, align_mode="auto")
    with pytest.raises(ValueError, match="expected 4"):
        P.chart_patch_centres([(0, 0), (1, 1)])
    with pytest.raises(ValueError, match="outside the 64 x 48 image"):
        P.calibrate_with_chart(a, [(0, 0), (60, 0), (60, 40), (0, 40)])
    with pytest.raises(ValueError, match="no signal"):
        P.compare_images(a, np.zeros_like(a))


def test_cli_compare_photo(tmp_path, capsys):
    camera = np.array([[0.9, 0.1, 0.0], [0.05, 0.9, 0.05], [0.0, 0.1, 0.8]])
    img, corners = chart_image(camera)
    render = img @ np.linalg.inv(camera).T  # what a perfect render of the scene would be
    P.write_exr(tmp_path / "render.exr", render)
    write_png(tmp_path / "photo.png", img * 0.5, 16)
    chart = " ".join(f"{x},{y}" for x, y in corners)
    out = tmp_path / "out"
    assert main(["compare-photo", str(tmp_path / "render.exr"), str(tmp_path / "photo.png"),
                 "--chart", chart, "--out", str(out)]) == 0
    text = capsys.readouterr().out
    assert "ColorChecker calibration" in text and "CIEDE2000" in text
    stats = json.loads((out / "photo_comparison.json").read_text())
    assert stats["mean"] < 1.0 and stats["chart_delta_e_mean"] < 1.0
    assert (out / "delta_e.png").is_file() and (out / "side_by_side.png").is_file()
    assert main(["compare-photo", str(tmp_path / "render.exr"), str(tmp_path / "photo.png"),
                 "--chart", "1,2 3,4", "--out", str(out)]) == 2
    assert "--chart '1,2 3,4'" in capsys.readouterr().err


def test_photo_and_model_comparisons_do_not_overwrite_each_other(tmp_path, capsys):
    """compare-photo and compare-models have their own default folders, and their own file
    names when given the same --out."""
    from mitsuba_powder.cli import build_parser
    from mitsuba_powder.fitting.comparison import write_comparison

    parser = build_parser()
    assert parser.parse_args(["compare-photo", "r.exr", "p.png"]).out == "photo_compare"
    assert parser.parse_args(["compare-models", "d.csv"]).out == "model_compare"
    with pytest.raises(SystemExit):  # the old, ambiguous name is gone
        parser.parse_args(["compare", "r.exr", "p.png"])
    capsys.readouterr()
    out = tmp_path / "same"
    rows = [{"model": "lambertian", "wavelength": 700.0, "parameters": 1,
             "relative_rmse_percent": 5.0, "max_abs_relative_error_percent": 9.0,
             "rmse_brf": 0.01, "seconds": 0.1, "fitted": {"rho": 0.5}}]
    table = write_comparison(rows, out)
    render = smooth_image()
    P.write_exr(tmp_path / "render.exr", render)
    P.write_exr(tmp_path / "photo.exr", render * 0.5)
    assert main(["compare-photo", str(tmp_path / "render.exr"), str(tmp_path / "photo.exr"),
                 "--out", str(out)]) == 0
    assert json.loads((out / "model_comparison.json").read_text()) == rows
    assert "| 700 | lambertian | 1 |" in table.read_text()
    assert json.loads((out / "photo_comparison.json").read_text())["mean"] < 0.01


def test_clipped_photo_pixels_are_left_out(tmp_path):
    """An over-exposed 8-bit photo: with the clipped pixels in, the gains are biased; left
    out (saturation 0.99), the exposure and white balance are recovered."""
    render = smooth_image() * 1.5
    gains = np.array([1.1, 1.0, 0.8]) * 2.0**0.4
    write_png(tmp_path / "photo.png", render * gains, 8)
    photo = P.read_image(tmp_path / "photo.png")
    assert np.any(photo >= 0.999)
    biased, _, _ = P.compare_images(render, photo, white=1.5)
    assert abs(biased.exposure_stops + 0.4) > 0.02
    # more than max_clipped of the region clipped: an error naming the option, not numbers
    # that describe what is left
    share = float(np.mean(np.any(photo >= 0.99, axis=2)))
    assert share > 0.1
    with pytest.raises(ValueError, match=r"are clipped .*--max-clipped\) = 0.1"):
        P.compare_images(render, photo, white=1.5, saturation=0.99)
    stats, _, _ = P.compare_images(render, photo, white=1.5, saturation=0.99, max_clipped=0.9)
    assert stats.saturated_pixels > 100
    assert stats.clipped_fraction == pytest.approx(share)
    assert stats.region_pixels == photo.shape[0] * photo.shape[1]
    np.testing.assert_allclose(stats.gains, 1.0 / gains, rtol=0.01)
    assert stats.mean < 0.5
    with pytest.raises(ValueError, match=r"max_clipped \(--max-clipped\) = 1.5 is out of range"):
        P.compare_images(render, photo, saturation=0.99, max_clipped=1.5)


def test_error_map_draws_left_out_pixels_in_grey(tmp_path):
    """delta_e.png: pixels outside the region are neutral grey, not a colour of the scale."""
    render = smooth_image()
    stats, aligned, de = P.compare_images(render, render * 0.9, region=(0, 0, 8, 8))
    P.write_report(tmp_path, stats, render, aligned, de)
    import matplotlib.image

    png = matplotlib.image.imread(tmp_path / "delta_e.png")[..., :3]
    grey = np.all(np.abs(png - 0.6) < 0.02, axis=2)
    assert grey.sum() > 100


def test_negative_chart_window_is_rejected():
    img, corners = chart_image(np.eye(3))
    with pytest.raises(ValueError, match=r"--chart-window\) = -1 px"):
        P.calibrate_with_chart(img, corners, half=-1)
