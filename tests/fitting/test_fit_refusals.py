"""Fits refuse what no powder has and what the data cannot decide (issue 33, case 2): a fixed
value outside the plugin's range, more free variables than distinct geometries, a BRF that is 0
everywhere, angles in radians; and a fit report never holds NaN or Infinity."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest

from mitsuba_powder.cli import main
from mitsuba_powder.fitting.report import dumps_report, statistics
from mitsuba_powder.io.measurements import MeasurementError, Measurements, load_measurements
from mitsuba_powder.outputs import OutputError, check_finite_json
from mitsuba_powder.plugin import registry

HEADER = "theta_i,theta_o,phi,wavelength,brf\n"
#: Ten SYNTHETIC rows at one wavelength (made-up BRF values, for the refusals only)
ROWS = ["30,0,0,550,0.4", "30,20,0,550,0.42", "30,-20,0,550,0.38", "30,40,0,550,0.45",
        "30,-40,0,550,0.35", "30,60,0,550,0.5", "30,-60,0,550,0.33", "0,30,0,550,0.4",
        "60,0,0,550,0.38", "60,30,0,550,0.42"]


def write_csv(path: Path, rows: list[str]) -> Path:
    path.write_text(HEADER + "\n".join(rows) + "\n")
    return path


def refused(capsys, args: list[str], out: Path, *fragments: str) -> str:
    """The command exits 2 with one line naming every fragment, no traceback, no output."""
    assert main(args) == 2
    err = capsys.readouterr().err
    assert "Traceback" not in err and err.startswith("mitsuba-powder: error: "), err
    for f in fragments:
        assert f in err, (f, err)
    assert not out.exists()
    return err


@pytest.mark.parametrize("setting,fragments", [
    ("albedo=2", ["albedo = 2.0", "[0, 1]"]),
    ("albedo=-0.5", ["albedo = -0.5", "[0, 1]"]),
    ("albedo=nan", ["albedo = nan", "[0, 1]"]),
    ("g=1.5", ["g = 1.5", "(-1, 1)"]),
    ("extinction=0", ["extinction = 0.0", str(registry.INTERVALS["extinction"])]),
    ("amplitude_surface=-1e-4", ["amplitude_surface = -0.0001",
                                 str(registry.INTERVALS["amplitude_surface"])]),
    ("g=abc", ["g = 'abc' is not a number"]),
])
def test_fit_refuses_a_fixed_value_no_powder_has(tmp_path, capsys, setting, fragments):
    """A --set value outside the plugin's range is refused before the fit, named with its
    range (albedo 2 used to be fitted and written into fit.json; albedo=nan blamed
    amplitude_volume)."""
    data = write_csv(tmp_path / "d.csv", ROWS)
    free = "extinction" if setting.startswith("g=") else "amplitude_volume,g"
    if setting.startswith(("extinction", "amplitude_surface")):
        free = "g"
    out = tmp_path / "fit"
    refused(capsys, ["fit", str(data), "--set", setting, "--free", free, "--out", str(out)],
            out, *fragments)


@pytest.mark.parametrize("options,fragment", [
    (["--seed", "-1"], "--seed = -1 is out of range; valid range is [0, 4294967295]"),
    (["--seed", str(2**40)], f"--seed = {2**40} is out of range"),
    (["--starts", "0"], "--starts = 0 is out of range; valid range is [1, inf)"),
    (["--global", "mlsl"], "--global = 'mlsl': the global stages mlsl and crs2 use nlopt, "
                           "which is not installed"),
])
def test_fit_refuses_bad_search_options_before_the_work(tmp_path, capsys, monkeypatch, options,
                                                        fragment):
    """The global stage's options named as the command line spells them (a seed past 2^32
    was nlopt's OverflowError traceback, a missing nlopt an ImportError traceback)."""
    import sys

    monkeypatch.setitem(sys.modules, "nlopt", None)
    data = write_csv(tmp_path / "d.csv", ROWS)
    out = tmp_path / "fit"
    refused(capsys, ["fit", str(data), "--free", "g", "--out", str(out), *options], out,
            fragment)


def test_fit_refuses_more_free_variables_than_geometries(tmp_path, capsys):
    """Two rows, six free parameters: refused (it used to exit 0 with uncertainties 0);
    replicated rows count once."""
    out = tmp_path / "fit"
    two = write_csv(tmp_path / "two.csv", ROWS[:2])
    refused(capsys, ["fit", str(two), "--out", str(out)], out,
            "6 free variables cannot be determined by 2 distinct geometries")
    replicated = write_csv(tmp_path / "rep.csv", ROWS[:3] * 5)
    refused(capsys, ["fit", str(replicated), "--out", str(out)], out,
            "by 3 distinct geometries")


def test_compare_models_refuses_a_model_the_data_cannot_determine(tmp_path, capsys):
    """compare-models with fewer geometries than a baseline's parameters is refused before
    any fit (it used to crown an 8-parameter Hapke at 0.00 %)."""
    data = write_csv(tmp_path / "d.csv", ROWS[:7])
    out = tmp_path / "cmp"
    refused(capsys, ["compare-models", str(data), "--out", str(out)], out,
            "the hapke fit at 550 nm: 8 free variables cannot be determined by 7 distinct")


def test_fit_refuses_a_brf_that_is_zero_everywhere(tmp_path, capsys):
    """An all-zero BRF is refused (it used to exit 0 and write Infinity into fit.json)."""
    zero = write_csv(tmp_path / "zero.csv", [r.rsplit(",", 1)[0] + ",0" for r in ROWS])
    out = tmp_path / "fit"
    refused(capsys, ["fit", str(zero), "--out", str(out)], out, "zero.csv", "every BRF value is 0")


def test_angles_in_radians_are_refused(tmp_path):
    """Every angle below 1.6 degrees: the file holds radians (it used to pass silently)."""
    rows = [f"{math.radians(float(a)):.6f},{math.radians(float(b)):.6f},0,550,0.4"
            for a, b in ((30, 0), (30, 20), (60, -40))]
    path = write_csv(tmp_path / "rad.csv", rows)
    with pytest.raises(MeasurementError, match=r"rad\.csv: every angle .* look like radians"):
        load_measurements(path)
    # normal incidence and emergence alone is degrees, not radians
    assert len(load_measurements(write_csv(tmp_path / "n.csv", ["0,0,0,550,0.4"]))) == 1


def test_fit_reports_never_hold_nan_or_infinity():
    """Relative errors leave out rows whose BRF is 0 (they used to be NaN), and a report
    with a non-finite number is refused, naming where."""
    d = Measurements(np.array([30.0, 30.0]), np.array([0.0, 20.0]), np.zeros(2),
                     np.full(2, 550.0), np.array([0.0, 0.5]))
    stats = statistics(np.array([0.1, 0.4]), d)
    assert stats["relative_rmse_percent"] == pytest.approx(20.0)
    assert stats["relative_rows"] == 1
    only_zero = statistics(np.array([0.1, 0.4]), d, np.array([True, False]))
    assert only_zero["relative_rmse_percent"] is None
    with pytest.raises(OutputError, match=r"fit.json would hold NaN or Infinity at a\.b\[1\]"):
        dumps_report({"a": {"b": [1.0, math.inf]}, "residuals": []})
    check_finite_json({"a": [1.0, None, "inf"]}, "x.json")  # text and null are fine
