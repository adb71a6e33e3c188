"""What a newcomer meets first (issue 33, case 7): the tutorial writes under out/, the data
files have their provenance, figure titles and showcase labels fit, progress counts the rounds
asked for, and options that would be ignored are refused."""

from __future__ import annotations

import importlib
import re
import shlex
import sys
from pathlib import Path

import numpy as np
import pytest

from mitsuba_powder.cli import main

ROOT = Path(__file__).resolve().parents[2]


def _tutorial_commands() -> list[list[str]]:
    text = (ROOT / "docs" / "tutorial.md").read_text()
    out = []
    for block in re.findall(r"^```bash\n(.*?)^```", text, flags=re.S | re.M):
        joined = re.sub(r"\\\n\s*", " ", block)
        out += [shlex.split(line, comments=True) for line in joined.splitlines()
                if line.strip() and not line.startswith("#")]
    return out


def test_the_tutorial_writes_only_under_out():
    """Every output the tutorial names (--out, -o, a redirection) lies under out/, which
    .gitignore covers: running it leaves the repository root clean."""
    outputs = []
    for words in _tutorial_commands():
        for k, w in enumerate(words[:-1]):
            if w in ("--out", "-o", ">"):
                outputs.append(words[k + 1])
    assert len(outputs) >= 6
    assert all(o.startswith("out/") for o in outputs), outputs
    assert "/out/" in (ROOT / ".gitignore").read_text().split()


def test_every_measurement_file_has_its_provenance():
    readme = (ROOT / "measurements" / "README.md").read_text()
    assert "None are bundled" not in readme
    files = [p for p in (ROOT / "measurements").iterdir() if p.name != "README.md"]
    assert files
    for p in files:
        assert f"`measurements/{p.name}`" in readme, p.name


def test_the_ptfe_header_names_a_module_that_exists():
    header = (ROOT / "measurements" / "ptfe_germer2017.csv").read_text()[:2000]
    module = re.search(r"Converted by (\S+) from", header).group(1)
    assert hasattr(importlib.import_module(module), "convert_germer_ptfe")


def test_a_one_wavelength_summary_title_is_not_clipped(monkeypatch, tmp_path):
    """The principal-plane summary of one wavelength wraps its title inside the figure (it
    was cut at both edges)."""
    from mitsuba_powder.fitting import figures
    from mitsuba_powder.io.measurements import Measurements

    saved = []
    monkeypatch.setattr(figures, "_save", lambda fig, path: saved.append(fig))
    n = 8
    data = Measurements(np.full(n, 30.0), np.linspace(-60, 60, n), np.zeros(n),
                        np.full(n, 550.0), np.full(n, 0.5))
    result = figures.FitFigures(data=data, model_brf=np.full(n, 0.5))
    figures.plot_principal_planes(result, [550.0], tmp_path / "p.png")
    fig = saved[0]
    renderer = fig.canvas.get_renderer()
    box, title = fig.bbox, fig.texts[0].get_window_extent(renderer)
    assert box.x0 <= title.x0 and title.x1 <= box.x1 and title.y1 <= box.y1


def test_the_showcase_labels_do_not_overlap():
    """At the figure's width (960 px) each label fits between its neighbours' centres."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    sys.path.insert(0, str(ROOT / "docs" / "scripts"))
    try:
        showcase = importlib.import_module("showcase")
    finally:
        sys.path.pop(0)
    width = 960
    fig = Figure(figsize=(width / 100, 3), dpi=100)
    ax = fig.add_axes([0, 0, 1, 1])
    ax.set_xlim(0, width)
    renderer = FigureCanvasAgg(fig).get_renderer()
    cols = showcase.dish_columns(width)
    for _, _, labels in showcase.SCENES:
        extents = [ax.text(c, 0.5, label, ha="center", fontsize=8, linespacing=1.1)
                   .get_window_extent(renderer) for c, label in zip(cols, labels)]
        for a, b in zip(extents, extents[1:]):
            assert a.x1 < b.x0, (a, b)


def test_rounds_are_counted_as_asked():
    """--rounds 1 prints 'round 1/1' (it printed 'round 1/2'); the per-pixel fit after the
    last gain update is named as such."""
    from mitsuba_powder.rti import fit_maps, synthetic_capture

    cap = synthetic_capture(6, 6, lights=12, noise=0.005, seed=1)
    for rounds in (1, 3):
        lines: list[str] = []
        fit_maps(cap["images"], cap["directions"], rounds=rounds, gains="fit",
                 max_iterations=4, progress=lines.append)
        counted = [ln for ln in lines if re.match(r"round \d+/\d+:", ln)]
        assert counted and all(f"/{rounds}:" in ln for ln in counted), lines
        assert any(ln.startswith("final fit under the fitted gains") for ln in lines)


@pytest.mark.parametrize("command", [["fit", "{csv}"], ["compare-models", "{csv}"],
                                     ["fit-maps", "{lp}"]])
def test_an_empty_free_list_is_refused(tmp_path, capsys, command):
    """--free "" used to fall back to the defaults without a word."""
    csv = tmp_path / "d.csv"
    csv.write_text("theta_i,theta_o,phi,wavelength,brf\n30,0,0,550,0.4\n")
    lp = tmp_path / "d.lp"
    lp.write_text("1\na.png 0 0 1\n")
    args = [a.format(csv=csv, lp=lp) for a in command]
    assert main([*args, "--free", "", "--out", str(tmp_path / "o")]) == 2
    assert "--free '' names no property" in capsys.readouterr().err


def test_simulate_refuses_a_layout_a_csv_cannot_have(tmp_path, capsys):
    params = tmp_path / "p.json"
    params.write_text("{}")
    out = tmp_path / "s.csv"
    assert main(["simulate", "--params", str(params), "--layout", "single", "--out",
                 str(out)]) == 2
    assert "--layout single applies to --format ipag" in capsys.readouterr().err
    assert not out.exists()
