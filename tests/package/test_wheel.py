"""tools/build-wheel: one manylinux wheel, without the libraries the mitsuba and drjit wheels
provide, that installs into a fresh virtual environment with no compiler, CMake or build tool
reachable, runs the README example and gives the source build's values (slow: the wheel is
built from scratch, all variants)."""

from __future__ import annotations

import json
import shutil
import sys
import zipfile

import mitsuba as mi
import numpy as np
import pytest

from helpers import (
    ROOT,
    clean_env,
    max_relative_difference,
    new_venv,
    powder_values,
    run,
    use_variant,
)

pytestmark = pytest.mark.skipif(sys.platform != "linux", reason="manylinux wheels: Linux only")


def read_exr(path) -> np.ndarray:
    use_variant("scalar_rgb")
    return np.array(mi.Bitmap(str(path)), dtype=np.float64)


@pytest.mark.slow
def test_wheel_installs_and_renders_without_a_compiler(tmp_path):
    dist = tmp_path / "dist"
    built = run([sys.executable, ROOT / "tools" / "build-wheel", dist])
    wheels = list(dist.iterdir())
    assert len(wheels) == 1 and wheels[0].suffix == ".whl", wheels
    wheel = wheels[0]
    assert "-manylinux_2_" in wheel.name, wheel.name
    # auditwheel show: the symbol versions allow the tag; the only libraries from outside the
    # wheel and the manylinux set are the four the mitsuba and drjit wheels provide (show has
    # no --exclude, so its overall verdict names them as missing: docs/install.md)
    shown = json.loads(run([sys.executable, "-m", "auditwheel", "show", "--json", wheel]).stdout)
    assert shown["sym_tag"] in wheel.name and shown["sym_tag"].startswith("manylinux_2_")
    assert set(shown["external_libs"]) == {"libmitsuba.so", "libdrjit-core.so",
                                           "libdrjit-extra.so", "libnanothread.so"}
    assert wheel.name.split("-")[-1].removesuffix(".whl") in built.stdout
    names = zipfile.ZipFile(wheel).namelist()
    assert "mitsuba_powder/plugins/powder.so" in names
    assert not [n for n in names if "libmitsuba" in n or "libdrjit" in n or "nanothread" in n]

    python = new_venv(tmp_path / "venv")
    env = clean_env(tmp_path / "venv")
    for tool in ("cc", "gcc", "c++", "g++", "clang", "cmake", "ninja", "make"):
        assert shutil.which(tool, path=env["PATH"]) is None, tool
    run([python, "-m", "pip", "install", "--only-binary=:all:", wheel], env=env,
        cwd=tmp_path)  # nothing may be compiled, this package or its dependencies

    version = run([tmp_path / "venv" / "bin" / "mitsuba-powder", "--version"], env=env)
    assert "built for mitsuba 3.9.1, drjit 1.5.0" in version.stdout
    # the README example, then the same scene at fewer samples in the wheel and the source
    # build, compared pixel by pixel
    scene = ROOT / "scenes" / "powder_patch.xml"
    run([tmp_path / "venv" / "bin" / "mitsuba-powder", "render", scene, "-o",
         tmp_path / "out" / "powder_patch.png"], env=env, cwd=tmp_path)
    assert (tmp_path / "out" / "powder_patch.png").stat().st_size > 1000
    images = {}
    for who, command in (("wheel", [tmp_path / "venv" / "bin" / "mitsuba-powder"]),
                         ("source", [sys.executable, "-m", "mitsuba_powder.cli"])):
        out = tmp_path / f"{who}.exr"
        run([*command, "render", scene, "-o", out, "-D", "spp=8", "-D", "res_x=96", "-D",
             "res_y=48"], env=env if who == "wheel" else None, cwd=tmp_path)
        images[who] = read_exr(out)
    assert images["wheel"].mean() > 0.05
    np.testing.assert_allclose(images["wheel"], images["source"], rtol=1e-5, atol=1e-6)
    for variant in ("scalar_rgb", "llvm_ad_rgb"):
        wheel_values = powder_values(python, variant, env=env)
        source_values = powder_values(sys.executable, variant)
        assert max_relative_difference(wheel_values, source_values) <= 1e-5, variant
