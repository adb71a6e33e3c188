"""The scripts that generate docs pages run (quick sizes), so the pages can be regenerated."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from helpers import write_exr_capture

ROOT = Path(__file__).resolve().parents[2]


def test_gonio_validation_script_quick(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / "gonio_validation.py"),
                           "--quick", "--out", str(tmp_path)], capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "| llvm_ad_spectral | collimated | emitter |" in proc.stdout
    assert "| llvm_ad_rgb | mis | 80 |" in proc.stdout


def test_showcase_script_small(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / "showcase.py"),
                           "--spp", "2", "--res", "96x30", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    meta = json.loads((tmp_path / "showcase.json").read_text())
    assert meta["variant"] == "llvm_ad_spectral" and meta["width"] == 96
    assert [r["scene"] for r in meta["renders"]] == ["scenes/showcase.xml",
                                                     "scenes/showcase_grains.xml"]
    assert (tmp_path / "showcase.png").stat().st_size > 5000
    assert not (tmp_path / "showcase_raw.exr").exists()


def test_energy_grid_script(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / "energy_grid.py")],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    conserving = proc.stdout.split("energy = conserving")[1]
    rows = [line for line in conserving.splitlines() if line.startswith("| 0.001 ")]
    assert rows and all(float(x) <= 1.002 for x in rows[0].strip("|").split("|")[1:]), rows


def test_grain_colour_script_quick(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / "grain_colour.py"),
                           "--quick", "--out", str(tmp_path)], capture_output=True, text=True,
                          timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    table = (tmp_path / "grain_colour_table.md").read_text()
    assert "| sphere | 0.01 |" in table and "| slab |" in table and "| agglomerate, fill" in table
    assert (tmp_path / "figures" / "grain_colour.png").stat().st_size > 5000


def test_rti_figure_script_on_a_small_synthetic_capture(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / "rti_figure.py"),
                           "--size", "16", "--out", str(tmp_path)], capture_output=True,
                          text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    summary = json.loads((tmp_path / "rti_synthetic.json").read_text())
    assert set(summary["rmse_8bit"]) == {"powder", "ptm", "hsh", "lambertian_clamped"}
    assert (tmp_path / "rti_synthetic.png").stat().st_size > 5000


def test_rti_identifiability_script(tmp_path):
    """The bounds of docs/rti.md: with 8 lights near the camera every bound is under 20 %
    and the darkest region's extinction bound is a third of the plain dome's (0.14 vs 0.44)."""
    out = tmp_path / "bounds.json"
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" /
                                                "rti_identifiability.py"), "--json", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "| dome 10-80 degrees | 0 | 0.045 |" in proc.stdout
    bounds = json.loads(out.read_text())["bounds"]
    dome, near = bounds["dome 10-80 degrees"], bounds["32 on the dome + 8 at 82-88 degrees"]
    for region in range(4):
        assert max(near[region]) < 0.2, region
    assert near[0][2] < 0.4 * dome[0][2]


def test_rti_gain_trend_script(tmp_path):
    """The gains' trend, far against near field, on a SYNTHETIC capture whose lights are at 3
    image widths and whose gains fall with elevation: the near-field fit's trend is recorded
    beside the distant one's, with the rings and the share of the slope."""
    from mitsuba_powder import rti

    d = rti.dome_directions(16)
    gains = np.exp(-0.3 * (d[:, 2] - d[:, 2].mean()))
    cap = rti.synthetic_capture(12, 12, 16, noise=0.005, gains=gains / gains.mean(),
                                light_distance=3.0, seed=2)
    lp = write_exr_capture(tmp_path, cap)
    out = tmp_path / "trend.json"
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / "rti_gain_trend.py"),
                           str(lp), "--light-distance", "3", "--rings", "2",
                           "--json", str(out)], capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "near-field share of the slope" in proc.stdout
    data = json.loads(out.read_text())
    assert set(data["trend"]) == {"far", "near"} and len(data["rings"]) == 2
    assert sum(r["lights"] for r in data["rings"]) == 16
    # the capture's own trend, -0.3 per unit of sin(elevation), is what the near fit finds
    assert abs(data["trend"]["near"]["slope"] + 0.3) < 0.1


@pytest.mark.parametrize("script", ["showcase.py", "grain_colour.py", "hematite_colour.py",
                                    "ochre_series.py",
                                    "gonio_validation.py", "ptfe_fits.py",
                                    "ipag_conventions.py", "rti_figure.py"])
def test_docs_scripts_do_not_write_the_committed_docs_by_default(script):
    """Without --out a docs script writes into a new temporary folder, and says where; the
    committed pages and figures change only with --refresh-docs."""
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / script), "--help"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0 and "--refresh-docs" in proc.stdout
    sys.path.insert(0, str(ROOT / "docs" / "scripts"))
    try:
        from docs_output import add_output_options, output_dir
    finally:
        sys.path.pop(0)
    import argparse

    parser = argparse.ArgumentParser()
    add_output_options(parser, ROOT / "docs", "pages")
    default = output_dir(parser.parse_args([]), ROOT / "docs")
    assert default.is_dir() and ROOT not in default.parents and not any(default.iterdir())
    assert output_dir(parser.parse_args(["--refresh-docs"]), ROOT / "docs") == ROOT / "docs"


def test_unmix_baselines_script_quick(tmp_path):
    """docs/colour.md's table of unmixing against the baselines: each rule recovers the
    mixture it made (within 0.01 by mass at 0.005 reflectance noise)."""
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / "unmix_baselines.py"),
                           "--quick", "--out", str(tmp_path)], capture_output=True, text=True,
                          timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    rows = [r.split(" | ") for r in (tmp_path / "unmix_baselines_table.md").read_text()
            .splitlines() if r.startswith("| ochre")]
    assert len(rows) == 8
    own = {(r[1], r[2]): float(r[4]) for r in rows}
    assert own[("powder", "powder")] < 0.01 and own[("hapke", "hapke")] < 0.01, own


def test_ochre_render_script_small(tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / "ochre_render.py"),
                           "--spp", "2", "--res", "96x36", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    meta = json.loads((tmp_path / "ochre_render.json").read_text())
    assert meta["variant"] == "llvm_ad_spectral" and meta["width"] == 96
    assert (tmp_path / "ochre_render.png").stat().st_size > 5000


@pytest.mark.parametrize("script,options", [("unmix_baselines.py", ["--quick"]),
                                            ("ochre_render.py", ["--spp", "1", "--res", "8x4"])])
def test_an_out_that_is_a_file_is_an_error_line(tmp_path, script, options):
    """--out naming a file: one error line and exit code 2 before any work, the file kept."""
    target = tmp_path / "notes.txt"
    target.write_text("mine\n")
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / script), *options,
                           "--out", str(target)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2, proc.stderr[-3000:]
    assert f"error: --out {target} is a file; give a folder" in proc.stderr
    assert "Traceback" not in proc.stderr and target.read_text() == "mine\n"


def test_ochre_render_refuses_an_unknown_variant_before_any_work(tmp_path):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, str(ROOT / "docs" / "scripts" / "ochre_render.py"),
                           "--variant", "bogus", "--out", str(out)], capture_output=True,
                          text=True, timeout=300)
    assert proc.returncode == 2 and "--variant: variant = 'bogus' is not available" in \
        proc.stderr, proc.stderr[-3000:]
    assert "Traceback" not in proc.stderr and not out.exists()


def test_ochre_render_writes_nothing_from_a_nan_render(tmp_path, monkeypatch, capsys):
    """A render holding NaN (a plugin bug) is an error (exit 2), not a figure."""
    import runpy

    import mitsuba as mi

    def nan_render(scene, *args, **kwargs):
        image = np.full((4, 8, 3), 0.5, dtype=np.float32)
        image[1, 2, 0] = np.nan
        return mi.TensorXf(image)

    monkeypatch.setattr(mi, "render", nan_render)
    monkeypatch.setattr(sys, "argv", ["ochre_render.py", "--spp", "1", "--res", "8x4",
                                      "--out", str(tmp_path)])
    monkeypatch.syspath_prepend(str(ROOT / "docs" / "scripts"))
    with pytest.raises(SystemExit) as info:
        runpy.run_path(str(ROOT / "docs" / "scripts" / "ochre_render.py"), run_name="__main__")
    assert info.value.code == 2
    assert "the render holds 1 NaN or infinite pixel values" in capsys.readouterr().err
    assert not any(tmp_path.iterdir())


def test_write_output_refuses_non_finite_numbers(tmp_path):
    """docs_output.write_output: a table whose numbers hold NaN is not written (the previous
    file is kept); a finite one is written whole."""
    sys.path.insert(0, str(ROOT / "docs" / "scripts"))
    try:
        from docs_output import write_output
    finally:
        sys.path.pop(0)
    from mitsuba_powder.outputs import OutputError

    (tmp_path / "table.md").write_text("previous\n")
    with pytest.raises(OutputError, match=r"table.md would hold NaN or Infinity at \[1\]\[0\]"):
        write_output(tmp_path, "table.md", "| nan |\n", finite=[[0.1], [float("nan")]])
    assert (tmp_path / "table.md").read_text() == "previous\n"
    write_output(tmp_path, "table.md", "| 0.1 |\n", finite=[[0.1]])
    assert sorted(p.name for p in tmp_path.iterdir()) == ["table.md"]
    assert (tmp_path / "table.md").read_text() == "| 0.1 |\n"
