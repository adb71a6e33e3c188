"""Reports of :func:`mitsuba_powder.rendering.gonio.render_gonio`: CSV, JSON summary and a
figure."""

from __future__ import annotations

import csv
import json
from pathlib import Path

import numpy as np

from ..outputs import output_file, output_path
from .gonio import GonioResult

COLUMNS = ("theta_i", "theta_o", "phi", "wavelength", "channel", "brf_rendered", "stderr",
           "brf_analytic", "z")


def write_gonio_csv(path: str | Path, result: GonioResult) -> Path:
    """One row per geometry and channel: rendered BRF, its Monte Carlo standard error, the
    analytic BRF, ``z`` and (when given) the measured BRF."""
    path = output_file(path)
    names = list(COLUMNS) + (["brf_measured"] if result.measured is not None else [])
    with path.open("w", newline="", encoding="utf-8") as fh:
        fh.write(f"# rendered by mitsuba_powder.gonio.render_gonio: variant {result.variant}, "
                 f"{result.spp} spp, {result.resolution}^2 pixels per geometry, source radius "
                 f"{result.source_radius:g} deg, {result.strategy} sampling\n")
        fh.write("# properties: " + json.dumps(result.properties) + "\n")
        writer = csv.writer(fh)
        writer.writerow(names)
        for row in result.rows():
            writer.writerow([row[n] if isinstance(row[n], str) else f"{row[n]:.8g}"
                             for n in names])
    return path


def summary_dict(result: GonioResult) -> dict:
    """Settings, timing and agreement statistics (``gonio.json``): ``deterministic`` (values
    without Monte Carlo noise, against the float32 tolerance: count, largest relative
    difference, the tolerance's range) and ``monte_carlo`` (the z-test: count, largest |z|,
    values beyond 3 sigma) separately."""
    out = {"variant": result.variant, "spp": result.spp, "resolution": result.resolution,
           "source_radius_deg": result.source_radius, "strategy": result.strategy,
           "render_seconds": result.seconds, "properties": result.properties,
           **result.summary()}
    out["checks"] = ("deterministic values (collimated source in RGB/mono variants, or a "
                     "standard error of exactly 0): |rendered - analytic| <= tolerance "
                     "|analytic|, the tolerance from float32 arithmetic; Monte Carlo values: "
                     "|rendered - analytic| <= 3 standard errors (z-test)")
    if result.measured is not None:
        model = result.rendered[:, 0]
        res = model - result.measured
        out["measurement"] = {"rmse": float(np.sqrt(np.mean(res**2))),
                              "relative_rmse_percent": float(100 * np.sqrt(np.mean(
                                  (res / np.maximum(result.measured, 1e-12)) ** 2)))}
    return out


def plot_gonio(path: str | Path, result: GonioResult) -> Path:
    """Principal plane (phi = 0 and 180) per incidence: rendered BRF with 3-sigma bars (none
    for deterministic values, which have no Monte Carlo error), the analytic curve and
    measurements."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    path = Path(path)
    incidences = np.unique(result.theta_i)
    fig, axes = plt.subplots(1, len(incidences), figsize=(3.6 * len(incidences), 3.3),
                             squeeze=False, sharey=True)
    colours = ["tab:red", "tab:green", "tab:blue"] if len(result.channels) == 3 else ["k"]
    bars = np.where(result.deterministic(), 0.0, 3.0 * result.stderr)
    for ax, ti in zip(axes[0], incidences, strict=True):
        plane = (result.theta_i == ti) & np.isclose(np.mod(result.phi, 180.0), 0.0)
        signed = np.where(np.isclose(np.mod(result.phi, 360.0), 180.0), -result.theta_o,
                          result.theta_o)[plane]
        order = np.argsort(signed)
        for c, col in enumerate(colours):
            ax.plot(signed[order], result.analytic[plane, c][order], "-", color=col, lw=1)
            ax.errorbar(signed[order], result.rendered[plane, c][order],
                        yerr=bars[plane, c][order], fmt="o", ms=3, color=col,
                        label=f"{result.channels[c]} rendered" if ti == incidences[0] else None)
        if result.measured is not None:
            ax.plot(signed[order], result.measured[plane][order], "x", color="0.4",
                    label="measured" if ti == incidences[0] else None)
        ax.set_title(f"theta_i = {ti:g} deg")
        ax.set_xlabel("signed theta_o (deg)")
    axes[0][0].set_ylabel("BRF (lines: analytic)")
    axes[0][0].legend(fontsize=7)
    s = result.summary()
    d, m = s["deterministic"], s["monte_carlo"]
    checks = []
    if d["values"]:
        checks.append(f"{d['values']} deterministic values: max rel. difference "
                      f"{d['max_relative_difference']:.1e} (float32 tolerance "
                      f"{d['relative_tolerance_min']:.1e}-{d['relative_tolerance_max']:.1e})")
    if m["values"]:
        checks.append(f"{m['values']} Monte Carlo values: max |z| {m['max_abs_z']:.2f}, "
                      f"{m['beyond_3_sigma']} beyond 3 sigma")
    fig.suptitle(f"{result.variant}, {result.spp} spp, {result.strategy}; "
                 + "; ".join(checks), fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def write_gonio_report(out_dir: str | Path, result: GonioResult) -> Path:
    """``gonio.csv``, ``gonio.json`` and ``gonio.png`` in ``out_dir``; returns the JSON path."""
    out = Path(out_dir)
    target = {n: output_path(out, n) for n in ("gonio.csv", "gonio.png", "gonio.json")}
    write_gonio_csv(target["gonio.csv"], result)
    plot_gonio(target["gonio.png"], result)
    path = target["gonio.json"]
    path.write_text(json.dumps(summary_dict(result), indent=1))
    return path
