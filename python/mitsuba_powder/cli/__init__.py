"""Command line interface: ``mitsuba-powder <command> ...`` (thin layer over the Python API).

The parser is :mod:`.parser`; the commands live by area in :mod:`.appearance`,
:mod:`.rendering`, :mod:`.fitting` and :mod:`.rti`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

from .parser import build_parser

__all__ = ["build_parser", "main"]


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mitsuba-powder`` command."""
    from ..outputs import guarding_inputs

    args = build_parser().parse_args(argv)
    try:
        with guarding_inputs():  # no command writes over a file it read
            return int(args.func(args))
    except (ValueError, OSError, RuntimeError, KeyError) as exc:
        print(f"mitsuba-powder: error: {exc}", file=sys.stderr)
        return 2
