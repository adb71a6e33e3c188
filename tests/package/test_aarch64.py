"""tools/check-aarch64: the plugin cross-compiled for Linux aarch64 gives the x86-64 build's
values under emulation, in scalar_rgb and llvm_ad_rgb (slow: an arm64 root, the aarch64
wheels and two builds; skipped where the host cannot run it: x86-64 Linux as root with
g++-aarch64-linux-gnu, qemu-user-static and debootstrap)."""

from __future__ import annotations

import json
import os
import shutil
import sys

import pytest

from helpers import ROOT, load_script, run

CHECK = load_script("check-aarch64")


def test_compare_counts_values_out_of_tolerance():
    """The comparison the check relies on: float32 rounding passes, a larger change fails."""
    x86 = {"variant": "scalar_rgb", "powders": {"p": {"eval": [0.5, 1.0, 0.0, 2.0]}}}
    arm = {"variant": "scalar_rgb", "powders": {"p": {"eval": [0.5 + 3e-8, 1.0, 5e-8, 2.0]}}}
    (row,) = CHECK.compare(x86, arm)
    assert row["out_of_tolerance"] == 0 and row["n"] == 4
    arm["powders"]["p"]["eval"][3] = 2.0 * (1 + 3e-5)
    (row,) = CHECK.compare(x86, arm)
    assert row["out_of_tolerance"] == 1 and row["max_abs"] == pytest.approx(6e-5, rel=1e-3)
    arm["powders"]["p"]["eval"].pop()
    assert CHECK.compare(x86, arm)[0]["out_of_tolerance"] >= 1  # a missing value fails too


def _cannot_run() -> str:
    if sys.platform != "linux" or os.uname().machine != "x86_64":
        return "compares with x86-64: needs an x86-64 Linux host"
    if os.geteuid() != 0:
        return "debootstrap needs root"
    missing = [t for t in CHECK.TOOLS if shutil.which(t) is None]
    return (f"missing {', '.join(missing)}: apt-get install -y "
            f"{' '.join(sorted({CHECK.TOOLS[t] for t in missing}))}") if missing else ""


@pytest.mark.slow
@pytest.mark.skipif(bool(_cannot_run()), reason=_cannot_run() or "runs")
def test_aarch64_values_equal_the_x86_64_build(tmp_path):
    proc = run([sys.executable, ROOT / "tools" / "check-aarch64", tmp_path / "work"])
    report = json.loads((tmp_path / "work" / "report.json").read_text())
    assert report["passed"] and "PASS" in proc.stdout
    for variant in ("scalar_rgb", "llvm_ad_rgb"):
        rows = [r for r in report["rows"] if r["variant"] == variant]
        assert len(rows) == 15 and all(r["n"] == r["n_aarch64"] > 0 for r in rows), variant
    assert (tmp_path / "work" / "aarch64" / "mitsuba_powder" / "plugins" / "powder.so").exists()
