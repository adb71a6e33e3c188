"""Command line interface: ``mitsuba-powder <command> ...`` (thin layer over the Python API)."""

from __future__ import annotations

import argparse
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
    from .render import render_scene

    result = render_scene(
        args.scene,
        args.output,
        variant=args.variant,
        spp=args.spp,
        defines=dict(_parse_define(d) for d in args.define),
    )
    print(
        f"wrote {result.output} ({result.width}x{result.height}, {result.spp} spp, "
        f"variant {result.variant}, {result.seconds:.2f} s)"
    )
    return 0


def _cmd_colour(args: argparse.Namespace) -> int:
    import numpy as np

    from .appearance import powder_colour

    if (args.radius2 is None) != (args.fraction2 is None):
        raise ValueError("give both --radius2 and --fraction2, or neither")
    c = powder_colour(args.radius, radius2=args.radius2, fraction2=args.fraction2,
                      material=args.material, samples=args.samples)
    grains = f"radius {args.radius:g} um"
    if args.radius2 is not None:
        grains += f" + radius2 {args.radius2:g} um (volume fraction {args.fraction2:g})"
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


def _parse_define(text: str) -> tuple[str, str]:
    if "=" not in text:
        raise SystemExit(f"mitsuba-powder: -D expects NAME=VALUE, got {text!r}")
    name, value = text.split("=", 1)
    return name, value


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="mitsuba-powder",
        description="Dry-powder reflectance (Gerardin et al. 2023) for Mitsuba 3.",
    )
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
    p.set_defaults(func=_cmd_render)

    p = sub.add_parser("colour", help="albedo, tau_o and colour of a powder from its grains")
    p.add_argument("--radius", type=float, default=0.017, help="grain radius, um")
    p.add_argument("--radius2", type=float, default=None, help="second population radius, um")
    p.add_argument("--fraction2", type=float, default=None,
                   help="volume fraction of the second population")
    p.add_argument("--material", default="hematite",
                   help="hematite, magnetite or a refractiveindex.info YAML file")
    p.add_argument("--samples", type=int, default=4096, help="quadrature nodes")
    p.set_defaults(func=_cmd_colour)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mitsuba-powder`` command."""
    args = build_parser().parse_args(argv)
    try:
        return int(args.func(args))
    except (ValueError, FileNotFoundError, RuntimeError) as exc:
        print(f"mitsuba-powder: error: {exc}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())
