"""Every file error names the file (issue 33, case 6): a binary CSV or JSON, a broken
fit.json, a corrupt PNG among a capture's images or as its mask, a truncated EXR map, a black
render, an .lp direction too large to square. The captures are SYNTHETIC."""

from __future__ import annotations

import json
import math
from pathlib import Path

import numpy as np
import pytest

from helpers import known_maps_folder, png_capture
from mitsuba_powder.cli import main
from mitsuba_powder.readers import FileFormatError, read_bitmap, read_json, read_text
from mitsuba_powder.rendering import photo
from mitsuba_powder.rti.capture import read_lp
from mitsuba_powder.variants import use_variant

#: The first bytes of a UTF-16 file with a byte-order mark: not UTF-8
BINARY = b"\xff\xfe\x00\x01\xefbinary\x00"


def error_line(capsys) -> str:
    """stderr of a command that must have failed cleanly: one line, no traceback."""
    err = capsys.readouterr().err
    assert err.startswith("mitsuba-powder: error: ") and "Traceback" not in err, err
    assert err.count("\n") == 1, err
    return err


def test_readers_name_the_file(tmp_path):
    (tmp_path / "b.csv").write_bytes(BINARY)
    with pytest.raises(FileFormatError, match=r"data .*b\.csv: not a UTF-8 text file \(byte"):
        read_text(tmp_path / "b.csv", "data")
    (tmp_path / "j.json").write_text('{"a": 1,}')
    with pytest.raises(FileFormatError, match=r"j\.json: not valid JSON \(line 1, column 9"):
        read_json(tmp_path / "j.json")
    (tmp_path / "i.png").write_bytes(b"\x89PNG\r\n\x1a\nnot a png")
    use_variant("scalar_rgb")
    with pytest.raises(FileFormatError, match=r"image .*i\.png: cannot be read as an image"):
        read_bitmap(tmp_path / "i.png")
    assert read_text(tmp_path / "j.json") == '{"a": 1,}'


def test_a_binary_csv_is_named(tmp_path, capsys):
    data = tmp_path / "data.csv"
    data.write_bytes(BINARY)
    assert main(["fit", str(data), "--out", str(tmp_path / "fit")]) == 2
    assert f"measurement file {data}: not a UTF-8 text file" in error_line(capsys)


def test_a_binary_json_given_as_params_is_named(tmp_path, capsys):
    params = tmp_path / "p.json"
    params.write_bytes(BINARY)
    scene = Path(__file__).resolve().parents[2] / "scenes" / "powder_patch.xml"
    assert main(["render", str(scene), "-o", str(tmp_path / "o.exr"), "--params",
                 str(params)]) == 2
    assert f"parameter file {params}: not a UTF-8 text file" in error_line(capsys)


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    """A SYNTHETIC 8 x 8 px capture under 12 lights, 8-bit PNG."""
    return png_capture(tmp_path_factory, seed=6)


def _copy(src: Path, dst: Path) -> Path:
    dst.mkdir()
    for p in src.iterdir():
        (dst / p.name).write_bytes(p.read_bytes())
    return dst


def test_a_corrupt_image_among_a_captures_is_named(tmp_path, capture, capsys):
    work = _copy(capture, tmp_path / "cap")
    (work / "light05.png").write_bytes(b"\x89PNG\r\n\x1a\ntruncated")
    assert main(["fit-maps", str(work / "dirs.lp"), "--out", str(tmp_path / "m")]) == 2
    assert f"image {work / 'light05.png'}: cannot be read as an image" in error_line(capsys)


def test_a_corrupt_mask_is_named(tmp_path, capture, capsys):
    mask = tmp_path / "mask.png"
    mask.write_bytes(b"not an image at all")
    assert main(["fit-maps", str(capture / "dirs.lp"), "--mask", str(mask), "--out",
                 str(tmp_path / "m")]) == 2
    assert f"{mask}: cannot be read as an image" in error_line(capsys)


@pytest.fixture
def maps(tmp_path) -> Path:
    """A maps folder of known SYNTHETIC maps (no fit), for the 12 lights of ``capture``."""
    return known_maps_folder(tmp_path / "maps")


def test_a_broken_fit_json_given_to_relight_is_named(tmp_path, maps, capture, capsys):
    (maps / "fit.json").write_text((maps / "fit.json").read_text()[:-40])
    assert main(["relight", str(maps), "--lp", str(capture / "dirs.lp"), "--out",
                 str(tmp_path / "r")]) == 2
    assert f"maps description {maps / 'fit.json'}: not valid JSON (line" in error_line(capsys)


def test_a_truncated_exr_map_is_named(tmp_path, maps, capture, capsys):
    exr = maps / "albedo.exr"
    exr.write_bytes(exr.read_bytes()[:60])
    assert main(["relight", str(maps), "--lp", str(capture / "dirs.lp"), "--out",
                 str(tmp_path / "r")]) == 2
    assert f"map {exr}: cannot be read as an image" in error_line(capsys)


def test_a_black_render_is_named_as_the_render():
    """compare-photo with a black render: the render has no signal (it used to blame the
    photo)."""
    lit = np.full((8, 8, 3), 0.5)
    with pytest.raises(ValueError, match="the render has no signal .*is the scene lit"):
        photo.compare_images(np.zeros_like(lit), lit)
    with pytest.raises(ValueError, match="the photo has no signal"):
        photo.compare_images(lit, np.zeros_like(lit))
    red = lit * np.array([1.0, 0.0, 0.0])
    with pytest.raises(ValueError, match="the render has no signal .channel G, B is 0"):
        photo.compare_images(red, lit)


def test_an_lp_direction_too_large_to_square_is_normalised(tmp_path):
    """(1e300, 0, 1e300) is a direction 45 degrees up (it used to be called the zero
    vector: its squares overflow)."""
    lp = tmp_path / "big.lp"
    lp.write_text("2\na.png 1e300 0 1e300\nb.png 0 0 1\n")
    _, directions = read_lp(lp)
    np.testing.assert_allclose(directions[0], [math.sqrt(0.5), 0.0, math.sqrt(0.5)])
    assert json.dumps(directions.tolist())  # finite
