"""The fit's figures drawn in a second process (fitting.figure_process): the same files as
drawn in the fitting process, byte for byte; a failure there is an error here; an unused
process ends."""

from __future__ import annotations

import time

import pytest

from mitsuba_powder.fitting.figure_process import FigureProcess
from mitsuba_powder.fitting.figures import FitFigures
from mitsuba_powder.fitting.fit import fit
from mitsuba_powder.fitting.protocols import simulate
from mitsuba_powder.fitting.report import SUMMARY_FIGURES, write_report


@pytest.fixture(scope="module")
def two():
    data = simulate({"radius": 0.05, "g": 0.2}, "shadows,backscatter", wavelengths=(450.0, 650.0),
                    noise=0.01, seed=3)
    return fit(data, free=["g"], starts=1, polish=1)


@pytest.mark.parametrize("figures", ["summary", "all"])
def test_the_process_draws_the_same_files(two, tmp_path, figures):
    here, there = tmp_path / "here", tmp_path / "there"
    write_report(two, here, figures=figures)
    with FigureProcess() as process:
        write_report(two, there, figures=figures, process=process)
    names = sorted(p.name for p in here.iterdir())
    assert names == sorted(p.name for p in there.iterdir())
    assert set(SUMMARY_FIGURES) <= set(names)
    for name in names:
        assert (here / name).read_bytes() == (there / name).read_bytes(), name


def test_a_failure_in_the_process_is_an_error(two, tmp_path):
    fig = FitFigures(two.data, two.model_brf)
    with FigureProcess() as process:
        assert process.submit([("plot_rmse", {"result": fig,
                                              "path": tmp_path / "no" / "such" / "a.png"})])
        with pytest.raises(RuntimeError, match="drawing the fit's figures failed"):
            process.wait()


def test_an_unknown_figure_is_refused(two, tmp_path):
    with FigureProcess() as process:
        assert process.submit([("plot_everything", {})])
        with pytest.raises(RuntimeError, match="'plot_everything' is not one of"):
            process.wait()


def test_a_process_given_no_jobs_is_ended(tmp_path):
    t = time.perf_counter()
    with FigureProcess() as process:
        assert process.running
    assert not process.running
    assert time.perf_counter() - t < 60
    assert process.submit([]) is False  # ended: the caller draws
