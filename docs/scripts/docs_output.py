"""Where a docs script writes: a new temporary folder, the folder given with ``--out``, or,
with ``--refresh-docs``, the committed page or figures it regenerates (never by default, so
that running a script to look at its output does not change tracked files)."""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path


def add_output_options(parser: argparse.ArgumentParser, committed: Path, what: str) -> None:
    """``--out DIR`` and ``--refresh-docs`` (mutually exclusive).

    Args:
        committed: the folder the committed files live in.
        what: the committed files, for the help text (e.g. ``docs/figures/showcase.png``).
    """
    group = parser.add_mutually_exclusive_group()
    group.add_argument("--out", type=Path, default=None,
                       help="output folder (default: a new temporary folder, printed)")
    group.add_argument("--refresh-docs", action="store_true",
                       help=f"write into {committed}, replacing the committed {what}")


def docs_parser(doc: str, committed: Path, what: str,
                quick: str | None = None) -> argparse.ArgumentParser:
    """A docs script's parser: its docstring's first line, the output options of
    :func:`add_output_options` and, with ``quick`` (its help text), ``--quick``."""
    parser = argparse.ArgumentParser(description=doc.splitlines()[0])
    add_output_options(parser, committed, what)
    if quick is not None:
        parser.add_argument("--quick", action="store_true", help=quick)
    return parser


def output_dir(args: argparse.Namespace, committed: Path) -> Path:
    """The folder to write to (created), as chosen by :func:`add_output_options`, checked
    before any work (:func:`mitsuba_powder.outputs.check_output_folder`: not a file, writable);
    a bad one is an error line and exit code 2, as the parser's."""
    from mitsuba_powder.outputs import OutputError, check_output_folder

    if args.refresh_docs:
        out = committed
    elif args.out is not None:
        out = Path(args.out)
    else:
        out = Path(tempfile.mkdtemp(prefix="mitsuba-powder-docs-"))
    try:
        check_output_folder(out, "--out")
    except OutputError as exc:
        print(f"{Path(sys.argv[0]).name}: error: {exc}", file=sys.stderr)
        raise SystemExit(2) from None
    print(f"writing to {out}" + (" (the committed docs)" if args.refresh_docs else ""))
    return out


def write_output(out: Path, name: str, data: str | bytes, finite=None) -> Path:
    """``out / name`` written whole or not at all (:func:`mitsuba_powder.outputs.write_whole`);
    with ``finite`` (numbers, nested lists or dicts of them: what ``data`` shows), refused
    when any of them is NaN or infinite (:func:`mitsuba_powder.outputs.check_finite_json`):
    nothing is written then."""
    from mitsuba_powder.outputs import check_finite_json, write_whole

    if finite is not None:
        check_finite_json(finite, str(out / name))
    return write_whole(out / name, data, "--out")


def render_size(parser: argparse.ArgumentParser, args: argparse.Namespace) -> tuple[int, int]:
    """(width, height) in pixels from ``--res WIDTHxHEIGHT``, checked with ``--spp`` (both
    positive); a bad value is the parser's error naming the option."""
    try:
        width, height = (int(v) for v in args.res.split("x"))
    except ValueError:
        parser.error(f"--res {args.res!r}: expected WIDTHxHEIGHT in pixels, e.g. 720x270")
    if width < 1 or height < 1 or args.spp < 1:
        parser.error(f"--res {args.res} and --spp {args.spp} must be positive")
    return width, height
