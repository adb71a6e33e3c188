"""Goniometric fitting commands: ``fit``, ``simulate`` and ``compare-models``."""

from __future__ import annotations

import argparse

from ..outputs import final_path
from .common import _load_data, _names, _parse_define, _value


def _cmd_fit(args: argparse.Namespace) -> int:
    from contextlib import nullcontext

    from ..fitting.figure_process import FigureProcess
    from ..fitting.optimise import check_search

    check_search(args.global_stage, args.starts, args.seed, ("--global", "--starts", "--seed"))
    data, held_out = _fit_data(args)
    # started now, the drawing process imports matplotlib while the optimiser runs
    with FigureProcess() if args.figures != "none" else nullcontext() as process:
        return _fit(args, data, held_out, process)


def _fit_data(args: argparse.Namespace):
    """``fit``'s measurements: (those to fit, those held out or None)."""
    import numpy as np

    data = _load_data(args.data, args)
    if args.wavelength:
        keep = np.isin(data.wavelength, args.wavelength)
        missing = sorted(set(args.wavelength) - set(data.wavelengths().tolist()))
        if missing:
            raise ValueError(f"--wavelength {missing}: not in {args.data} "
                             f"(it has {data.wavelengths().tolist()})")
        data = data.subset(keep)
    held_out = None
    if args.fit_incidences:
        try:
            incidences = [float(v) for v in args.fit_incidences.split(",")]
        except ValueError:
            raise ValueError(f"--fit-incidences {args.fit_incidences!r}: expected "
                             "comma-separated angles in degrees, e.g. 0,30,60") from None
        mask = np.isin(data.theta_i, incidences)
        if not mask.any():
            raise ValueError(f"--fit-incidences {incidences}: no such incidence in the data "
                             f"({np.unique(data.theta_i).tolist()})")
        held_out = data.subset(~mask)
        data = data.subset(mask)
    return data, held_out


def _fit(args: argparse.Namespace, data, held_out, process) -> int:
    """``fit``: fit ``data``, predict ``held_out``, report (figures drawn by ``process`` when
    given)."""
    from ..fitting.fit import default_free, fit, predict
    from ..fitting.report import write_report

    fixed = dict(_parse_define(d) for d in args.set)
    fixed = {k: _value(v) for k, v in fixed.items()}
    free = _names(args.free) or default_free(data, fixed)
    print(f"fitting {len(data)} measurements at {data.wavelengths().tolist()} nm; "
          f"free: {', '.join(free)}; fixed: {fixed or 'plugin defaults'}")
    result = fit(data, free, fixed, starts=args.starts, polish=args.polish, seed=args.seed,
                 progress=print, regime=args.regime, global_stage=args.global_stage)
    held = None
    if held_out is not None and len(held_out):
        held = (held_out, predict(result, held_out))
    path = write_report(result, args.out, held, figures=args.figures, process=process)
    for name in result.free:
        keys = [k for k in result.uncertainties if k == name or k.startswith(name + "@")]
        for k in keys:
            value = (result.parameters[k] if "@" not in k else
                     result.parameters_by_wavelength[float(k.split("@")[1])][name])
            print(f"  {k:22s} = {value:.6g} +- {result.uncertainties[k]:.3g}")
    print(f"RMSE(BRF) {result.rmse():.4g}, relative RMSE {result.relative_rmse_percent():.2f} %, "
          f"{result.evaluations} evaluations in {result.seconds:.1f} s")
    if result.chi2_per_point is not None:
        print(f"chi2/N = {result.chi2_per_point:.4g} (the data's sigma)")
    ratios = result.regime["kappa_over_k0"].values()
    print(f"regime {result.regime['name']}: kappa/k0 {min(ratios):.3g}-{max(ratios):.3g}"
          + (f" (bound 0.25: extinction <= {result.regime['extinction_limit']:.4g} /um)"
             if result.regime["name"] == "ebs" else " (not bounded)"))
    print(f"{result.agreeing} of {len(result.starts)} starts reached the best loss (within 1 %)")
    for b in result.radius_branches:
        print(f"  radius {b['radius']:.5g} um (albedo within 1-sigma for "
              f"{b['lower']:.5g}-{b['upper']:.5g} um)")
    if "radius_note" in result.optics:
        print(f"  {result.optics['radius_note']}")
    for line in result.warnings:
        print(f"warning: {line}")
    if held is not None:
        from ..fitting.report import statistics

        st = statistics(held[1], held[0])
        print(f"prediction of {st['n']} held-out measurements: relative RMSE "
              f"{st['relative_rmse_percent']:.2f} %")
    print(f"wrote {final_path(path)}" + {"none": " (no figures: --figures none)",
                             "summary": f" and the summary figures in {args.out}",
                             "all": f" and the summary and per-wavelength figures in "
                                    f"{args.out}"}[args.figures])
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    import numpy as np

    from ..fitting.protocols import simulate
    from ..io.measurements import Measurements, save_measurements
    from ..plugin.params import load_properties

    if args.format == "csv" and args.layout != "multi":
        raise ValueError(f"--layout {args.layout} applies to --format ipag; a CSV file holds "
                         "every geometry (give --format ipag for a folder of single-geometry "
                         "files)")
    wavelengths = args.wavelength or [700.0]
    parts = []
    for k, lam in enumerate(wavelengths):
        props = load_properties(args.params, lam)
        parts.append(simulate(props, args.protocol, (lam,), args.noise, args.seed + k))
    cat = lambda name: np.concatenate([getattr(p, name) for p in parts])  # noqa: E731
    data = Measurements(cat("theta_i"), cat("theta_o"), cat("phi"), cat("wavelength"),
                        cat("brf"), cat("sigma") if args.noise > 0 else None,
                        parts[0].comments + [f"parameters from {args.params}"], "synthetic")
    if args.format == "ipag":
        from ..io.ipag import save_ipag

        save_ipag(args.out, data, layout=args.layout, sample=args.sample,
                  convention=args.convention)
    else:
        save_measurements(args.out, data, digits=None)
    how = f", {args.layout} layout, {args.convention} convention" if args.format == "ipag" else ""
    print(f"wrote {len(data)} synthetic measurements to {args.out} ({args.format}{how})")
    return 0


def _cmd_compare_models(args: argparse.Namespace) -> int:
    import numpy as np

    from ..fitting.comparison import compare_models, write_comparison

    data = _load_data(args.data, args)
    if args.wavelength:
        data = data.subset(np.isin(data.wavelength, args.wavelength))
        if not len(data):
            raise ValueError(f"--wavelength {args.wavelength}: not in {args.data}")
    free = _names(args.free)
    fixed = {k: _value(v) for k, v in (_parse_define(d) for d in args.set)}
    from ..fitting.comparison import surface_fresnel_settings

    modes = surface_fresnel_settings(fixed)
    print(f"comparing the powder model (surface_fresnel: {', '.join(modes)}) with lambertian, "
          f"oren_nayar, rtlsr and hapke on {len(data)} measurements at "
          f"{data.wavelengths().tolist()} nm")
    rows = compare_models(data, free, fixed, starts=args.starts)
    path = write_comparison(rows, args.out)
    print(path.read_text())
    print(f"wrote {final_path(path)} and {path.with_suffix('.json').name}")
    return 0
