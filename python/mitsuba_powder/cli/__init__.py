"""Command line interface: ``mitsuba-powder <command> ...`` (thin layer over the Python API).

The parser is :mod:`.parser`; the commands live by area in :mod:`.appearance`,
:mod:`.rendering`, :mod:`.fitting` and :mod:`.rti`.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence
from contextlib import ExitStack

from .parser import build_parser

__all__ = ["build_parser", "main"]


#: The exit status of a command interrupted by Ctrl-C (128 + SIGINT), as shells report it
INTERRUPTED = 130


def main(argv: Sequence[str] | None = None) -> int:
    """Entry point of the ``mitsuba-powder`` command.

    Every command runs with its inputs protected (:func:`~mitsuba_powder.outputs.guarding_inputs`);
    a command that writes an output folder (``--out``) writes it whole or not at all
    (:func:`~mitsuba_powder.outputs.staged_output`: the folder is checked before the work starts).
    Errors print one line and return 2; Ctrl-C prints one line and returns 130.
    """
    from ..outputs import guarding_inputs, staged_output

    args = build_parser().parse_args(argv)
    folder = args.out if getattr(args, "out_folder", False) else None
    try:
        with ExitStack() as stack:
            stack.enter_context(guarding_inputs())  # no command writes over a file it read
            if folder is not None:
                stack.enter_context(staged_output(folder, "--out", args.command))
            return int(args.func(args))
    except KeyboardInterrupt:
        kept = f"; {folder} was left as it was" if folder is not None else ""
        print(f"mitsuba-powder: interrupted{kept}", file=sys.stderr)
        return INTERRUPTED
    except (ValueError, OSError, RuntimeError, KeyError) as exc:
        print(f"mitsuba-powder: error: {exc}", file=sys.stderr)
        return 2
