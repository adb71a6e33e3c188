"""The supported range's other end: the documented ``--no-build-isolation`` path builds the
plugin against mitsuba 3.8.0 (drjit 1.3.1) in a fresh environment, the build records and pins
that release, the value tests pass there, and the values equal this build's (slow: a fresh
environment and a build of two variants)."""

from __future__ import annotations

import sys
from importlib.metadata import version

import pytest

from helpers import ROOT, max_relative_difference, new_venv, powder_values, run

#: the releases of the supported range other than the one build-system.requires pins
OTHER_RELEASES = [("3.8.0", "1.3.1")]
#: what the value tests and the package import need, besides mitsuba
TEST_DEPENDENCIES = ["numpy>=1.22", "matplotlib>=3.5", "colour-science>=0.4", "scipy>=1.10",
                     "OpenEXR>=3.3", "dask[distributed]>=2024.1", "tqdm>=4.60", "pytest>=7",
                     "miepython>=3.0"]
BUILD_DEPENDENCIES = ["scikit-build-core>=0.10", "nanobind==2.14.0", "cmake>=3.18", "ninja"]


@pytest.mark.slow
@pytest.mark.parametrize("mitsuba, drjit", OTHER_RELEASES)
def test_builds_against_another_release_and_passes_the_value_tests(tmp_path, mitsuba, drjit):
    python = new_venv(tmp_path / "venv")
    pip = [python, "-m", "pip", "install", "--only-binary=:all:"]
    run([*pip, f"mitsuba=={mitsuba}", f"drjit=={drjit}", *BUILD_DEPENDENCIES,
         *TEST_DEPENDENCIES])
    # docs/install.md, "Another mitsuba release" (a build folder of its own and two variants,
    # to keep the test short; the source's build/ is left alone)
    run([python, "-m", "pip", "install", "--no-build-isolation", "--no-deps",
         f"-Cbuild-dir={tmp_path / 'build'}",
         "-Ccmake.define.POWDER_VARIANTS=scalar_rgb,llvm_ad_rgb", ROOT])
    shown = run([python, "-m", "mitsuba_powder.cli", "--version"], cwd=tmp_path).stdout
    assert f"built for mitsuba {mitsuba}, drjit {drjit}" in shown
    requires = run([python, "-c", "import importlib.metadata as m; "
                                  "print(m.requires('mitsuba-powder'))"]).stdout
    assert f"mitsuba=={mitsuba}" in requires and f"drjit=={drjit}" in requires
    tests = run([python, "-m", "pytest", "-q", "-p", "no:cacheprovider",
                 ROOT / "tests" / "plugin" / "test_values.py",
                 ROOT / "tests" / "package" / "test_versions.py"], cwd=ROOT).stdout
    assert " passed" in tests and " failed" not in tests, tests[-2000:]
    assert version("mitsuba") != mitsuba  # the comparison is between two releases
    for variant in ("scalar_rgb", "llvm_ad_rgb"):
        ours = powder_values(sys.executable, variant)
        theirs = powder_values(python, variant)
        assert theirs["mitsuba"] == mitsuba
        assert max_relative_difference(ours, theirs) <= 1e-5, variant
