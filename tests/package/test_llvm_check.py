"""import mitsuba_powder detects an LLVM that would abort the process, and says what to do."""

from __future__ import annotations

import glob
import os
import subprocess
import sys

import pytest

import mitsuba_powder

BROKEN = sorted(glob.glob("/usr/lib/*/libLLVM-15.so*") + glob.glob("/usr/lib/libLLVM-15.so*"))


def run(code: str, libllvm: str) -> subprocess.CompletedProcess:
    env = dict(os.environ, DRJIT_LIBLLVM_PATH=libllvm)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True,
                          env=env, timeout=300)


def test_current_llvm_is_usable():
    status = mitsuba_powder.check_llvm()
    assert status.usable, status.message
    assert status.version[0] >= 1


@pytest.mark.skipif(not BROKEN, reason="Debian's libLLVM 15 is not installed here")
def test_llvm15_is_reported_instead_of_aborting():
    code = ("import mitsuba as mi\n"
            "mi.set_variant('llvm_ad_rgb')\n"
            "import mitsuba_powder\n")
    proc = run(code, BROKEN[0])
    assert proc.returncode == 1, proc.stderr  # a Python exception, not an abort (-6)
    assert "RuntimeError" in proc.stderr
    assert "libLLVM 15" in proc.stderr and "libllvm19" in proc.stderr


@pytest.mark.skipif(not BROKEN, reason="Debian's libLLVM 15 is not installed here")
def test_llvm15_only_warns_for_scalar_variants():
    code = ("import warnings, mitsuba as mi\n"
            "mi.set_variant('scalar_rgb')\n"
            "with warnings.catch_warnings(record=True) as w:\n"
            "    warnings.simplefilter('always')\n"
            "    import mitsuba_powder\n"
            "print('WARN', [str(x.message) for x in w])\n"
            "print(mi.load_dict({'type': 'powder', 'albedo': 0.5}).class_name())\n")
    proc = run(code, BROKEN[0])
    assert proc.returncode == 0, proc.stderr
    assert "llvm_* variants are unusable" in proc.stdout and "Powder" in proc.stdout


def test_missing_llvm_is_reported():
    code = ("import mitsuba_powder\n"
            "s = mitsuba_powder.check_llvm()\n"
            "print(s.usable, s.version, s.message)\n")
    proc = run(code, "/nonexistent/libLLVM.so")
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.startswith("False (-1, -1, -1)") and "no libLLVM" in proc.stdout
