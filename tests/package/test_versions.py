"""The package's version has one source, the build records the mitsuba and drjit it compiled
against, pins them, and refuses to import into others with a message that says what to do."""

from __future__ import annotations

import importlib.util
import re
import subprocess
import sys
from importlib.metadata import PackageNotFoundError, requires, version
from pathlib import Path

import drjit as dr
import mitsuba as mi
import pytest

import mitsuba_powder
from mitsuba_powder._versions import built_for, check_versions

ROOT = Path(__file__).resolve().parents[2]
PYPROJECT = (ROOT / "pyproject.toml").read_text()  # (tomllib: Python 3.11+ only)


def other(release: str) -> str:
    """A release that is not ``release`` (same form: one more patch)."""
    major, minor, patch = release.split(".")
    return f"{major}.{minor}.{int(patch) + 1}"


def import_with(module: str, fake: str) -> subprocess.CompletedProcess:
    """``import mitsuba_powder`` in a fresh process where ``module.__version__`` is ``fake``
    (set after ``import mitsuba``, which checks its own drjit)."""
    code = (f"import mitsuba, drjit\n{module}.__version__ = {fake!r}\n"
            "import mitsuba_powder\n")
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          timeout=300)


@pytest.mark.parametrize("module", ["mitsuba", "drjit"])
def test_import_refuses_another_release(module):
    built = built_for()
    fake = other(built[module])
    proc = import_with(module, fake)
    assert proc.returncode == 1
    last = proc.stderr.strip().splitlines()[-1]
    assert last.startswith("ImportError: mitsuba_powder ")
    found = {"mitsuba": mi.__version__, "drjit": dr.__version__, module: fake}
    assert (f"built for mitsuba {built['mitsuba']} and drjit {built['drjit']}, but this "
            f"environment has mitsuba {found['mitsuba']} and drjit {found['drjit']}") in last
    assert "pip install --no-build-isolation --no-deps --force-reinstall" in last
    assert "docs/install.md" in last
    assert f"pip install mitsuba=={built['mitsuba']} drjit=={built['drjit']}" in last


def test_check_versions_accepts_only_the_built_releases():
    built = built_for()
    check_versions(built["mitsuba"], built["drjit"])
    with pytest.raises(ImportError, match="Rebuild it against the installed ones"):
        check_versions(built["mitsuba"], other(built["drjit"]))


def test_built_for_what_is_imported_and_pinned():
    built = built_for()
    assert (built["mitsuba"], built["drjit"]) == (mi.__version__, dr.__version__)
    assert built["mitsuba-powder"] == mitsuba_powder.__version__ == version("mitsuba-powder")
    deps = requires("mitsuba-powder")
    assert f"mitsuba=={built['mitsuba']}" in deps and f"drjit=={built['drjit']}" in deps


def test_version_flag_prints_the_three_versions():
    proc = subprocess.run([sys.executable, "-m", "mitsuba_powder.cli", "--version"],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr
    built = built_for()
    assert proc.stdout.strip() == (f"mitsuba-powder {built['mitsuba-powder']} (built for "
                                   f"mitsuba {built['mitsuba']}, drjit {built['drjit']})")


def test_one_version_source():
    """pyproject.toml's version is the package's, CITATION.cff's and the changelog's first."""
    (pyproject_version,) = re.findall(r'^version = "([^"]+)"$', PYPROJECT, re.MULTILINE)
    assert pyproject_version == mitsuba_powder.__version__
    cff = (ROOT / "CITATION.cff").read_text()
    assert re.search(r'^version: "([^"]+)"$', cff, re.MULTILINE).group(1) == pyproject_version
    assert "doi: 10.1364/JOSAA.487498" in cff
    first = re.search(r"^## \[([^\]]+)\]", (ROOT / "CHANGELOG.md").read_text(), re.MULTILINE)
    assert first.group(1) == pyproject_version
    assert "BSD 3-Clause" in (ROOT / "LICENSE").read_text()
    assert 'license = { text = "BSD-3-Clause" }' in PYPROJECT


def _pins_module():
    spec = importlib.util.spec_from_file_location("powder_pins", ROOT / "tools" / "powder_pins.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_pins_provider(monkeypatch):
    """The metadata provider pins the environment's mitsuba and drjit, keeps the rest, and
    says what to do when mitsuba is missing."""
    pins = _pins_module()
    settings = {"requires": ["numpy>=1.22", "tqdm>=4.60"]}
    assert pins.dynamic_metadata("dependencies", settings) == [
        f"mitsuba=={version('mitsuba')}", f"drjit=={version('drjit')}", "numpy>=1.22",
        "tqdm>=4.60"]
    with pytest.raises(RuntimeError, match="not 'version'"):
        pins.dynamic_metadata("version", settings)

    def missing(name):
        raise PackageNotFoundError(name)

    monkeypatch.setattr(pins, "version", missing)
    with pytest.raises(RuntimeError, match="has none: install mitsuba.*--no-build-isolation"):
        pins.dynamic_metadata("dependencies", settings)


def test_supported_range_is_stated_once_and_holds_the_pinned_release():
    """CMakeLists.txt's range contains build-system.requires' mitsuba; docs/install.md and
    the changelog state the releases tested."""
    cmake = (ROOT / "CMakeLists.txt").read_text()
    low = re.search(r"set\(POWDER_MITSUBA_MIN ([\d.]+)\)", cmake).group(1)
    below = re.search(r"set\(POWDER_MITSUBA_BELOW ([\d.]+)\)", cmake).group(1)
    build_system = PYPROJECT[PYPROJECT.index("[build-system]"):PYPROJECT.index("[project]")]
    (pinned,) = re.findall(r'"mitsuba==([\d.]+)"', build_system)
    as_tuple = lambda v: tuple(int(p) for p in v.split("."))  # noqa: E731
    assert as_tuple(low) <= as_tuple(pinned) < as_tuple(below)
    docs = (ROOT / "docs" / "install.md").read_text()
    assert f"mitsuba >= {low}, < {below}" in docs
