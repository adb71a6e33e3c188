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
