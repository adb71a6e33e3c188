"""RTI commands: ``fit-maps``, ``relight`` and ``compare-maps``."""

from __future__ import annotations

import argparse
import json
import math

import numpy as np

from .common import _fixed_properties, _names


def _powder_fitter(free: list[str] | None, fixed: dict, progress=None,
                   light_distance: float = math.inf):
    """compare-maps' powder model: rti.fit_maps with these settings."""
    from ..rti import fit_maps

    def fit(images, directions, mask=None):
        return fit_maps(images, directions, free=free, mask=mask, fixed=fixed,
                        progress=progress, light_distance=light_distance)

    return fit


def _light_distance(args: argparse.Namespace, capture) -> tuple[object, str]:
    """The capture's light distance (image widths: a number, one per light, or ``"fit"``)
    from ``--light-distance``, ``--pixel-size`` and the .lp vectors, and what the .lp holds
    (``directions`` or ``positions``).

    Raises:
        ValueError: naming the option, its value and the valid range.
    """
    from ..rti.lights import check_distance, read_lp_rig

    h, w = capture.shape
    text = getattr(args, "light_distance", None)
    size = getattr(args, "pixel_size", None)
    if size is not None and not (math.isfinite(size) and size > 0):
        raise ValueError(f"--pixel-size = {size!r} is out of range; valid range is (0, inf) "
                         "(the size of a pixel in the unit of the .lp light positions)")
    value: object = math.inf
    if text is not None and text != "fit":
        try:
            value = float(text)
        except ValueError:
            raise ValueError(f"--light-distance = {text!r} is not valid; give a number of "
                             "image widths, 'inf' or 'fit'") from None
        check_distance(value, (h, w), "--light-distance")
    elif text == "fit":
        value = "fit"
    if size is None:  # without the positions' unit the vectors are directions (normalised)
        return value, "directions"
    _, rig, kind = read_lp_rig(capture.lp_path, "auto", size * w)
    if kind == "positions":
        if text is not None:
            raise ValueError(f"--light-distance = {text!r} was given but {capture.lp_path} "
                             "holds light positions, which set each light's distance; leave "
                             "--light-distance out")
        check_distance(rig.distance, (h, w), f"{capture.lp_path}: light distance")
        value = rig.distance
    return value, kind


def _cmd_fit_maps(args: argparse.Namespace) -> int:
    from ..rti import fit_maps, load_capture
    from ..rti.blocks import GAIN_PIXELS
    from ..rti.gains import GainOptions
    from ..rti.maps import write_maps

    if args.tile_size is not None:
        return _cmd_fit_maps_tiled(args)
    _check_untiled(args)
    capture = load_capture(args.capture, encoding=args.encoding, mask=args.mask)
    k, h, w, c = capture.images.shape
    print(f"{args.capture}: {k} lights, {w} x {h} px, {c} channels, {capture.file_format} "
          f"{capture.bit_depth} bit, encoding {capture.encoding}")
    free = _names(args.free)
    distance, _ = _light_distance(args, capture)
    options = GainOptions(args.gain_model, args.gain_degree, 0, args.gain_spread)
    result = fit_maps(capture.images, capture.directions, free=free, mask=capture.mask,
                      fixed=_fixed_properties(args.set), gains=args.gains,
                      max_iterations=args.iterations, rounds=args.rounds, progress=print,
                      light_distance=distance, gain_model=options, solver=args.solver,
                      gain_pixels=args.gain_pixels or GAIN_PIXELS, memory_gb=args.memory_gb)
    path = write_maps(result, args.out, capture, list(capture.names), args.pixel_size)
    _print_maps_summary(result, path, args.out)
    return 0


def _print_maps_summary(result, path, out: str) -> None:
    """What fit-maps found: the free properties and each map's median and 5-95 % range."""
    info = json.loads(path.read_text())
    print(f"free per pixel: normal + {', '.join(result.free)} ({result.n_parameters} numbers)")
    for name, st in info["statistics"].items():
        if st.get("median") is not None:
            print(f"  {name}: median {st['median']:.4g} (5-95 %: {st['p5']:.4g}-{st['p95']:.4g})")
    print(f"wrote {out}: maps (EXR), fit.json, scene.xml")


#: fit-maps options that need --tile-size, by attribute
_TILE_OPTIONS = {"workers": "--workers", "scheduler": "--scheduler", "resume": "--resume"}


def _check_untiled(args: argparse.Namespace) -> None:
    """Without --tile-size the tile options have no meaning: name the one given."""
    for attr, option in _TILE_OPTIONS.items():
        if getattr(args, attr) not in (None, False):
            raise ValueError(f"{option} applies to tiled fits only; give --tile-size N "
                             "(pixels, >= 8) as well")


def _check_tiled(args: argparse.Namespace) -> None:
    """The options a tiled fit does not take yet (a tile is fitted as an image of its own:
    near-field lights need the pixels' positions in the whole image)."""
    for given, option, value in (
            (args.light_distance not in (None, "inf"), "--light-distance",
             args.light_distance),
            (args.pixel_size is not None, "--pixel-size", args.pixel_size),
            (args.gain_model not in ("none", "free"), "--gain-model", args.gain_model),
            (args.gain_spread is not None, "--gain-spread", args.gain_spread)):
        if given:
            raise ValueError(f"{option} {value} is not supported with --tile-size; tiled fits "
                             "take distant lights (--light-distance inf) and free gains")


def _cmd_fit_maps_tiled(args: argparse.Namespace) -> int:
    """fit-maps --tile-size: rti.fit_maps_tiled on a Dask cluster, then the maps written."""
    import numpy as np

    from ..outputs import note_input, note_inputs, output_path
    from ..rti import MAP_DEFAULT_FREE, Capture, lp_image_paths, read_lp
    from ..rti.cluster import open_client
    from ..rti.maps import maps_files, write_maps
    from ..rti.tiles import GAIN_PIXELS, fit_maps_tiled

    _check_tiled(args)
    names, directions = read_lp(args.capture)
    note_inputs(lp_image_paths(args.capture, names))
    if args.mask is not None:
        note_input(args.mask)
    free = _names(args.free) or MAP_DEFAULT_FREE
    fixed = _fixed_properties(args.set)
    for name in maps_files([n for n in free if n != "albedo"] + list(fixed)):
        output_path(args.out, name, mkdir=False)  # a refused output fails before the fit
    with open_client(scheduler=args.scheduler, workers=args.workers,
                     names=("--scheduler", "--workers")) as client:
        workers = len(client.scheduler_info()["workers"])
        print(f"cluster: {client.scheduler.address}, {workers} worker(s), dashboard "
              f"{client.dashboard_link}")
        result = fit_maps_tiled(
            args.capture, args.out, args.tile_size, encoding=args.encoding, mask=args.mask,
            gains=args.gains, gain_pixels=args.gain_pixels or GAIN_PIXELS, client=client,
            resume=args.resume, log=print, free=free, fixed=fixed,
            max_iterations=args.iterations,
            rounds=args.rounds, solver=args.solver, memory_gb=args.memory_gb)
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
    from ..rti.maps import relight_files

    distance = None
    if args.light_distance is not None:
        try:
            distance = float(args.light_distance)
        except ValueError:
            raise ValueError(f"--light-distance = {args.light_distance!r} is not valid; give "
                             "a number of image widths or 'inf'") from None
    if args.pixel_size is not None and not (math.isfinite(args.pixel_size)
                                            and args.pixel_size > 0):
        raise ValueError(f"--pixel-size = {args.pixel_size!r} is out of range; valid range "
                         "is (0, inf)")
    paths = relight_files(args.maps, args.lp, args.out, args.pixel_size, distance)
    print(f"wrote {len(paths)} images to {args.out}")
    return 0


def _cmd_compare_maps(args: argparse.Namespace) -> int:
    from ..rti import load_capture
    from ..rti.comparison import baseline_fitter, compare, write_comparison

    names = [m.strip() for m in args.models.split(",") if m.strip()]
    free = _names(args.free)
    from ..rti.baselines import BASELINES

    unknown = [n for n in names if n != "powder" and n not in BASELINES]
    if unknown or not names:
        raise ValueError(f"--models {args.models!r}: unknown {unknown}; valid models are "
                         f"{', '.join(list(BASELINES) + ['powder'])}")
    capture = load_capture(args.capture, encoding=args.encoding, mask=args.mask)
    k, h, w, c = capture.images.shape
    print(f"{args.capture}: {k} lights, {w} x {h} px, {c} channels, {capture.file_format} "
          f"{capture.bit_depth} bit, encoding {capture.encoding}")
    distance = _compare_distance(args, capture, free)
    near = np.any(np.isfinite(distance))
    field = args.field or ("both" if near else "far")
    if field != "far" and not near:
        raise ValueError(f"--field = {field!r} needs a finite light distance (--light-distance "
                         "R or fit, or an .lp of positions)")
    fixed = _fixed_properties(args.set)
    models = {}
    for name in names:
        for r, suffix in (((math.inf, ""),) if field == "far" else ((distance, "_near"),)
                          if field == "near" else ((math.inf, ""), (distance, "_near"))):
            models[name + suffix] = (_powder_fitter(free, fixed, light_distance=r)
                                     if name == "powder" else baseline_fitter(name, r))
    comp = compare(capture, models, phase=args.phase, light_distance=distance)
    path = write_comparison(comp, args.out, error_images=not args.no_error_images)
    print(path.read_text())
    print(f"wrote {path}, compare.json" + ("" if args.no_error_images else
                                            " and error_<protocol>_<model>.png"))
    return 0


def _compare_distance(args: argparse.Namespace, capture, free) -> float | np.ndarray:
    """compare-maps' light distance: given, the .lp positions', or fitted once on the whole
    capture (a calibration of the dome, like the gains' mean) with the powder fit."""
    from ..rti.fit import fit_light_distance

    distance, _ = _light_distance(args, capture)
    if isinstance(distance, str):
        distance, _ = fit_light_distance(capture.images, capture.directions, free=free,
                                         mask=capture.mask, fixed=_fixed_properties(args.set),
                                         progress=print)
        print(f"light distance fitted: {distance:.4g} image widths")
    if np.ndim(distance) == 1:  # the .lp positions: the models take one distance
        distance = float(np.median(distance))
        print(f"light distance: the median of the .lp positions, {distance:.4g} image widths")
    return distance
