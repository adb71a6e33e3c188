"""Command line interface: ``mitsuba-powder <command> ...`` (thin layer over the Python API)."""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Sequence


def _cmd_info(args: argparse.Namespace) -> int:
    import mitsuba_powder

    status = mitsuba_powder.check_llvm()
    print(f"mitsuba-powder {mitsuba_powder.__version__}")
    print(f"plugin:     {mitsuba_powder.plugin_path()}")
    print(f"plugin dir: {mitsuba_powder.plugin_dir()}  (use: mitsuba -a <plugin dir> scene.xml)")
    llvm = ".".join(str(v) for v in status.version)
    print(f"LLVM:       {llvm} ({'usable' if status.usable else status.message})")
    return 0


def _cmd_render(args: argparse.Namespace) -> int:
    from .plugin.params import load_properties
    from .rendering.render import render_scene

    overrides = {k: _value(v) for k, v in (_parse_define(d) for d in args.set)}
    props = (load_properties(args.params, None, overrides)
             if args.params or overrides else None)
    result = render_scene(
        args.scene,
        args.output,
        variant=args.variant,
        spp=args.spp,
        defines=dict(_parse_define(d) for d in args.define),
        properties=props,
        allow_missing=args.allow_missing,
    )
    if props:
        shown = lambda v: f"{v:.6g}" if isinstance(v, float) else str(v)  # noqa: E731
        print("set on every powder BSDF: " + (", ".join(
            f"{k} = {shown(props[k])}" for k in result.applied) or "nothing"))
    if result.removed:
        print(f"removed from the scene's powder (they would override what was set): "
              f"{', '.join(result.removed)}")
    if result.not_applied:
        print(f"NOT applied (--allow-missing; not changeable after loading, or absent from "
              f"this scene; set them in the scene file): {', '.join(result.not_applied)}")
    spp = f"{result.spp} spp" + ("" if args.spp else " (the scene's)")
    print(f"wrote {result.output} ({result.width}x{result.height}, {spp}, "
          f"variant {result.variant}, {result.seconds:.2f} s)")
    return 0


def _cmd_colour(args: argparse.Namespace) -> int:
    import numpy as np

    from .plugin.appearance import powder_colour

    if (args.radius2 is None) != (args.fraction2 is None):
        raise ValueError("give both --radius2 and --fraction2, or neither")
    model = {}
    if args.grains != "sphere":
        model["grains"] = args.grains
    if args.agglomerate_radius is not None:
        model["agglomerate_radius"] = args.agglomerate_radius
    if args.agglomerate_fill is not None:
        model["agglomerate_fill"] = args.agglomerate_fill
    if args.mixing is not None:
        model["mixing"] = args.mixing
    c = powder_colour(args.radius, radius2=args.radius2, fraction2=args.fraction2,
                      material=args.material, samples=args.samples, **model)
    grains = f"{args.grains} grains, radius {args.radius:g} um"
    if args.radius2 is not None:
        grains += f" + radius2 {args.radius2:g} um (volume fraction {args.fraction2:g})"
    if args.grains == "agglomerate":
        grains += (f" (crystallites) in agglomerates of radius {args.agglomerate_radius:g} um, "
                   f"fill {c.properties.get('agglomerate_fill', 0.5):g}, "
                   f"{c.properties.get('mixing', 'bruggeman')}")
    print(f"{args.material}, {grains}; plugin defaults otherwise")
    print(f"{'nm':>5s} {'albedo':>8s} {'Q_ext':>9s} {'Q_sca':>9s} {'tau_o':>7s} {'R(0/d)':>8s}")
    step = max(1, len(c.wavelengths_nm) // 12)
    for i in range(0, len(c.wavelengths_nm), step):
        print(f"{c.wavelengths_nm[i]:5.0f} {c.albedo[i]:8.4f} {c.q_ext[i]:9.4g} "
              f"{c.q_sca[i]:9.4g} {c.tau_o[i]:7.3f} {c.reflectance[i]:8.4f}")
    print(f"CIE XYZ (D65): {np.array2string(c.xyz, precision=4)}")
    print(f"sRGB: {np.array2string(c.srgb, precision=4)} (8 bit: {c.srgb8})")
    print(f"CIELAB: L* {c.lab[0]:.2f}, a* {c.lab[1]:.2f}, b* {c.lab[2]:.2f}")
    return 0


def _read_reflectance_csv(path: str) -> tuple:
    """(wavelengths nm, reflectance) from a CSV of two columns (an optional header line;
    ``#`` lines are comments)."""
    import csv
    from pathlib import Path

    import numpy as np

    from .outputs import note_input

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"--reflectance {path}: no such file")
    note_input(p)
    wl, values = [], []
    with p.open(newline="", encoding="utf-8") as fh:
        for lineno, row in enumerate(csv.reader(fh), start=1):
            if not row or row[0].strip().startswith("#"):
                continue
            if len(row) != 2:
                raise ValueError(f"{path}, line {lineno}: {len(row)} fields, expected 2 "
                                 "(wavelength in nm, reflectance)")
            try:
                a, b = float(row[0]), float(row[1])
            except ValueError:
                if not wl:  # a header line
                    continue
                raise ValueError(f"{path}, line {lineno}: {row!r} is not two numbers") from None
            wl.append(a)
            values.append(b)
    if not wl:
        raise ValueError(f"{path}: no data rows (wavelength nm, reflectance)")
    return np.array(wl), np.array(values)


def _cmd_albedo(args: argparse.Namespace) -> int:
    from .plugin.appearance import albedo_for_reflectance, reflectance_of_srgb, write_spectrum

    if (args.reflectance is None) == (args.srgb is None):
        raise ValueError("give exactly one of --reflectance FILE.csv and --srgb R,G,B")
    if args.srgb is not None:
        try:
            rgb = [float(v) for v in args.srgb.split(",")]
        except ValueError:
            raise ValueError(f"--srgb {args.srgb!r}: expected R,G,B, e.g. 0.7,0.35,0.25") \
                from None
        wl, target = reflectance_of_srgb(rgb)
        source = f"sRGB {args.srgb} (spectral upsampling: Mallett & Yuksel 2019)"
    else:
        wl, target = _read_reflectance_csv(args.reflectance)
        source = args.reflectance
    props = {k: _value(v) for k, v in (_parse_define(d) for d in args.set)}
    albedo = albedo_for_reflectance(wl, target, args.geometry, **props)
    write_spectrum(args.out, wl, albedo)
    print(f"albedo for {source}, geometry {args.geometry}, properties "
          f"{props or 'plugin defaults'}: {len(wl)} wavelengths {wl.min():g}-{wl.max():g} nm, "
          f"albedo {albedo.min():.4f}-{albedo.max():.4f}")
    print(f"wrote {args.out} (use it as <spectrum name=\"albedo\" filename=\"{args.out}\"/>)")
    return 0


def _value(text: str):
    """A --set value: a number if it parses as one, else the string."""
    try:
        return float(text)
    except ValueError:
        return text


def _load_data(path: str, args: argparse.Namespace):
    """Load measurements (CSV, IPAG file or folder) and print what the loader did."""
    from .io.measurements import load_measurements

    data = load_measurements(path, convention=args.convention, zero_error=args.zero_error)
    for line in data.comments:
        if line.startswith("loader: "):
            print(line[len("loader: "):])
    if data.convention == "project":
        g = data.geometry_summary()
        print(f"{path}: {g['rows']} measurements, {g['geometries']} unique geometries "
              f"(incidence, viewing direction, wavelength), {g['replicated_rows']} replicated")
    return data


def _add_capture_options(p: argparse.ArgumentParser, use: str) -> None:
    """The capture argument and its options (commands that read RTI captures)."""
    p.add_argument("capture", help="the capture's .lp file (first line the count, then "
                                   "'filename lx ly lz'); images beside it")
    p.add_argument("--encoding", choices=("srgb", "linear"), default="srgb",
                   help="srgb: file values are sRGB-encoded (linearised on read); linear: "
                        "value / full scale is linear (default srgb)")
    p.add_argument("--mask", default=None,
                   help=f"mask image (PNG): pixels above half scale are {use}")


def _add_data_options(p: argparse.ArgumentParser) -> None:
    """Options of the commands that read measurement files."""
    p.add_argument("--convention", choices=("signed", "physical"), default=None,
                   help="IPAG files: angle convention (default: decided from the file; "
                        "see docs/fitting.md, 'Files from IPAG goniometers and SSHADE')")
    p.add_argument("--zero-error", choices=("raise", "unweighted", "skip"), default="raise",
                   help="IPAG files where some errors are zero or missing: stop (raise), "
                        "fit unweighted, or skip those values")


def _cmd_fit(args: argparse.Namespace) -> int:
    import numpy as np

    from .fitting.fit import default_free, fit, predict
    from .fitting.report import write_report

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
    fixed = dict(_parse_define(d) for d in args.set)
    fixed = {k: _value(v) for k, v in fixed.items()}
    free = ([n.strip() for n in args.free.split(",")] if args.free else
            default_free(data, fixed))
    print(f"fitting {len(data)} measurements at {data.wavelengths().tolist()} nm; "
          f"free: {', '.join(free)}; fixed: {fixed or 'plugin defaults'}")
    result = fit(data, free, fixed, starts=args.starts, polish=args.polish, seed=args.seed,
                 progress=print, regime=args.regime)
    held = None
    if held_out is not None and len(held_out):
        held = (held_out, predict(result, held_out))
    path = write_report(result, args.out, held, figures=args.figures)
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
        from .fitting.report import statistics

        st = statistics(held[1], held[0])
        print(f"prediction of {st['n']} held-out measurements: relative RMSE "
              f"{st['relative_rmse_percent']:.2f} %")
    print(f"wrote {path}" + {"none": " (no figures: --figures none)",
                             "summary": f" and the summary figures in {args.out}",
                             "all": f" and the summary and per-wavelength figures in "
                                    f"{args.out}"}[args.figures])
    return 0


def _cmd_simulate(args: argparse.Namespace) -> int:
    import numpy as np

    from .fitting.protocols import simulate
    from .io.measurements import Measurements, save_measurements
    from .plugin.params import load_properties

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
        from .io.ipag import save_ipag

        save_ipag(args.out, data, layout=args.layout, sample=args.sample,
                  convention=args.convention)
    else:
        save_measurements(args.out, data, digits=None)
    how = f", {args.layout} layout, {args.convention} convention" if args.format == "ipag" else ""
    print(f"wrote {len(data)} synthetic measurements to {args.out} ({args.format}{how})")
    return 0


def _cmd_compare_models(args: argparse.Namespace) -> int:
    import numpy as np

    from .fitting.comparison import compare_models, write_comparison

    data = _load_data(args.data, args)
    if args.wavelength:
        data = data.subset(np.isin(data.wavelength, args.wavelength))
        if not len(data):
            raise ValueError(f"--wavelength {args.wavelength}: not in {args.data}")
    free = [n.strip() for n in args.free.split(",")] if args.free else None
    fixed = {k: _value(v) for k, v in (_parse_define(d) for d in args.set)}
    from .fitting.comparison import surface_fresnel_settings

    modes = surface_fresnel_settings(fixed)
    print(f"comparing the powder model (surface_fresnel: {', '.join(modes)}) with lambertian, "
          f"oren_nayar, rtlsr and hapke on {len(data)} measurements at "
          f"{data.wavelengths().tolist()} nm")
    rows = compare_models(data, free, fixed, starts=args.starts)
    path = write_comparison(rows, args.out)
    print(path.read_text())
    print(f"wrote {path} and {path.with_suffix('.json').name}")
    return 0


def _cmd_render_gonio(args: argparse.Namespace) -> int:
    from .fitting.protocols import protocol_geometries
    from .plugin.params import load_properties
    from .rendering.gonio import render_gonio, render_measurements
    from .rendering.gonio_report import write_gonio_report

    overrides = {k: _value(v) for k, v in (_parse_define(d) for d in args.set)}
    kwargs = dict(spp=args.spp, resolution=args.resolution, source_radius=args.source_radius,
                  strategy=args.strategy, seed=args.seed, progress=print)
    if args.data:
        if args.protocol:
            raise ValueError("give --data or --protocol, not both")
        data = _load_data(args.data, args)
        if args.wavelength is not None:
            data = data.subset(data.wavelength == args.wavelength)
            if not len(data):
                raise ValueError(f"--wavelength {args.wavelength:g}: not in {args.data}")
        props = lambda lam: load_properties(args.params, lam, overrides)  # noqa: E731
        result = render_measurements(props, data, variant=args.variant or "llvm_ad_mono",
                                     **kwargs)
    else:
        ti, to, ph = protocol_geometries(args.protocol or "shadows,backscatter")
        variant = args.variant or "llvm_ad_rgb"
        if args.wavelength is not None and "mono" not in variant:
            raise ValueError(f"--wavelength {args.wavelength:g} applies to mono variants "
                             f"(--variant {variant} renders every channel); use e.g. "
                             "--variant llvm_ad_mono")
        wl = args.wavelength if "mono" in variant else None
        props = load_properties(args.params, wl, overrides)
        result = render_gonio(props, ti, to, ph, wavelength=wl, variant=variant, **kwargs)
    path = write_gonio_report(args.out, result)
    s = result.summary()
    d, m = s["deterministic"], s["monte_carlo"]
    print(f"{s['geometries']} geometries x {len(result.channels)} channels in "
          f"{result.seconds:.1f} s ({result.variant}, {result.spp} spp)")
    print(f"  deterministic (no Monte Carlo noise): {d['values']} values" + (
        f", max relative difference {d['max_relative_difference']:.2g} against a float32 "
        f"tolerance of {d['relative_tolerance_min']:.2g}-{d['relative_tolerance_max']:.2g}, "
        f"{d['beyond_tolerance']} beyond it" if d["values"] else ""))
    print(f"  Monte Carlo: {m['values']} values" + (
        f", max |z| {m['max_abs_z']:.2f}, {m['beyond_3_sigma']} beyond 3 sigma (expected "
        f"{m['expected_beyond_3_sigma_if_gaussian']} if Gaussian)" if m["values"]
        else " (no z-test)"))
    print(f"wrote {path}, gonio.csv and gonio.png")
    return 0


def _corners(text: str):
    try:
        pts = [tuple(float(v) for v in p.split(",")) for p in text.split()]
    except ValueError:
        pts = []
    if len(pts) != 4 or any(len(p) != 2 for p in pts):
        raise ValueError(f"--chart {text!r}: expected four 'x,y' pixel positions separated by "
                         "spaces (centres of the dark skin, bluish green, black and white "
                         "patches)")
    return pts


def _cmd_compare_photo(args: argparse.Namespace) -> int:
    from .rendering.photo import compare_images, read_image, write_report

    render = read_image(args.render, args.render_encoding)
    photo = read_image(args.photo, args.photo_encoding)
    region = None
    if args.region:
        try:
            region = [int(v) for v in args.region.split(",")]
        except ValueError:
            region = []
        if len(region) != 4:
            raise ValueError(f"--region {args.region!r}: expected x0,y0,x1,y1 in pixels")
    stats, aligned, de = compare_images(
        render, photo, corners=_corners(args.chart) if args.chart else None,
        chart_half=args.chart_window, align_mode=args.align, region=region, white=args.white,
        saturation=(None if args.saturation < 0 else args.saturation) if args.saturation
        is not None else (None if args.photo.lower().endswith(".exr") else 0.99),
        max_clipped=args.max_clipped)
    path = write_report(args.out, stats, render, aligned, de)
    if stats.chart_delta_e_mean is not None:
        print(f"ColorChecker calibration: patches Delta E 2000 mean "
              f"{stats.chart_delta_e_mean:.2f}, max {stats.chart_delta_e_max:.2f}")
    wb = ", ".join(f"{v:.3f}" for v in stats.white_balance)
    print(f"alignment ({args.align}): exposure {stats.exposure_stops:+.3f} stops, "
          f"white balance (R/G, 1, B/G) = ({wb})")
    if stats.saturated_pixels:
        print(f"left out {stats.saturated_pixels} clipped photo pixels "
              f"({100 * stats.clipped_fraction:.1f} % of the {stats.region_pixels} pixels "
              "compared)")
    print(f"CIEDE2000 over {stats.pixels} pixels: mean {stats.mean:.2f}, median "
          f"{stats.median:.2f}, p95 {stats.p95:.2f}, max {stats.max:.2f}")
    print(f"wrote {path}, delta_e.png and side_by_side.png")
    return 0


def _names(text: str | None) -> list[str] | None:
    """A comma-separated --free list (None when not given)."""
    return [n.strip() for n in text.split(",") if n.strip()] if text else None


def _fixed_properties(items: list[str]) -> dict:
    """--set NAME=VALUE items as a property dict."""
    fixed = {}
    for item in items:
        name, sep, value = item.partition("=")
        if not sep or not name:
            raise ValueError(f"--set {item!r}: expected NAME=VALUE")
        fixed[name] = _value(value)
    return fixed


def _powder_fitter(free: list[str] | None, fixed: dict, progress=None):
    """compare-maps' powder model: rti.fit_maps with these settings."""
    from .rti import fit_maps

    def fit(images, directions, mask=None):
        return fit_maps(images, directions, free=free, mask=mask, fixed=fixed,
                        progress=progress)

    return fit


def _cmd_fit_maps(args: argparse.Namespace) -> int:
    from .rti import fit_maps, load_capture
    from .rti.maps import write_maps

    capture = load_capture(args.capture, encoding=args.encoding, mask=args.mask)
    k, h, w, c = capture.images.shape
    print(f"{args.capture}: {k} lights, {w} x {h} px, {c} channels, {capture.file_format} "
          f"{capture.bit_depth} bit, encoding {capture.encoding}")
    free = _names(args.free)
    result = fit_maps(capture.images, capture.directions, free=free, mask=capture.mask,
                      fixed=_fixed_properties(args.set), gains=args.gains,
                      max_iterations=args.iterations, rounds=args.rounds, progress=print)
    path = write_maps(result, args.out, capture, list(capture.names))
    info = json.loads(path.read_text())
    print(f"free per pixel: normal + {', '.join(result.free)} ({result.n_parameters} numbers)")
    for name, st in info["statistics"].items():
        if st.get("median") is not None:
            print(f"  {name}: median {st['median']:.4g} (5-95 %: {st['p5']:.4g}-{st['p95']:.4g})")
    print(f"wrote {args.out}: maps (EXR), fit.json, scene.xml")
    return 0


def _cmd_relight(args: argparse.Namespace) -> int:
    from .rti.maps import relight_files

    paths = relight_files(args.maps, args.lp, args.out)
    print(f"wrote {len(paths)} images to {args.out}")
    return 0


def _cmd_compare_maps(args: argparse.Namespace) -> int:
    from .rti import load_capture
    from .rti.comparison import baseline_fitter, compare, write_comparison

    names = [m.strip() for m in args.models.split(",") if m.strip()]
    free = _names(args.free)
    from .rti.baselines import BASELINES

    unknown = [n for n in names if n != "powder" and n not in BASELINES]
    if unknown or not names:
        raise ValueError(f"--models {args.models!r}: unknown {unknown}; valid models are "
                         f"{', '.join(list(BASELINES) + ['powder'])}")
    models = {name: (_powder_fitter(free, _fixed_properties(args.set))
                     if name == "powder" else baseline_fitter(name)) for name in names}
    capture = load_capture(args.capture, encoding=args.encoding, mask=args.mask)
    k, h, w, c = capture.images.shape
    print(f"{args.capture}: {k} lights, {w} x {h} px, {c} channels, {capture.file_format} "
          f"{capture.bit_depth} bit, encoding {capture.encoding}")
    comp = compare(capture, models, phase=args.phase)
    path = write_comparison(comp, args.out, error_images=not args.no_error_images)
    print(path.read_text())
    print(f"wrote {path}, compare.json" + ("" if args.no_error_images else
                                            " and error_<protocol>_<model>.png"))
    return 0


def _parse_define(text: str) -> tuple[str, str]:
    if "=" not in text:
        raise SystemExit(f"mitsuba-powder: -D expects NAME=VALUE, got {text!r}")
    name, value = text.split("=", 1)
    return name, value


class _HelpFormatter(argparse.HelpFormatter):
    """Every option's help ends with its default, unless the help already states it."""

    def _get_help_string(self, action: argparse.Action) -> str:
        text = action.help or ""
        if ("default" in text or not action.option_strings or action.default is None
                or action.default is argparse.SUPPRESS or isinstance(action.default, bool)
                or action.default == []):
            return text
        return text + " (default: %(default)s)"


def _version() -> str:
    """The installed distribution's version (no import of mitsuba needed)."""
    from importlib.metadata import PackageNotFoundError, version

    try:
        return version("mitsuba-powder")
    except PackageNotFoundError:  # run from a source tree that is not installed
        from . import __version__

        return __version__


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mitsuba-powder",
        description="Dry-powder reflectance (Gerardin et al. 2023) for Mitsuba 3.",
        formatter_class=_HelpFormatter,
    )
    parser.add_argument("--version", action="version", version=f"mitsuba-powder {_version()}")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("info", help="show where the plugin is and whether LLVM works")
    p.set_defaults(func=_cmd_info)

    p = sub.add_parser("render", help="render a scene file that uses the powder BSDF")
    p.add_argument("scene", help="scene XML file")
    p.add_argument("-o", "--output", required=True, help="output image (.exr or .png)")
    p.add_argument("--variant", default="scalar_rgb", help="Mitsuba variant (default scalar_rgb)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel (default: scene's)")
    p.add_argument(
        "-D", "--define", action="append", default=[], metavar="NAME=VALUE",
        help="set a scene parameter declared with <default name=...> (repeatable)",
    )
    p.add_argument("--params", default=None,
                   help="JSON of powder properties or a fit.json, set on every powder BSDF")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a powder property set on every powder BSDF (repeatable); a name that "
                        "is not a powder property is an error")
    p.add_argument("--allow-missing", action="store_true",
                   help="render even if some --params/--set properties cannot be set on this "
                        "scene (default: an error naming them)")
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("albedo", help="the albedo spectrum that reproduces a measured "
                                      "reflectance or an sRGB colour")
    p.add_argument("--reflectance", default=None, metavar="FILE.csv",
                   help="CSV of wavelength (nm), reflectance")
    p.add_argument("--srgb", default=None, metavar="R,G,B",
                   help="an sRGB colour (0-1 or 0-255), upsampled to a spectrum")
    p.add_argument("--geometry", default="0:d",
                   help="0:d (directional-hemispherical at normal incidence) or "
                        "THETA_I:THETA_O, e.g. 0:45 (the BRF in the plane of incidence)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="another plugin property, e.g. --set extinction=0.5 (repeatable)")
    p.add_argument("--out", required=True, help="output spectrum file (.spd)")
    p.set_defaults(func=_cmd_albedo)

    p = sub.add_parser("colour", help="albedo, tau_o and colour of a powder from its grains")
    p.add_argument("--radius", type=float, default=0.017, help="grain radius, um")
    p.add_argument("--radius2", type=float, default=None, help="second population radius, um")
    p.add_argument("--fraction2", type=float, default=None,
                   help="volume fraction of the second population")
    p.add_argument("--material", default="hematite",
                   help="hematite, magnetite or a refractiveindex.info YAML file")
    p.add_argument("--grains", default="sphere", choices=["sphere", "agglomerate", "slab"],
                   help="grain model (docs/powder.md, Grain models)")
    p.add_argument("--agglomerate-radius", type=float, default=None,
                   help="agglomerate radius, um (--grains agglomerate)")
    p.add_argument("--agglomerate-fill", type=float, default=None,
                   help="volume fill of crystallites in an agglomerate (default 0.5)")
    p.add_argument("--mixing", default=None, choices=["bruggeman", "maxwell_garnett"],
                   help="effective-medium rule of an agglomerate (default bruggeman)")
    p.add_argument("--samples", type=int, default=4096, help="quadrature nodes")
    p.set_defaults(func=_cmd_colour)

    p = sub.add_parser("fit", help="fit the powder model to goniometer measurements")
    p.add_argument("data", help="measurement CSV, IPAG file, or folder of IPAG "
                   "single-geometry files (see mitsuba_powder.io.measurements)")
    p.add_argument("--wavelength", type=float, nargs="+", default=None,
                   help="fit only these wavelengths, nm (several: a joint fit)")
    p.add_argument("--free", default=None,
                   help="plugin properties to fit, comma-separated (default: amplitude_volume,"
                        "g,extinction,amplitude_surface,correlation_length, plus radius when "
                        "several wavelengths are fitted)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a fixed plugin property, e.g. --set tau_o=0.6667 (repeatable)")
    p.add_argument("--fit-incidences", default=None, metavar="DEG,DEG,...",
                   help="fit only these incidences and report the prediction of the others")
    p.add_argument("--starts", type=int, default=64,
                   help="starts of the global phase (Sobol design; with the radius free, on a "
                        "log grid of radii)")
    p.add_argument("--polish", type=int, default=4,
                   help="distinct end points of the global phase polished (scipy)")
    p.add_argument("--regime", choices=("ebs", "free"), default="ebs",
                   help="ebs: bound the extinction so that kappa/k0 <= 0.25 at every fitted "
                        "wavelength (the narrow-cone regime of the theory); free: lift it")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="fit_out", help="output folder (fit.json, figures)")
    p.add_argument("--figures", choices=("summary", "all", "none"), default="summary",
                   help="summary: one set for the whole fit (relative RMSE per wavelength, "
                        "residuals against the angles, the plane of incidence at up to 4 "
                        "wavelengths); all: also a plane-of-incidence and a polar figure per "
                        "wavelength; none: fit.json only (default summary)")
    _add_data_options(p)
    p.set_defaults(func=_cmd_fit)

    p = sub.add_parser("simulate", help="simulate measurements at protocol geometries")
    p.add_argument("--params", required=True,
                   help="JSON of plugin properties, or a fit.json (its 'parameters')")
    p.add_argument("--protocol", default="shadows,backscatter",
                   help="comma-separated: shadows, backscatter")
    p.add_argument("--wavelength", type=float, nargs="+", default=None, help="nm (700)")
    p.add_argument("--noise", type=float, default=0.0, help="relative 1-sigma noise")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", required=True,
                   help="output CSV, IPAG file (--layout multi) or folder (--layout single)")
    p.add_argument("--format", choices=("csv", "ipag"), default="csv",
                   help="csv (project format) or ipag (IPAG goniometer text)")
    p.add_argument("--layout", choices=("multi", "single"), default="multi",
                   help="ipag: one multi-geometry file, or a folder of single-geometry files")
    p.add_argument("--convention", choices=("physical", "signed"), default="physical",
                   help="ipag: angles as newer files and SSHADE (physical) or older files "
                        "(signed; plane of incidence only)")
    p.add_argument("--sample", default="synthetic", help="ipag: sample name in the file")
    p.set_defaults(func=_cmd_simulate)

    p = sub.add_parser("compare-models",
                       help="fit the powder model and four baselines to the same data")
    p.add_argument("data", help="measurement CSV, IPAG file or folder")
    p.add_argument("--wavelength", type=float, nargs="+", default=None, help="nm")
    p.add_argument("--free", default=None, help="powder properties to fit (as in fit)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="fixed powder property (repeatable)")
    p.add_argument("--starts", type=int, default=64,
                   help="starts of each model's global phase")
    p.add_argument("--out", default="model_compare",
                   help="output folder (model_comparison.md and .json)")
    _add_data_options(p)
    p.set_defaults(func=_cmd_compare_models)

    p = sub.add_parser("render-gonio",
                       help="render the patch at gonio geometries; rendered vs analytic BRF")
    p.add_argument("--protocol", default=None,
                   help="comma-separated protocols: shadows, backscatter (default both)")
    p.add_argument("--data", default=None,
                   help="measurement CSV, IPAG file or folder: render its geometries and "
                        "wavelengths (mono)")
    p.add_argument("--params", default=None, help="JSON of plugin properties or a fit.json")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="plugin property (repeatable), e.g. --set extinction=2")
    p.add_argument("--variant", default=None,
                   help="Mitsuba variant (default llvm_ad_rgb; llvm_ad_mono with --data)")
    p.add_argument("--wavelength", type=float, default=None,
                   help="nm: with --protocol, the mono variants' wavelength (default 700); "
                        "with --data, render only that wavelength's rows")
    p.add_argument("--spp", type=int, default=64, help="samples per pixel")
    p.add_argument("--resolution", type=int, default=16, help="pixels per side per geometry")
    p.add_argument("--source-radius", type=float, default=0.0,
                   help="angular radius of the source, degrees (0: collimated)")
    p.add_argument("--strategy", default="emitter", choices=("emitter", "bsdf", "mis"),
                   help="how the source is sampled: emitter, bsdf or multiple importance "
                        "sampling")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--out", default="gonio_out", help="output folder")
    _add_data_options(p)
    p.set_defaults(func=_cmd_render_gonio)

    p = sub.add_parser("compare-photo", help="compare a render with a photo (CIEDE2000)")
    p.add_argument("render", help="rendered image (.exr, .png, .jpg)")
    p.add_argument("photo", help="photograph (.exr, .png, .jpg; 8 or 16 bit)")
    for who in ("render", "photo"):
        p.add_argument(f"--{who}-encoding", default="auto", choices=("auto", "linear", "srgb"),
                       help="auto: EXR linear, PNG/JPEG sRGB-encoded")
    p.add_argument("--chart", default=None, metavar="'X,Y X,Y X,Y X,Y'",
                   help="calibrate the photo with the ColorChecker 24 in it: pixel centres of "
                        "its dark skin, bluish green, black and white patches")
    p.add_argument("--chart-window", type=int, default=3,
                   help="half-size of the patch sampling window, px")
    p.add_argument("--align", default="white-balance",
                   choices=("none", "exposure", "white-balance"),
                   help="exposure: one gain; white-balance: per-channel gains")
    p.add_argument("--region", default=None, help="x0,y0,x1,y1: pixels to compare")
    p.add_argument("--white", type=float, default=None,
                   help="linear level of L* = 100 (default: the render's 99th percentile)")
    p.add_argument("--saturation", type=float, default=None,
                   help="leave out photo pixels with a channel >= this linear value (default "
                        "0.99 for PNG/JPEG, none for EXR; negative: keep all)")
    p.add_argument("--max-clipped", type=float, default=0.1, metavar="FRACTION",
                   help="stop with an error when more than this fraction of the compared "
                        "region is clipped in the photo (0-1; 1: never)")
    p.add_argument("--out", default="photo_compare",
                   help="output folder (photo_comparison.json, delta_e.png, side_by_side.png)")
    p.set_defaults(func=_cmd_compare_photo)

    p = sub.add_parser("compare-maps", help="held-out-light error of per-pixel models (PTM, "
                                            "HSH, Lambertian) on an RTI capture")
    p.add_argument("--out", required=True,
                   help="output folder (compare.md, compare.json, error maps)")
    _add_capture_options(p, "scored")
    p.add_argument("--models", default="ptm,hsh,lambertian,lambertian_clamped",
                   help="comma-separated: ptm, hsh, lambertian, lambertian_clamped, powder "
                        "(the per-pixel powder fit of fit-maps)")
    p.add_argument("--free", default=None,
                   help="powder model: properties fitted per pixel besides the normal "
                        "(default: see fit-maps)")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="powder model: a plugin property held for every pixel (repeatable)")
    p.add_argument("--phase", type=int, default=4,
                   help="interpolation protocol: hold out the lights k %% 5 == PHASE (.lp "
                        "order from 0; default 4)")
    p.add_argument("--no-error-images", action="store_true",
                   help="do not write the per-pixel error maps (PNG)")
    p.set_defaults(func=_cmd_compare_maps)

    p = sub.add_parser("fit-maps", help="fit a normal and powder parameters to every pixel of "
                                        "an RTI capture; write EXR maps and a scene")
    p.add_argument("--out", required=True,
                   help="output folder: <property>.exr, albedo.exr, normal.exr, residual.exr, "
                        "fit.json, scene.xml")
    p.add_argument("--free", default=None,
                   help="comma-separated properties fitted per pixel besides the normal "
                        "(default: albedo, amplitude_surface, correlation_length; "
                        "docs/rti.md says why)")
    _add_capture_options(p, "fitted")
    p.add_argument("--gains", choices=("fit", "fixed"), default="fit",
                   help="per-light gains shared by all pixels: fitted (mean 1) or all 1")
    p.add_argument("--set", action="append", default=[], metavar="NAME=VALUE",
                   help="a plugin property held for every pixel (repeatable), e.g. "
                        "--set extinction=0.5")
    p.add_argument("--iterations", type=int, default=30,
                   help="Levenberg-Marquardt iterations per round")
    p.add_argument("--rounds", type=int, default=3,
                   help="alternations of the per-pixel fit with the gains")
    p.set_defaults(func=_cmd_fit_maps)

    p = sub.add_parser("relight", help="images of a fit-maps result under the lights of an "
                                       ".lp file")
    p.add_argument("maps", help="folder written by fit-maps")
    p.add_argument("--lp", required=True,
                   help="lights: an .lp file (count, then 'filename lx ly lz' per line)")
    p.add_argument("--out", required=True, help="output folder (one image per .lp line, "
                                                "the capture's format and bit depth)")
    p.set_defaults(func=_cmd_relight)
    for command in sub.choices.values():
        command.formatter_class = _HelpFormatter
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mitsuba-powder`` command."""
    from .outputs import guarding_inputs

    args = build_parser().parse_args(argv)
    try:
        with guarding_inputs():  # no command writes over a file it read
            return int(args.func(args))
    except (ValueError, OSError, RuntimeError, KeyError) as exc:
        print(f"mitsuba-powder: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
