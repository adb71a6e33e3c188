"""Fit reports: ``fit.json`` and figures (principal plane, polar maps)."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from .fit import FitResult
from .measurements import Measurements


def _signed_principal(data: Measurements) -> tuple[np.ndarray, np.ndarray]:
    """(mask, signed theta_o) of the rows in the plane of incidence (phi = 0 or 180)."""
    ph = np.mod(data.phi, 360.0)
    on0 = np.isclose(ph, 0.0, atol=1e-3) | np.isclose(ph, 360.0, atol=1e-3)
    on180 = np.isclose(ph, 180.0, atol=1e-3)
    signed = np.where(on180, -data.theta_o, data.theta_o)
    return on0 | on180, signed


def statistics(model: np.ndarray, data: Measurements, mask: np.ndarray | None = None) -> dict:
    """RMSE of BRF, relative RMSE in %, max |relative error| in %, count."""
    if mask is None:
        mask = np.ones(len(data), dtype=bool)
    if not np.any(mask):
        return {"n": 0}
    r = model[mask] - data.brf[mask]
    rel = r / data.brf[mask]
    return {"n": int(mask.sum()), "rmse_brf": float(np.sqrt(np.mean(r**2))),
            "relative_rmse_percent": float(100 * np.sqrt(np.mean(rel**2))),
            "max_abs_relative_error_percent": float(100 * np.max(np.abs(rel)))}


def _geometry_summary(data: Measurements) -> dict:
    """Rows, unique geometries and replicates (see ``Measurements.geometry_summary``)."""
    summary = getattr(data, "geometry_summary", None)
    return summary() if summary is not None else {"rows": len(data)}


def _correlation(result: FitResult) -> dict | None:
    """The correlation matrix of the free variables, as names and rows (None: undetermined)."""
    if result.correlation is None:
        return None
    names, matrix = result.correlation
    return {"names": names,
            "matrix": [[None if not np.isfinite(v) else round(float(v), 6) for v in row]
                       for row in np.asarray(matrix)]}


def report_dict(result: FitResult, held_out: tuple[Measurements, np.ndarray] | None = None
                ) -> dict:
    """The content of ``fit.json``."""
    d = result.data
    out = {
        "data": d.source,
        "data_comments": d.comments,
        "parameters": result.parameters,
        "uncertainties": {k: (v if np.isfinite(v) else None)
                          for k, v in result.uncertainties.items()},
        "free": result.free,
        "parameters_by_wavelength": {f"{k:g}": v for k, v in
                                     result.parameters_by_wavelength.items()},
        "n_measurements": len(d),
        "wavelengths_nm": [float(w) for w in d.wavelengths()],
        "weighted_sum_of_squares": result.loss,
        "weights": "1/sigma" if d.sigma is not None else "uniform",
        **{k: v for k, v in statistics(result.model_brf, d).items() if k != "n"},
        "per_incidence": [{"theta_i": float(t), **statistics(result.model_brf, d,
                                                              d.theta_i == t)}
                          for t in np.unique(d.theta_i)],
        "per_wavelength": [{"wavelength": float(w), **statistics(result.model_brf, d,
                                                                 d.wavelength == w)}
                           for w in d.wavelengths()],
        "chi2_per_point": result.chi2_per_point,
        "regime": result.regime,
        "geometry": _geometry_summary(d),
        "optics": result.optics,
        "warnings": result.warnings,
        "correlation": _correlation(result),
        "radius_branches": result.radius_branches,
        "optimizer": {"evaluations": result.evaluations, "seconds": result.seconds,
                      "starts": len(result.starts),
                      "agreeing_starts": result.agreeing,
                      "agreement": "final loss within 1 % of the best",
                      "trusted": result.agreeing >= 2,
                      "start_losses": sorted(result.starts),
                      "stages": result.stages},
        "residuals": [
            {"theta_i": float(d.theta_i[i]), "theta_o": float(d.theta_o[i]),
             "phi": float(d.phi[i]), "wavelength": float(d.wavelength[i]),
             "measured": float(d.brf[i]), "fitted": float(result.model_brf[i]),
             "residual": float(result.model_brf[i] - d.brf[i])}
            for i in range(len(d))],
    }
    if held_out is not None:
        data_h, model_h = held_out
        out["prediction"] = {
            "note": "measurements not used in the fit, predicted by the fitted parameters",
            **statistics(model_h, data_h),
            "per_incidence": [{"theta_i": float(t), **statistics(model_h, data_h,
                                                                  data_h.theta_i == t)}
                              for t in np.unique(data_h.theta_i)],
        }
    return out


def write_report(result: FitResult, out_dir: str | Path,
                 held_out: tuple[Measurements, np.ndarray] | None = None) -> Path:
    """Write ``fit.json`` and the figures into ``out_dir``; returns the JSON path."""
    out_dir = Path(out_dir)
    out_dir.mkdir(parents=True, exist_ok=True)
    path = out_dir / "fit.json"
    path.write_text(json.dumps(report_dict(result, held_out), indent=1))
    for lam in result.data.wavelengths():
        plot_principal_plane(result, lam, out_dir / f"principal_plane_{lam:g}nm.png")
        plot_polar(result, lam, out_dir / f"polar_{lam:g}nm.png")
    return path


def plot_principal_plane(result: FitResult, wavelength: float, path: Path) -> None:
    """BRF in the plane of incidence against signed theta_o, per incidence: measurement,
    fitted model (a dense curve from the plugin) and residuals."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from .model import PowderBRF

    d = result.data
    sel = d.wavelength == wavelength
    plane, signed = _signed_principal(d)
    incidences = np.unique(d.theta_i[sel])
    fig, (ax, axr) = plt.subplots(2, 1, figsize=(7, 6), sharex=True,
                                  gridspec_kw={"height_ratios": [3, 1]})
    to = np.linspace(-85.0, 85.0, 341)
    dense = Measurements(np.repeat(incidences, len(to)), np.tile(to, len(incidences)),
                         np.zeros(len(to) * len(incidences)),
                         np.full(len(to) * len(incidences), wavelength),
                         np.zeros(len(to) * len(incidences)))
    curve = PowderBRF(dense, result.parameters_by_wavelength[float(wavelength)]).brf()
    for k, t in enumerate(incidences):
        col = plt.get_cmap("tab10")(k % 10)
        m = sel & plane & (d.theta_i == t)
        order = np.argsort(signed[m])
        ax.plot(signed[m][order], d.brf[m][order], "o", color=col, ms=4,
                label=f"measured, theta_i = {t:g}")
        ax.plot(to, curve[k * len(to):(k + 1) * len(to)], "-", color=col, lw=1)
        axr.plot(signed[m][order], (result.model_brf[m] - d.brf[m])[order], "o-", color=col,
                 ms=3, lw=0.5)
    ax.set(ylabel="BRF", title=f"plane of incidence, {wavelength:g} nm (lines: fit)")
    ax.legend(fontsize=7)
    axr.axhline(0.0, color="k", lw=0.5)
    axr.set(xlabel="signed theta_o (deg; + = back-scattering side)", ylabel="fit - measured")
    fig.tight_layout()
    fig.savefig(path, dpi=100)
    plt.close(fig)


def plot_polar(result: FitResult, wavelength: float, path: Path) -> None:
    """Polar maps (radius theta_o, angle phi) of measured, fitted and difference BRF."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    d = result.data
    sel = d.wavelength == wavelength
    incidences = np.unique(d.theta_i[sel])
    fig, axes = plt.subplots(len(incidences), 3, subplot_kw={"projection": "polar"},
                             figsize=(9, 3 * len(incidences)), squeeze=False)
    theta = np.abs(d.theta_o)
    phi = np.radians(np.where(d.theta_o < 0, d.phi + 180.0, d.phi))
    vmin, vmax = np.percentile(d.brf[sel], [1, 99])
    diff = result.model_brf - d.brf
    dmax = np.max(np.abs(diff[sel])) or 1.0
    for row, t in enumerate(incidences):
        m = sel & (d.theta_i == t)
        for col, (values, kwargs, title) in enumerate([
                (d.brf, {"vmin": vmin, "vmax": vmax, "cmap": "viridis"}, "measured"),
                (result.model_brf, {"vmin": vmin, "vmax": vmax, "cmap": "viridis"}, "fitted"),
                (diff, {"vmin": -dmax, "vmax": dmax, "cmap": "coolwarm"}, "fit - measured")]):
            ax = axes[row, col]
            sc = ax.scatter(phi[m], theta[m], c=values[m], s=14, **kwargs)
            ax.set_ylim(0, 90)
            ax.set_title(f"{title}, theta_i = {t:g}", fontsize=8)
            ax.tick_params(labelsize=6)
            fig.colorbar(sc, ax=ax, fraction=0.04)
    fig.suptitle(f"BRF at {wavelength:g} nm (radius: theta_o, angle: phi; light at phi = 0)",
                 fontsize=9)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)
