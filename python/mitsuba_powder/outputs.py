"""Where a command writes: only under the output it was given, never over one of its inputs.

Every file the package writes goes through :func:`output_path` (a file inside an output folder)
or :func:`output_file` (an output file the caller named; :func:`write_whole` and
:func:`write_json` write one whole or not at all). Both check the target against the
*inputs* of the running command: within :func:`guarding_inputs` (the command line opens one
around each command; :func:`mitsuba_powder.rendering.render.render_scene` and
:func:`mitsuba_powder.rti.maps.relight_files` open their own), every file the package's loaders
read is recorded by :func:`note_input`, and a write whose resolved path is one of them is
refused with :class:`OutputError` before anything is written.

A command that writes a folder (``--out``) writes it whole or not at all
(:func:`staged_output`): its files go to a staging folder inside it (:data:`STAGING`) and are
moved into place once the work is done, so an interrupted run leaves the previous result as it
was; while they are moved, :data:`INCOMPLETE` marks the folder, and the readers of results
(:func:`check_complete`) refuse a folder so marked. The folder is checked (not a file, not an
input, writable) before the work starts.

File names that come from a data file (the images named by an RTI ``.lp`` file) are reduced by
:func:`output_names`: a relative name without ``..`` is kept, an absolute name or one with a
``..`` component is reduced to its base name, and two lights whose names reduce to one file are
an error naming both lines.
"""

from __future__ import annotations

import json
import os
import shutil
import uuid
from collections.abc import Callable, Iterable, Iterator, Sequence
from contextlib import contextmanager
from contextvars import ContextVar
from pathlib import Path, PurePath, PurePosixPath, PureWindowsPath
from typing import BinaryIO

__all__ = ["INCOMPLETE", "MANIFEST", "STAGING", "OutputError", "check_complete",
           "check_finite_json", "check_output_folder", "final_path", "guarding_inputs",
           "note_input", "output_file", "output_names", "output_path", "protected_inputs",
           "replace_whole", "staged_output", "write_json", "write_whole"]

_INPUTS: ContextVar[set[Path] | None] = ContextVar("mitsuba_powder_inputs", default=None)
#: {resolved output folder: its staging folder} of the running command (:func:`staged_output`)
_STAGED: ContextVar[dict[Path, Path] | None] = ContextVar("mitsuba_powder_staged", default=None)

#: The staging folder inside an output folder, removed once its files are moved into place
STAGING = ".partial"
#: Present in an output folder while a command moves its finished result's files into it
#: (``{command}``: the command's name)
INCOMPLETE = ".incomplete.{command}"
#: The files of the last whole result a command wrote into an output folder (JSON list;
#: ``{command}``: the command's name, so that commands sharing a folder keep their files)
MANIFEST = ".written.{command}.json"
#: Top-level names written in place, not staged: the resume files of long fits (their own
#: files are written whole, and a later run finds them)
_IN_PLACE = ("tiles",)


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


def write_whole(path: str | Path, data: str | bytes, what: str = "output") -> Path:
    """Write the output file ``path`` whole or not at all: checked by :func:`output_file`
    when it is written (so against every input read by then), ``data`` (text as UTF-8, or
    bytes) written to a temporary file beside it and renamed over it; a failed or interrupted
    write leaves the previous file as it was.

    Raises:
        OutputError: as :func:`output_file`.
    """
    raw = data.encode("utf-8") if isinstance(data, str) else data
    return replace_whole(output_file(path, what), lambda f: f.write(raw))


def replace_whole(path: Path, write: Callable[[BinaryIO], object]) -> Path:
    """``write(f)`` into a temporary file beside ``path`` (an output already checked), synced
    and renamed over ``path``: the file is whole or as it was (the temporary file removed on
    any failure)."""
    part = path.with_name(f".{path.name}.{uuid.uuid4().hex[:8]}.part")
    try:
        with open(part, "wb") as f:
            write(f)
            f.flush()
            os.fsync(f.fileno())
        os.replace(part, path)
    finally:
        part.unlink(missing_ok=True)
    return path


def write_json(path: str | Path, obj, what: str = "output") -> Path:
    """``obj`` as a JSON file (indent 1) through :func:`write_whole`, refused when it holds
    NaN or Infinity (:func:`check_finite_json`): nothing is written then.

    Raises:
        OutputError: a non-finite value, or as :func:`output_file`.
    """
    check_finite_json(obj, f"{what} {path}")
    return write_whole(path, json.dumps(obj, indent=1, allow_nan=False) + "\n", what)


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
    path = _staged_path(target, path)
    if mkdir:
        path.parent.mkdir(parents=True, exist_ok=True)
    return path


def final_path(path: str | Path) -> Path:
    """Where a file that :func:`output_path` placed in a staging folder will be once the
    output is moved into place (other paths unchanged): what messages show."""
    p = Path(path)
    parts = p.parts
    if STAGING in parts:
        i = parts.index(STAGING)
        return Path(*parts[:i], *parts[i + 1:])
    return p


def _staged_path(target: Path, path: Path) -> Path:
    """Where a write to ``path`` (resolved: ``target``) goes: inside a staged output folder,
    its staging folder (but for :data:`_IN_PLACE` names), else ``path``."""
    for root, staging in (_STAGED.get() or {}).items():
        if target.is_relative_to(root) and target != root:
            rel = target.relative_to(root)
            if rel.parts[0] not in _IN_PLACE and rel.parts[0] != STAGING:
                return staging / rel
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


def _non_finite(obj, path: str) -> Iterator[str]:
    """The paths (``a.b[3]``) of the NaN and infinite floats inside JSON-like ``obj``."""
    if isinstance(obj, float):
        if obj != obj or obj in (float("inf"), float("-inf")):
            yield path or "(the value)"
    elif isinstance(obj, dict):
        for k, v in obj.items():
            yield from _non_finite(v, f"{path}.{k}" if path else str(k))
    elif isinstance(obj, (list, tuple)):
        for i, v in enumerate(obj):
            yield from _non_finite(v, f"{path}[{i}]")


def check_finite_json(obj, name: str) -> None:
    """Refuse to write NaN or Infinity into a JSON file (they are not JSON, and no result of
    this package may end in them with exit 0).

    Raises:
        OutputError: naming ``name`` and the first paths of the non-finite values.
    """
    bad = list(_non_finite(obj, ""))
    if bad:
        shown = ", ".join(bad[:5]) + (f" and {len(bad) - 5} more" if len(bad) > 5 else "")
        raise OutputError(f"{name} would hold NaN or Infinity at {shown}: the result is "
                          "degenerate; nothing was written")


def check_output_folder(out: str | Path, what: str = "--out") -> Path:
    """An output folder checked before any work: not a file, not an input, creatable and
    writable; created.

    Raises:
        OutputError: naming ``what``, the folder and what is wrong.
    """
    base = Path(out).expanduser()
    if base.exists() and not base.is_dir():
        raise OutputError(f"{what} {out} is a file; give a folder")
    _check_not_input(_resolved(base), base, what)
    try:
        base.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise OutputError(f"{what} {out}: cannot create the folder ({exc.strerror})") from None
    if not os.access(base, os.W_OK | os.X_OK):
        raise OutputError(f"{what} {out}: the folder is not writable")
    return base


@contextmanager
def staged_output(out: str | Path, what: str = "--out", command: str = "output"
                  ) -> Iterator[Path]:
    """Write the output folder ``out`` whole or not at all.

    ``out`` is checked first (not a file, not an input, writable). Inside the block,
    :func:`output_path` sends every file under ``out`` to ``out/.partial`` (but for the resume
    files of tiled fits); when the block ends normally, the files are moved into ``out``:
    :data:`INCOMPLETE` is created, the files of the previous result (:data:`MANIFEST`) that this
    one does not write again are removed (those of the same ``command``: commands may share a
    folder), the new ones moved into place, the manifest written
    and :data:`INCOMPLETE` removed. An exception or an interrupt leaves ``out`` as it was (the
    staging folder is removed).

    Yields:
        ``out`` as a Path.

    Raises:
        OutputError: ``out`` is a file, an input of the command, or not writable.
    """
    created = not Path(out).expanduser().exists()
    base = check_output_folder(out, what)
    root = _resolved(base)
    staging = base / STAGING
    _remove_tree(staging)
    staging.mkdir()
    token = _STAGED.set({**(_STAGED.get() or {}), root: staging})
    try:
        yield base
    except BaseException:
        _remove_tree(staging)
        if created and not any(base.iterdir()):  # a folder this call made, left empty
            base.rmdir()
        raise
    finally:
        _STAGED.reset(token)
    _commit(base, staging, command)


def _remove_tree(path: Path) -> None:
    """Remove a staging folder (a link in its place is removed, not followed)."""
    if path.is_symlink() or path.is_file():
        path.unlink()
    elif path.exists():
        shutil.rmtree(path)


def _commit(base: Path, staging: Path, command: str) -> None:
    """Move a finished result from ``staging`` into ``base`` (see :func:`staged_output`)."""
    new = sorted(str(p.relative_to(staging)) for p in staging.rglob("*") if p.is_file())
    manifest = base / MANIFEST.format(command=command)
    marker = base / INCOMPLETE.format(command=command)
    marker.write_text("a result is being moved into this folder; if this file stays, the "
                      "run was interrupted: run the command again\n")
    for rel in sorted(set(_manifest(manifest)) - set(new)):
        old = base / rel
        if _is_safe_relative(rel) and _resolved(old).is_relative_to(_resolved(base)) and \
                _resolved(old) not in (_INPUTS.get() or ()):
            old.unlink(missing_ok=True)
    for rel in new:
        (base / rel).parent.mkdir(parents=True, exist_ok=True)
        os.replace(staging / rel, base / rel)
    manifest.write_text(json.dumps(new, indent=1) + "\n")
    _remove_tree(staging)
    marker.unlink()


def _manifest(path: Path) -> list[str]:
    """The files a command's previous whole result wrote (empty without its manifest)."""
    try:
        names = json.loads(path.read_text())
    except (OSError, ValueError):
        return []
    return [n for n in names if isinstance(n, str)] if isinstance(names, list) else []


def check_complete(folder: str | Path) -> None:
    """Refuse a result folder that an interrupted run left half moved into place
    (:data:`INCOMPLETE` present).

    Raises:
        OutputError: naming the folder and what to do.
    """
    left = sorted(Path(folder).glob(INCOMPLETE.format(command="*")))
    if left:
        command = left[0].name[len(INCOMPLETE.format(command="")):]
        raise OutputError(f"{folder} is incomplete: a run of {command} writing it was "
                          f"interrupted while its files were moved into place ({left[0].name} "
                          f"is there); run {command} again")
