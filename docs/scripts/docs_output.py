"""Where a docs script writes: a new temporary folder, the folder given with ``--out``, or,
with ``--refresh-docs``, the committed page or figures it regenerates (never by default, so
that running a script to look at its output does not change tracked files)."""

from __future__ import annotations

import argparse
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
    """The folder to write to (created), as chosen by :func:`add_output_options`."""
    if args.refresh_docs:
        out = committed
    elif args.out is not None:
        out = Path(args.out)
    else:
        out = Path(tempfile.mkdtemp(prefix="mitsuba-powder-docs-"))
    out.mkdir(parents=True, exist_ok=True)
    print(f"writing to {out}" + (" (the committed docs)" if args.refresh_docs else ""))
    return out


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
