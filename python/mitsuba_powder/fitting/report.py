"""Fit reports: ``fit.json`` and figures.

``figures="summary"`` draws one set for the whole fit, whatever the number of wavelengths
(:data:`SUMMARY_FIGURES`: relative RMSE per wavelength, the residuals of every wavelength
against the angles, the plane of incidence at up to :data:`SUMMARY_WAVELENGTHS` wavelengths);
``"all"`` adds a plane-of-incidence and a polar figure per wavelength; ``"none"`` writes
``fit.json`` only. Figures are drawn on matplotlib's object-oriented API with the Agg canvas and
fixed margins (no ``tight_layout``, which drew every figure twice and dominated the report's
time), so that a report costs a fraction of the fit.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..io.measurements import Measurements
from ..outputs import output_path
from .fit import FitResult


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


def _residual_rows(result: FitResult) -> list[dict]:
    """One dict per measurement: its angles, wavelength, measured, fitted and residual BRF
    (columns converted at once: a loop of float() per value cost more than the JSON)."""
    d = result.data
    keys = ("theta_i", "theta_o", "phi", "wavelength", "measured", "fitted", "residual")
    columns = [np.asarray(c, dtype=np.float64).tolist() for c in (
        d.theta_i, d.theta_o, d.phi, d.wavelength, d.brf, result.model_brf,
        result.model_brf - d.brf)]
    return [dict(zip(keys, row, strict=True)) for row in zip(*columns, strict=True)]


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
        "residuals": _residual_rows(result),
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


def dumps_report(report: dict) -> str:
    """``report`` as the text of ``fit.json``: indented, one line per residual row (json's
    indenting encoder is pure Python; the rows go through its C encoder)."""
    rows = report.get("residuals")
    if not rows:
        return json.dumps(report, indent=1)
    marker = json.dumps("@@ the residual rows @@")
    text = json.dumps({**report, "residuals": [json.loads(marker)]}, indent=1)
    if text.count(marker) != 1:  # the marker's text occurs elsewhere in the report
        return json.dumps(report, indent=1)
    return text.replace(marker, ",\n  ".join(map(json.dumps, rows)))


#: The values of ``figures`` (``write_report`` and ``fit --figures``)
FIGURES = ("summary", "all", "none")
#: Files of ``figures="summary"`` (the same for any number of wavelengths)
SUMMARY_FIGURES = ("summary_rmse.png", "summary_residuals.png",
                   "summary_principal_plane.png")
#: The most wavelengths that ``summary_principal_plane.png`` shows (spread over the range)
SUMMARY_WAVELENGTHS = 4
#: PNG resolution of the report's figures
DPI = 100


def check_figures(figures: str) -> str:
    """``figures`` if it is one of :data:`FIGURES`.

    Raises:
        ValueError: naming the parameter, its value and the valid values.
    """
    if not isinstance(figures, str) or figures not in FIGURES:
        raise ValueError(f"figures = {figures!r} is not valid; valid values are "
                         f"{', '.join(FIGURES)}")
    return figures


def write_report(result: FitResult, out_dir: str | Path,
                 held_out: tuple[Measurements, np.ndarray] | None = None, *,
                 figures: str = "summary") -> Path:
    """Write ``fit.json`` and figures into ``out_dir``; returns the JSON path.

    Args:
        figures: ``"summary"`` (default): :data:`SUMMARY_FIGURES`, one set for the whole fit;
            ``"all"``: those and ``principal_plane_<nm>.png`` and ``polar_<nm>.png`` for
            every wavelength; ``"none"``: ``fit.json`` only.

    Raises:
        ValueError: ``figures`` is not one of :data:`FIGURES`; a target that is an input of
            the running command (:mod:`mitsuba_powder.outputs`). Both are checked before
            anything is written.
    """
    check_figures(figures)
    out_dir = Path(out_dir)
    wavelengths = [float(w) for w in result.data.wavelengths()]
    names = ["fit.json"]
    if figures != "none":
        names += list(SUMMARY_FIGURES)
    if figures == "all":
        names += [f"{kind}_{lam:g}nm.png" for lam in wavelengths
                  for kind in ("principal_plane", "polar")]
    target = {name: output_path(out_dir, name) for name in names}
    path = target["fit.json"]
    path.write_text(dumps_report(report_dict(result, held_out)))
    if figures == "none":
        return path
    plot_rmse(result, target[SUMMARY_FIGURES[0]])
    plot_residuals(result, target[SUMMARY_FIGURES[1]])
    plot_principal_planes(result, summary_wavelengths(wavelengths),
                          target[SUMMARY_FIGURES[2]])
    if figures == "all":
        curves = _plane_curves(result, wavelengths)  # one call of the plugin for all
        for lam in wavelengths:
            plot_principal_plane(result, lam, target[f"principal_plane_{lam:g}nm.png"],
                                 curves)
            plot_polar(result, lam, target[f"polar_{lam:g}nm.png"])
    return path


def summary_wavelengths(wavelengths, count: int = SUMMARY_WAVELENGTHS) -> list[float]:
    """At most ``count`` of ``wavelengths`` (sorted), spread evenly over the range, the first
    and last included."""
    w = sorted(float(v) for v in wavelengths)
    if len(w) <= count:
        return w
    return [w[i] for i in sorted({int(round(k)) for k in np.linspace(0, len(w) - 1, count)})]


# ----------------------------------------------------------------- figures

def _figure(width: float, height: float):
    """A matplotlib figure on the Agg canvas (no pyplot: nothing to close, no global state)."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=(width, height))
    FigureCanvasAgg(fig)
    return fig


def _margins(fig, left: float, right: float, bottom: float, top: float, **space) -> None:
    """Fixed margins in inches (instead of a layout engine, which measures every text)."""
    w, h = fig.get_size_inches()
    fig.subplots_adjust(left=left / w, right=1 - right / w, bottom=bottom / h,
                        top=1 - top / h, **space)


def _save(fig, path: Path) -> None:
    """Write ``fig`` as PNG (zlib level 3: nearly the size of the default 6, less time)."""
    fig.savefig(path, dpi=DPI, pil_kwargs={"compress_level": 3})


def _incidence_colour(k: int):
    from matplotlib import colormaps

    return colormaps["tab10"](k % 10)


_DENSE_THETA_O = np.linspace(-85.0, 85.0, 341)


def _relative_percent(result: FitResult) -> np.ndarray:
    """100 (fit - measured) / measured per row (inf where a measurement is 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return 100.0 * (result.model_brf - result.data.brf) / result.data.brf


def _plane_curves(result: FitResult, wavelengths) -> dict:
    """{wavelength: (incidences, BRF of the fit along signed theta_o, one row per incidence)}
    in the plane of incidence, all wavelengths in one call of the plugin."""
    from .fit import predict

    d = result.data
    to = _DENSE_THETA_O
    ti, lam = [], []
    for w in wavelengths:
        for t in np.unique(d.theta_i[d.wavelength == w]):
            ti.append(t)
            lam.append(w)
    if not ti:
        return {}
    n = len(to)
    dense = Measurements(np.repeat(ti, n), np.tile(to, len(ti)), np.zeros(n * len(ti)),
                         np.repeat(lam, n), np.zeros(n * len(ti)))
    brf = predict(result, dense).reshape(len(ti), n)
    out = {}
    for w in wavelengths:
        rows = [k for k, v in enumerate(lam) if v == w]
        out[float(w)] = (np.asarray(ti)[rows], brf[rows])
    return out


def _draw_plane(ax, axr, result: FitResult, wavelength: float, curves: dict,
                fontsize: float = 7) -> None:
    """Measured points and the dense fitted curves of ``curves`` (:func:`_plane_curves`) in
    the plane of incidence (``ax``) and the residuals (``axr``) at one wavelength, one colour
    per incidence."""
    d = result.data
    sel = d.wavelength == wavelength
    plane, signed = _signed_principal(d)
    incidences, dense = curves[float(wavelength)]
    for k, t in enumerate(incidences):
        col = _incidence_colour(k)
        m = sel & plane & (d.theta_i == t)
        order = np.argsort(signed[m])
        x = signed[m][order]
        ax.plot(x, d.brf[m][order], "o", color=col, ms=3.5, label=f"theta_i = {t:g}")
        ax.plot(_DENSE_THETA_O, dense[k], "-", color=col, lw=1)
        axr.plot(x, (result.model_brf[m] - d.brf[m])[order], "o-", color=col, ms=2.5, lw=0.5)
    axr.axhline(0.0, color="k", lw=0.5)
    ax.legend(fontsize=fontsize, loc="best")
    for a in (ax, axr):
        a.tick_params(labelsize=fontsize)


def plot_principal_plane(result: FitResult, wavelength: float, path: Path,
                         curves: dict | None = None) -> None:
    """BRF in the plane of incidence against signed theta_o, per incidence: measurement,
    fitted model (a dense curve from the plugin) and residuals. ``curves``: from
    :func:`_plane_curves` (computed here when it lacks ``wavelength``)."""
    wavelength = float(wavelength)
    if curves is None or wavelength not in curves:
        curves = _plane_curves(result, [wavelength])
    fig = _figure(7, 6)
    ax, axr = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    _margins(fig, 0.75, 0.15, 0.6, 0.35, hspace=0.08)
    _draw_plane(ax, axr, result, wavelength, curves)
    ax.set_ylabel("BRF")
    ax.set_title(f"plane of incidence, {wavelength:g} nm (points: measured, lines: fit)",
                 fontsize=9)
    axr.set(xlabel="signed theta_o (deg; + = back-scattering side)", ylabel="fit - measured")
    _save(fig, path)


def plot_principal_planes(result: FitResult, wavelengths, path: Path) -> None:
    """The plane of incidence at a few ``wavelengths`` side by side: measured points and the
    fitted values at the same angles (crosses: no plugin evaluation, which would cost more
    than the figure). The residuals of every wavelength are in :func:`plot_residuals`."""
    from matplotlib.ticker import FixedLocator, MaxNLocator

    d = result.data
    plane, signed = _signed_principal(d)
    wavelengths = [float(w) for w in wavelengths]
    n = len(wavelengths)
    fig = _figure(0.9 + 3.0 * n, 3.6)
    axes = fig.subplots(1, n, sharex=True, squeeze=False)[0]
    _margins(fig, 0.65, 0.15, 0.5, 0.5, wspace=0.25)
    for j, (ax, lam) in enumerate(zip(axes, wavelengths, strict=True)):
        sel = (d.wavelength == lam) & plane
        incidences = np.unique(d.theta_i[d.wavelength == lam])
        for k, t in enumerate(incidences):
            m = sel & (d.theta_i == t)
            order = np.argsort(signed[m])
            col = _incidence_colour(k)
            ax.plot(signed[m][order], d.brf[m][order], "o-", color=col, ms=3.5, mew=0,
                    lw=0.5, label=f"theta_i = {t:g}")
            ax.plot(signed[m][order], result.model_brf[m][order], "x", color="k", ms=3.5,
                    mew=0.7, label="fit" if t == incidences[-1] else None)
        ax.set_title(f"{lam:g} nm", fontsize=8)
        ax.set_xlabel("signed theta_o (deg)", fontsize=7)
        ax.xaxis.set_major_locator(FixedLocator([-60, -30, 0, 30, 60]))
        ax.yaxis.set_major_locator(MaxNLocator(5))
        ax.tick_params(labelsize=6)
        if j == 0:
            ax.set_ylabel("BRF", fontsize=8)
            ax.legend(fontsize=6)
    fig.suptitle("plane of incidence (points: measured, joined per incidence; crosses: the fit "
                 "at the same angles; + = back-scattering side)", fontsize=9)
    _save(fig, path)


def plot_rmse(result: FitResult, path: Path) -> None:
    """Relative RMSE and max |relative error| (%) of the fit per wavelength, overall and per
    incidence."""
    d = result.data
    lam = d.wavelengths()
    rel = _relative_percent(result)

    def per_wavelength(mask):
        out = np.full(len(lam), np.nan)
        for i, w in enumerate(lam):
            m = mask & (d.wavelength == w)
            if m.any():
                out[i] = np.sqrt(np.mean(rel[m] ** 2))
        return out

    everything = np.ones(len(d), dtype=bool)
    fig = _figure(7, 3.6)
    ax = fig.subplots()
    _margins(fig, 0.7, 0.15, 0.55, 0.35)
    line = "-" if len(lam) > 1 else "none"
    for k, t in enumerate(np.unique(d.theta_i)):
        ax.plot(lam, per_wavelength(d.theta_i == t), ls=line, marker=".",
                color=_incidence_colour(k), lw=0.8, ms=4, label=f"theta_i = {t:g}")
    ax.plot(lam, per_wavelength(everything), ls=line, marker="o", color="k", lw=1.5, ms=4,
            label="all incidences")
    worst = [np.max(np.abs(rel[d.wavelength == w])) for w in lam]
    ax.plot(lam, worst, ls=":" if len(lam) > 1 else "none", marker="x", color="k", ms=4,
            lw=0.8, label="max |relative error|")
    ax.set(xlabel="wavelength (nm)", ylabel="relative error (%)", ylim=(0, None))
    ax.set_title(f"relative RMSE per wavelength ({len(d)} measurements)", fontsize=9)
    ax.legend(fontsize=6, ncol=2)
    ax.tick_params(labelsize=7)
    _save(fig, path)


def plot_residuals(result: FitResult, path: Path) -> None:
    """Relative residuals (%) of every measurement against theta_i, theta_o and the phase
    angle (between the directions to the light and to the viewer; 0 = back-scattering),
    coloured by wavelength: one figure for all wavelengths."""
    from matplotlib.colors import Normalize
    from matplotlib.ticker import MaxNLocator

    d = result.data
    rel = _relative_percent(result)
    wi, wo = d.directions()
    phase = np.degrees(np.arccos(np.clip(np.sum(wi * wo, axis=1), -1.0, 1.0)))
    lam = d.wavelengths()
    pad = 0.5 if len(lam) == 1 else 0.0
    norm = Normalize(lam[0] - pad, lam[-1] + pad)
    order = np.random.default_rng(0).permutation(len(d))  # no wavelength drawn on top
    fig = _figure(10, 3.6)
    axes = fig.subplots(1, 3, sharey=True)
    _margins(fig, 0.7, 1.0, 0.5, 0.35, wspace=0.06)
    sc = None
    for ax, (x, label) in zip(axes, [
            (d.theta_i, "theta_i (deg)"), (d.theta_o, "theta_o (deg)"),
            (phase, "phase angle (deg; 0 = back-scattering)")], strict=True):
        sc = ax.scatter(x[order], rel[order], c=d.wavelength[order], s=4, cmap="viridis",
                        norm=norm, linewidths=0)
        ax.axhline(0.0, color="k", lw=0.5)
        ax.set_xlabel(label, fontsize=8)
        ax.xaxis.set_major_locator(MaxNLocator(6))
        ax.yaxis.set_major_locator(MaxNLocator(6))
        ax.tick_params(labelsize=7)
    axes[0].set_ylabel("(fit - measured) / measured (%)", fontsize=8)
    w, h = fig.get_size_inches()
    cax = fig.add_axes([1 - 0.85 / w, 0.5 / h, 0.15 / w, 1 - 0.85 / h])
    fig.colorbar(sc, cax=cax).set_label("wavelength (nm)", fontsize=8)
    cax.tick_params(labelsize=7)
    fig.suptitle(f"relative residuals of {len(d)} measurements at {len(lam)} wavelength"
                 f"{'s' if len(lam) > 1 else ''}", fontsize=9, y=1 - 0.05 / h, va="top")
    _save(fig, path)


def plot_polar(result: FitResult, wavelength: float, path: Path) -> None:
    """Polar maps (radius theta_o, angle phi) of measured, fitted and difference BRF, one row
    per incidence; measured and fitted share a colour scale."""
    d = result.data
    sel = d.wavelength == wavelength
    incidences = np.unique(d.theta_i[sel])
    rows = len(incidences)
    fig = _figure(9, 0.8 + 2.8 * rows)
    axes = fig.subplots(rows, 3, subplot_kw={"projection": "polar"}, squeeze=False)
    _margins(fig, 0.3, 0.9, 0.25, 0.75, hspace=0.45, wspace=0.25)
    theta = np.abs(d.theta_o)
    phi = np.radians(np.where(d.theta_o < 0, d.phi + 180.0, d.phi))
    vmin, vmax = np.percentile(d.brf[sel], [1, 99])
    diff = result.model_brf - d.brf
    dmax = np.max(np.abs(diff[sel])) or 1.0
    mappables = [None, None]
    for row, t in enumerate(incidences):
        m = sel & (d.theta_i == t)
        for col, (values, kwargs, title) in enumerate([
                (d.brf, {"vmin": vmin, "vmax": vmax, "cmap": "viridis"}, "measured"),
                (result.model_brf, {"vmin": vmin, "vmax": vmax, "cmap": "viridis"}, "fitted"),
                (diff, {"vmin": -dmax, "vmax": dmax, "cmap": "coolwarm"}, "fit - measured")]):
            ax = axes[row, col]
            sc = ax.scatter(phi[m], theta[m], c=values[m], s=14, **kwargs)
            mappables[col == 2] = sc
            ax.set_ylim(0, 90)
            ax.set_rticks([30, 60, 90])
            ax.set_thetagrids([0, 90, 180, 270])
            ax.set_title(f"{title}, theta_i = {t:g}", fontsize=8)
            ax.tick_params(labelsize=6)
    w, h = fig.get_size_inches()
    bottom, top = 0.25 / h, 1 - 0.75 / h
    for k, (label, sc) in enumerate(zip(("BRF (measured, fitted)", "fit - measured"),
                                        mappables, strict=True)):
        cax = fig.add_axes([1 - 0.7 / w, bottom + (1 - k) * 0.52 * (top - bottom), 0.12 / w,
                            0.48 * (top - bottom)])
        fig.colorbar(sc, cax=cax).set_label(label, fontsize=7)
        cax.tick_params(labelsize=6)
    fig.suptitle(f"BRF at {wavelength:g} nm (radius: theta_o, angle: phi; light at phi = 0)",
                 fontsize=9, y=1 - 0.1 / h, va="top")
    _save(fig, path)
