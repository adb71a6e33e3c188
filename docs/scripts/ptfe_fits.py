"""Fit the powder model to the NIST PTFE measurements (Germer 2017) at each wavelength.

For each of 351, 532, 633 and 1064 nm: a fit on all incidences, the four baselines
(Lambertian, Oren-Nayar, RTLSR, Hapke) on the same data, and a fit on theta_i in {0, 30, 60}
that predicts {15, 45, 75}. PTFE is not hematite: the albedo is free and the grain
index is that of PTFE (eta = 1.35, k = 0; tau_o from its Fresnel reflectance).
Writes docs/ptfe_fits.md and docs/figures/ptfe/*.png. Run from the repository root:
    python docs/scripts/ptfe_fits.py [--quick]
"""

from __future__ import annotations

import json
import shutil
import tempfile
from pathlib import Path

import numpy as np
from docs_output import docs_parser, output_dir

from mitsuba_powder.fitting.baselines import MODELS, fit_baseline
from mitsuba_powder.fitting.fit import DEFAULT_STARTS, fit, predict
from mitsuba_powder.fitting.report import statistics, write_report
from mitsuba_powder.io.measurements import load_measurements

ROOT = Path(__file__).resolve().parents[2]
FREE = ["amplitude_volume", "g", "extinction", "albedo", "amplitude_surface",
        "correlation_length"]
FIXED = {"eta": 1.35, "k": 0.0}


def main() -> None:
    args = docs_parser(__doc__, ROOT / "docs", "ptfe_fits.md and figures/ptfe",
                       quick="one wavelength, eight starts").parse_args()
    args.out = output_dir(args, ROOT / "docs")
    data = load_measurements(ROOT / "measurements" / "ptfe_germer2017.csv")
    wavelengths = [532.0] if args.quick else [351.0, 532.0, 633.0, 1064.0]
    starts = 8 if args.quick else DEFAULT_STARTS
    reference = {r["wavelength_nm"]: r["loss"] for r in json.loads(
        (ROOT / "benchmarks" / "results" / "ptfe_reference.json").read_text())["rows"]}
    figures = args.out / "figures" / "ptfe"
    figures.mkdir(parents=True, exist_ok=True)
    rows, held_rows, compare_rows, warn_rows, regime_rows = [], [], [], [], []
    for lam in wavelengths:
        d = data.subset(data.wavelength == lam)
        result = fit(d, FREE, FIXED, starts=starts)
        with tempfile.TemporaryDirectory() as tmp:
            write_report(result, tmp, figures="all")
            for name in ("fit.json", f"principal_plane_{lam:g}nm.png", f"polar_{lam:g}nm.png"):
                shutil.copy(Path(tmp) / name, figures / (f"{lam:g}nm_{name}"
                                                         if name == "fit.json" else name))
        st = statistics(result.model_brf, d)
        p, u = result.parameters, result.uncertainties
        rows.append(f"| {lam:g} | {len(d)} | {st['relative_rmse_percent']:.2f} | "
                    f"{st['max_abs_relative_error_percent']:.1f} | {st['rmse_brf']:.4f} | "
                    f"{result.loss:.6f} | {reference[lam]:.6f} | "
                    f"{result.agreeing}/{len(result.starts)} | "
                    + " | ".join(f"{p[n]:.4g} +- {u[n]:.2g}" for n in FREE)
                    + f" | {result.seconds:.1f} |")
        warn_rows += [f"- {lam:g} nm: {w}" for w in result.warnings]
        models = [("powder", len(result.uncertainties), result.model_brf, result.seconds)]
        for name in MODELS:
            b = fit_baseline(name, d, starts=min(starts, 32))[0]
            models.append((name, len(b.parameters), b.model_brf, b.seconds))
        for name, n_par, brf, secs in sorted(
                models, key=lambda m: statistics(m[2], d)["relative_rmse_percent"]):
            stm = statistics(brf, d)
            compare_rows.append(f"| {lam:g} | {name} | {n_par} | "
                                f"{stm['relative_rmse_percent']:.2f} | "
                                f"{stm['max_abs_relative_error_percent']:.1f} | "
                                f"{stm['rmse_brf']:.4f} | {secs:.1f} |")
        train = np.any(np.isclose(d.theta_i[:, None], [0.0, 30.0, 60.0], atol=0.01), axis=1)
        part = fit(d.subset(train), FREE, FIXED, starts=starts)
        held = d.subset(~train)
        pred = predict(part, held)
        st_fit = statistics(part.model_brf, d.subset(train))
        st_held = statistics(pred, held)
        per = ", ".join(f"{t:g} deg: {statistics(pred, held, held.theta_i == t)['relative_rmse_percent']:.2f} %"  # noqa: E501
                        for t in np.unique(held.theta_i))
        # the same two fits with the extinction unbounded (--regime free), side by side
        free = fit(d, FREE, FIXED, starts=starts, regime="free")
        free_part = fit(d.subset(train), FREE, FIXED, starts=starts, regime="free")
        free_held = statistics(predict(free_part, held), held)
        for name, full, train_fit, held_st in (("ebs", result, part, st_held),
                                               ("free", free, free_part, free_held)):
            ratio = max(full.regime["kappa_over_k0"].values())
            regime_rows.append(
                f"| {lam:g} | {name} | {full.loss:.6f} | "
                f"{statistics(full.model_brf, d)['relative_rmse_percent']:.2f} | "
                f"{full.parameters['extinction']:.4g} | {ratio:.3g} | "
                f"{train_fit.parameters['extinction']:.4g} | "
                f"{held_st['relative_rmse_percent']:.2f} |")
        held_rows.append(f"| {lam:g} | {st_fit['n']} | {st_fit['relative_rmse_percent']:.2f} | "
                         f"{st_held['n']} | {st_held['relative_rmse_percent']:.2f} | "
                         f"{st_held['max_abs_relative_error_percent']:.1f} | {per} |")
        print(rows[-1])
        print(held_rows[-1])
    header = ("| nm | N | rel. RMSE % | max rel. err. % | RMSE BRF | loss | best known loss | "
              "starts at the best | " + " | ".join(FREE) + " | s |")
    lines = ["<!-- generated by docs/scripts/ptfe_fits.py --refresh-docs; do not edit -->", "",
             "Fits on all incidences (parameter +- 1-sigma from the Jacobian):", "", header,
             "|" + "---|" * (9 + len(FREE)), *rows, "",
             "Best known loss: the independent 60-start reference fit "
             "(`benchmarks/ptfe_reference_fit.py`, NumPy model + scipy). Warnings of the fits:",
             "", *(warn_rows or ["- none"]), "",
             "Fit on theta_i in {0, 30, 60} deg, prediction of {15, 45, 75} deg:", "",
             "| nm | N fitted | rel. RMSE fitted % | N predicted | rel. RMSE predicted % | "
             "max rel. err. predicted % | per held-out incidence |",
             "|---|---|---|---|---|---|---|", *held_rows, "",
             "Both regimes (`--regime ebs`, the default: kappa/k0 <= 0.25; `--regime free`: "
             "the extinction up to 1000/um), on all incidences and predicting the held-out "
             "ones:", "",
             "| nm | regime | loss | rel. RMSE % | extinction (1/um) | kappa/k0 | "
             "extinction, fit on 0/30/60 deg | rel. RMSE predicted % |",
             "|---|---|---|---|---|---|---|---|", *regime_rows, "",
             "The same data fitted by the baselines (same least squares and optimiser; sorted "
             "by relative RMSE):", "",
             "| nm | model | parameters | rel. RMSE % | max rel. err. % | RMSE BRF | s |",
             "|---|---|---|---|---|---|---|", *compare_rows, ""]
    (args.out / "ptfe_fits.md").write_text("\n".join(lines))


if __name__ == "__main__":
    main()
