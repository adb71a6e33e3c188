"""RTI captures (mitsuba_powder.rti.capture), per-pixel baselines (rti.baselines) and the
held-out-light comparison (rti.comparison), on SYNTHETIC captures generated here."""

from __future__ import annotations

import json
import math
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from mitsuba_powder.cli import main
from mitsuba_powder.rti import Capture, load_capture, read_lp, write_images, write_lp
from mitsuba_powder.rti.baselines import basis, fit_baseline
from mitsuba_powder.rti.comparison import baseline_fitter, compare, held_out, write_comparison
from mitsuba_powder.variants import use_variant

K, H, W = 30, 24, 32


def _directions(k: int = K, seed: int = 0) -> np.ndarray:
    """k unit vectors on the upper hemisphere, elevations 5-85 degrees (SYNTHETIC)."""
    rng = np.random.default_rng(seed)
    elev = np.radians(rng.uniform(5.0, 85.0, k))
    azim = rng.uniform(0.0, 2.0 * np.pi, k)
    return np.stack([np.cos(elev) * np.cos(azim), np.cos(elev) * np.sin(azim), np.sin(elev)],
                    axis=1)


def _images(d: np.ndarray) -> np.ndarray:
    """Smooth SYNTHETIC linear images in [0.02, 0.95], (K, H, W, 3)."""
    y, x = np.mgrid[0:H, 0:W] / np.array([H, W])[:, None, None]
    base = np.stack([0.2 + 0.6 * x, 0.3 + 0.5 * y, 0.5 + 0.3 * x * y], axis=-1)
    shade = 0.1 + 0.9 * d[:, 2]
    return np.clip(base[None] * shade[:, None, None, None], 0.02, 0.95).astype(np.float32)


def _srgb_encode(x: np.ndarray) -> np.ndarray:
    """IEC 61966-2-1 encoding, written out here as the independent reference."""
    x = np.asarray(x, dtype=np.float64)
    return np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(np.maximum(x, 0), 1 / 2.4)
                    - 0.055)


def _write_capture(folder: Path, fmt: str, depth: int, encoding: str, scale: float = 2.5):
    d = _directions()
    imgs = _images(d)
    names = [f"light {i:02d}.{fmt}" for i in range(K)]  # a space in the names, as allowed
    like = Capture(imgs, d, names, encoding, {"jpg": "jpeg"}.get(fmt, fmt), depth)
    write_images(like, imgs, names, folder)
    write_lp(folder / "capture.lp", names, d * scale)  # not unit vectors on purpose
    return d, imgs, folder / "capture.lp"


@pytest.mark.parametrize("fmt,depth,encoding,tol", [
    ("png", 8, "srgb", 0.5 / 255), ("png", 16, "linear", 0.5 / 65535),
    ("png", 16, "srgb", 0.5 / 65535), ("exr", 32, "linear", 0.0), ("exr", 16, "linear", 1e-3),
    ("jpg", 8, "srgb", 6 / 255)])  # JPEG: lossy (chroma subsampling)
def test_round_trip(tmp_path, fmt, depth, encoding, tol):
    d, imgs, lp = _write_capture(tmp_path, fmt, depth, encoding)
    cap = load_capture(lp, encoding=encoding)
    assert cap.images.shape == (K, H, W, 3) and cap.images.dtype == np.float32
    assert cap.file_format == {"jpg": "jpeg"}.get(fmt, fmt) and cap.bit_depth == depth
    assert cap.names == [f"light {i:02d}.{fmt}" for i in range(K)]
    np.testing.assert_allclose(np.linalg.norm(cap.directions, axis=1), 1.0, atol=1e-12)
    np.testing.assert_allclose(cap.directions, d, atol=1e-8)
    # quantisation happens on the file's (encoded) values
    enc = _srgb_encode if encoding == "srgb" else np.asarray
    err = np.abs(enc(cap.images) - enc(imgs))
    assert err.max() <= tol + 1e-6, err.max()
    # written back with the same format and depth: the same file values
    out = tmp_path / "again"
    write_images(cap, cap.images, lp, out)
    again = load_capture(out / "capture.lp", encoding=encoding)
    assert (again.file_format, again.bit_depth) == (cap.file_format, cap.bit_depth)
    if fmt != "jpg":
        np.testing.assert_allclose(again.images, cap.images, atol=1e-6)


def test_srgb_decoding_reference(tmp_path):
    # an 8-bit PNG written with known integers; decoding checked against IEC 61966-2-1
    levels = np.arange(256, dtype=np.uint8).reshape(16, 16)
    with use_variant("scalar_rgb"):
        mi.Bitmap(np.repeat(levels[..., None], 3, axis=2), mi.Bitmap.PixelFormat.RGB).write(
            str(tmp_path / "a.png"))
    write_lp(tmp_path / "c.lp", ["a.png"], np.array([[0.0, 0.0, 1.0]]))
    v = levels / 255.0
    ref = np.where(v <= 0.04045, v / 12.92, ((v + 0.055) / 1.055) ** 2.4)
    cap = load_capture(tmp_path / "c.lp", encoding="srgb")
    np.testing.assert_allclose(cap.images[0, ..., 1], ref, atol=2e-7)
    lin = load_capture(tmp_path / "c.lp", encoding="linear")
    np.testing.assert_allclose(lin.images[0, ..., 0], v, atol=1e-7)


def test_mask_and_blank_lines(tmp_path):
    d, imgs, lp = _write_capture(tmp_path, "png", 8, "linear")
    lp.write_text("\n" + lp.read_text().replace("\n", "\n\n", 3) + "\n\n")
    mask = np.zeros((H, W, 3), dtype=np.uint8)
    mask[5:10, 3:20] = 255
    with use_variant("scalar_rgb"):
        mi.Bitmap(mask, mi.Bitmap.PixelFormat.RGB).write(str(tmp_path / "mask.png"))
    cap = load_capture(lp, encoding="linear", mask=tmp_path / "mask.png")
    assert len(cap.names) == K and cap.mask.sum() == 5 * 17 and cap.mask[5, 3]
    small = np.zeros((H, W - 1, 3), dtype=np.uint8) + 255
    with use_variant("scalar_rgb"):
        mi.Bitmap(small, mi.Bitmap.PixelFormat.RGB).write(str(tmp_path / "small.png"))
    with pytest.raises(ValueError, match="small.png: 31 x 24 pixels"):
        load_capture(lp, mask=tmp_path / "small.png")


GOOD = "3\na.png 0 0 1\nb.png 0.5 0 0.5\nc.png 0 -0.3 0.9\n"


@pytest.mark.parametrize("text,message", [
    ("", "empty file"),
    ("three\na.png 0 0 1\n", r"line 1: 'three' is not the number of lights"),
    ("0\n", "number of lights 0; expected >= 1"),
    ("4\na.png 0 0 1\nb.png 0.5 0 0.5\nc.png 0 -0.3 0.9\n",
     r"line 1: the count says 4 lights but the file has 3 light lines"),
    ("2\na.png 0 0 1\nb.png 0.5 0 0.5\nc.png 0 -0.3 0.9\n",
     r"line 1: the count says 2 lights but the file has 3"),
    ("3\na.png 0 0 1\nb.png 0.5 0.5\nc.png 0 -0.3 0.9\n",
     r"line 3: 'b.png 0.5 0.5' has 3 fields; expected 'filename lx ly lz'"),
    ("3\na.png 0 0 1\nb.png 0.5 x 0.5\nc.png 0 -0.3 0.9\n",
     r"line 3: ly = 'x' is not a number"),
    ("3\na.png 0 0 1\nb.png 0.5 0 nan\nc.png 0 -0.3 0.9\n", r"line 3: lz = 'nan' is not finite"),
    ("3\na.png 0 0 1\nb.png 0 0 0\nc.png 0 -0.3 0.9\n", r"line 3: .* is the zero vector"),
    ("3\na.png 0 0 1\nb.png 0.5 0 -0.5\nc.png 0 -0.3 0.9\n",
     r"line 3: .* normalised lz = -0.7071 < -0.1"),
    ("3\na.png 0 0 1\nb.png 0.5 0 0.5\na.png 0 -0.3 0.9\n",
     r"line 4: file name 'a.png' repeats line 2"),
    ("3\n# lights\na.png 0 0 1\nb.png 0.5 0 0.5\n", r"line 2: '# lights' has 2 fields"),
])
def test_malformed_lp(tmp_path, text, message):
    lp = tmp_path / "bad.lp"
    lp.write_text(text)
    with pytest.raises(ValueError, match=message) as info:
        read_lp(lp)
    assert str(lp) in str(info.value)


def test_lp_reads_slightly_negative_lz(tmp_path):
    lp = tmp_path / "ok.lp"
    text = GOOD.replace("c.png 0 -0.3 0.9", "c.png 0.962735 0.270443 -0.001191")
    lp.write_bytes(text.replace("\n", "\r\n").encode())  # Windows line ends
    names, d = read_lp(lp)
    assert names == ["a.png", "b.png", "c.png"]
    np.testing.assert_allclose(d[1], [math.sqrt(0.5), 0, math.sqrt(0.5)])
    assert -0.0013 < d[2, 2] < 0


def test_missing_and_mismatched_images(tmp_path):
    _, _, lp = _write_capture(tmp_path, "png", 8, "srgb")
    (tmp_path / "light 07.png").unlink()
    with pytest.raises(FileNotFoundError, match=r"capture.lp, line 9: image 'light 07.png' "
                                                r"not found"):
        load_capture(lp)
    with use_variant("scalar_rgb"):
        mi.Bitmap(np.zeros((H + 1, W, 3), np.uint8), mi.Bitmap.PixelFormat.RGB).write(
            str(tmp_path / "light 07.png"))
    with pytest.raises(ValueError, match=r"line 9: image 'light 07.png' is 32 x 25 px, 3 "
                                         r"channels, png 8 bit; expected 32 x 24 px"):
        load_capture(lp)
    with use_variant("scalar_rgb"):
        mi.Bitmap(np.zeros((H, W, 3), np.uint16), mi.Bitmap.PixelFormat.RGB).write(
            str(tmp_path / "light 07.png"))
    with pytest.raises(ValueError, match=r"line 9: .* png 16 bit; expected .* png 8 bit"):
        load_capture(lp)
    with pytest.raises(ValueError, match="encoding = 'gamma'"):
        load_capture(lp, encoding="gamma")
    with pytest.raises(FileNotFoundError, match="nope.lp does not exist"):
        load_capture(tmp_path / "nope.lp")


def _ptm_reference(d: np.ndarray) -> np.ndarray:
    u, v = d[:, 0], d[:, 1]
    return np.stack([u * u, v * v, u * v, u, v, np.ones_like(u)], axis=1)


def test_ptm_reproduces_its_span():
    rng = np.random.default_rng(1)
    d = _directions()
    coef = rng.normal(size=(6, H, W, 3))
    imgs = np.einsum("kn,nhwc->khwc", _ptm_reference(d), coef).astype(np.float32)
    model = fit_baseline("ptm", imgs, d)
    assert model.n_parameters == 18
    np.testing.assert_allclose(model.coefficients, coef, atol=1e-5)
    new = _directions(7, seed=5)
    ref = np.einsum("kn,nhwc->khwc", _ptm_reference(new), coef)
    np.testing.assert_allclose(model.predict(new), ref, atol=1e-5)


def test_hsh_is_orthonormal_on_the_hemisphere():
    # midpoint quadrature in (cos theta, phi): d omega = d(cos theta) d phi
    n = 400
    x = (np.arange(n) + 0.5) / n
    phi = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    xx, pp = np.meshgrid(x, phi, indexing="ij")
    s = np.sqrt(1 - xx ** 2)
    d = np.stack([s * np.cos(pp), s * np.sin(pp), xx], axis=-1).reshape(-1, 3)
    b = basis("hsh", d)
    gram = b.T @ b * (1.0 / n) * (2 * np.pi / (2 * n))
    np.testing.assert_allclose(gram, np.eye(9), atol=2e-3)


def test_hsh_reproduces_its_span_and_horizon():
    rng = np.random.default_rng(2)
    d = _directions()
    coef = rng.normal(size=(9, H, W, 3))
    imgs = np.einsum("kn,nhwc->khwc", basis("hsh", d), coef).astype(np.float32)
    model = fit_baseline("hsh", imgs, d)
    assert model.n_parameters == 27
    np.testing.assert_allclose(model.coefficients, coef, atol=1e-5)
    # a light a little below the horizon is evaluated on it (documented)
    below = np.array([[0.6, 0.8, -0.001]])
    on = np.array([[0.6, 0.8, 0.0]])
    np.testing.assert_allclose(basis("hsh", below), basis("hsh", on), atol=1e-12)


def test_lambertian_recovers_normals():
    rng = np.random.default_rng(3)
    d = _directions()
    theta = np.radians(rng.uniform(0, 60, (H, W)))
    phi = rng.uniform(0, 2 * np.pi, (H, W))
    normals = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi),
                        np.cos(theta)], axis=-1)
    albedo = rng.uniform(0.1, 0.9, (H, W, 3))
    shading = np.einsum("kj,hwj->khw", d, normals)  # unclamped, negative where back-lit
    assert (shading < 0).any()
    imgs = (shading[..., None] * albedo[None]).astype(np.float32)
    model = fit_baseline("lambertian", imgs, d)
    n = model.normals.astype(np.float64)
    angle = np.arctan2(np.linalg.norm(np.cross(n, normals), axis=-1),
                       np.sum(n * normals, axis=-1))
    assert np.degrees(angle).max() < 0.01
    np.testing.assert_allclose(model.albedo, albedo, rtol=1e-5)
    new = _directions(5, seed=9)
    ref = np.einsum("kj,hwj->khw", new, normals)[..., None] * albedo[None]
    np.testing.assert_allclose(model.predict(new), ref, atol=1e-5)
    clamped = fit_baseline("lambertian_clamped", imgs, d)
    np.testing.assert_allclose(clamped.predict(new), np.maximum(ref, 0), atol=1e-5)


def test_light_mask_leaves_out_observations():
    rng = np.random.default_rng(4)
    d = _directions()
    coef = rng.normal(size=(6, H, W, 3))
    imgs = np.einsum("kn,nhwc->khwc", _ptm_reference(d), coef).astype(np.float32)
    keep = rng.uniform(size=(K, H, W)) > 0.3
    keep[:8] = True  # at least 8 lights at every pixel
    corrupted = imgs.copy()
    corrupted[~keep] = 1e3  # "saturated" observations: must not matter
    model = fit_baseline("ptm", corrupted, d, light_mask=keep)
    np.testing.assert_allclose(model.coefficients, coef, atol=1e-4)
    few = np.zeros((K, H, W), dtype=bool)
    few[:6] = True
    few[:, 3, 2] = False
    few[:4, 3, 2] = True
    with pytest.raises(ValueError, match=r"leaves 4 lights at pixel \(x=2, y=3\) \(1 pixels"):
        fit_baseline("ptm", imgs, d, light_mask=few)
    with pytest.raises(ValueError, match="light_mask of shape"):
        fit_baseline("ptm", imgs, d, light_mask=keep[:, :5])


def test_baseline_input_errors():
    d = _directions()
    imgs = _images(d)
    with pytest.raises(ValueError, match="baseline 'rbf' is not known"):
        fit_baseline("rbf", imgs, d)
    with pytest.raises(ValueError, match="29 images for 30 light directions"):
        fit_baseline("ptm", imgs[1:], d)
    with pytest.raises(ValueError, match="5 lights are too few"):
        fit_baseline("hsh", imgs[:5], d[:5])
    flat = d.copy()
    flat[:, 0] = 0.0  # all lights in the y-z plane: lu never varies
    with pytest.raises(ValueError, match="determine only .* of the 6 functions"):
        fit_baseline("ptm", imgs, flat)
    d0 = d.copy()
    d0[3] = 0
    with pytest.raises(ValueError, match=r"directions\[3\]"):
        fit_baseline("ptm", imgs, d0)


def test_protocols_pick_the_documented_lights():
    d = _directions()
    assert held_out("interpolation", d).tolist() == [4, 9, 14, 19, 24, 29]
    assert held_out("interpolation", d, phase=2).tolist() == [2, 7, 12, 17, 22, 27]
    lz = np.linspace(0.9, 0.1, K)  # decreasing elevation along the .lp order
    lz[[3, 11]] = 0.05  # the two lowest
    lz[20] = lz[27]  # ties with the 5th lowest (27): the earlier line (20) is held out
    dd = np.stack([np.sqrt(1 - lz ** 2), np.zeros(K), lz], axis=1)
    assert held_out("grazing", dd).tolist() == [3, 11, 20, 28, 29]
    assert len(held_out("grazing", _directions(31))) == 6  # ceil(31 / 6)
    with pytest.raises(ValueError, match="protocol 'random' is not known"):
        held_out("random", d)
    with pytest.raises(ValueError, match="phase = 5"):
        held_out("interpolation", d, phase=5)


def test_compare_scores_and_plugs_in_models(tmp_path):
    rng = np.random.default_rng(6)
    d = _directions()
    coef = rng.normal(0.4, 0.1, size=(6, H, W, 3))
    imgs = np.einsum("kn,nhwc->khwc", _ptm_reference(d), coef).astype(np.float32)
    mask = np.zeros((H, W), dtype=bool)
    mask[:, :16] = True
    # values above 1: an EXR capture (an integer format would record at most 1)
    cap = Capture(imgs, d, [f"{i}.exr" for i in range(K)], "linear", "exr", 32, mask)

    class Offset:  # a plug-in model: truth + 1/255 everywhere -> RMSE exactly 1 level
        n_parameters = 1

        def __init__(self, images, directions, mask):
            self.mask = mask

        def predict(self, directions):
            return np.einsum("kn,nhwc->khwc", _ptm_reference(directions), coef) + 1 / 255

    comp = compare(cap, {"ptm": baseline_fitter("ptm"), "offset": Offset,
                         "lambertian": baseline_fitter("lambertian")})
    by = {(r.protocol, r.model): r for r in comp.rows}
    for protocol in ("interpolation", "grazing"):
        assert by[(protocol, "ptm")].rmse_8bit < 1e-3
        assert by[(protocol, "offset")].rmse_8bit == pytest.approx(1.0, rel=1e-5)
        assert by[(protocol, "lambertian")].rmse_8bit > 1.0
    assert by[("grazing", "ptm")].held_out == held_out("grazing", d).tolist()
    assert comp.capture["pixels_scored"] == 16 * H
    assert np.isnan(comp.error_maps[("grazing", "ptm")][:, 16:]).all()
    md = write_comparison(comp, tmp_path)
    doc = json.loads((tmp_path / "compare.json").read_text())
    assert len(doc["rows"]) == 6 and "| offset | 1 | 1.00 |" in md.read_text()
    assert (tmp_path / "error_grazing_lambertian.png").is_file()


def test_compare_srgb_scale():
    d = _directions()
    imgs = _images(d)
    cap = Capture(imgs, d, [f"{i}.png" for i in range(K)], "srgb", "png", 8)

    def fit(images, directions, mask):
        class Scaled:
            def predict(self, dirs):
                return imgs[held_out("grazing", d)] * 1.1
        return Scaled()

    row = compare(cap, {"scaled": fit}, protocols=("grazing",)).rows[0]
    truth = imgs[held_out("grazing", d)].astype(np.float64)
    ref = 255 * np.sqrt(np.mean((_srgb_encode(1.1 * truth) - _srgb_encode(truth)) ** 2))
    assert row.rmse_8bit == pytest.approx(ref, rel=1e-5)
    assert row.rmse_linear_8bit == pytest.approx(255 * np.sqrt(np.mean((0.1 * truth) ** 2)),
                                                 rel=1e-5)


@pytest.mark.parametrize("file_format", ["png", "jpeg", "exr"])
def test_compare_scores_what_the_file_records(file_format):
    """A prediction above the full scale is scored as the full scale in an integer format (a
    camera records no more), as predicted in EXR."""
    d = _directions()
    imgs = np.full((K, H, W, 3), 0.5, dtype=np.float32)
    cap = Capture(imgs, d, [f"{i}.{file_format}" for i in range(K)], "linear", file_format,
                  8 if file_format != "exr" else 32)

    def fit(images, directions, mask):
        class Spike:  # the truth, and 40x the full scale at one pixel
            def predict(self, dirs):
                out = np.full((len(dirs), H, W, 3), 0.5)
                out[:, 0, 0] = 40.0
                return out
        return Spike()

    row = compare(cap, {"spike": fit}, protocols=("grazing",)).rows[0]
    top = 1.0 if file_format != "exr" else 40.0
    assert row.rmse_8bit == pytest.approx(255 * (top - 0.5) / np.sqrt(H * W), rel=1e-6)


def test_cli_compare_maps(tmp_path, capsys):
    _, _, lp = _write_capture(tmp_path / "cap", "png", 16, "srgb")
    out = tmp_path / "out"
    assert main(["compare-maps", str(lp), "--out", str(out), "--models", "ptm,hsh"]) == 0
    doc = json.loads((out / "compare.json").read_text())
    assert {r["model"] for r in doc["rows"]} == {"ptm", "hsh"}
    assert doc["capture"]["bit_depth"] == 16 and (out / "compare.md").is_file()
    assert main(["compare-maps", str(lp), "--out", str(out), "--models", "rbf"]) == 2
    assert "unknown ['rbf']; valid models are ptm, hsh, lambertian, lambertian_clamped, powder" \
        in capsys.readouterr().err
