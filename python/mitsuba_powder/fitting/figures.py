"""The fit report's figures, drawn from the data and the fitted values alone (no plugin call),
so that a second process can draw them while the fitting process writes ``fit.json``
(:mod:`mitsuba_powder.fitting.figure_process`). Matplotlib's object-oriented API on the Agg
canvas with fixed margins: no ``pyplot`` state and no layout engine (``tight_layout`` drew every
figure twice).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..io.dataset import Measurements

#: PNG resolution of the report's figures
DPI = 100


@dataclass
class FitFigures:
    """What the figures show of a fit: the measurements and the fitted BRF at each row
    (a :class:`~mitsuba_powder.fitting.fit.FitResult` has both attributes too)."""

    data: Measurements
    model_brf: np.ndarray


def _signed_principal(data: Measurements) -> tuple[np.ndarray, np.ndarray]:
    """(mask, signed theta_o) of the rows in the plane of incidence (phi = 0 or 180)."""
    ph = np.mod(data.phi, 360.0)
    on0 = np.isclose(ph, 0.0, atol=1e-3) | np.isclose(ph, 360.0, atol=1e-3)
    on180 = np.isclose(ph, 180.0, atol=1e-3)
    signed = np.where(on180, -data.theta_o, data.theta_o)
    return on0 | on180, signed


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


def _suptitle(fig, text: str, fontsize: float = 9, **kwargs) -> None:
    """A figure title wrapped to the figure's width (a narrow figure, e.g. one wavelength,
    gets two or more lines instead of a title cut at its edges)."""
    import textwrap

    width_in = fig.get_size_inches()[0]
    chars = max(20, int(width_in * 72 / (0.55 * fontsize)))  # a character is ~0.55 em wide
    fig.suptitle(textwrap.fill(text, chars), fontsize=fontsize, **kwargs)


def _save(fig, path: Path) -> None:
    """Write ``fig`` as PNG (zlib level 3: nearly the size of the default 6, less time)."""
    fig.savefig(path, dpi=DPI, pil_kwargs={"compress_level": 3})


def _incidence_colour(k: int):
    from matplotlib import colormaps

    return colormaps["tab10"](k % 10)


#: signed theta_o (deg) of the fitted curves in the plane of incidence
DENSE_THETA_O = np.linspace(-85.0, 85.0, 341)


def _relative_percent(result: FitFigures) -> np.ndarray:
    """100 (fit - measured) / measured per row (inf where a measurement is 0)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        return 100.0 * (result.model_brf - result.data.brf) / result.data.brf


def _draw_plane(ax, axr, result: FitFigures, wavelength: float, curves: dict,
                fontsize: float = 7) -> None:
    """Measured points and the dense fitted curves of ``curves`` (:func:`plot_principal_plane`) in
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
        ax.plot(DENSE_THETA_O, dense[k], "-", color=col, lw=1)
        axr.plot(x, (result.model_brf[m] - d.brf[m])[order], "o-", color=col, ms=2.5, lw=0.5)
    axr.axhline(0.0, color="k", lw=0.5)
    ax.legend(fontsize=fontsize, loc="best")
    for a in (ax, axr):
        a.tick_params(labelsize=fontsize)


def plot_principal_plane(result: FitFigures, wavelength: float, path: Path,
                         curves: dict) -> None:
    """BRF in the plane of incidence against signed theta_o, per incidence: measurement,
    fitted model (a dense curve from the plugin) and residuals. ``curves``: {wavelength:
    (incidences, BRF along :data:`DENSE_THETA_O`, one row per incidence)}, from
    :func:`mitsuba_powder.fitting.report.plane_curves`."""
    wavelength = float(wavelength)
    fig = _figure(7, 6)
    ax, axr = fig.subplots(2, 1, sharex=True, gridspec_kw={"height_ratios": [3, 1]})
    _margins(fig, 0.75, 0.15, 0.6, 0.35, hspace=0.08)
    _draw_plane(ax, axr, result, wavelength, curves)
    ax.set_ylabel("BRF")
    ax.set_title(f"plane of incidence, {wavelength:g} nm (points: measured, lines: fit)",
                 fontsize=9)
    axr.set(xlabel="signed theta_o (deg; + = back-scattering side)", ylabel="fit - measured")
    _save(fig, path)


def plot_principal_planes(result: FitFigures, wavelengths, path: Path) -> None:
    """The plane of incidence at a few ``wavelengths`` side by side: measured points and the
    fitted values at the same angles (crosses: no plugin evaluation, which would cost more
    than the figure). The residuals of every wavelength are in :func:`plot_residuals`."""
    from matplotlib.ticker import FixedLocator, MaxNLocator

    d = result.data
    plane, signed = _signed_principal(d)
    wavelengths = [float(w) for w in wavelengths]
    n = len(wavelengths)
    fig = _figure(0.9 + 3.0 * n, 3.6 + (0.3 if n == 1 else 0.0))
    axes = fig.subplots(1, n, sharex=True, squeeze=False)[0]
    _margins(fig, 0.65, 0.15, 0.5, 0.8 if n == 1 else 0.5, wspace=0.25)
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
    _suptitle(fig, "plane of incidence (points: measured, joined per incidence; crosses: the "
              "fit at the same angles; + = back-scattering side)")
    _save(fig, path)


def plot_rmse(result: FitFigures, path: Path) -> None:
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


def plot_residuals(result: FitFigures, path: Path) -> None:
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


def plot_polar(result: FitFigures, wavelength: float, path: Path) -> None:
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


#: The figures a job may name (:func:`draw`)
PLOTS = {f.__name__: f for f in (plot_rmse, plot_residuals, plot_principal_planes,
                                 plot_principal_plane, plot_polar)}


def draw(jobs: list[tuple[str, dict]]) -> None:
    """Draw each ``(name, arguments)`` of ``jobs``: a function of :data:`PLOTS` and its keyword
    arguments (``result`` a :class:`FitFigures`, ``path`` the PNG to write).

    Raises:
        ValueError: a name that is not one of :data:`PLOTS`.
    """
    for name, kwargs in jobs:
        if name not in PLOTS:
            raise ValueError(f"figure {name!r} is not one of {', '.join(PLOTS)}")
        PLOTS[name](**kwargs)


def preload() -> None:
    """Import what the figures use (most of a first figure's time), ahead of drawing."""
    import matplotlib.backends.backend_agg  # noqa: F401
    import matplotlib.colors  # noqa: F401
    import matplotlib.figure  # noqa: F401
    import matplotlib.ticker  # noqa: F401
    from matplotlib import colormaps

    colormaps["tab10"], colormaps["viridis"]  # noqa: B018  (built on first use)
