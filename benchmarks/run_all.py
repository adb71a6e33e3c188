"""Run every benchmark script; ``--quick`` runs them at tiny sizes (CI).

    python benchmarks/run_all.py [--quick] [--out DIR]

Each script prints its table and writes ``<name>.json`` (raw figures and the machine) and
``<name>.png`` into ``benchmarks/results/`` (or ``--out``).
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import time
from pathlib import Path

from registry import BENCHMARKS

HERE = Path(__file__).resolve().parent
#: every registered benchmark script, in the order they run
SCRIPTS = [bench.script for bench in BENCHMARKS]


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="tiny sizes (CI)")
    parser.add_argument("--out", type=Path, default=HERE / "results")
    parser.add_argument("--only", nargs="*", default=None, help="script names to run")
    args = parser.parse_args()
    failed = []
    for script in SCRIPTS:
        if args.only and script not in args.only and script[:-3] not in args.only:
            continue
        cmd = [sys.executable, str(HERE / script), "--out", str(args.out)]
        if args.quick:
            cmd.append("--quick")
        print(f"=== {script}{' --quick' if args.quick else ''}", flush=True)
        t = time.perf_counter()
        proc = subprocess.run(cmd)
        print(f"=== {script}: exit {proc.returncode}, {time.perf_counter() - t:.1f} s",
              flush=True)
        if proc.returncode != 0:
            failed.append(script)
    if failed:
        print(f"failed: {', '.join(failed)}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
