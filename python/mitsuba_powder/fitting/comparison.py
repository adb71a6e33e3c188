"""Compare the powder model with the baselines on the same measurements."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .._checks import check_range
from ..io.measurements import Measurements
from ..outputs import output_path
from .baselines import MODELS, fit_baseline
from .fit import fit
from .optimise import check_determined
from .report import statistics

#: The powder model's rows, by its ``surface_fresnel`` setting
POWDER_ROWS = {"none": "powder", "fresnel": "powder + surface Fresnel"}


def surface_fresnel_settings(fixed: dict | None) -> list[str]:
    """The ``surface_fresnel`` settings :func:`compare_models` fits: the one ``fixed`` gives,
    else both (Eq. 23, and the surface term times the interface's Fresnel factor), except
    where ``tau_o`` is given without the grain index the factor needs."""
    fixed = fixed or {}
    if "surface_fresnel" in fixed:
        return [str(fixed["surface_fresnel"])]
    if "tau_o" in fixed and not any(k in fixed for k in ("eta", "material")):
        return ["none"]
    return list(POWDER_ROWS)


def compare_models(data: Measurements, free: list[str] | None = None,
                   fixed: dict | None = None, starts: int = 64) -> list[dict]:
    """Fit the powder model (per wavelength) and every baseline; one row per model and
    wavelength with the number of parameters and the fit statistics.

    The powder model is fitted as published (Eq. 23, ``powder``) and with the surface term's
    Fresnel factor (``powder + surface Fresnel``, ``surface_fresnel = fresnel``), side by side
    (:func:`surface_fresnel_settings`), each in the EBS regime (kappa/k0 <= 0.25) and, as a
    row of its own where the optimum differs, with the bound lifted (``... (free
    regime)``)."""
    check_range("starts", starts, 1)
    for lam in data.wavelengths():  # before any fit: every model must be determined
        geometries = data.subset(data.wavelength == lam).geometry_summary()["geometries"]
        for name, (_, specs) in MODELS.items():
            check_determined(geometries, len(specs), f"the {name} fit at {lam:g} nm")
    rows = []
    for lam in data.wavelengths():
        d = data.subset(data.wavelength == lam)
        for mode in surface_fresnel_settings(fixed):
            label = POWDER_ROWS.get(mode, f"powder (surface_fresnel = {mode})")
            props = {**(fixed or {}), "surface_fresnel": mode}
            results = {regime: fit(d, free, props, starts=starts, regime=regime)
                       for regime in ("ebs", "free")}
            # the EBS regime is the powder model's row; the free regime gets its own row
            # where lifting the bound changes the optimum
            differ = results["free"].loss < results["ebs"].loss * (1.0 - 1e-6)
            for regime, result in results.items():
                if regime == "free" and not differ:
                    continue
                rows.append({"model": label if regime == "ebs" else f"{label} (free regime)",
                             "regime": regime, "surface_fresnel": mode,
                             "wavelength": float(lam),
                             "parameters": len(result.uncertainties),
                             **statistics(result.model_brf, d), "seconds": result.seconds,
                             "fitted": {k: v for k, v in result.parameters.items()
                                        if k in result.free},
                             "kappa_over_k0": result.regime["kappa_over_k0"],
                             "warnings": result.warnings})
    for name in MODELS:
        for b in fit_baseline(name, data, starts=starts):
            sel = data.wavelength == b.wavelength
            rows.append({"model": name, "wavelength": b.wavelength,
                         "parameters": len(b.parameters),
                         **statistics(b.model_brf, data.subset(sel)), "seconds": b.seconds,
                         "fitted": b.parameters})
    return rows


def write_comparison(rows: list[dict], out_dir: str | Path) -> Path:
    """``model_comparison.json`` (every row) and ``model_comparison.md`` (a table per
    wavelength) in ``out_dir``; returns the path of the table."""
    out_dir = Path(out_dir)
    path = output_path(out_dir, "model_comparison.md")
    output_path(out_dir, "model_comparison.json").write_text(json.dumps(rows, indent=1))
    lines = ["| nm | model | parameters | rel. RMSE % | max rel. err. % | RMSE BRF | s |",
             "|---|---|---|---|---|---|---|"]
    for lam in sorted({r["wavelength"] for r in rows}):
        for r in sorted((r for r in rows if r["wavelength"] == lam),
                        key=lambda r: r["relative_rmse_percent"]):
            lines.append(f"| {lam:g} | {r['model']} | {r['parameters']} | "
                         f"{r['relative_rmse_percent']:.2f} | "
                         f"{r['max_abs_relative_error_percent']:.1f} | {r['rmse_brf']:.4f} | "
                         f"{r['seconds']:.1f} |")
    path.write_text("\n".join(lines) + "\n")
    return path


def best_per_wavelength(rows: list[dict]) -> dict[float, str]:
    """The model with the lowest relative RMSE at each wavelength."""
    out = {}
    for lam in sorted({r["wavelength"] for r in rows}):
        sub = [r for r in rows if r["wavelength"] == lam]
        out[lam] = sub[int(np.argmin([r["relative_rmse_percent"] for r in sub]))]["model"]
    return out
