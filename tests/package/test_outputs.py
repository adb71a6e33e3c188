"""Outputs never touch inputs: every command that writes writes only under the output it was
given, never over one of its input files, whatever names the files it reads contain (absolute
names and ``..`` in an ``.lp`` file, ``--out`` equal to the capture's or the data's folder).

Each test records the bytes of every file outside the output before the command and checks
them after it; the data are SYNTHETIC (rendered or simulated by the package)."""

from __future__ import annotations

import hashlib
import json
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from helpers import known_maps_folder, png_capture
from mitsuba_powder.cli import main
from mitsuba_powder.outputs import (
    MANIFEST,
    OutputError,
    guarding_inputs,
    note_input,
    output_file,
    output_names,
    output_path,
    write_json,
    write_whole,
)
from mitsuba_powder.variants import use_variant


def snapshot(root: Path) -> dict[str, str]:
    """sha256 of every file below ``root`` (relative path -> digest)."""
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


def unchanged_outside(before: dict[str, str], after: dict[str, str], out: str) -> None:
    """Every file of ``before`` is byte-identical in ``after``; new files lie under ``out``."""
    for name, digest in before.items():
        assert after.get(name) == digest, f"{name} was changed or removed"
    new = sorted(set(after) - set(before))
    assert all(n == out or n.startswith(out + "/") for n in new), new


def _copy(src: Path, dst: Path) -> Path:
    """A copy of the files of ``src`` in a new folder ``dst``."""
    dst.mkdir(parents=True)
    for p in src.iterdir():
        (dst / p.name).write_bytes(p.read_bytes())
    return dst


# ------------------------------------------------------------------ the helpers


def test_output_names_reduce_absolute_and_dotdot():
    names = ["/data/cap/img_00.png", "../outside.png", "sub/img_02.png", "C:\\dome\\img_03.png",
             "img_04.png"]
    where = [f"dirs.lp, line {k + 2}" for k in range(len(names))]
    assert output_names(names, where) == ["img_00.png", "outside.png", "sub/img_02.png",
                                          "img_03.png", "img_04.png"]


def test_output_names_collision_names_both_lines():
    with pytest.raises(OutputError, match=r"dirs.lp, line 3.*dirs.lp, line 2"):
        output_names(["/a/img.png", "/b/img.png"], ["dirs.lp, line 2", "dirs.lp, line 3"])


def test_output_path_refuses_escapes_and_inputs(tmp_path):
    for bad in ("/etc/x.png", "../x.png", "a/../../x.png", ""):
        with pytest.raises(OutputError, match="relative file name"):
            output_path(tmp_path, bad)
    data = tmp_path / "data.csv"
    data.write_text("1\n")
    with guarding_inputs():
        note_input(data)
        with pytest.raises(OutputError, match="is an input file"):
            output_path(tmp_path, "data.csv")
        with pytest.raises(OutputError, match="is an input file"):
            output_file(tmp_path / "sub" / ".." / "data.csv")
        link = tmp_path / "link.csv"
        link.symlink_to(data)
        with pytest.raises(OutputError, match="is an input file"):
            output_file(link)
    assert data.read_text() == "1\n"
    # outside a guard nothing is protected (the Python API's own writers)
    assert output_file(data) == data


def test_write_json_is_whole_or_nothing(tmp_path, monkeypatch):
    """A NaN, an input named as the output or a failed rename leave the previous file as it
    was, and no temporary file beside it."""
    import os

    out = tmp_path / "r.json"
    out.write_text("previous\n")
    with pytest.raises(OutputError, match=r"r.json would hold NaN or Infinity at a\[1\]"):
        write_json(out, {"a": [1.0, float("nan")]}, "--json")
    data = tmp_path / "data.csv"
    data.write_text("1\n")
    with guarding_inputs(data):
        with pytest.raises(OutputError, match="--json .*data.csv is an input file"):
            write_whole(data, "x", "--json")

    def full(*args, **kwargs):
        raise OSError(28, "No space left on device")

    with monkeypatch.context() as m:
        m.setattr(os, "replace", full)
        with pytest.raises(OSError, match="No space"):
            write_json(out, {"a": 1.0})
    assert out.read_text() == "previous\n" and data.read_text() == "1\n"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["data.csv", "r.json"]
    assert write_json(out, {"a": [1.5]}) == out and out.read_text() == '{\n "a": [\n  1.5\n ]\n}\n'


# ------------------------------------------------------------------ RTI commands


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    """A SYNTHETIC capture: 8 x 8 px, 12 lights, 8-bit PNG (sRGB), a mask image."""
    folder = png_capture(tmp_path_factory, seed=4)
    mask = np.ones((8, 8, 1), np.uint8) * 255
    with use_variant("scalar_rgb"):
        mi.Bitmap(mask, mi.Bitmap.PixelFormat.Y).write(str(folder / "mask.png"))
    return folder


@pytest.fixture(scope="module")
def maps(tmp_path_factory) -> Path:
    """A maps folder of known SYNTHETIC maps (no fit)."""
    return known_maps_folder(tmp_path_factory.mktemp("maps"))


def _absolute_lp(capture: Path, path: Path, extra: str | None = None) -> None:
    """An .lp naming the capture's photographs by absolute path (as dome software does)."""
    lines = (capture / "dirs.lp").read_text().splitlines()
    out = [lines[0]] + [f"{capture / ln.split()[0]} {' '.join(ln.split()[1:])}"
                        for ln in lines[1:]]
    if extra is not None:
        out[0] = str(len(out))
        out.append(extra)
    path.write_text("\n".join(out) + "\n")


def test_relight_with_absolute_names_writes_only_under_out(tmp_path, capture, maps):
    root = tmp_path
    lights = root / "lights" / "dirs_abs.lp"
    lights.parent.mkdir()
    # 13 lights: the capture's 12 by absolute path, and one named '../outside.png'
    _absolute_lp(capture, lights, extra="../outside.png 0.1 0.2 0.9")
    before = {**{f"capture/{k}": v for k, v in snapshot(capture).items()},
              **{f"maps/{k}": v for k, v in snapshot(maps).items()},
              **{f"root/{k}": v for k, v in snapshot(root).items()}}
    out = root / "relit"
    assert main(["relight", str(maps), "--lp", str(lights), "--out", str(out)]) == 0
    after = {**{f"capture/{k}": v for k, v in snapshot(capture).items()},
             **{f"maps/{k}": v for k, v in snapshot(maps).items()},
             **{f"root/{k}": v for k, v in snapshot(root).items()}}
    unchanged_outside(before, after, "root/relit")
    manifest = MANIFEST.format(command="relight")
    written = sorted(p.name for p in out.iterdir() if p.name != manifest)
    assert written == sorted([f"light{k:02d}.png" for k in range(12)]
                             + ["outside.png", "dirs_abs.lp"])
    assert json.loads((out / manifest).read_text()) == written  # what the run wrote, whole
    assert not (root / "outside.png").exists() and not (root / "lights" / "..").joinpath(
        "outside.png").exists()
    # the .lp beside the images names what was written: the output is itself a capture
    copied = (out / "dirs_abs.lp").read_text().split()
    assert "light00.png" in copied and str(capture) not in " ".join(copied)


def test_relight_refuses_two_lights_of_one_base_name(tmp_path, maps, capsys):
    lp = tmp_path / "dup.lp"
    lp.write_text("2\n/a/img.png 0 0 1\n/b/img.png 0.1 0 1\n")
    assert main(["relight", str(maps), "--lp", str(lp), "--out", str(tmp_path / "o")]) == 2
    err = capsys.readouterr().err
    assert "line 2" in err and "line 3" in err and "img.png" in err
    assert not (tmp_path / "o").exists()


def test_relight_into_the_capture_folder_refuses_to_overwrite_photos(capture, maps, capsys):
    before = snapshot(capture)
    assert main(["relight", str(maps), "--lp", str(capture / "dirs.lp"), "--out",
                 str(capture)]) == 2
    assert "is an input file" in capsys.readouterr().err
    assert snapshot(capture) == before


def test_relight_into_the_maps_folder_refuses(tmp_path, maps, capsys):
    lp = tmp_path / "l.lp"
    lp.write_text("1\nnormal.exr 0 0 1\n")
    before = snapshot(maps)
    assert main(["relight", str(maps), "--lp", str(lp), "--out", str(maps)]) == 2
    assert "is an input file" in capsys.readouterr().err
    assert snapshot(maps) == before


def test_fit_maps_and_compare_maps_with_out_equal_to_the_capture(tmp_path, capture, capsys):
    work = _copy(capture, tmp_path / "cap")
    before = snapshot(work)
    args = ["--rounds", "1", "--iterations", "4"]
    assert main(["fit-maps", str(work / "dirs.lp"), "--out", str(work), *args]) == 0
    after = snapshot(work)
    assert all(after[k] == v for k, v in before.items()), "the capture was changed"
    assert "fit.json" in after and "normal.exr" in after
    before = after
    assert main(["compare-maps", str(work / "dirs.lp"), "--out", str(work), "--models",
                 "lambertian"]) == 0
    after = snapshot(work)
    assert all(after[k] == v for k, v in before.items() if not k.startswith("compare"))
    assert "compare.json" in after


@pytest.mark.parametrize("tiles", [[], ["--tile-size", "8", "--workers", "1"]],
                         ids=["untiled", "tiled"])
def test_fit_maps_refuses_to_write_over_its_mask(tmp_path, capture, capsys, tiles):
    """The user's mask is named as a map fit-maps writes, in the output folder: refused
    before anything is written (tiled: before a cluster starts or a tile is fitted)."""
    work = _copy(capture, tmp_path / "cap")
    with use_variant("scalar_rgb"):
        mi.Bitmap(np.ones((8, 8, 1), np.float32), mi.Bitmap.PixelFormat.Y).write(
            str(work / "mask.exr"))
    before = snapshot(work)
    assert main(["fit-maps", str(work / "dirs.lp"), "--out", str(work), "--mask",
                 str(work / "mask.exr"), "--rounds", "1", "--iterations", "4", *tiles]) == 2
    err = capsys.readouterr().err
    assert "mask.exr" in err and "is an input file" in err
    assert snapshot(work) == before


def test_tiled_fit_maps_with_out_equal_to_the_capture(tmp_path, capture):
    work = _copy(capture, tmp_path / "cap")
    before = snapshot(work)
    args = ["--rounds", "1", "--iterations", "4", "--tile-size", "8", "--workers", "1"]
    assert main(["fit-maps", str(work / "dirs.lp"), "--out", str(work), *args]) == 0
    after = snapshot(work)
    assert all(after[k] == v for k, v in before.items()), "the capture was changed"
    assert "fit.json" in after and "tiles/tile_r0000_c0000.npz" in after
    assert not any(n.endswith(".part") for n in after)  # tiles renamed into place



def test_compare_maps_refuses_an_input_named_as_its_output(tmp_path, capture, capsys):
    work = _copy(capture, tmp_path / "cap")
    # an .lp file named like the comparison's JSON, in the output folder
    (work / "dirs.lp").rename(work / "compare.json")
    before = snapshot(work)
    assert main(["compare-maps", str(work / "compare.json"), "--out", str(work), "--models",
                 "lambertian", "--no-error-images"]) == 2
    assert "is an input file" in capsys.readouterr().err
    assert snapshot(work) == before


# ------------------------------------------------------------------ goniometric commands


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory) -> Path:
    """SYNTHETIC measurements (simulated, 2 % noise) and their parameter file."""
    folder = tmp_path_factory.mktemp("data")
    (folder / "params.json").write_text(json.dumps({"albedo": 0.8, "extinction": 0.5}))
    assert main(["simulate", "--params", str(folder / "params.json"), "--protocol",
                 "backscatter", "--noise", "0.02", "--out", str(folder / "data.csv")]) == 0
    return folder


@pytest.mark.parametrize("command, output, renamed", [
    (["simulate", "--params", "{d}/params.json", "--out", "{d}/params.json"], None, None),
    (["fit", "{d}/fit.json", "--starts", "4", "--out", "{d}"], None, "fit.json"),
    (["compare-models", "{d}/model_comparison.json", "--starts", "4", "--out", "{d}"], None,
     "model_comparison.json"),
    (["render-gonio", "--data", "{d}/gonio.csv", "--spp", "1", "--resolution", "2", "--out",
      "{d}"], None, "gonio.csv"),
    (["albedo", "--reflectance", "{d}/r.csv", "--out", "{d}/r.csv"], "r.csv", None),
])
def test_commands_refuse_to_write_over_their_inputs(tmp_path, data_dir, capsys, command,
                                                    output, renamed):
    work = _copy(data_dir, tmp_path / "d")
    if renamed:  # the data file carries the name of one of the command's outputs
        (work / "data.csv").rename(work / renamed)
    if output == "r.csv":
        (work / "r.csv").write_text("400,0.5\n500,0.6\n600,0.7\n700,0.7\n")
    before = snapshot(work)
    assert main([a.format(d=work) for a in command]) == 2
    assert "is an input file" in capsys.readouterr().err
    assert snapshot(work) == before


def test_fit_and_compare_models_with_out_equal_to_the_data_folder(tmp_path, data_dir):
    work = _copy(data_dir, tmp_path / "d")
    before = snapshot(work)
    assert main(["fit", str(work / "data.csv"), "--starts", "4", "--out", str(work)]) == 0
    after = snapshot(work)
    assert all(after[k] == v for k, v in before.items())
    assert "fit.json" in after


def test_render_refuses_to_write_over_a_texture_of_its_scene(tmp_path, capsys):
    with use_variant("scalar_rgb"):
        mi.Bitmap(np.full((2, 2, 3), 0.5, np.float32)).write(str(tmp_path / "tex.exr"))
    (tmp_path / "scene.xml").write_text("""<scene version="3.0.0">
  <sensor type="orthographic"><film type="hdrfilm"><integer name="width" value="4"/>
    <integer name="height" value="4"/></film><sampler type="independent">
    <integer name="sample_count" value="1"/></sampler></sensor>
  <shape type="rectangle"><bsdf type="powder"><texture type="bitmap" name="albedo">
    <string name="filename" value="tex.exr"/></texture></bsdf></shape>
  <emitter type="constant"/>
  <integrator type="path"/>
</scene>
""")
    before = snapshot(tmp_path)
    assert main(["render", str(tmp_path / "scene.xml"), "-o", str(tmp_path / "tex.exr")]) == 2
    assert "is an input file" in capsys.readouterr().err
    assert snapshot(tmp_path) == before
    assert main(["render", str(tmp_path / "scene.xml"), "-o", str(tmp_path / "img.exr")]) == 0
    after = snapshot(tmp_path)
    assert all(after[k] == v for k, v in before.items()) and "img.exr" in after


def test_compare_photo_refuses_to_write_over_the_photo(tmp_path, capsys):
    from mitsuba_powder.rendering.photo import write_exr

    img = np.full((6, 6, 3), 0.3, np.float32)
    write_exr(tmp_path / "render.exr", img)
    with use_variant("scalar_rgb"):
        bmp = mi.Bitmap(np.full((6, 6, 3), 120, np.uint8), mi.Bitmap.PixelFormat.RGB)
        bmp.write(str(tmp_path / "delta_e.png"))
    before = snapshot(tmp_path)
    assert main(["compare-photo", str(tmp_path / "render.exr"), str(tmp_path / "delta_e.png"),
                 "--out", str(tmp_path)]) == 2
    assert "is an input file" in capsys.readouterr().err
    assert snapshot(tmp_path) == before


def test_relight_into_the_folder_that_holds_the_lights(tmp_path, maps, capsys):
    """Lights in an .lp inside the output folder: the images it names that do not exist yet
    are written there and the .lp is left as it is; once they exist (they could be
    photographs), a second run into the same folder is refused."""
    out = tmp_path / "relit"
    out.mkdir()
    lp = out / "l.lp"
    lp.write_text("2\na.png 0 0 1\nb.png 0.2 0 1\n")
    kept = lp.read_bytes()
    assert main(["relight", str(maps), "--lp", str(lp), "--out", str(out)]) == 0
    assert lp.read_bytes() == kept and (out / "a.png").is_file()
    before = snapshot(out)
    assert main(["relight", str(maps), "--lp", str(lp), "--out", str(out)]) == 2
    assert "is an input file" in capsys.readouterr().err
    assert snapshot(out) == before


def test_an_output_folder_that_is_a_file_is_a_clean_error(tmp_path, maps, capsys):
    (tmp_path / "f").write_text("x")
    lp = tmp_path / "l.lp"
    lp.write_text("1\na.png 0 0 1\n")
    assert main(["relight", str(maps), "--lp", str(lp), "--out", str(tmp_path / "f")]) == 2
    assert "is a file" in capsys.readouterr().err
    assert (tmp_path / "f").read_text() == "x"
