"""RTI commands: ``fit-maps``, ``relight`` and ``compare-maps``."""

from __future__ import annotations

import argparse
import json

from .common import _fixed_properties, _names


def _powder_fitter(free: list[str] | None, fixed: dict, progress=None):
    """compare-maps' powder model: rti.fit_maps with these settings."""
    from ..rti import fit_maps

    def fit(images, directions, mask=None):
        return fit_maps(images, directions, free=free, mask=mask, fixed=fixed,
                        progress=progress)

    return fit


def _cmd_fit_maps(args: argparse.Namespace) -> int:
    from ..rti import fit_maps, load_capture
    from ..rti.maps import write_maps

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
    from ..rti.maps import relight_files

    paths = relight_files(args.maps, args.lp, args.out)
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
