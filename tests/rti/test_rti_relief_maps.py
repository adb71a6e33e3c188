"""fit-maps writes the relief (relief.exr, relief.ply, scene.xml renders the mesh), relight
shades by it and renders it, compare-maps scores the powder rows with and without it."""

import json
from pathlib import Path

import numpy as np
import pytest

from helpers import write_image_capture
from mitsuba_powder.cli import main
from mitsuba_powder.rti import load_capture
from mitsuba_powder.rti.maps import read_maps
from mitsuba_powder.rti.synthetic import synthetic_capture


@pytest.fixture(scope="module")
def capture_dir(tmp_path_factory) -> Path:
    """A SYNTHETIC capture on disk: 16 x 20 px, 24 lights, 16-bit PNG, linear encoding."""
    folder = tmp_path_factory.mktemp("capture")
    cap = synthetic_capture(16, 20, lights=24, noise=0.005, seed=3)
    write_image_capture(folder, cap["images"], cap["directions"], "linear", 16)
    return folder


def read_ply_header(path: Path) -> list[str]:
    data = path.read_bytes()
    return data[:data.index(b"end_header\n")].decode("ascii").splitlines()


def test_fit_maps_writes_the_relief_and_relight_renders_it(capture_dir, tmp_path):
    out = tmp_path / "maps"
    assert main(["fit-maps", str(capture_dir / "dirs.lp"), "--out", str(out),
                 "--encoding", "linear", "--rounds", "1", "--iterations", "15",
                 "--shadows", "relief"]) == 0
    info = json.loads((out / "fit.json").read_text())
    assert info["relief"]["height"] == "relief.exr" and info["fit"]["shadows"] == "relief"
    header = read_ply_header(out / "relief.ply")
    assert "element vertex 396" in header and "element face 714" in header  # (16+2) x (20+2)
    scene = (out / "scene.xml").read_text()
    assert 'type="ply"' in scene and 'type="path"' in scene
    assert 'type="rectangle"' in (out / "scene_flat.xml").read_text()
    result, _ = read_maps(out)
    assert result.relief.height.shape == (16, 20)
    # per-pixel relight (shaded by the relief) and the rendered relief agree where little
    # shades: the capture's bumps are shallow
    relit, rendered = tmp_path / "relit", tmp_path / "rendered"
    lp = capture_dir / "dirs.lp"
    assert main(["relight", str(out), "--lp", str(lp), "--out", str(relit)]) == 0
    assert main(["relight", str(out), "--lp", str(lp), "--out", str(rendered), "--render",
                 "--spp", "16"]) == 0
    a = load_capture(relit / "dirs.lp", encoding="linear").images
    b = load_capture(rendered / "dirs.lp", encoding="linear").images
    assert abs(float(b.mean() / a.mean()) - 1) < 0.02
    original = load_capture(lp, encoding="linear").images
    assert float(np.sqrt(np.mean((a - original) ** 2))) < 0.02


def test_fit_maps_ratio_keeps_the_relief_unused(capture_dir, tmp_path):
    """--shadows ratio writes the relief too; relight shades by it only when asked (relight
    --shadows)."""
    out = tmp_path / "maps"
    assert main(["fit-maps", str(capture_dir / "dirs.lp"), "--out", str(out),
                 "--encoding", "linear", "--rounds", "1", "--iterations", "15",
                 "--shadows", "ratio"]) == 0
    info = json.loads((out / "fit.json").read_text())
    assert info["fit"]["shadows"] == "ratio" and info["relief"]["height"] == "relief.exr"
    assert info["fit"]["shadows_choice"] is None
    assert (out / "relief.ply").exists() and 'type="ply"' in (out / "scene.xml").read_text()
    lp = capture_dir / "dirs.lp"
    relit = {}
    for flag in ("", "--no-shadows", "--shadows"):
        folder = tmp_path / f"relit{flag}"
        assert main(["relight", str(out), "--lp", str(lp), "--out", str(folder)]
                    + ([flag] if flag else [])) == 0
        relit[flag] = load_capture(folder / "dirs.lp", encoding="linear").images
    result, _ = read_maps(out)
    d = load_capture(lp, encoding="linear").directions
    np.testing.assert_array_equal(relit[""], relit["--no-shadows"])
    np.testing.assert_allclose(relit[""], result.predict(d, shadows=False), atol=1e-4)
    np.testing.assert_allclose(relit["--shadows"], result.predict(d, shadows=True), atol=1e-4)


def test_fit_maps_default_chooses_the_shadows(capture_dir, tmp_path, capsys):
    """The default (--shadows auto) records its choice and both cross-validated errors in
    fit.json and says them; relight's default follows the choice."""
    out = tmp_path / "maps"
    assert main(["fit-maps", str(capture_dir / "dirs.lp"), "--out", str(out),
                 "--encoding", "linear", "--rounds", "1", "--iterations", "15"]) == 0
    printed = capsys.readouterr().out
    info = json.loads((out / "fit.json").read_text())
    choice = info["fit"]["shadows_choice"]
    assert choice["option"] == "auto" and choice["chosen"] == info["fit"]["shadows"]
    cv = choice["cv_rms"]
    assert 0 < cv["ratio"] < 0.05 and 0 < cv["relief"] < 0.05
    expected = "relief" if choice["z"] > choice["margin_z"] else "ratio"
    assert choice["chosen"] == expected
    assert f"shadows: {expected} (" in printed and "chosen by cross-validation" in printed
    assert info["relief"]["height"] == "relief.exr"
    lp = capture_dir / "dirs.lp"
    folder = tmp_path / "relit"
    assert main(["relight", str(out), "--lp", str(lp), "--out", str(folder)]) == 0
    result, _ = read_maps(out)
    d = load_capture(lp, encoding="linear").directions
    np.testing.assert_allclose(load_capture(folder / "dirs.lp", encoding="linear").images,
                               result.predict(d, shadows=expected == "relief"), atol=1e-4)


def test_bad_shadow_options_are_named(capture_dir, tmp_path, capsys):
    assert main(["fit-maps", str(capture_dir / "dirs.lp"), "--out", str(tmp_path / "o"),
                 "--shadows", "none"]) == 2
    err = capsys.readouterr().err
    assert "--shadows = 'none'" in err and "('auto', 'relief', 'ratio')" in err
    assert main(["compare-maps", str(capture_dir / "dirs.lp"), "--out", str(tmp_path / "c"),
                 "--models", "powder", "--shadows", "shade"]) == 2
    assert "--shadows = 'shade'" in capsys.readouterr().err
    assert main(["fit-maps", str(capture_dir / "dirs.lp"), "--out", str(tmp_path / "o"),
                 "--light-size", "60"]) == 2
    assert "--light-size = 60" in capsys.readouterr().err


def test_compare_maps_powder_rows(capture_dir, tmp_path):
    out = tmp_path / "compare"
    assert main(["compare-maps", str(capture_dir / "dirs.lp"), "--out", str(out),
                 "--encoding", "linear", "--models",
                 "powder,powder_shadows,powder_rendered", "--spp", "8",
                 "--no-error-images"]) == 0
    rows = json.loads((out / "compare.json").read_text())["rows"]
    got = {(r["model"], r["protocol"]): r["rmse_8bit"] for r in rows}
    assert len(got) == 6 and all(np.isfinite(v) for v in got.values())
    # each powder row says the shadows its fit used (the powder row: the default, auto)
    notes = {(r["model"], r["protocol"]): r["note"] for r in rows}
    assert all(notes[("powder", p)].startswith(("shadows ratio (auto", "shadows relief (auto"))
               for p in ("interpolation", "grazing")), notes
    assert notes[("powder_shadows", "grazing")].startswith("shadows relief")
    assert "- powder: shadows " in (out / "compare.md").read_text()
    # a shallow relief: the rows agree within 15 %
    for protocol in ("interpolation", "grazing"):
        base = got[("powder", protocol)]
        for name in ("powder_shadows", "powder_rendered"):
            assert got[(name, protocol)] < 1.15 * base + 0.5, (name, protocol, got)
