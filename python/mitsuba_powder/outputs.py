"""Where a command writes: only under the output it was given, never over one of its inputs.

Every file the package writes goes through :func:`output_path` (a file inside an output folder)
or :func:`output_file` (an output file the caller named). Both check the target against the
*inputs* of the running command: within :func:`guarding_inputs` (the command line opens one
around each command; :func:`mitsuba_powder.rendering.render.render_scene` and
:func:`mitsuba_powder.rti.maps.relight_files` open their own), every file the package's loaders
read is recorded by :func:`note_input`, and a write whose resolved path is one of them is
refused with :class:`OutputError` before anything is written.

File names that come from a data file (the images named by an RTI ``.lp`` file) are reduced by
:func:`output_names`: a relative name without ``..`` is kept, an absolute name or one with a
``..`` component is reduced to its base name, and two lights whose names reduce to one file are
an error naming both lines.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path, PurePath, PurePosixPath, PureWindowsPath

__all__ = ["OutputError", "guarding_inputs", "note_input", "output_path", "output_file",
           "output_names", "protected_inputs"]

_INPUTS: ContextVar[set[Path] | None] = ContextVar("mitsuba_powder_inputs", default=None)


class OutputError(ValueError):
    """A write that would land outside the given output or over an input file."""


def _resolved(path: str | Path) -> Path:
    return Path(path).expanduser().resolve()


@contextmanager
def guarding_inputs(*paths: str | Path) -> Iterator[set[Path]]:
    """Protect ``paths`` and every file noted by :func:`note_input` inside the block.

    Blocks nest: an inner block adds to the outer block's set (one command, one set).

    Yields:
        The set of resolved input paths (grows as loaders read files).
    """
    current = _INPUTS.get()
    if current is not None:
        current.update(_resolved(p) for p in paths)
        yield current
        return
    inputs = {_resolved(p) for p in paths}
    token = _INPUTS.set(inputs)
    try:
        yield inputs
    finally:
        _INPUTS.reset(token)


def note_input(path: str | Path) -> None:
    """Record ``path`` as an input of the running command (no-op outside
    :func:`guarding_inputs`)."""
    current = _INPUTS.get()
    if current is not None:
        current.add(_resolved(path))


def note_inputs(paths: Iterable[str | Path]) -> None:
    """:func:`note_input` for each path."""
    for p in paths:
        note_input(p)


def protected_inputs() -> frozenset[Path]:
    """The resolved inputs recorded so far (empty outside :func:`guarding_inputs`)."""
    return frozenset(_INPUTS.get() or ())


def _check_not_input(target: Path, shown: Path, what: str = "output") -> None:
    if target in (_INPUTS.get() or ()):
        raise OutputError(f"{what} {shown} is an input file of this command (resolved: "
                          f"{target}); choose another output, nothing was written over it")


def output_file(path: str | Path, what: str = "output") -> Path:
    """A file the caller named as output: checked not to be an input; its folder is created.

    Args:
        path: the file to write.
        what: the parameter's name for messages (e.g. ``--out``).

    Raises:
        OutputError: ``path`` (resolved, links followed) is an input of the running command,
            or an existing folder.
    """
    p = Path(path).expanduser()
    target = _resolved(p)
    if target.is_dir():
        raise OutputError(f"{what} {p}: is a folder; expected a file name")
    _check_not_input(target, p, what)
    p.parent.mkdir(parents=True, exist_ok=True)
    return p


def _is_safe_relative(name: str) -> bool:
    """A name that stays inside a folder: relative on POSIX and Windows, no ``..``."""
    if not name or name in (".",):
        return False
    for flavour in (PurePosixPath, PureWindowsPath):
        pure: PurePath = flavour(name)
        if pure.is_absolute() or pure.anchor or ".." in pure.parts:
            return False
    return True


def output_path(folder: str | Path, name: str | Path, mkdir: bool = True) -> Path:
    """``folder / name``, checked to lie inside ``folder`` and not to be an input.

    Args:
        folder: the output folder (created).
        name: a relative file name without ``..`` components.
        mkdir: create the file's parent folders.

    Raises:
        OutputError: ``name`` is absolute or has ``..``; the resolved target leaves ``folder``
            (through a link) or is an input of the running command.
    """
    name = str(name)
    if not _is_safe_relative(name):
        raise OutputError(f"output name {name!r}: expected a relative file name without '..' "
                          f"inside the output folder {folder}")
    base = Path(folder).expanduser()
    if base.exists() and not base.is_dir():
        raise OutputError(f"output folder {folder} is a file; give a folder")
    path = base / name
    root, target = _resolved(base), _resolved(path)
    if not target.is_relative_to(root):
        raise OutputError(f"output {path} resolves to {target}, outside the output folder "
                          f"{root} (a link?); nothing was written")
    _check_not_input(target, path)
    if mkdir:
        path.parent.mkdir(parents=True, exist_ok=True)
    return path


def output_names(names: Sequence[str], where: Sequence[str]) -> list[str]:
    """Output file names for names read from a data file (e.g. an ``.lp`` file's images).

    A relative name without ``..`` is kept; an absolute name, or one with a ``..`` component,
    is reduced to its base name (``/capture/img_01.png`` -> ``img_01.png``).

    Args:
        names: the names as written in the file.
        where: for each name, where it was read (e.g. ``"dirs.lp, line 3"``), for messages.

    Raises:
        OutputError: a name has no base name, or two names reduce to one output file (both
            places named).
    """
    out: list[str] = []
    seen: dict[str, int] = {}
    for k, (name, place) in enumerate(zip(names, where, strict=True)):
        reduced = name
        if not _is_safe_relative(name):
            reduced = PureWindowsPath(name).name if "\\" in name else PurePosixPath(name).name
            if not _is_safe_relative(reduced):
                raise OutputError(f"{place}: image name {name!r} has no file name to write "
                                  "an output under")
        key = reduced.replace("\\", "/").casefold()
        if key in seen:
            j = seen[key]
            raise OutputError(f"{place}: image name {name!r} and {where[j]}: {names[j]!r} "
                              f"would both be written as {reduced!r}; give the lights "
                              "distinct file names")
        seen[key] = k
        out.append(reduced)
    return out
