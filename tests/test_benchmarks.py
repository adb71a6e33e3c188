"""Every benchmark script runs in quick mode (tiny sizes) and writes its JSON and plot, so
that none of them rots. Nothing here asserts on times."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.parametrize("script,name,columns", [
    ("bench_bsdf.py", "bsdf", ["eval M/s", "eval cost/diffuse"]),
    ("bench_python_bsdf.py", "python_bsdf", ["eval speedup", "render speedup"]),
    ("bench_render.py", "render", ["gain", "DE00 mean", "cost/diffuse"]),
    ("bench_memory.py", "memory", ["peak RSS MiB"]),
])
def test_benchmark_quick_mode(script, name, columns, tmp_path):
    proc = subprocess.run([sys.executable, str(ROOT / "benchmarks" / script), "--quick",
                           "--out", str(tmp_path)], capture_output=True, text=True,
                          timeout=900, cwd=str(tmp_path))
    assert proc.returncode == 0, proc.stderr[-3000:]
    for col in columns:
        assert col in proc.stdout
    data = json.loads((tmp_path / f"{name}.json").read_text())
    assert data["meta"]["quick"] is True and data["meta"]["cpus"] >= 1
    assert (tmp_path / f"{name}.png").stat().st_size > 5000


def test_python_bsdf_matches_the_plugin(tmp_path):
    """The benchmark's Python re-implementation computes the same values as the plugin
    (otherwise the speed comparison would compare different work)."""
    subprocess.run([sys.executable, str(ROOT / "benchmarks" / "bench_python_bsdf.py"),
                    "--quick", "--out", str(tmp_path)], check=True, capture_output=True,
                   timeout=900, cwd=str(tmp_path))
    rows = json.loads((tmp_path / "python_bsdf.json").read_text())["rows"]
    assert len(rows) == 6
    assert all(r["max_rel_difference"] < 1e-5 for r in rows)


def test_run_all_lists_every_script():
    from importlib.util import module_from_spec, spec_from_file_location

    spec = spec_from_file_location("run_all", ROOT / "benchmarks" / "run_all.py")
    mod = module_from_spec(spec)
    spec.loader.exec_module(mod)
    scripts = {p.name for p in (ROOT / "benchmarks").glob("bench_*.py")}
    assert scripts == set(mod.SCRIPTS)
