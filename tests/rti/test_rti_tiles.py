"""Tiled fits on a Dask cluster (mitsuba_powder.rti.tiles), on a SYNTHETIC capture on disk.

The capture (48 x 48 px, 12 lights, float EXR, linear) is cut into 3 x 3 tiles of 16 px. A
two-worker local cluster (worker processes) is started once for the module. References: an
untiled :func:`fit_maps` under the same held gains; an uninterrupted tiled run for the
interrupted, resumed and worker-killed runs (bit for bit).
"""

from __future__ import annotations

import logging
import os
import shutil
import signal

import numpy as np
import pytest

from mitsuba_powder import rti
from mitsuba_powder.cli import main
from mitsuba_powder.rti.cluster import check_scheduler, check_workers, open_client
from mitsuba_powder.rti.maps import read_maps
from mitsuba_powder.rti.tile_files import read_meta
from mitsuba_powder.rti.tiles import TILES_FOLDER, check_tile_size, fit_maps_tiled, plan_tiles

distributed = pytest.importorskip("distributed")

SIZE, LIGHTS, TILE = 48, 12, 16
#: a short fit: one round, 8 iterations (the tiles' equality does not depend on convergence)
OPTIONS = {"rounds": 1, "max_iterations": 8}
GAIN_PIXELS = 256


@pytest.fixture(scope="module")
def capture_lp(tmp_path_factory):
    """The SYNTHETIC capture's .lp file (float EXR images, linear)."""
    folder = tmp_path_factory.mktemp("capture")
    rng = np.random.default_rng(2)
    rel = 1.0 + 0.05 * rng.standard_normal(LIGHTS)
    cap = rti.synthetic_capture(SIZE, SIZE, LIGHTS, noise=0.005, gains=rel / rel.mean(), seed=3)
    names = [f"light{k:02d}.exr" for k in range(LIGHTS)]
    rti.write_lp(folder / "dirs.lp", names, cap["directions"])
    like = rti.Capture(images=cap["images"], directions=cap["directions"], names=names,
                       encoding="linear", file_format="exr", bit_depth=32)
    rti.write_images(like, cap["images"], names, folder)
    return folder / "dirs.lp"


@pytest.fixture(scope="module")
def client():
    """A local cluster of two worker processes, one thread each."""
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True,
                                  dashboard_address=":0", silence_logs=logging.ERROR) as lc, \
            distributed.Client(lc) as cl:
        yield cl


def _tiled(capture_lp, out, client, **kwargs):
    args = {"encoding": "linear", "gain_subsample": GAIN_PIXELS, "client": client,
            "progress": False, "gains": "fit", **OPTIONS, **kwargs}
    return fit_maps_tiled(capture_lp, out, TILE, **args)


@pytest.fixture(scope="module")
def reference(capture_lp, client, tmp_path_factory):
    """An uninterrupted tiled run, gains fitted on 256 pixels."""
    return _tiled(capture_lp, tmp_path_factory.mktemp("reference"), client)


def _fields(result):
    return {"normals": result.normals, "albedo": result.albedo,
            "residual_rms": result.residual_rms,
            **{f"maps[{n}]": v for n, v in result.maps.items()}}


def _assert_identical(a, b):
    assert a.maps.keys() == b.maps.keys()
    for name, value in _fields(a).items():
        assert np.array_equal(value, _fields(b)[name], equal_nan=True), name
    assert np.array_equal(a.used, b.used) and np.array_equal(a.mask, b.mask)
    assert np.array_equal(a.gains, b.gains)


def test_plan_tiles_covers_the_image_once():
    tiles = plan_tiles((40, 33), 16)
    assert len(tiles) == 3 * 3
    cover = np.zeros((40, 33), int)
    for t in tiles:
        cover[t.row0:t.row1, t.col0:t.col1] += 1
    assert np.all(cover == 1)
    assert tiles[-1].window == (32, 40, 32, 33) and tiles[-1].name == "tile_r0002_c0002.npz"


def test_tiled_fit_equals_the_untiled_fit_under_the_same_gains(capture_lp, client, reference,
                                                                tmp_path):
    gains = reference.gains  # fitted once, on the subsample, held in both fits
    assert reference.fit_settings["tiles"]["fitted"] == 9
    assert not np.allclose(gains, 1.0)
    capture = rti.load_capture(capture_lp, encoding="linear")
    tiled = _tiled(capture_lp, tmp_path, client, gains="fixed", initial_gains=gains)
    # the free set chosen on the subsample (the gains held there) holds in every tile
    assert list(tiled.free) == tiled.fit_settings["free_choice"]["chosen"]
    # with the gains held the subsample only chooses: no maps fitted there
    stages = read_meta(tmp_path / TILES_FOLDER / "gains.npz")["stages"]
    assert stages and all(line.startswith("free set") for line in stages), stages
    untiled = rti.fit_maps(capture.images, capture.directions, gains="fixed",
                           initial_gains=gains, free=tiled.free, **OPTIONS)
    assert tiled.maps.keys() == untiled.maps.keys() and tiled.free == untiled.free
    for name, value in _fields(untiled).items():
        np.testing.assert_allclose(_fields(tiled)[name], value, rtol=0, atol=1e-4,
                                   err_msg=name)
    assert np.array_equal(tiled.used, untiled.used)
    assert np.array_equal(tiled.mask, untiled.mask)


def test_interrupted_run_resumes_the_missing_tiles_only(capture_lp, client, reference,
                                                        tmp_path):
    class Stop(Exception):
        pass

    def stop_after_three(name, done, total):
        if done == 3:
            raise Stop(name)

    with pytest.raises(Stop):
        _tiled(capture_lp, tmp_path, client, on_tile=stop_after_three)
    written = sorted(p.name for p in (tmp_path / TILES_FOLDER).iterdir())
    assert written[0] == "gains.npz" and len(written) == 4  # 3 tiles, no partial file
    assert all(n.startswith("tile_r") and n.endswith(".npz") for n in written[1:])
    resumed = _tiled(capture_lp, tmp_path, client, resume=True)
    tiles = resumed.fit_settings["tiles"]
    assert (tiles["fitted"], tiles["resumed"]) == (6, 3)
    _assert_identical(resumed, reference)
    assert resumed.fit_settings["free_choice"] == reference.fit_settings["free_choice"]
    again = _tiled(capture_lp, tmp_path, client, resume=True)
    assert again.fit_settings["tiles"]["fitted"] == 0
    _assert_identical(again, reference)


def test_a_killed_worker_loses_at_most_its_tile(capture_lp, client, reference, tmp_path):
    killed = []

    def kill_a_busy_worker(name, done, total):
        if killed:
            return
        busy = [a for a, keys in client.processing().items() if keys]
        pids = client.run(os.getpid)
        victim = (busy or list(pids))[0]
        os.kill(pids[victim], signal.SIGKILL)
        killed.append(victim)

    result = _tiled(capture_lp, tmp_path, client, on_tile=kill_a_busy_worker)
    assert killed and result.fit_settings["tiles"]["fitted"] == 9
    _assert_identical(result, reference)
    client.wait_for_workers(2, timeout=60)  # the nanny restarts the worker


def test_the_free_set_is_chosen_once_on_the_gains_subsample(capture_lp, client, reference,
                                                          tmp_path):
    """Not given, the free set is chosen by the untiled fit's cross-validation on the gains'
    subsample (recorded and printed), and every tile fits it; given, nothing is chosen."""
    choice = reference.fit_settings["free_choice"]
    assert choice["chosen"] == list(reference.free)
    assert [c["free"] for c in choice["candidates"]] == [
        ["albedo"], ["albedo", "amplitude_surface", "correlation_length"]]
    assert all(c["cv_rms"] > 0 for c in choice["candidates"])
    assert choice["pixels"] <= GAIN_PIXELS
    lines: list[str] = []
    given = _tiled(capture_lp, tmp_path, client, free=["albedo"], log=lines.append)
    assert given.free == ["albedo"] and given.fit_settings.get("free_choice") is None
    assert not any(line.startswith("free set") for line in lines)


def test_the_full_scale_is_the_files_unless_given(capture_lp, client, tmp_path):
    """The cross-validations' full scale is the files' (EXR: none) unless the caller gives
    one, which is kept (not replaced by the files')."""
    args = {"gains": "fixed", "exposure": 1.0, "free": ["albedo"]}
    files = _tiled(capture_lp, tmp_path / "files", client, **args)
    assert files.fit_settings["full_scale"] is None
    given = _tiled(capture_lp, tmp_path / "given", client, full_scale=0.5, **args)
    assert given.fit_settings["full_scale"] == 0.5


def test_resume_refuses_tiles_of_other_settings(capture_lp, client, reference, tmp_path):
    out = tmp_path / "run"
    shutil.copytree(reference_dir(reference), out)
    with pytest.raises(ValueError, match="gains.npz was written with other settings"):
        _tiled(capture_lp, out, client, resume=True, max_iterations=7)
    # the free set given where it was chosen: the gains (fitted with the choice) are refused
    with pytest.raises(ValueError, match="gains.npz was written with other settings"):
        _tiled(capture_lp, out, client, resume=True, free=list(reference.free))
    # the same gains, another tile size: the first tile file is refused
    with pytest.raises(ValueError, match="tile_r0000_c0000.npz was written with other"):
        fit_maps_tiled(capture_lp, out, 24, encoding="linear", gain_subsample=GAIN_PIXELS,
                       client=client, progress=False, resume=True, gains="fit", **OPTIONS)


def reference_dir(result):
    """The output folder of a tiled run (from its tile hash's record)."""
    return result.fit_settings["tiles"]["out"]


@pytest.mark.parametrize(("call", "message"), [
    (lambda: check_tile_size(4), r"tile_size = 4 is out of range; valid range is \[8, inf\]"),
    (lambda: check_tile_size(16.5), "tile_size = 16.5 is not a whole number"),
    (lambda: check_tile_size("big"), "tile_size = 'big' is not a number"),
    (lambda: check_workers(0), r"workers = 0 is out of range; valid range is \[1, inf\]"),
    (lambda: check_scheduler("localhost:8786"), "expected tcp://HOST:PORT"),
    (lambda: check_scheduler("tcp://host:99999"), "port in 1-65535"),
])
def test_bad_values_are_named(call, message):
    with pytest.raises(ValueError, match=message):
        call()


def test_a_scheduler_that_does_not_answer_is_named():
    import socket

    with socket.socket() as s:  # a free port: nothing listens there
        s.bind(("127.0.0.1", 0))
        port = s.getsockname()[1]
    with pytest.raises(ValueError, match=rf"scheduler = 'tcp://127.0.0.1:{port}': no Dask "
                                         "scheduler answered within 1 s"):
        with open_client(scheduler=f"tcp://127.0.0.1:{port}", timeout=1.0):
            pass


def test_cli_tile_options_need_a_tile_size(capture_lp, tmp_path, capsys):
    assert main(["fit-maps", str(capture_lp), "--out", str(tmp_path), "--resume"]) == 2
    assert "--resume applies to tiled fits only" in capsys.readouterr().err


@pytest.mark.parametrize(("extra", "message"), [
    (["--light-distance", "3"], "--light-distance = 3.0 is not supported by tiled fits"),
    (["--light-distance", "fit"], "--light-distance = 'fit' is not supported by tiled fits"),
    (["--pixel-size", "0.1"], "--pixel-size 0.1 is not supported with --tile-size"),
    (["--gain-model", "smooth"], "--gain-model smooth is not supported with --tile-size"),
])
def test_cli_tiled_fits_refuse_near_field_options(capture_lp, tmp_path, capsys, extra,
                                                   message):
    """A tile is fitted as an image of its own: near-field lights, which depend on the
    pixels' positions in the whole image, are refused before anything starts (the light
    distance by the tiled fit itself: tests/rti/test_rti_options.py)."""
    out = tmp_path / "maps"
    assert main(["fit-maps", str(capture_lp), "--out", str(out), "--tile-size", "16",
                 *extra]) == 2
    assert message in capsys.readouterr().err
    assert not out.exists()


def test_api_tiled_fit_refuses_lights_at_a_distance(capture_lp, tmp_path):
    with pytest.raises(ValueError, match="light_distance = 3.0 is not supported by tiled "
                                         "fits; valid value: inf"):
        fit_maps_tiled(capture_lp, tmp_path / "maps", 16, light_distance=3.0)
    assert not (tmp_path / "maps").exists()


def test_api_tiled_fit_refuses_the_relief(capture_lp, tmp_path):
    with pytest.raises(ValueError, match="shadows = 'relief' is not supported with tiles"):
        fit_maps_tiled(capture_lp, tmp_path / "maps", 16, shadows="relief")
    assert not (tmp_path / "maps").exists()


def test_cli_tiled_fit_writes_maps_and_resumes(capture_lp, tmp_path, capsys):
    out = tmp_path / "maps"
    args = ["fit-maps", str(capture_lp), "--out", str(out), "--encoding", "linear",
            "--tile-size", "24", "--workers", "1", "--gain-pixels", "128", "--rounds", "1",
            "--iterations", "8"]
    assert main(args) == 0
    assert "tiles: 4 fitted, 0 resumed" in capsys.readouterr().out
    assert (out / "fit.json").is_file() and (out / "normal.exr").is_file()
    assert len(list((out / TILES_FOLDER).glob("tile_*.npz"))) == 4
    result, info = read_maps(out)
    assert info["fit"]["tiles"]["tile_size"] == 24 and np.all(result.mask)
    assert main(args + ["--resume"]) == 0
    assert "tiles: 0 fitted, 4 resumed" in capsys.readouterr().out
