"""Output folders are written whole or not at all (issue 33, case 4): an interrupted re-run
leaves the previous result as it was; a result interrupted while its files are moved into
place is refused by its readers; Ctrl-C prints one line and exits 130; ``--out`` is checked
before the work starts. The captures are SYNTHETIC."""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest

from helpers import png_capture
from mitsuba_powder.cli import INTERRUPTED, main
from mitsuba_powder.outputs import INCOMPLETE, STAGING, OutputError, output_path, staged_output

FAST = ["--rounds", "1", "--iterations", "4"]


def snapshot(root: Path) -> dict[str, str]:
    return {str(p.relative_to(root)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(root.rglob("*")) if p.is_file()}


@pytest.fixture(scope="module")
def capture(tmp_path_factory) -> Path:
    """A SYNTHETIC 8 x 8 px capture under 12 lights, 8-bit PNG."""
    return png_capture(tmp_path_factory, seed=5)


def test_an_interrupted_rerun_of_fit_maps_leaves_the_old_result_whole(tmp_path, capture,
                                                                      capsys, monkeypatch):
    """Re-running fit-maps with other settings into a finished folder and interrupting it
    after the new maps are written (while scene.xml is being made): the folder is the old
    result, byte for byte, and relight uses it; one line on stderr, exit 130."""
    out = tmp_path / "maps"
    assert main(["fit-maps", str(capture / "dirs.lp"), "--out", str(out), *FAST]) == 0
    old = snapshot(out)

    from mitsuba_powder.rti import maps as maps_module

    def interrupted(*args, **kwargs):
        assert (out / STAGING / "normal.exr").is_file()  # the new maps were written
        raise KeyboardInterrupt

    monkeypatch.setattr(maps_module, "scene_xml", interrupted)
    capsys.readouterr()
    assert main(["fit-maps", str(capture / "dirs.lp"), "--out", str(out), *FAST,
                 "--free", "albedo"]) == INTERRUPTED
    err = capsys.readouterr().err
    assert err == f"mitsuba-powder: interrupted; {out} was left as it was\n"
    assert snapshot(out) == old and not (out / STAGING).exists()
    monkeypatch.undo()
    assert main(["relight", str(out), "--lp", str(capture / "dirs.lp"), "--out",
                 str(tmp_path / "relit")]) == 0


def test_a_result_interrupted_while_moved_into_place_is_refused(tmp_path, capture, capsys,
                                                                 monkeypatch):
    """Interrupted while the finished files are moved into the folder: relight refuses the
    folder (naming it); a new run of the command makes it whole again."""
    out = tmp_path / "maps"
    lp = str(capture / "dirs.lp")
    assert main(["fit-maps", lp, "--out", str(out), *FAST]) == 0
    real_replace, moved = os.replace, []

    def replace(src, dst):
        if moved:
            raise KeyboardInterrupt
        moved.append(dst)
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", replace)
    assert main(["fit-maps", lp, "--out", str(out), *FAST, "--free", "albedo"]) == INTERRUPTED
    monkeypatch.undo()
    assert (out / INCOMPLETE.format(command="fit-maps")).exists()
    capsys.readouterr()
    assert main(["relight", str(out), "--lp", lp, "--out", str(tmp_path / "relit")]) == 2
    err = capsys.readouterr().err
    assert f"{out} is incomplete: a run of fit-maps" in err and not (tmp_path / "relit").exists()
    assert main(["fit-maps", lp, "--out", str(out), *FAST]) == 0
    assert not (out / INCOMPLETE.format(command="fit-maps")).exists()
    assert main(["relight", str(out), "--lp", lp, "--out", str(tmp_path / "relit")]) == 0


def test_a_rerun_removes_the_files_of_the_previous_result_it_does_not_write(tmp_path):
    """A command's previous result (its manifest) is replaced whole: a file it wrote last time
    and not this time goes; files it never wrote (the user's, another command's) stay."""
    out = tmp_path / "o"
    out.mkdir()
    (out / "mine.txt").write_text("the user's")
    with staged_output(out, command="demo"):
        output_path(out, "a.txt").write_text("1")
        output_path(out, "b.txt").write_text("1")
        assert not (out / "a.txt").exists()  # staged until the block ends
    with staged_output(out, command="other"):
        output_path(out, "c.txt").write_text("other")
    with staged_output(out, command="demo"):
        output_path(out, "a.txt").write_text("2")
    names = sorted(p.name for p in out.iterdir() if not p.name.startswith("."))
    assert names == ["a.txt", "c.txt", "mine.txt"] and (out / "a.txt").read_text() == "2"


@pytest.fixture
def gonio_csv(tmp_path) -> Path:
    """Ten SYNTHETIC rows (made-up values): enough for a fit to start."""
    rows = ["30,0,0,550,0.4", "30,20,0,550,0.42", "30,-20,0,550,0.38", "30,40,0,550,0.45",
            "30,-40,0,550,0.35", "30,60,0,550,0.5", "30,-60,0,550,0.33", "0,30,0,550,0.4",
            "60,0,0,550,0.38", "60,30,0,550,0.42"]
    path = tmp_path / "d.csv"
    path.write_text("theta_i,theta_o,phi,wavelength,brf\n" + "\n".join(rows) + "\n")
    return path


@pytest.mark.parametrize("command", ["fit", "compare-models", "render-gonio", "fit-maps"])
def test_out_is_checked_before_the_work_starts(tmp_path, capture, gonio_csv, capsys, command):
    """--out that is a file, or lies under a file: a clean error before the command does
    anything (it used to be found after the whole computation)."""
    args = {"fit": ["fit", str(gonio_csv)], "compare-models": ["compare-models", str(gonio_csv)],
            "render-gonio": ["render-gonio", "--data", str(gonio_csv)],
            "fit-maps": ["fit-maps", str(capture / "dirs.lp")]}[command]
    a_file = tmp_path / "taken"
    a_file.write_text("x")
    for out, fragment in ((a_file, "is a file"), (a_file / "sub", "cannot create the folder")):
        assert main([*args, "--out", str(out)]) == 2
        captured = capsys.readouterr()
        assert captured.out == ""  # nothing ran: the command prints as soon as it starts
        assert f"--out {out}" in captured.err and fragment in captured.err
    assert a_file.read_text() == "x"


def test_an_output_folder_that_is_an_input_is_refused_before_anything(tmp_path):
    from mitsuba_powder.outputs import guarding_inputs, note_input

    with guarding_inputs():
        note_input(tmp_path)
        with pytest.raises(OutputError, match="is an input file"), staged_output(tmp_path):
            pass
    assert not (tmp_path / STAGING).exists()


def test_a_failed_command_leaves_no_folder_it_made(tmp_path, gonio_csv, capsys):
    out = tmp_path / "new"
    assert main(["fit", str(gonio_csv), "--set", "albedo=2", "--free", "g",
                 "--out", str(out)]) == 2
    assert not out.exists()
