"""``mitsuba-powder unmix`` with bad input: every option and every CSV it reads, each refused with
one line naming the option (or the file, line and column), the value and the valid range, exit
code 2 and no traceback; no option silently ignored; ``--json`` never written over an input.
The spectra are made up (the refusals come before any fit)."""

from __future__ import annotations

import hashlib
import shutil
import sys
from pathlib import Path

import numpy as np
import pytest

from mitsuba_powder.cli import main
from mitsuba_powder.plugin import registry

WL = np.arange(360.0, 861.0, 20.0)
MIX = "kaolinite:50%:1um,hematite:25%:0.1um,magnetite:25%:0.3um"


def write_csv(path: Path, rows) -> str:
    path.write_text("wavelength_nm,value,sigma\n" + "".join(
        ",".join(f"{v:g}" for v in row) + "\n" for row in rows))
    return str(path)


def albedo_rows() -> list[tuple[float, float, float]]:
    return [(w, 0.5 + 0.3 * np.sin(w / 90.0), 0.01) for w in WL]


def run(argv, capsys) -> tuple[int, str]:
    """The exit code and stderr of a command (a SystemExit or an exception fails the test:
    every refusal is an error line and exit code 2)."""
    code = main(argv)
    return code, capsys.readouterr().err


@pytest.fixture
def albedo_csv(tmp_path) -> str:
    return write_csv(tmp_path / "albedo.csv", albedo_rows())


@pytest.mark.parametrize("options,fragment", [
    (["--mix", "kaolinite:50%:0um,hematite:50%:0.1um"],
     "the radius of kaolinite = 0.0 um is out of range; valid range is (0, inf)"),
    (["--mix", "kaolinite:50%:-1um,hematite:50%:0.1um", "--free-radii"],
     "the radius of kaolinite = -1.0 um is out of range"),
    (["--mix", "kaolinite:50%:nan,hematite:50%:0.1um"], "the radius of kaolinite = nan um"),
    (["--mix", "kaolinite:110%:1um,hematite:-10%:0.1um"],
     "--mix 'kaolinite:110%:1um,hematite:-10%:0.1um': the volume fraction of kaolinite = 1.1 "
     "is out of range; valid range is [0, 1]"),
    (["--mix", "kaolinite:50%:1um,hematite:40%:0.1um"], "sum to 0.9; they must sum to 1"),
    (["--mix", "unobtainium:50%:1um,hematite:50%:0.1um"],
     "--mix 'unobtainium:50%:1um,hematite:50%:0.1um': material = 'unobtainium' is not valid"),
    (["--mix", ",".join(f"kaolinite:20%:{r}um" for r in (1, 2, 3, 4, 5))],
     "the number of populations = 5 is out of range; valid range is [2, 4]"),
    (["--mix", "kaolinite:50%"], "--mix 'kaolinite:50%': mixture item"),
    (["--mix", "kaolinite:50%:1um,kaolinite:50%:1um"],
     "kaolinite of radius 1 um is given twice: two identical populations cannot be told apart"),
    (["--mix", MIX, "--starts", "0"], "--starts = 0 is out of range; valid range is [1, inf)"),
    (["--mix", MIX, "--seed", "-1"], "--seed = -1 is out of range; valid range is [0, "
                                     "4294967295]"),
    (["--mix", MIX, "--seed", str(2**70), "--global", "crs2"], f"--seed = {2**70} is out of"),
    (["--mix", MIX, "--geometry", "45:0"], "--geometry needs --baseline"),
    (["--mix", MIX, "--json", ""], "--json '': give a file name"),
    (["--mix", MIX, "--tints", "t.csv:10%"], "--tints needs --baseline"),
])
def test_bad_options_name_the_option_and_the_range(albedo_csv, capsys, options, fragment):
    code, err = run(["unmix", albedo_csv, *options], capsys)
    assert code == 2 and fragment in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("row,fragment", [
    ((500.0, float("nan"), 0.01), "line 9 (albedo) = nan is out of range; valid range is [0, 1]"),
    ((500.0, float("inf"), 0.01), "line 9 (albedo) = inf is out of range"),
    ((500.0, 1.2, 0.01), "line 9 (albedo) = 1.2 is out of range; valid range is [0, 1]"),
    ((500.0, -0.1, 0.01), "line 9 (albedo) = -0.1 is out of range"),
    ((500.0, 0.5, -0.01), "line 9 (sigma) = -0.01 is out of range; valid range is (0, inf)"),
    ((500.0, 0.5, 0.0), "line 9 (sigma) = 0.0 is out of range"),
    ((500.0, 0.5, float("nan")), "line 9 (sigma) = nan is out of range"),
    ((float("nan"), 0.5, 0.01), "line 9 (wavelength) = nan is out of range; valid range is "
                                "(0, inf)"),
    ((480.0, 0.5, 0.01), "line 9: wavelength 480 nm after 480 nm on line 8; the wavelengths "
                         "must increase"),
    ((300.0, 0.5, 0.01), "line 9: wavelength 300 nm after 480 nm on line 8"),
])
def test_bad_rows_of_the_albedo_csv_name_the_line(tmp_path, capsys, row, fragment):
    rows = albedo_rows()
    rows[7] = row  # line 9 of the file (after the header and rows 360-480 nm)
    path = write_csv(tmp_path / "albedo.csv", rows)
    code, err = run(["unmix", path, "--mix", MIX], capsys)
    assert code == 2 and f"{path}, {fragment}" in err, err


def test_a_wavelength_outside_a_materials_table_names_the_file(tmp_path, capsys):
    rows = albedo_rows() + [(1200.0, 0.5, 0.01)]
    path = write_csv(tmp_path / "albedo.csv", rows)
    code, err = run(["unmix", path, "--mix", MIX], capsys)
    assert code == 2 and f"{path}: wavelength 1200 nm lies outside the optical constants of " \
                         "kaolinite" in err, err


def test_too_few_rows_for_the_free_variables(tmp_path, capsys, swatches):
    path = write_csv(tmp_path / "albedo.csv", albedo_rows()[:2])
    code, err = run(["unmix", path, "--mix", MIX], capsys)
    assert code == 2 and "2 wavelengths for 2 free variables: the fit is not determined" in err
    for name in ("mix", "e0", "e1", "e2"):  # the header and two wavelengths in each spectrum
        lines = Path(swatches[name]).read_text().splitlines()[:3]
        Path(swatches[name]).write_text("\n".join(lines) + "\n")
    code, err = run(["unmix", swatches["mix"], "--mix", MIX, "--baseline", "hapke",
                     "--endmembers", swatches["ends"]], capsys)
    assert code == 2 and "2 wavelengths for 2 free fractions: the fit is not determined" in \
        err, err


def test_unsorted_wavelengths_are_refused_not_fitted(tmp_path, capsys):
    path = write_csv(tmp_path / "albedo.csv", albedo_rows()[::-1])
    code, err = run(["unmix", path, "--mix", MIX], capsys)
    assert code == 2 and "the wavelengths must increase" in err, err


def test_a_global_stage_without_nlopt_is_an_error_naming_global(albedo_csv, capsys,
                                                                monkeypatch):
    monkeypatch.setitem(sys.modules, "nlopt", None)
    for stage in ("mlsl", "crs2"):
        code, err = run(["unmix", albedo_csv, "--mix", MIX, "--global", stage], capsys)
        assert code == 2, err
        assert f"--global = '{stage}': the global stages mlsl and crs2 use nlopt, which is " \
               "not installed: pip install" in err, err


# ------------------------------------------------------------------------ --baseline


@pytest.fixture
def swatches(tmp_path) -> dict[str, str]:
    """The mixture's reflectance CSV, three endmembers and two tints (made up)."""
    ends = [0.8 + 0.1 * np.sin(WL / 100), 0.1 + 0.3 * (WL > 600), 0.05 + 0 * WL]
    files = {}
    for name, r in [("e0", ends[0]), ("e1", ends[1]), ("e2", ends[2]),
                    ("t1", 0.9 * ends[0] + 0.1 * ends[1]), ("t2", 0.9 * ends[0] + 0.1 * ends[2])]:
        files[name] = str(tmp_path / f"{name}.csv")
        Path(files[name]).write_text("wavelength,reflectance\n" + "".join(
            f"{w:g},{v:.6f}\n" for w, v in zip(WL, r)))
    mix = 0.6 * ends[0] + 0.3 * ends[1] + 0.1 * ends[2]
    files["mix"] = write_csv(tmp_path / "mix.csv", [(w, r, 0.005) for w, r in zip(WL, mix)])
    files["ends"] = f"{files['e0']},{files['e1']},{files['e2']}"
    files["tints"] = f"{files['t1']}:10%,{files['t2']}:10%"
    return files


@pytest.mark.parametrize("options,fragment", [
    (["--baseline", "hapke", "--endmembers", "{e0},{e1}"],
     "2 files for the 3 populations of --mix"),
    (["--baseline", "km", "--endmembers", "{ends}", "--tints", "{t1}:10%"],
     "1 tints for the 2 pigments of --mix"),
    (["--baseline", "km", "--endmembers", "{ends}", "--tints", "{t1}:0%,{t2}:10%"],
     "the pigment's mass fraction = 0.0 is out of range; valid range is (0, 1)"),
    (["--baseline", "km", "--endmembers", "{ends}", "--tints", "{t1}:100%,{t2}:10%"],
     "the pigment's mass fraction = 1.0 is out of range"),
    (["--baseline", "hapke", "--endmembers", "{ends}", "--tints", "{tints}"],
     "--tints are Kubelka-Munk's: with --baseline km or all"),
    (["--baseline", "hapke", "--endmembers", "{ends}", "--global", "crs2"],
     "--global not with --baseline"),
    (["--baseline", "hapke", "--endmembers", "{ends}", "--starts", "8"],
     "--starts not with --baseline"),
    (["--baseline", "hapke", "--endmembers", "{ends}", "--seed", "-2"], "--seed = -2 is out"),
    (["--baseline", "all", "--endmembers", "{ends}", "--set", "tau_o"],
     "--set 'tau_o': expected NAME=VALUE"),
    (["--baseline", "hapke", "--endmembers", "{ends}", "--geometry", "95:0"],
     "--geometry: geometry = '95:0': theta_i must lie in [0, 90)"),
    (["--baseline", "km", "--endmembers", "{ends}", "--geometry", "0:45"],
     "--geometry 0:45: Kubelka-Munk's R_inf is a hemispherical reflectance; give 0:d"),
    (["--baseline", "hapke", "--endmembers", "{e0},{e1},{big}"],
     "big.csv, line 2 (reflectance) = 1.2 is out of range; valid range is [0, 1]"),
])
def test_bad_baseline_options_are_errors(swatches, tmp_path, capsys, options, fragment):
    (tmp_path / "big.csv").write_text("wavelength,reflectance\n" + "".join(
        f"{w:g},1.2\n" for w in WL))
    swatches["big"] = str(tmp_path / "big.csv")
    argv = ["unmix", swatches["mix"], "--mix", MIX] + [o.format(**swatches) for o in options]
    code, err = run(argv, capsys)
    assert code == 2 and fragment in err, err
    assert "Traceback" not in err and len(err.strip().splitlines()) == 1, err


@pytest.mark.parametrize("value,fragment", [(1.3, "= 1.3 is out of range; valid range is "
                                                  "[0, 1]"),
                                            (-0.1, "= -0.1 is out of range")])
def test_a_hemispherical_reflectance_outside_0_1_is_refused(swatches, capsys, value, fragment):
    rows = [line.split(",") for line in Path(swatches["mix"]).read_text().splitlines()[1:]]
    rows[3][1] = str(value)
    Path(swatches["mix"]).write_text("wavelength,reflectance,sigma\n" + "".join(
        ",".join(r) + "\n" for r in rows))
    for baseline in ("hapke", "km"):
        code, err = run(["unmix", swatches["mix"], "--mix", MIX, "--baseline", baseline,
                         "--endmembers", swatches["ends"]], capsys)
        assert code == 2 and f"line 5 (reflectance) {fragment}" in err, err


def test_the_seed_reaches_the_baselines(swatches, capsys, monkeypatch):
    from mitsuba_powder.fitting import unmix_baselines

    seeds = []
    real = unmix_baselines.unmix_hapke

    def spy(*args, seed=0, **kwargs):
        seeds.append(seed)
        return real(*args, seed=seed, **kwargs)

    monkeypatch.setattr(unmix_baselines, "unmix_hapke", spy)
    assert main(["unmix", swatches["mix"], "--mix", MIX, "--baseline", "hapke",
                 "--endmembers", swatches["ends"], "--seed", "7"]) == 0
    assert seeds == [7]


# ------------------------------------------------------------------------ --json


def digests(paths) -> dict[str, str]:
    return {p: hashlib.sha256(Path(p).read_bytes()).hexdigest() for p in paths}


@pytest.mark.parametrize("target", ["e1", "t2", "mix"])
def test_json_over_an_endmember_tint_or_the_spectrum_is_refused(swatches, capsys, target):
    inputs = [swatches[k] for k in ("e0", "e1", "e2", "t1", "t2", "mix")]
    before = digests(inputs)
    code, err = run(["unmix", swatches["mix"], "--mix", MIX, "--baseline", "km",
                     "--endmembers", swatches["ends"], "--tints", swatches["tints"],
                     "--json", swatches[target]], capsys)
    assert code == 2 and f"--json {swatches[target]} is an input file of this command" in err
    assert digests(inputs) == before


def test_json_over_a_material_yaml_file_is_refused(tmp_path, albedo_csv, capsys):
    yml = tmp_path / "my_clay.yml"
    shutil.copy(registry.material_files("kaolinite")[0], yml)
    before = yml.read_bytes()
    code, err = run(["unmix", albedo_csv, "--mix", f"{yml}:50%:1um,hematite:50%:0.1um",
                     "--json", str(yml)], capsys)
    assert code == 2 and "is an input file of this command" in err, err
    assert yml.read_bytes() == before


@pytest.mark.parametrize("baseline", [False, True])
def test_json_is_written_whole_or_not_at_all(swatches, albedo_csv, tmp_path, capsys,
                                             monkeypatch, baseline):
    """A write that fails half way (here: the rename into place) leaves the previous file as
    it was and no temporary file beside it, with and without --baseline."""
    import os

    out = tmp_path / "result.json"
    out.write_text("previous\n")

    def failing(*args, **kwargs):
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(os, "replace", failing)
    argv = (["unmix", swatches["mix"], "--mix", MIX, "--baseline", "hapke", "--endmembers",
             swatches["ends"]] if baseline else
            ["unmix", albedo_csv, "--mix", MIX, "--starts", "1"])
    code, err = run(argv + ["--json", str(out)], capsys)
    assert code == 2 and "No space left on device" in err, err
    assert out.read_text() == "previous\n"
    assert sorted(p.name for p in tmp_path.iterdir() if "result" in p.name) == ["result.json"]


def test_a_degenerate_result_is_an_error_not_a_nan_with_exit_0(swatches, tmp_path, capsys,
                                                               monkeypatch):
    """A fit whose uncertainties are not finite (a singular Jacobian: e.g. identical
    masstones, where rounding decides between huge and NaN) is printed with its warnings,
    then exit code 2, and --json is not written."""
    from mitsuba_powder.fitting import unmix_baselines

    real = unmix_baselines.unmix_km

    def singular(*args, **kwargs):
        u = real(*args, **kwargs)
        u.mass_fraction_errors[1] = np.nan
        u.warnings.append("the Jacobian is singular: the data cannot decide the fractions")
        return u

    monkeypatch.setattr(unmix_baselines, "unmix_km", singular)
    out = tmp_path / "km.json"
    for json_option in ([], ["--json", str(out)]):
        code = main(["unmix", swatches["mix"], "--mix", MIX, "--baseline", "km",
                     "--endmembers", swatches["ends"], *json_option])
        captured = capsys.readouterr()
        assert code == 2 and "the Jacobian is singular" in captured.out
        assert "would hold NaN or Infinity at [0].mass_fraction_errors[1]" in captured.err
    assert not out.exists()


def test_km_takes_the_geometry_as_the_other_rules_spell_it(swatches, capsys):
    """``0/D`` is 0:d for every rule (Kubelka-Munk refused it as not 0:d)."""
    code = main(["unmix", swatches["mix"], "--mix", MIX, "--baseline", "km", "--endmembers",
                 swatches["ends"], "--geometry", "0/D"])
    assert code == 0, capsys.readouterr().err


def test_help_shows_the_tints_metavar_as_typed(capsys):
    """A metavar is not %-formatted: ``10%%`` showed as typed."""
    with pytest.raises(SystemExit):
        main(["unmix", "--help"])
    out = capsys.readouterr().out
    assert "--tints T2.csv:10%,..." in out and "%%" not in out


def test_free_radii_stay_in_the_plugins_range(albedo_csv, capsys):
    """With --free-radii the radii's box was a factor 10 around --mix whatever the plugin
    accepts: a 2 um host searched up to 20 um and failed with the plugin's error about a
    radius nobody gave. The box now stays within the fittable radii, and a start outside
    them is refused."""
    mix = "kaolinite:50%:2um,hematite:50%:0.1um"
    assert main(["unmix", albedo_csv, "--mix", mix, "--free-radii", "--starts", "4"]) == 0, \
        capsys.readouterr().err
    code, err = run(["unmix", albedo_csv, "--mix", "kaolinite:50%:5um,hematite:50%:0.1um",
                     "--free-radii"], capsys)
    assert code == 2 and "the start radius of kaolinite = 5.0 um is out of range; valid range " \
                         "is [0.003, 3] um" in err, err
