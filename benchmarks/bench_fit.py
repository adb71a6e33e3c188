"""Time of one fit against the number of geometries and wavelengths.

Synthetic data (2 % noise) from fixed parameters, fitted with the default free set (one
wavelength: the paper's five, radius fixed; several: the six with the radius profile).
Prints a table, writes benchmarks/results/fit.json and fit.png.
Run:  python benchmarks/bench_fit.py [--quick]
"""

from __future__ import annotations

import json
import platform
import time

from _common import arg_parser

TRUTH = {"amplitude_volume": 1.1, "g": 0.2, "extinction": 0.45, "radius": 0.05,
         "amplitude_surface": 5e-4, "correlation_length": 1.2}


def main() -> None:
    from mitsuba_powder.fit import fit
    from mitsuba_powder.protocols import simulate

    parser = arg_parser(__doc__)
    args = parser.parse_args()
    cases = [("backscatter", (700.0,)), ("shadows,backscatter", (700.0,))]
    if not args.quick:
        cases += [("shadows,backscatter", (450.0, 700.0)),
                  ("shadows,backscatter", (450.0, 550.0, 650.0))]
    starts_list = [1] if args.quick else [1, 4]
    rows = []
    for protocol, wavelengths in cases:
        data = simulate(TRUTH, protocol, wavelengths, noise=0.02, seed=1)
        fixed = {"radius": TRUTH["radius"]} if len(wavelengths) == 1 else {}
        for starts in starts_list:
            t = time.perf_counter()
            result = fit(data, fixed=fixed, starts=starts)
            seconds = time.perf_counter() - t
            rows.append({"protocol": protocol, "geometries": len(data) // len(wavelengths),
                         "wavelengths": len(wavelengths), "free": len(result.free),
                         "starts": starts, "evaluations": result.evaluations,
                         "seconds": seconds, "ms_per_evaluation": 1e3 * seconds /
                         result.evaluations, "chi2_per_point": result.loss / len(data)})
    print(f"{'protocol':22s} {'geom':>5s} {'wl':>3s} {'free':>4s} {'starts':>6s} "
          f"{'evals':>6s} {'s':>7s} {'ms/eval':>8s} {'chi2/N':>7s}")
    for r in rows:
        print(f"{r['protocol']:22s} {r['geometries']:5d} {r['wavelengths']:3d} {r['free']:4d} "
              f"{r['starts']:6d} {r['evaluations']:6d} {r['seconds']:7.2f} "
              f"{r['ms_per_evaluation']:8.3f} {r['chi2_per_point']:7.3f}")
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.processor() or platform.machine(), "quick": args.quick}
    (args.out / "fit.json").write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    for starts in starts_list:
        sel = [r for r in rows if r["starts"] == starts]
        ax.plot([r["geometries"] * r["wavelengths"] for r in sel], [r["seconds"] for r in sel],
                "o-", label=f"starts = {starts}")
    ax.set(xlabel="measurements (geometries x wavelengths)", ylabel="fit time (s)",
           title="fit time, 2-core machine")
    ax.legend()
    fig.tight_layout()
    fig.savefig(args.out / "fit.png", dpi=100)


if __name__ == "__main__":
    main()
