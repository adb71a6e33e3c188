"""Rendering commands: ``info``, ``render``, ``render-gonio`` and ``compare-photo``."""

from __future__ import annotations

import argparse

from ..outputs import final_path
from .common import _load_data, _parse_define, _value


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
    from ..plugin.params import load_properties
    from ..rendering.render import render_scene

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


def _cmd_render_gonio(args: argparse.Namespace) -> int:
    from ..fitting.protocols import protocol_geometries
    from ..plugin.params import load_properties
    from ..rendering.gonio import render_gonio, render_measurements
    from ..rendering.gonio_report import write_gonio_report

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
    print(f"wrote {final_path(path)}, gonio.csv and gonio.png")
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
    from ..rendering.photo import compare_images, read_image, write_report

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
    print(f"wrote {final_path(path)}, delta_e.png and side_by_side.png")
    return 0
