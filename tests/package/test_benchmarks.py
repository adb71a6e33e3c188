"""Every benchmark script runs in quick mode (tiny sizes) and writes its JSON and plot, and the
report script turns the results into the tables of docs/benchmarks.md, so that none of them
rots. Nothing here asserts on times."""

from __future__ import annotations

import json
import re
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
BENCHMARKS_DIR = ROOT / "benchmarks"


def _load_script(name: str):
    """A module of benchmarks/ (which import each other by their bare names)."""
    from importlib.util import module_from_spec, spec_from_file_location

    if str(BENCHMARKS_DIR) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS_DIR))
    spec = spec_from_file_location(name, BENCHMARKS_DIR / f"{name}.py")
    mod = module_from_spec(spec)
    sys.modules[name] = mod  # a dataclass looks its module up there
    spec.loader.exec_module(mod)
    return mod


#: {script: (results name, printed column headers)}, from the one registry of benchmarks
SCRIPTS = {b.script: (b.results, list(b.prints)) for b in _load_script("registry").BENCHMARKS}


@pytest.fixture(scope="module")
def quick_results(tmp_path_factory):
    """Run every script once in quick mode; {script: stdout} and the results folder."""
    out = tmp_path_factory.mktemp("bench")
    stdout = {}
    for script in SCRIPTS:
        proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), "--quick",
                               "--out", str(out)], capture_output=True, text=True,
                              timeout=900, cwd=str(out))
        assert proc.returncode == 0, f"{script}:\n{proc.stderr[-3000:]}"
        stdout[script] = proc.stdout
    return stdout, out


@pytest.mark.parametrize("script", list(SCRIPTS))
def test_benchmark_quick_mode(script, quick_results):
    stdout, out = quick_results
    name, columns = SCRIPTS[script]
    for col in columns:
        assert col in stdout[script]
    data = json.loads((out / f"{name}.json").read_text())
    assert data["meta"]["quick"] is True
    assert (out / f"{name}.png").stat().st_size > 5000
    if name == "python_bsdf":
        # the benchmark's Python re-implementation computes the same values as the plugin
        # (otherwise the speed comparison would compare different work)
        assert len(data["rows"]) == 6
        assert all(r["max_rel_difference"] < 1e-5 for r in data["rows"])
    if name == "ab":
        # without --baseline the A/B times the installed plugin against itself (a control)
        assert data["meta"]["baseline"].startswith("installed")
        assert {r["variant"] for r in data["rows"]} == {"llvm_ad_rgb", "llvm_ad_spectral"}


def test_ab_compares_the_baseline_build_it_is_given(tmp_path):
    """bench_ab loads the --baseline file as a plugin of its own: a copy of the installed
    build evaluates to the same values (differences 0), a file that is not a build of the
    plugin stops the run (so the baseline is the file given, not the installed plugin)."""
    import shutil

    import mitsuba_powder

    copy = tmp_path / "baseline" / "powder.so"
    copy.parent.mkdir()
    shutil.copy(mitsuba_powder.plugin_path(), copy)
    out = tmp_path / "same"
    proc = subprocess.run([sys.executable, str(BENCHMARKS_DIR / "bench_ab.py"), "--quick",
                           "--baseline", str(copy), "--out", str(out)], capture_output=True,
                          text=True, timeout=900)
    assert proc.returncode == 0, proc.stderr[-3000:]
    data = json.loads((out / "ab.json").read_text())
    assert data["meta"]["baseline"] == str(copy)
    assert len(data["rows"]) == 2 * len(_load_script("bench_ab").CONFIGS)  # RGB, spectral
    assert all(r["max_rel_difference"] == 0.0 for r in data["rows"])
    broken = tmp_path / "broken" / "powder.so"
    broken.parent.mkdir()
    broken.write_bytes(b"not a shared library")
    proc = subprocess.run([sys.executable, str(BENCHMARKS_DIR / "bench_ab.py"), "--quick",
                           "--baseline", str(broken), "--out", str(tmp_path / "broken_out")],
                          capture_output=True, text=True, timeout=900)
    assert proc.returncode != 0 and "powder_baseline" in proc.stderr
    assert not (tmp_path / "broken_out" / "ab.json").exists()


@pytest.mark.parametrize("args, message", [
    (["--pairs", "30"], "--pairs: 30 is outside the valid range [10, 24]"),
    (["--pairs", "-1"], "--pairs: -1 is outside the valid range [10, 24]"),
    (["--baseline", "/nonexistent/powder.so"], "--baseline: no such file: /nonexistent"),
])
def test_ab_rejects_bad_options(args, message, tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_ab.py"), *args,
                           "--out", str(tmp_path)], capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr
    assert not (tmp_path / "ab.json").exists()


@pytest.mark.parametrize("threads", ["0", "-3", "1000"])
def test_eval_size_rejects_bad_threads(threads, tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_eval_size.py"),
                           "--threads", threads, "--quick", "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=300)
    message = f"--threads: {threads} is outside the valid range [1, 256]"
    assert proc.returncode == 2 and message in proc.stderr, proc.stderr
    assert not (tmp_path / "eval_size.json").exists()


def test_report_fills_every_table(quick_results, tmp_path):
    """report.py replaces every table of the page with the one the results give: each table
    body is first replaced by a sentinel, which must be gone afterwards."""
    _, results = quick_results
    doc = tmp_path / "benchmarks.md"
    original = (ROOT / "docs" / "benchmarks.md").read_text()
    names = re.findall(r"<!-- table:(\w+) -->", original)
    stale = original
    for name in names:
        stale = re.sub(rf"(<!-- table:{name} -->\n).*?(<!-- /table:{name} -->)",
                       lambda m: m.group(1) + "STALE TABLE\n" + m.group(2), stale, flags=re.S)
    assert stale.count("STALE TABLE") == len(names) >= 10
    doc.write_text(stale)
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "report.py"), "--results",
                    str(results), "--doc", str(doc)], check=True, timeout=300)
    text = doc.read_text()
    assert "STALE TABLE" not in text
    expected = _load_script("report").tables(results)
    assert sorted(names) == sorted(expected)
    for name in names:
        body = re.search(rf"<!-- table:{name} -->\n(.*?)\n<!-- /table:{name} -->", text,
                         re.S).group(1)
        assert body == expected[name], name
    assert "| llvm_ad_spectral | powder |" in text


def test_run_all_lists_every_script():
    """Every script of benchmarks/ that is not a helper module is registered, and run_all runs
    exactly the registered ones."""
    mod = _load_script("run_all")
    helpers = {"_common.py", "python_powder.py", "registry.py", "report.py", "run_all.py"}
    scripts = {p.name for p in BENCHMARKS_DIR.glob("*.py")} - helpers
    assert scripts == set(mod.SCRIPTS) == set(SCRIPTS)


def test_sorted_wavelengths_keep_the_lanes_values():
    """random_pairs' sorted_wavelengths (bench_eval_breakdown --sorted-wavelengths) changes
    only the order of each channel's wavelengths across the lanes: the same values per
    channel, sorted, and the same directions, so the kernel does the same work."""
    import numpy as np

    common = _load_script("_common")
    common.use_variant("llvm_ad_spectral")
    si, wo = common.random_pairs(1000, "llvm_ad_spectral", seed=3)
    si_s, wo_s = common.random_pairs(1000, "llvm_ad_spectral", seed=3, sorted_wavelengths=True)
    lam, lam_s = np.array(si.wavelengths), np.array(si_s.wavelengths)
    assert lam.shape == lam_s.shape == (4, 1000)
    assert np.all(np.diff(lam_s, axis=1) >= 0) and not np.all(np.diff(lam, axis=1) >= 0)
    np.testing.assert_array_equal(np.sort(lam, axis=1), lam_s)
    np.testing.assert_array_equal(np.array(si.wi), np.array(si_s.wi))
    np.testing.assert_array_equal(np.array(wo), np.array(wo_s))
