"""Write the tables of docs/benchmarks.md from benchmarks/results/*.json.

    python benchmarks/report.py [--results DIR] [--doc docs/benchmarks.md]

Each table sits between ``<!-- table:NAME -->`` and ``<!-- /table:NAME -->`` in the page and
is replaced; the prose around them is not touched. Which benchmark fills which table is
registered in ``registry.py``.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

from registry import BENCHMARKS

ROOT = Path(__file__).resolve().parents[1]


def tables(results: Path) -> dict[str, str]:
    """{table name: Markdown table} of every registered benchmark, from ``results``."""
    out = {}
    for bench in BENCHMARKS:
        if bench.tables:
            data = json.loads((results / f"{bench.results}.json").read_text())
            out.update({name: build(data) for name, build in bench.tables.items()})
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=ROOT / "benchmarks" / "results")
    parser.add_argument("--doc", type=Path, default=ROOT / "docs" / "benchmarks.md")
    args = parser.parse_args()
    text = args.doc.read_text()
    for name, table in tables(args.results).items():
        pattern = re.compile(rf"(<!-- table:{name} -->\n)(?:.*?\n)?(<!-- /table:{name} -->)",
                             re.S)
        if not pattern.search(text):
            raise SystemExit(f"{args.doc}: no <!-- table:{name} --> block")
        text = pattern.sub(lambda m, t=table: m.group(1) + t + "\n" + m.group(2), text)
    args.doc.write_text(text)
    print(f"updated {args.doc}")


if __name__ == "__main__":
    main()
