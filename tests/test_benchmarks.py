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

ROOT = Path(__file__).resolve().parents[1]
SCRIPTS = {
    "bench_bsdf.py": ("bsdf", ["eval M/s", "eval cost/diffuse"]),
    "bench_eval_breakdown.py": ("eval_breakdown", ["eval ms", "cost / principled"]),
    "bench_eval_size.py": ("eval_size", ["log2 pairs", "cost / coloured principled"]),
    "bench_ab.py": ("ab", ["new / baseline", "max rel. difference"]),
    "bench_jit_ops.py": ("jit_ops", ["ms per op", "cost / fma"]),
    "bench_python_bsdf.py": ("python_bsdf", ["eval speedup", "render speedup"]),
    "bench_render.py": ("render", ["gain", "DE00 mean", "cost/diffuse"]),
    "bench_mie_update.py": ("mie_update", ["update+AD ms", "Fresnel ms"]),
    "bench_fit.py": ("fit", ["s (first)", "loss/best", "agreeing"]),
    "bench_memory.py": ("memory", ["peak RSS MiB"]),
    "bench_textures.py": ("textures", ["relative to constant", "max relative error"]),
    "bench_rti_fit.py": ("rti_fit", ["fit s", "peak MiB"]),
    "ptfe_reference_fit.py": ("ptfe_reference", ["RMSE BRF", "within 1 %"]),
}
#: benchmark scripts whose name does not start with bench_
OTHER_SCRIPTS = {"ptfe_reference_fit.py"}


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
        # without --baseline the A/B compares the installed plugin with itself: a control
        # whose values must be identical
        assert data["meta"]["baseline"].startswith("installed")
        assert all(r["max_rel_difference"] == 0.0 for r in data["rows"])


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


def _load_script(name: str):
    from importlib.util import module_from_spec, spec_from_file_location

    spec = spec_from_file_location(name, ROOT / "benchmarks" / f"{name}.py")
    mod = module_from_spec(spec)
    spec.loader.exec_module(mod)
    return mod


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
    mod = _load_script("run_all")
    scripts = {p.name for p in (ROOT / "benchmarks").glob("bench_*.py")} | OTHER_SCRIPTS
    assert scripts == set(mod.SCRIPTS) == set(SCRIPTS)
