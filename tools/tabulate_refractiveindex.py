"""Tabulate a refractiveindex.info dispersion formula as a ``tabulated nk`` YAML file.

The plugin's loader reads ``tabulated nk`` data only. Some materials of the database (calcite
and quartz, Ghosh 1999; rutile, Devore 1951) are given as dispersion formulas of transparent
crystals; this script evaluates the formula at a regular grid over the formula's own
``wavelength_range`` (no extrapolation) and writes the rows ``wavelength (um), n, 0`` with the
source file's REFERENCES and COMMENTS kept, so that the bundled files are reproducible:

    python tools/tabulate_refractiveindex.py DATABASE/data/main/CaCO3/nk/Ghosh-o.yml \\
        python/mitsuba_powder/data/optical_constants/calcite_Ghosh-o.yml \\
        --name data/main/CaCO3/nk/Ghosh-o.yml

Formulas supported (refractiveindex.info's numbering, wavelength ``l`` in um):
``formula 2`` n^2 - 1 = C1 + sum_i C(2i) l^2 / (l^2 - C(2i+1)) and
``formula 4`` n^2 = C1 + C2 l^C3 / (l^2 - C4^C5) + C6 l^C7 / (l^2 - C8^C9) + sum C(i) l^C(i+1).
Standard library only.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

STEP_UM = 0.005


def formula_index(kind: int, c: list[float], wl: float) -> float:
    """The real index n of refractiveindex.info's formula `kind` at wavelength `wl` (um)."""
    l2 = wl * wl
    if kind == 2:
        n2 = 1.0 + c[0]
        for i in range(1, len(c) - 1, 2):
            n2 += c[i] * l2 / (l2 - c[i + 1])
    elif kind == 4:
        c = c + [0.0] * max(0, 9 - len(c))
        n2 = (c[0] + c[1] * wl ** c[2] / (l2 - c[3] ** c[4])
              + c[5] * wl ** c[6] / (l2 - c[7] ** c[8]))
        for i in range(9, len(c) - 1, 2):
            n2 += c[i] * wl ** c[i + 1]
    else:
        raise ValueError(f"formula {kind} is not supported (only formulas 2 and 4)")
    if not n2 > 0.0:
        raise ValueError(f"formula {kind} gives n^2 = {n2} at {wl} um")
    return n2 ** 0.5


def read_formula(text: str) -> tuple[int, list[float], float, float, list[str]]:
    """(formula number, coefficients, lo um, hi um, the header lines to keep) of a file."""
    kind = None
    coefficients: list[float] = []
    lo = hi = 0.0
    header: list[str] = []
    for line in text.splitlines():
        body = line.strip()
        if body.startswith("DATA:"):
            continue
        if body.startswith("- type:"):
            kind_text = body.split(":", 1)[1].strip()
            if not kind_text.startswith("formula "):
                raise ValueError(f"data of type {kind_text!r} is not a formula")
            kind = int(kind_text.split()[1])
        elif body.startswith("wavelength_range:"):
            lo, hi = (float(v) for v in body.split(":", 1)[1].split())
        elif body.startswith("coefficients:"):
            coefficients = [float(v) for v in body.split(":", 1)[1].split()]
        elif kind is None:
            header.append(line)
    if kind is None or not coefficients or not hi > lo:
        raise ValueError("no formula with coefficients and a wavelength_range")
    return kind, coefficients, lo, hi, header


def tabulate(text: str, source: str) -> str:
    kind, c, lo, hi, header = read_formula(text)
    n_steps = int((hi - lo) / STEP_UM + 1e-9)
    grid = [round(lo + i * STEP_UM, 6) for i in range(n_steps + 1)]
    if grid[-1] < hi - 1e-9:
        grid.append(hi)
    while header and not header[-1].strip():
        header.pop()
    out = header + [
        "TABULATED: |",
        f"    Formula {kind} of {source}, evaluated every {STEP_UM * 1e3:g} nm over its",
        f"    wavelength_range {lo:g}-{hi:g} um by tools/tabulate_refractiveindex.py;",
        "    k = 0 (a transparent crystal: the formula gives n only).",
        "DATA:",
        "  - type: tabulated nk",
        "    data: |",
    ]
    out += [f"        {wl:.4f} {formula_index(kind, c, wl):.6f} 0.000" for wl in grid]
    return "\n".join(out) + "\n"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("source", type=Path, help="refractiveindex.info YAML file with a formula")
    parser.add_argument("out", type=Path, help="the tabulated nk YAML file to write")
    parser.add_argument("--name", help="the source's name in the comment (default: its file "
                        "name), e.g. its path in the database")
    args = parser.parse_args(argv)
    try:
        text = tabulate(args.source.read_text(), args.name or args.source.name)
    except (OSError, ValueError) as e:
        print(f"tabulate_refractiveindex: {args.source}: {e}", file=sys.stderr)
        return 1
    args.out.write_text(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
