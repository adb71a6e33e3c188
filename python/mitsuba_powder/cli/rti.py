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
    from ..rti.gains import GainOptions
    from ..rti.maps import write_maps

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
                      light_distance=distance, gain_model=options)
    path = write_maps(result, args.out, capture, list(capture.names), args.pixel_size)
    info = json.loads(path.read_text())
    print(f"free per pixel: normal + {', '.join(result.free)} ({result.n_parameters} numbers)")
    for name, st in info["statistics"].items():
        if st.get("median") is not None:
            print(f"  {name}: median {st['median']:.4g} (5-95 %: {st['p5']:.4g}-{st['p95']:.4g})")
    print(f"wrote {args.out}: maps (EXR), fit.json, scene.xml")
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
