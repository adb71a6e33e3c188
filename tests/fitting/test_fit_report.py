"""Fit reports: the ``figures`` choice of ``write_report`` and ``fit --figures`` (summary, all,
none), valid PNG files, and a summary whose size does not grow with the wavelengths (issue:
fit reports cost 10x the fit)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import pytest

from mitsuba_powder.cli import build_parser, main
from mitsuba_powder.fitting.fit import fit
from mitsuba_powder.fitting.protocols import simulate
from mitsuba_powder.fitting.report import (
    FIGURES,
    SUMMARY_FIGURES,
    SUMMARY_WAVELENGTHS,
    dumps_report,
    report_dict,
    summary_wavelengths,
    write_report,
)
from mitsuba_powder.io.measurements import save_measurements
from mitsuba_powder.outputs import MANIFEST

PNG_SIGNATURE = b"\x89PNG\r\n\x1a\n"


def _fitted(wavelengths) -> object:
    """A quick fit (one free parameter, one start) of noisy synthetic data at the SHADOWS +
    back-scattering geometries: enough for a report, not a test of the fit."""
    data = simulate({"radius": 0.05, "g": 0.2}, "shadows,backscatter",
                    wavelengths=tuple(float(w) for w in wavelengths), noise=0.01, seed=3)
    return fit(data, free=["g"], starts=1, polish=1)


@pytest.fixture(scope="module")
def three() -> object:
    return _fitted((450.0, 600.0, 750.0))


def _per_wavelength(wavelengths) -> set[str]:
    return ({f"principal_plane_{w:g}nm.png" for w in wavelengths}
            | {f"polar_{w:g}nm.png" for w in wavelengths})


def assert_valid_png(path: Path) -> None:
    """``path`` is a PNG that decodes: signature, an IHDR chunk of a plausible size, and
    matplotlib (Pillow) reads it back to an image of that size that is not blank."""
    from matplotlib.image import imread

    raw = path.read_bytes()
    assert raw[:8] == PNG_SIGNATURE, path
    assert raw[12:16] == b"IHDR", path
    width, height = struct.unpack(">II", raw[16:24])
    assert 200 <= width <= 4000 and 200 <= height <= 4000, (path, width, height)
    image = imread(path)
    assert image.shape[:2] == (height, width), path
    assert float(np.ptp(image[..., :3])) > 0.5, f"{path}: blank image"


@pytest.mark.parametrize("figures", ["summary", "all", "none"])
def test_each_mode_writes_its_files(three, tmp_path, figures):
    wavelengths = three.data.wavelengths()
    path = write_report(three, tmp_path, figures=figures)
    assert path == tmp_path / "fit.json"
    written = {p.name for p in tmp_path.iterdir()}
    expected = {"fit.json"}
    if figures in ("summary", "all"):
        expected |= set(SUMMARY_FIGURES)
    if figures == "all":
        expected |= _per_wavelength(wavelengths)
    assert written == expected
    for name in sorted(written - {"fit.json"}):
        assert_valid_png(tmp_path / name)
    report = json.loads(path.read_text())
    assert report["n_measurements"] == len(three.data)
    assert len(report["residuals"]) == len(three.data)


def test_write_report_default_is_the_summary(three, tmp_path):
    """The Python API and the command line default to the summary figures."""
    write_report(three, tmp_path)
    names = {p.name for p in tmp_path.iterdir()}
    assert names == {"fit.json", *SUMMARY_FIGURES}


@pytest.mark.parametrize("bad", ["Summary", "some", "", None, 1])
def test_write_report_rejects_a_bad_figures_value(three, tmp_path, bad):
    with pytest.raises(ValueError) as info:
        write_report(three, tmp_path / "out", figures=bad)
    message = str(info.value)
    assert f"figures = {bad!r}" in message
    assert "summary, all, none" in message
    assert not (tmp_path / "out").exists()  # checked before anything is written


def test_summary_does_not_grow_with_the_wavelengths(tmp_path):
    one = _fitted((700.0,))
    many = _fitted(np.arange(400.0, 861.0, 40.0))  # 12 wavelengths
    names = {}
    for label, result in (("one", one), ("many", many)):
        write_report(result, tmp_path / label, figures="summary")
        names[label] = sorted(p.name for p in (tmp_path / label).glob("*.png"))
    assert names["one"] == names["many"] == sorted(SUMMARY_FIGURES)
    # and the plane-of-incidence figure shows a few wavelengths, not all 12
    assert summary_wavelengths(many.data.wavelengths()) == [400.0, 560.0, 680.0, 840.0]
    for name in SUMMARY_FIGURES:
        assert_valid_png(tmp_path / "many" / name)


def test_summary_wavelengths_spread_over_the_range():
    w = np.arange(360.0, 861.0, 20.0)  # 26
    shown = summary_wavelengths(w)
    assert len(shown) == SUMMARY_WAVELENGTHS and shown[0] == 360.0 and shown[-1] == 860.0
    assert np.all(np.diff(shown) > 100.0)
    assert summary_wavelengths([700.0, 500.0]) == [500.0, 700.0]
    assert summary_wavelengths([532.0]) == [532.0]


def test_fit_json_text_is_the_report(three):
    report = report_dict(three)
    text = dumps_report(report)
    assert json.loads(text) == json.loads(json.dumps(report))
    # one line per residual row
    assert text.count('{"theta_i": ') == len(three.data)
    # a report whose text holds the marker the writer uses falls back to plain JSON
    odd = {**report, "data_comments": ["@@ the residual rows @@"]}
    assert json.loads(dumps_report(odd)) == json.loads(json.dumps(odd))


# ----------------------------------------------------------------- command line

def _fit_parser_help(capsys) -> str:
    with pytest.raises(SystemExit) as info:
        main(["fit", "--help"])
    assert info.value.code == 0
    return " ".join(capsys.readouterr().out.split())


def test_cli_figures_choices_and_default(capsys):
    text = _fit_parser_help(capsys)
    assert "--figures {summary,all,none}" in text
    assert "(default summary)" in text
    args = build_parser().parse_args(["fit", "data.csv"])
    assert args.figures == "summary"
    sub = next(a for a in build_parser()._subparsers._group_actions[0].choices["fit"]._actions
               if a.dest == "figures")
    assert tuple(sub.choices) == FIGURES


def test_cli_rejects_a_bad_figures_value(tmp_path, capsys):
    with pytest.raises(SystemExit) as info:
        main(["fit", str(tmp_path / "data.csv"), "--figures", "every"])
    assert info.value.code == 2
    err = capsys.readouterr().err
    assert "--figures" in err and "'every'" in err
    assert "summary" in err and "all" in err and "none" in err


@pytest.mark.parametrize("figures", [None, "all", "none"])
def test_cli_writes_the_files_of_each_mode(tmp_path, capsys, figures):
    data = simulate({"radius": 0.05}, "backscatter", wavelengths=(500.0, 700.0), noise=0.01)
    csv = tmp_path / "synthetic.csv"
    save_measurements(csv, data)
    out = tmp_path / "fit"
    argv = ["fit", str(csv), "--free", "g", "--starts", "2", "--polish", "1", "--out", str(out)]
    assert main(argv + ([] if figures is None else ["--figures", figures])) == 0
    printed = capsys.readouterr().out
    manifest = out / MANIFEST.format(command="fit")
    written = {p.name for p in out.iterdir()} - {manifest.name}
    assert set(json.loads(manifest.read_text())) == written  # the result, whole
    if figures == "none":
        assert written == {"fit.json"}
        assert "no figures" in printed
    elif figures is None:  # the default: summary
        assert written == {"fit.json", *SUMMARY_FIGURES}
        assert "summary figures" in printed
    else:
        assert written == {"fit.json", *SUMMARY_FIGURES, *_per_wavelength([500.0, 700.0])}
    for name in written - {"fit.json"}:
        assert_valid_png(out / name)
