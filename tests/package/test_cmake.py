"""CMakeLists.txt reads what it builds against from the wheels: the mitsuba and drjit releases
(refusing those outside the supported range), the variants, features and C++ string ABI of
libmitsuba, and the target's vector flags. Configured against fake wheel folders (headers and
library files with just what CMake reads), nothing compiled."""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BIN = Path(sys.executable).parent
CMAKE = shutil.which("cmake", path=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
NINJA = shutil.which("ninja", path=f"{BIN}{os.pathsep}{os.environ.get('PATH', '')}")
pytestmark = pytest.mark.skipif(CMAKE is None, reason="cmake is not installed (test extra)")

#: libmitsuba's Object::parameters_changed, mangled with each libstdc++ string ABI
SYMBOL = {"cxx11": "_ZN7mitsuba6Object18parameters_changedERKSt6vectorINSt7__cxx1112basic_"
                   "stringIcSt11char_traitsIcESaIcEEESaIS7_EE",
          "old": "_ZN7mitsuba6Object18parameters_changedERKSt6vectorISsSaISsEE"}


def fake_wheels(tmp: Path, mitsuba: str, drjit: str, abi: str = "cxx11",
                variants=("scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb")) -> dict[str, Path]:
    """mitsuba/, drjit/ and nanobind/ folders with the files CMakeLists.txt reads."""
    dirs = {name: tmp / name for name in ("mitsuba", "drjit", "nanobind")}
    files = {
        "mitsuba/include/mitsuba/mitsuba.h": "".join(
            f"#define MI_VERSION_{k} {v}\n" for k, v in zip(("MAJOR", "MINOR", "PATCH"),
                                                            mitsuba.split("."))),
        "mitsuba/config.py": f"MI_VARIANTS = {list(variants)!r}\n",
        "mitsuba/libmitsuba.so": f"\x7fELF\0\0{SYMBOL[abi]}\0other\0",
        "mitsuba/libembree3.so": "",
        "drjit/include/drjit/array.h": "",
        "drjit/include/drjit/fwd.h": "".join(
            f"#define DRJIT_VERSION_{k} {v}\n" for k, v in zip(("MAJOR", "MINOR", "PATCH"),
                                                               drjit.split("."))),
        **{f"drjit/lib{n}.so": "" for n in ("drjit-core", "drjit-extra", "nanothread")},
        "nanobind/include/nanobind/nanobind.h": "",
        "nanobind/ext/robin_map/include/tsl/robin_map.h": "",
    }
    for rel, text in files.items():
        (tmp / rel).parent.mkdir(parents=True, exist_ok=True)
        (tmp / rel).write_text(text)
    return dirs


def configure(tmp: Path, dirs: dict[str, Path], *extra: str) -> subprocess.CompletedProcess:
    """``cmake -S <repo> -B tmp/build`` against ``dirs`` (plugin only: no Python headers)."""
    cmd = [CMAKE, "-S", ROOT, "-B", tmp / "build", f"-DMI_DIR={dirs['mitsuba']}",
           f"-DDRJIT_DIR={dirs['drjit']}", f"-DNANOBIND_DIR={dirs['nanobind']}",
           "-DPOWDER_PYTHON_MODULE=OFF", f"-DPython_EXECUTABLE={sys.executable}", *extra]
    if NINJA:
        cmd += ["-G", "Ninja", f"-DCMAKE_MAKE_PROGRAM={NINJA}"]
    return subprocess.run([str(c) for c in cmd], capture_output=True, text=True, timeout=300)


def flags(tmp: Path) -> str:
    """The generated build rules (compile flags and definitions of every target)."""
    build = tmp / "build"
    return "".join(p.read_text() for p in [*build.glob("build.ninja"),
                                           *build.glob("CMakeFiles/*.dir/flags.make")])


def test_records_the_releases_and_reads_the_wheel(tmp_path):
    proc = configure(tmp_path, fake_wheels(tmp_path, "3.8.0", "1.3.1"))
    assert proc.returncode == 0, proc.stderr
    info = (tmp_path / "build" / "generated" / "_build_info.py").read_text()
    assert 'MITSUBA_VERSION = "3.8.0"' in info and 'DRJIT_VERSION = "1.3.1"' in info
    assert "powder variants: scalar_rgb;llvm_ad_rgb;cuda_ad_rgb" in proc.stdout
    rules = flags(tmp_path)
    for define in ("MI_ENABLE_LLVM=1", "MI_ENABLE_CUDA=1", "MI_ENABLE_EMBREE=1",
                   "_GLIBCXX_USE_CXX11_ABI=1"):
        assert define in rules
    assert "MI_ENABLE_METAL" not in rules
    assert "-mavx2" in rules  # this machine is x86-64, as is the target here


def test_variants_features_and_abi_follow_the_wheel(tmp_path):
    """A wheel without CUDA variants and with the old string ABI (as aarch64's): no CUDA
    define, the old ABI, and only the wheel's variants by default."""
    dirs = fake_wheels(tmp_path, "3.9.1", "1.5.0", abi="old", variants=("scalar_rgb",))
    proc = configure(tmp_path, dirs)
    assert proc.returncode == 0, proc.stderr
    assert "powder variants: scalar_rgb\n" in proc.stdout
    rules = flags(tmp_path)
    assert "_GLIBCXX_USE_CXX11_ABI=0" in rules
    assert "MI_ENABLE_CUDA" not in rules and "MI_ENABLE_LLVM" not in rules
    asked = configure(tmp_path, dirs, "-DPOWDER_VARIANTS=llvm_ad_rgb")
    assert asked.returncode != 0
    assert 'the mitsuba wheel has no variant "llvm_ad_rgb"' in asked.stderr


def test_arch_flags_follow_the_target(tmp_path):
    """Configured for an aarch64 target (this machine's compiler stands in: nothing is
    compiled), no x86 flag is used."""
    proc = configure(tmp_path, fake_wheels(tmp_path, "3.9.1", "1.5.0"),
                     "-DCMAKE_SYSTEM_NAME=Linux", "-DCMAKE_SYSTEM_PROCESSOR=aarch64")
    assert proc.returncode == 0, proc.stderr
    assert "Linux-aarch64" in proc.stdout
    rules = flags(tmp_path)
    assert "-mavx" not in rules and "-mfma" not in rules and "powder_scalar_rgb" in rules


@pytest.mark.parametrize("mitsuba, drjit", [("3.7.1", "1.2.0"), ("3.10.0", "1.6.0")])
def test_refuses_releases_outside_the_supported_range(tmp_path, mitsuba, drjit):
    dirs = fake_wheels(tmp_path, mitsuba, drjit)
    proc = configure(tmp_path, dirs)
    assert proc.returncode != 0
    text = " ".join(proc.stderr.split())
    assert f"mitsuba {mitsuba} is outside the supported range >= 3.8.0, < 3.10" in text
    assert "-DPOWDER_ANY_MITSUBA=ON" in text
    anyway = configure(tmp_path, dirs, "-DPOWDER_ANY_MITSUBA=ON")
    assert anyway.returncode == 0, anyway.stderr
    assert "building anyway" in " ".join(anyway.stderr.split())
