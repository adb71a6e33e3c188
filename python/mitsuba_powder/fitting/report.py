"""Fit reports: ``fit.json`` and figures.

``figures="summary"`` draws one set for the whole fit, whatever the number of wavelengths
(:data:`SUMMARY_FIGURES`: relative RMSE per wavelength, the residuals of every wavelength
against the angles, the plane of incidence at up to :data:`SUMMARY_WAVELENGTHS` wavelengths);
``"all"`` adds a plane-of-incidence and a polar figure per wavelength; ``"none"`` writes
``fit.json`` only. The figures are :mod:`mitsuba_powder.fitting.figures`, drawn here or, given
a :class:`~mitsuba_powder.fitting.figure_process.FigureProcess` started before the fit, in that
second process while this one writes ``fit.json``.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np

from ..io.measurements import Measurements
from ..outputs import check_finite_json, output_path
from .figure_process import FigureProcess
from .figures import DENSE_THETA_O, FitFigures, draw
from .fit import FitResult


def statistics(model: np.ndarray, data: Measurements, mask: np.ndarray | None = None) -> dict:
    """RMSE of BRF, relative RMSE in %, max |relative error| in %, count."""
    if mask is None:
        mask = np.ones(len(data), dtype=bool)
    if not np.any(mask):
        return {"n": 0}
    r = model[mask] - data.brf[mask]
    positive = data.brf[mask] > 0  # a relative error is defined where the BRF is not 0
    rel = r[positive] / data.brf[mask][positive]
    out = {"n": int(mask.sum()), "rmse_brf": float(np.sqrt(np.mean(r**2)))}
    if rel.size:
        out["relative_rmse_percent"] = float(100 * np.sqrt(np.mean(rel**2)))
        out["max_abs_relative_error_percent"] = float(100 * np.max(np.abs(rel)))
    else:
        out["relative_rmse_percent"] = out["max_abs_relative_error_percent"] = None
    if not positive.all():
        out["relative_rows"] = int(positive.sum())  # rows with BRF 0 left out of them
    return out


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
    check_finite_json(report, "fit.json")
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
                 figures: str = "summary", process: FigureProcess | None = None) -> Path:
    """Write ``fit.json`` and figures into ``out_dir``; returns the JSON path.

    Args:
        figures: ``"summary"`` (default): :data:`SUMMARY_FIGURES`, one set for the whole fit;
            ``"all"``: those and ``principal_plane_<nm>.png`` and ``polar_<nm>.png`` for
            every wavelength; ``"none"``: ``fit.json`` only.
        process: a drawing process started before the fit
            (:class:`~mitsuba_powder.fitting.figure_process.FigureProcess`): it draws the
            figures while this process writes ``fit.json``; without one (or where it did not
            start) they are drawn here.

    Raises:
        ValueError: ``figures`` is not one of :data:`FIGURES`; a target that is an input of
            the running command (:mod:`mitsuba_powder.outputs`). Both are checked before
            anything is written.
        RuntimeError: the drawing process failed.
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
    jobs = _figure_jobs(result, figures, wavelengths, target)
    sent = bool(jobs) and process is not None and process.submit(jobs)
    path = target["fit.json"]
    path.write_text(dumps_report(report_dict(result, held_out)))
    if sent:
        process.wait()
    elif jobs:
        draw(jobs)
    return path


def _figure_jobs(result: FitResult, figures: str, wavelengths: list[float],
                 target: dict[str, Path]) -> list[tuple[str, dict]]:
    """The figures of ``figures`` as jobs of :func:`mitsuba_powder.fitting.figures.draw`
    (the plugin's dense curves computed here, so that drawing needs no plugin)."""
    if figures == "none":
        return []
    fit = FitFigures(result.data, np.asarray(result.model_brf))
    jobs = [("plot_rmse", {"result": fit, "path": target[SUMMARY_FIGURES[0]]}),
            ("plot_residuals", {"result": fit, "path": target[SUMMARY_FIGURES[1]]}),
            ("plot_principal_planes", {"result": fit,
                                       "wavelengths": summary_wavelengths(wavelengths),
                                       "path": target[SUMMARY_FIGURES[2]]})]
    if figures == "all":
        curves = plane_curves(result, wavelengths)  # one call of the plugin for all
        for lam in wavelengths:
            jobs.append(("plot_principal_plane", {
                "result": fit, "wavelength": lam, "curves": {lam: curves[lam]},
                "path": target[f"principal_plane_{lam:g}nm.png"]}))
            jobs.append(("plot_polar", {"result": fit, "wavelength": lam,
                                        "path": target[f"polar_{lam:g}nm.png"]}))
    return jobs


def summary_wavelengths(wavelengths, count: int = SUMMARY_WAVELENGTHS) -> list[float]:
    """At most ``count`` of ``wavelengths`` (sorted), spread evenly over the range, the first
    and last included."""
    w = sorted(float(v) for v in wavelengths)
    if len(w) <= count:
        return w
    return [w[i] for i in sorted({int(round(k)) for k in np.linspace(0, len(w) - 1, count)})]


# ----------------------------------------------------------------- plugin curves

def plane_curves(result: FitResult, wavelengths) -> dict:
    """{wavelength: (incidences, BRF of the fit along signed theta_o, one row per incidence)}
    in the plane of incidence, all wavelengths in one call of the plugin."""
    from .fit import predict

    d = result.data
    to = DENSE_THETA_O
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
