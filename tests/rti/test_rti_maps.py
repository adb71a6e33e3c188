"""fit-maps results on disk: EXR maps, fit.json and scene.xml; the scene renders (with the
``mitsuba`` executable and ``mitsuba-powder render``) exactly what relight predicts; the CLI
runs fit-maps, relight and compare-maps with the powder model on a SYNTHETIC capture."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from mitsuba_powder.cli import main
from mitsuba_powder.rendering.render import render_scene
from mitsuba_powder.rti import (
    Capture,
    MapsResult,
    load_capture,
    synthetic_capture,
    synthetic_maps,
    write_images,
    write_lp,
)
from mitsuba_powder.rti.maps import read_maps, write_maps
from mitsuba_powder.variants import use_variant


def known_maps(h: int = 18, w: int = 24) -> MapsResult:
    """A MapsResult of the SYNTHETIC maps (no fit): four regions and a relief."""
    maps, _ = synthetic_maps(h, w, relief=0.3, seed=2)
    props = {k: np.asarray(v, np.float32) for k, v in maps.items()
             if k not in ("normal", "albedo")}
    return MapsResult(normals=maps["normal"].astype(np.float32),
                      albedo=maps["albedo"].astype(np.float32), maps=props, settings={},
                      residual_rms=np.zeros((h, w), np.float32), gains=np.ones(4),
                      used=np.ones((4, h, w), bool), free=["albedo"] + sorted(props),
                      mask=np.ones((h, w), bool))


LIGHT = np.array([0.45, -0.3, 0.84]) / np.linalg.norm([0.45, -0.3, 0.84])


def read_exr(path: Path) -> np.ndarray:
    with use_variant("scalar_rgb"):
        return np.array(mi.Bitmap(str(path)), dtype=np.float64)[..., :3]


def test_maps_round_trip_and_scene_equals_relight(tmp_path):
    result = known_maps()
    write_maps(result, tmp_path)
    for name in ["albedo", "normal", "residual", "mask", *result.maps]:
        assert (tmp_path / f"{name}.exr").is_file(), name
    back, info = read_maps(tmp_path)
    assert info["parameters_per_pixel"] == result.n_parameters
    expected = result.predict(LIGHT[None])[0]
    np.testing.assert_allclose(back.predict(LIGHT[None])[0], expected, rtol=1e-6, atol=1e-9)
    defines = {"lx": repr(LIGHT[0]), "ly": repr(LIGHT[1]), "lz": repr(LIGHT[2])}
    render_scene(tmp_path / "scene.xml", tmp_path / "relit.exr", variant="llvm_ad_rgb", spp=2,
                 defines=defines)
    img = read_exr(tmp_path / "relit.exr")
    assert img.shape == expected.shape
    np.testing.assert_allclose(img, expected, rtol=1e-5, atol=1e-7)


def test_scene_renders_with_the_mitsuba_executable(tmp_path):
    # the executable the mitsuba wheel installed beside this interpreter (a virtual
    # environment's bin, on PATH or not), else one on PATH
    here = f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}"
    exe = shutil.which("mitsuba", path=here)
    if exe is None:
        assert os.environ.get("CI") != "true", "the mitsuba wheel's executable is missing"
        pytest.skip("no mitsuba executable beside the interpreter or on PATH")
    import mitsuba_powder

    result = known_maps(8, 10)
    write_maps(result, tmp_path)
    cmd = [exe, "-m", "scalar_rgb", "-a", str(mitsuba_powder.plugin_dir()),
           str(tmp_path / "scene.xml"), "-o", str(tmp_path / "exe.exr"),
           "-D", f"lx={LIGHT[0]!r}", "-D", f"ly={LIGHT[1]!r}", "-D", f"lz={LIGHT[2]!r}"]
    proc = subprocess.run(cmd, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    # the executable writes half-float EXR (11-bit mantissa): 1e-3
    np.testing.assert_allclose(read_exr(tmp_path / "exe.exr"), result.predict(LIGHT[None])[0],
                               rtol=1e-3, atol=1e-6)


def test_read_maps_errors(tmp_path):
    with pytest.raises(FileNotFoundError, match="fit.json"):
        read_maps(tmp_path)
    (tmp_path / "fit.json").write_text(json.dumps({"kind": "something else"}))
    with pytest.raises(ValueError, match="not a fit-maps result"):
        read_maps(tmp_path)


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    """A SYNTHETIC capture on disk: 16 x 16 px, 24 lights, 16-bit PNG, linear encoding."""
    folder = tmp_path_factory.mktemp("capture")
    cap = synthetic_capture(16, 16, lights=24, noise=0.005, seed=3)
    names = [f"light{k:02d}.png" for k in range(len(cap["directions"]))]
    write_lp(folder / "capture.lp", names, cap["directions"])
    like = Capture(images=cap["images"], directions=cap["directions"], names=names,
                   encoding="linear", file_format="png", bit_depth=16)
    write_images(like, cap["images"], names, folder)
    (folder / "README.txt").write_text("SYNTHETIC capture rendered by mitsuba-powder\n")
    return folder


def test_cli_fit_maps_then_relight(capture_dir, tmp_path, capsys):
    out = tmp_path / "maps"
    assert main(["fit-maps", str(capture_dir / "capture.lp"), "--out", str(out),
                 "--encoding", "linear", "--rounds", "1", "--iterations", "15"]) == 0
    text = capsys.readouterr().out
    assert "free per pixel: normal + albedo" in text
    info = json.loads((out / "fit.json").read_text())
    assert info["capture"] == {"encoding": "linear", "bit_depth": 16, "file_format": "png",
                               "lp": str(capture_dir / "capture.lp")}
    assert len(info["gains"]) == 24 and info["lights"][0] == "light00.png"
    assert info["fit"]["full_scale"] == 1.0   # PNG: held-out predictions scored as recorded
    assert (out / "scene.xml").is_file() and (out / "normal.exr").is_file()
    # relight under the capture's own lights: same names, format and bit depth, and close
    # to the (noisy) capture
    relit = tmp_path / "relit"
    assert main(["relight", str(out), "--lp", str(capture_dir / "capture.lp"),
                 "--out", str(relit)]) == 0
    written = load_capture(relit / "capture.lp", encoding="linear")
    original = load_capture(capture_dir / "capture.lp", encoding="linear")
    assert written.names == original.names and written.bit_depth == 16
    rms = float(np.sqrt(np.mean((written.images - original.images) ** 2)))
    assert rms < 0.02, rms


def test_cli_compare_maps_with_the_powder_model(capture_dir, tmp_path, monkeypatch):
    from mitsuba_powder.rti import relief_rows

    scales = []
    fit = relief_rows.run_fit

    def recording(images, directions, options, *args, **kwargs):
        scales.append(options.full_scale)
        return fit(images, directions, options, *args, **kwargs)

    monkeypatch.setattr(relief_rows, "run_fit", recording)
    out = tmp_path / "compare"
    assert main(["compare-maps", str(capture_dir / "capture.lp"), "--out", str(out),
                 "--encoding", "linear", "--models", "lambertian,powder",
                 "--no-error-images"]) == 0
    data = json.loads((out / "compare.json").read_text())
    text = json.dumps(data)
    assert "powder" in text and "lambertian" in text
    # the powder rows' cross-validations score as the PNG files record (as the table does)
    assert scales and all(s == 1.0 for s in scales), scales


def test_cli_fit_maps_errors(tmp_path, capsys):
    assert main(["fit-maps", str(tmp_path / "missing.lp"), "--out", str(tmp_path / "o")]) == 2
    assert "missing.lp" in capsys.readouterr().err
    assert main(["relight", str(tmp_path), "--lp", str(tmp_path / "x.lp"), "--out",
                 str(tmp_path / "r")]) == 2
    assert "fit.json" in capsys.readouterr().err


def test_python_m_entry_point_lists_the_new_commands():
    proc = subprocess.run([sys.executable, "-m", "mitsuba_powder.cli", "--help"],
                          capture_output=True, text=True, timeout=120)
    assert "fit-maps" in proc.stdout and "relight" in proc.stdout


def test_scene_with_a_radius_map_equals_relight(tmp_path):
    """Per-pixel grain radius: the scene gives the plugin a radius texture (its own albedo
    table), relight the fit's (GrainAlbedo): equal to the tables' accuracy."""
    result = known_maps(12, 16)
    region = (np.arange(12)[:, None] >= 6) * 2 + (np.arange(16)[None, :] >= 8)
    result.maps["radius"] = np.array([0.04, 0.07, 0.2, 0.6], np.float32)[region]
    result.settings["material"] = "hematite"
    write_maps(result, tmp_path)
    text = (tmp_path / "scene.xml").read_text()
    assert 'name="radius"' in text and 'name="albedo"' not in text
    expected = result.predict(LIGHT[None])[0]
    render_scene(tmp_path / "scene.xml", tmp_path / "relit.exr", variant="llvm_ad_rgb", spp=2,
                 defines={"lx": repr(LIGHT[0]), "ly": repr(LIGHT[1]), "lz": repr(LIGHT[2])})
    np.testing.assert_allclose(read_exr(tmp_path / "relit.exr"), expected, rtol=1e-3, atol=1e-6)


def test_near_field_scene_equals_relight(tmp_path):
    """A fit with lights at r = 3 image widths: scene.xml's point light at r l (scene units)
    renders what relight predicts at every pixel (the light turns and fades across the image);
    the tolerance covers the light's turn within a pixel, which the render averages over 256
    samples (0.23 % at most here) where relight takes the pixel's centre."""
    import dataclasses

    r = 3.0
    result = dataclasses.replace(known_maps(), light_distance=r)
    write_maps(result, tmp_path)
    h, w = result.mask.shape
    scene_width = 2.0 * w / h  # the rectangle's width in scene units
    p = r * scene_width * LIGHT
    defines = {"px": repr(p[0]), "py": repr(p[1]), "pz": repr(p[2]),
               "intensity": repr((r * scene_width) ** 2)}
    render_scene(tmp_path / "scene.xml", tmp_path / "relit.exr", variant="llvm_ad_rgb", spp=256,
                 defines=defines)
    img = read_exr(tmp_path / "relit.exr")
    expected = result.predict(LIGHT[None])[0]
    distant = dataclasses.replace(result, light_distance=np.inf).predict(LIGHT[None])[0]
    assert np.max(np.abs(expected / distant - 1.0)) > 0.05  # the near field matters here
    np.testing.assert_allclose(img, expected, rtol=5e-3, atol=1e-6)
