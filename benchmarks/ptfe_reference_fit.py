"""Independent reference fit of NIST PTFE: the best loss the product's fitter must reach.

The measured sintered PTFE BRF (measurements/ptfe_germer2017.csv, Germer 2017) at 351, 532,
633 and 1064 nm is fitted by tests/oracles/fit.py (NumPy float64 model of docs/model.md +
scipy least_squares from a 60-point Sobol design; no code of the product): free A_v, g,
extinction, albedo, A_s', l_c; eta = 1.35, k = 0; Harvey-Shack; infinite thickness; plain sum of
squares of BRF residuals. Prints a table, writes benchmarks/results/ptfe_reference.json (per
wavelength: best loss, RMSE, parameters, starts within 1 % of the best, sorted start losses,
seconds) and ptfe_reference.png (sorted start losses / best loss). bench_fit.py compares the
product's PTFE fits with these losses (the product's loss should be within 2 % of them).
Run:  OMP_NUM_THREADS=1 OPENBLAS_NUM_THREADS=1 python benchmarks/ptfe_reference_fit.py [--quick]
"""

from __future__ import annotations

import csv
import os
import shlex
import sys
from pathlib import Path

import numpy as np

from _common import arg_parser, print_table, pyplot, save, save_figure

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "tests"))  # tests/oracles/ (the reference fit and model)

from oracles.fit import FREE, reference_fit  # noqa: E402

DATA = ROOT / "measurements" / "ptfe_germer2017.csv"
WAVELENGTHS = (351.0, 532.0, 633.0, 1064.0)
COLUMNS = ("theta_i", "theta_o", "phi", "wavelength", "brf")
SHORT = {"amplitude_volume": "A_v", "g": "g", "extinction": "kappa 1/um", "albedo": "rho",
         "amplitude_surface": "A_s' um^2", "correlation_length": "l_c um"}


def read_ptfe(path: Path) -> dict[str, np.ndarray]:
    """Columns of a gonio CSV (lines starting with '#' are comments; header
    ``theta_i,theta_o,phi,wavelength,brf``; angles in degrees, wavelength in nm).

    Raises:
        ValueError: naming the file, line and column of a missing column or a bad number.
    """
    rows: list[list[float]] = []
    header: list[str] | None = None
    with open(path, newline="") as f:
        for lineno, row in enumerate(csv.reader(f), start=1):
            if not row or row[0].lstrip().startswith("#"):
                continue
            if header is None:
                header = [h.strip() for h in row]
                missing = [c for c in COLUMNS if c not in header]
                if missing:
                    raise ValueError(f"{path}:{lineno}: missing column(s) {missing} in header "
                                     f"{header}")
                index = [header.index(c) for c in COLUMNS]
                continue
            values = []
            for c, i in zip(COLUMNS, index):
                try:
                    values.append(float(row[i]))
                except (IndexError, ValueError):
                    cell = row[i] if i < len(row) else "<missing>"
                    raise ValueError(f"{path}:{lineno}: column {c!r}: {cell!r} is not a "
                                     f"number") from None
            rows.append(values)
    if header is None or not rows:
        raise ValueError(f"{path}: no data rows")
    table = np.array(rows, dtype=np.float64)
    return {c: table[:, j] for j, c in enumerate(COLUMNS)}


def _relative(path: Path) -> str:
    """``path`` relative to the repository when it lies inside it."""
    try:
        return str(path.resolve().relative_to(ROOT))
    except ValueError:
        return str(path)


def main() -> None:
    parser = arg_parser(__doc__)
    parser.add_argument("--starts", type=int, default=None,
                        help="starts per wavelength (default 60; 4 with --quick)")
    parser.add_argument("--seed", type=int, default=0, help="seed of the Sobol design")
    parser.add_argument("--eta", type=float, default=1.35, help="real index of PTFE")
    parser.add_argument("--wavelengths", type=float, nargs="+", default=None,
                        help="nm (default 351 532 633 1064; 532 with --quick)")
    parser.add_argument("--data", type=Path, default=DATA, help="gonio CSV")
    args = parser.parse_args()
    starts = args.starts if args.starts is not None else (4 if args.quick else 60)
    wavelengths = args.wavelengths or ([532.0] if args.quick else list(WAVELENGTHS))
    threads = {k: os.environ.get(k) for k in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS")}
    command = shlex.join([f"{k}={v}" for k, v in threads.items() if v is not None]
                         + ["python", "benchmarks/ptfe_reference_fit.py", *sys.argv[1:]])

    data = read_ptfe(args.data)
    rows = []
    for lam in wavelengths:
        sel = data["wavelength"] == lam
        if not sel.any():
            raise ValueError(f"--wavelengths: no rows at {lam} nm in {args.data} (it has "
                             f"{sorted(set(data['wavelength'].tolist()))})")
        r = reference_fit(data["theta_i"][sel], data["theta_o"][sel], data["phi"][sel], lam,
                          data["brf"][sel], eta=args.eta, starts=starts, seed=args.seed)
        rows.append({"wavelength_nm": lam, "n": r["n"], "loss": r["loss"], "rmse": r["rmse"],
                     "parameters": r["parameters"], "at_bound": r["at_bound"],
                     "starts": r["starts"], "starts_within_1pct": r["starts_within_1pct"],
                     "start_losses": r["start_losses"], "seconds": r["seconds"],
                     "evaluations": r["evaluations"], "tau_o": r["tau_o"], "eta": r["eta"],
                     "seed": r["seed"], "minima": r["minima"], "command": command})

    flat = [{**r, **r["parameters"], "agree": f"{r['starts_within_1pct']}/{r['starts']}"}
            for r in rows]
    print(f"reference fit of {args.data.name}: eta = {args.eta}, tau_o = {rows[0]['tau_o']:.4f}, "
          f"{starts} starts, seed {args.seed}")
    print_table(flat, [("wavelength_nm", "nm", ".0f"), ("n", "N", "d"), ("loss", "loss", ".6g"),
                       ("rmse", "RMSE BRF", ".5f"), ("agree", "within 1 %", "s"),
                       ("seconds", "s", ".1f")]
                + [(k, SHORT[k], ".4g") for k in FREE])
    for r in rows:
        others = ", ".join(f"{m['loss']:.4g} (RMSE {m['rmse']:.4f}, {m['starts']} starts)"
                           for m in r["minima"][1:])
        print(f"{r['wavelength_nm']:.0f} nm: other end points: {others or 'none'}")
    save(args.out, "ptfe_reference", rows, args.quick, command=command, data=_relative(args.data),
         starts=starts, seed=args.seed, eta=args.eta, threads=threads,
         free=list(FREE), loss="sum((BRF_model - BRF)^2)")

    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for r in rows:
        losses = np.asarray(r["start_losses"])
        ax.plot(np.arange(1, losses.size + 1), losses / r["loss"], "o-", ms=3,
                label=f"{r['wavelength_nm']:.0f} nm (RMSE {r['rmse']:.4f})")
    ax.axhline(1.01, color="k", lw=0.8, ls=":", label="best + 1 %")
    ax.set_yscale("log")
    ax.set(xlabel="start (sorted by final loss)", ylabel="final loss / best loss",
           title=f"PTFE reference fit, {starts} starts per wavelength")
    ax.legend(fontsize=7)
    save_figure(fig, args.out / "ptfe_reference.png")


if __name__ == "__main__":
    main()
