"""RTI commands: ``fit-maps``, ``relight`` and ``compare-maps``.

The fit's options are built once, from the command line, by
:func:`mitsuba_powder.rti.options.fit_options` (every check and message there; the parser
converts nothing): the same object the Python API builds.
"""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from ..outputs import final_path
from .common import _fixed_properties, _names

#: How messages name the fit's options given by a flag of another name
FLAGS = {"light_distance": "--light-distance", "memory_gb": "--memory-gb",
         "saturation": "--saturation", "exposure": "--exposure",
         "shadows": "--shadows", "light_size": "--light-size",
         "gain_subsample": "--gain-pixels", "tile_size": "--tile-size", "workers": "--workers",
         "scheduler": "--scheduler"}


def _number(text):
    """A command-line value as the user typed it: a whole number, a number, or the text (the
    checks of :func:`~mitsuba_powder.rti.options.fit_options` name what is wrong)."""
    if not isinstance(text, str):
        return text
    if text.strip().lstrip("+-").isdigit():
        return int(text)
    try:
        return float(text)
    except ValueError:
        return text


def _pixel_size(args: argparse.Namespace) -> float | None:
    """``--pixel-size``, checked: > 0 (None: not given)."""
    from .._checks import check_range

    if args.pixel_size is None:
        return None
    return check_range("--pixel-size", args.pixel_size, 0.0, math.inf, "()",
                       note="(the size of a pixel in the unit of the .lp light positions)")


def _fit_options(args: argparse.Namespace, tiled: bool = False, **given):
    """fit-maps' options from the command line (with ``given`` ones), checked before the
    capture is read. A tiled fit takes neither the gains' trend nor the .lp positions'
    distance (:func:`_check_tiled`)."""
    from ..rti.gains import GainTrend
    from ..rti.options import fit_options

    given.update(gains=args.gains, max_iterations=_number(args.iterations),
                 rounds=_number(args.rounds), solver=args.solver,
                 memory_gb=_number(args.memory_gb))
    if args.exposure is not None:
        if args.reference is not None:
            raise ValueError(f"--exposure {args.exposure} and --reference {args.reference} "
                             "were both given; the reference card gives the exposure: give one")
        given["exposure"] = args.exposure if args.exposure == "fit" else _number(args.exposure)
    if args.gain_pixels is not None:
        given["gain_subsample"] = _number(args.gain_pixels)
    if args.light_distance is not None:
        given["light_distance"] = args.light_distance
    if args.saturation is not None:
        given["saturation"] = _number(args.saturation)
    if args.shadows is not None:
        given["shadows"] = args.shadows
    if args.light_size is not None:
        given["light_size"] = _number(args.light_size)
    trend = GainTrend(args.gain_model, _number(args.gain_degree), 0, _number(args.gain_spread))
    if not tiled:
        given["gain_trend"] = trend
    return fit_options(names=FLAGS, **given)


def _reference(args: argparse.Namespace, capture, options):
    """With ``--reference``: the capture without the card's pixels, the options with the
    exposure and the relative gains the card gives (:mod:`mitsuba_powder.rti.reference`), and
    the calibration; else the capture, the options and None."""
    from dataclasses import replace

    from ..rti.reference import calibrate, parse_reference

    if args.reference is None:
        return capture, options, None
    ref = parse_reference(args.reference)
    cal = calibrate(capture.images, capture.directions, ref, options.saturation)
    card = ref.mask(capture.shape)
    mask = ~card if capture.mask is None else capture.mask & ~card
    if not mask.any():
        raise ValueError(f"--reference {args.reference} covers every pixel to fit; the card "
                         "must be a part of the image")
    e = cal["irradiance"]
    print(f"reference card: {cal['pixels']} pixels, reflectance {ref.reflectance:g}: exposure "
          f"{cal['exposure']:.4g}, light irradiances {np.min(e):.4g}-{np.max(e):.4g}"
          + ("" if cal["estimated"].all() else
             f" ({int(np.sum(~cal['estimated']))} lights grazing or saturated on the card: "
             "the others' median)"))
    options = options.replace(exposure=cal["exposure"],
                              gains=replace(options.gains, initial=cal["gains"]))
    return replace(capture, mask=mask), options, cal


def _reference_record(cal: dict) -> dict:
    """fit.json's record of a reference calibration."""
    return {"box": cal["box"], "reflectance": cal["reflectance"], "pixels": cal["pixels"],
            "irradiance": [float(v) for v in cal["irradiance"]],
            "estimated": [bool(v) for v in cal["estimated"]]}


def _lp_distance(args: argparse.Namespace, capture, options, size: float | None):
    """``options`` with the lights' distances of an .lp of positions (``size``: the
    checked ``--pixel-size``, their unit; an .lp of unit directions leaves ``options`` as
    they are)."""
    from ..rti.lights import read_lp_rig

    if size is None:  # without the positions' unit the vectors are directions (normalised)
        return options
    _, rig, kind = read_lp_rig(capture.lp_path, "auto", size * capture.shape[1])
    if kind != "positions":
        return options
    if args.light_distance is not None:
        raise ValueError(f"--light-distance = {args.light_distance!r} was given but "
                         f"{capture.lp_path} holds light positions, which set each light's "
                         "distance; leave --light-distance out")
    return options.replace(light_distance=rig.distance, names={
        **options.names, "light_distance": f"{capture.lp_path}: light distance"})


def _load(args: argparse.Namespace):
    """The capture of ``args``, its size printed."""
    from ..rti import load_capture

    capture = load_capture(args.capture, encoding=args.encoding, mask=args.mask)
    k, h, w, c = capture.images.shape
    print(f"{args.capture}: {k} lights, {w} x {h} px, {c} channels, {capture.file_format} "
          f"{capture.bit_depth} bit, encoding {capture.encoding}")
    return capture


def _cmd_fit_maps(args: argparse.Namespace) -> int:
    from ..rti.maps import write_maps
    from ..rti.plan import run_fit

    if args.tile_size is not None:
        return _cmd_fit_maps_tiled(args)
    _check_untiled(args)
    options = _fit_options(args, free=_names(args.free), fixed=_fixed_properties(args.set))
    size = _pixel_size(args)
    capture = _load(args)
    options = _lp_distance(args, capture, options.replace(full_scale=capture.full_scale), size)
    capture, options, cal = _reference(args, capture, options)
    result = run_fit(capture.images, capture.directions, options, capture.mask, print)
    _keep_relief(result, options)
    if cal is not None:
        result.fit_settings["exposure"].update(source="reference",
                                               reference=_reference_record(cal))
    path = write_maps(result, args.out, capture, list(capture.names), args.pixel_size)
    _print_maps_summary(result, path, args.out)
    return 0


def _keep_relief(result, options) -> None:
    """A fit without the relief's shadows (``--shadows ratio``, or ``auto`` where it chose
    ``ratio``) keeps the relief of its normals too (relief.exr, relief.ply, scene.xml's
    mesh), unused by the fit: relight shades by it only when asked (``relight --shadows``,
    ``--render``)."""
    from ..rti.relief import make_relief

    result.fit_settings.setdefault("shadows", options.shadows)
    if result.relief is None:
        result.relief = make_relief(result.normals, result.residual_rms, result.mask,
                                    options.light_size)


def _print_maps_summary(result, path, out: str) -> None:
    """What fit-maps found: the free properties and each map's median and 5-95 % range."""
    info = json.loads(path.read_text())
    exposure = result.fit_settings.get("exposure") or {}
    sigma = exposure.get("sigma")
    print(f"exposure: {result.exposure:.4g}" + (f" +- {sigma:.2g}" if sigma else "")
          + f" ({exposure.get('source', 'given')}"
          + ("" if exposure.get("determined", True) else ", NOT determined by the capture")
          + ")")
    print(f"free per pixel: normal + {', '.join(result.free)} ({result.n_parameters} numbers)"
          + ("" if not result.fit_settings.get("free_choice") else
             ", chosen by cross-validation over held-out lights"))
    print(_shadows_summary(result.fit_settings))
    for name, st in info["statistics"].items():
        if st.get("median") is not None:
            print(f"  {name}: median {st['median']:.4g} (5-95 %: {st['p5']:.4g}-{st['p95']:.4g})")
    print(f"wrote {out}: maps (EXR), fit.json, scene.xml")


def _shadows_summary(settings: dict) -> str:
    """fit-maps' line on the cast shadows: the mode used and, with ``auto``, both
    cross-validated RMS."""
    mode = settings.get("shadows", "ratio")
    line = f"shadows: {mode} (" + ("the relief's cast shadows in the fit and relight's "
                                    "default" if mode == "relief" else
                                    "the ratio test; the relief kept unused") + ")"
    choice = settings.get("shadows_choice")
    if choice:
        cv = choice["cv_rms"]
        line += (f", chosen by cross-validation over held-out lights: RMS {cv['ratio']:.4g} "
                 f"without the relief, {cv['relief']:.4g} with it, better with it by "
                 f"{choice['z']:.3g} standard errors on the "
                 f"{choice.get('shaded_pixels', choice['pixels'])} pixels it shades (the "
                 f"relief needs more than {choice['margin_z']:g})")
    return line


#: fit-maps options that need --tile-size, by attribute
_TILE_OPTIONS = {"workers": "--workers", "scheduler": "--scheduler", "resume": "--resume"}


def _check_untiled(args: argparse.Namespace) -> None:
    """Without --tile-size the tile options have no meaning: name the one given."""
    for attr, option in _TILE_OPTIONS.items():
        if getattr(args, attr) not in (None, False):
            raise ValueError(f"{option} applies to tiled fits only; give --tile-size N "
                             "(pixels, >= 8) as well")


def _check_tiled(args: argparse.Namespace) -> None:
    """The command-line options a tiled fit does not take yet: the unit of .lp positions
    and the gains' trend (lights at a distance are refused by the tiled fit itself)."""
    for given, option, value in (
            (args.pixel_size is not None, "--pixel-size", args.pixel_size),
            (args.gain_model not in ("none", "free"), "--gain-model", args.gain_model),
            (args.gain_spread is not None, "--gain-spread", args.gain_spread)):
        if given:
            raise ValueError(f"{option} {value} is not supported with --tile-size; tiled fits "
                             "take distant lights (--light-distance inf) and free gains")


def _cmd_fit_maps_tiled(args: argparse.Namespace) -> int:
    """fit-maps --tile-size: rti.fit_maps_tiled on a Dask cluster, then the maps written."""
    from ..outputs import note_input, note_inputs, output_path
    from ..rti import MAP_DEFAULT_FREE, Capture, lp_image_paths, read_lp
    from ..rti.maps import maps_files, write_maps
    from ..rti.tiles import fit_maps_tiled

    free = _names(args.free)   # None: chosen on the gains' subsample
    fixed = _fixed_properties(args.set)
    options = _fit_options(args, tiled=True, free=free, fixed=fixed)
    _check_tiled(args)
    names, directions = read_lp(args.capture)
    note_inputs(lp_image_paths(args.capture, names))
    if args.mask is not None:
        note_input(args.mask)
    for name in maps_files([n for n in free or MAP_DEFAULT_FREE if n != "albedo"]
                           + list(fixed), relief=False):
        output_path(args.out, name, mkdir=False)  # a refused output fails before the fit
    result = fit_maps_tiled(
        args.capture, args.out, _number(args.tile_size), encoding=args.encoding,
        mask=args.mask, scheduler=args.scheduler, workers=_number(args.workers),
        resume=args.resume, log=print, options=options)
    tiles = result.fit_settings["tiles"]
    print(f"tiles: {tiles['fitted']} fitted, {tiles['resumed']} resumed or empty, in "
          f"{result.fit_settings['seconds']:.1f} s")
    header = result.fit_settings["capture"]
    like = Capture(images=np.zeros((0, 1, 1, 3), np.float32), directions=directions,
                   names=list(names), encoding=header["encoding"],
                   file_format=header["file_format"], bit_depth=int(header["bit_depth"]),
                   lp_path=header["lp"])
    path = write_maps(result, args.out, like, list(names))
    _print_maps_summary(result, path, args.out)
    return 0


def _cmd_relight(args: argparse.Namespace) -> int:
    from ..rti.lights import parse_light_distance
    from ..rti.maps import relight_files

    distance = None if args.light_distance is None else parse_light_distance(
        args.light_distance, "--light-distance", fit=False)
    render = {"spp": _number(args.spp), "variant": args.render_variant} if args.render \
        else None
    paths = relight_files(args.maps, args.lp, args.out, _pixel_size(args), distance,
                          shadows=False if args.no_shadows else (True if args.shadows
                                                                 else None), render=render)
    print(f"wrote {len(paths)} images to {args.out}")
    return 0


def _cmd_compare_maps(args: argparse.Namespace) -> int:
    from ..rti.baselines import BASELINES
    from ..rti.comparison import compare, write_comparison
    from ..rti.relief_rows import POWDER_ROWS

    names = [m.strip() for m in args.models.split(",") if m.strip()]
    unknown = [n for n in names if n not in POWDER_ROWS and n not in BASELINES]
    if unknown or not names:
        raise ValueError(f"--models {args.models!r}: unknown {unknown}; valid models are "
                         f"{', '.join(list(BASELINES) + list(POWDER_ROWS))}")
    options = _fit_options(args, free=_names(args.free), fixed=_fixed_properties(args.set))
    render = {"spp": _number(args.spp), "variant": args.render_variant}
    size = _pixel_size(args)
    capture = _load(args)
    capture, options, cal = _reference(args, capture,
                                       options.replace(full_scale=capture.full_scale))
    distance = _compare_distance(args, capture, options, size)
    near = np.any(np.isfinite(distance))
    field = args.field or ("both" if near else "far")
    if field != "far" and not near:
        raise ValueError(f"--field = {field!r} needs a finite light distance (--light-distance "
                         "R or fit, or an .lp of positions)")
    models = _compared_models(names, field, distance, options, render, capture, cal)
    comp = compare(capture, models, phase=args.phase, light_distance=distance,
                   saturation=options.saturation, saturation_name=options.name("saturation"))
    path = write_comparison(comp, args.out, error_images=not args.no_error_images)
    print(path.read_text())
    print(f"wrote {final_path(path)}, compare.json" + ("" if args.no_error_images else
                                            " and error_<protocol>_<model>.png"))
    return 0


def _compared_models(names: list[str], field: str, distance, options, render: dict,
                     capture=None, cal: dict | None = None) -> dict:
    """compare-maps' fitters by row name: each model with distant lights (``far``), at the
    light distance (``near``, rows ``<model>_near``) or both; the powder rows are the
    per-pixel fit of fit-maps with ``options``
    (:func:`mitsuba_powder.rti.relief_rows.powder_fitters`; with a reference card's
    calibration ``cal``: the fitted lights' relative gains held, the held-out lights relit at
    their irradiance)."""
    from ..rti.comparison import baseline_fitter
    from ..rti.relief_rows import POWDER_ROWS, powder_fitters

    calibration = None if cal is None else {
        "directions": capture.directions, "gains": cal["gains"],
        "irradiance": cal["irradiance"]}

    fields = {"far": ((math.inf, ""),), "near": ((distance, "_near"),),
              "both": ((math.inf, ""), (distance, "_near"))}[field]
    out = {}
    for r, suffix in fields:
        powders = powder_fitters([n for n in names if n in POWDER_ROWS],
                                 options.replace(light_distance=r), render, calibration)
        for name in names:
            out[name + suffix] = powders[name] if name in POWDER_ROWS else \
                baseline_fitter(name, r)
    return out


def _compare_distance(args: argparse.Namespace, capture, options, size: float | None
                      ) -> float | np.ndarray:
    """compare-maps' light distance: given, the .lp positions', or fitted once on the whole
    capture (a calibration of the dome, like the gains' mean) with the powder fit."""
    from ..rti.lights import check_distance
    from ..rti.plan import fit_distance

    options = _lp_distance(args, capture, options, size)
    distance = options.light_distance
    if isinstance(distance, str):
        distance, _ = fit_distance(capture.images, capture.directions, options, capture.mask,
                                   print)
        print(f"light distance fitted: {distance:.4g} image widths")
    else:
        check_distance(distance, capture.shape, options.name("light_distance"))
    if np.ndim(distance) == 1:  # the .lp positions: the models take one distance
        distance = float(np.median(distance))
        print(f"light distance: the median of the .lp positions, {distance:.4g} image widths")
    return distance
