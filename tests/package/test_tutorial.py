"""docs/tutorial.md and README.md run as written: every ``bash`` and ``python`` block of the
tutorial runs, in order, in a fresh folder beside links to the repository's ``measurements``,
``scenes`` and ``docs``, and every line the tutorial quotes as a command's output (the ``#``
lines under it) is a line of what the command printed, times in seconds aside. README's Python
example runs too. So the pages cannot drift from what the commands do.

Small sizes: the showcase script gets ``--spp 2 --res 96x30`` (its figure is tested at that
size in tests/package/test_docs_scripts.py)."""

from __future__ import annotations

import os
import re
import shlex
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
#: extra arguments that make a command small (command prefix -> arguments appended)
SMALL = {"python docs/scripts/showcase.py": "--spp 2 --res 96x30"}
#: a time in seconds, which varies from run to run and machine to machine
_SECONDS = re.compile(r"\b\d+(?:\.\d+)? s\b")


def blocks(path: Path) -> list[tuple[str, str]]:
    """(language, text) of every fenced block of a Markdown file, in order."""
    return re.findall(r"^```(\w+)\n(.*?)^```", path.read_text(), flags=re.S | re.M)


def commands(block: str) -> list[tuple[str, list[str]]]:
    """(command, quoted output lines) of a bash block: continuation lines joined, the
    ``#`` lines under a command are its output (a leading ``... `` marks lines left out)."""
    out: list[tuple[str, list[str]]] = []
    pending = ""
    for line in block.splitlines():
        if pending:
            pending += " " + line.strip()
        elif line.startswith("#"):
            assert out, f"an output line before any command: {line!r}"
            text = line[1:].strip()
            out[-1][1].append(text[4:] if text.startswith("... ") else text)
            continue
        else:
            pending = line.strip()
        if pending.endswith("\\"):
            pending = pending[:-1].rstrip()
            continue
        if pending:
            out.append((pending, []))
        pending = ""
    return out


def _normalised(line: str) -> str:
    return _SECONDS.sub("<t> s", line.strip())


@pytest.fixture(scope="module")
def workdir(tmp_path_factory) -> Path:
    folder = tmp_path_factory.mktemp("tutorial")
    for name in ("measurements", "scenes", "docs"):
        (folder / name).symlink_to(ROOT / name)
    return folder


def _env() -> dict:
    bin_dir = str(Path(sys.executable).parent)  # the environment's mitsuba-powder and python
    return {**os.environ, "PATH": bin_dir + os.pathsep + os.environ.get("PATH", ""),
            "PYTHONUNBUFFERED": "1"}


def test_tutorial_commands_print_what_the_tutorial_quotes(workdir):
    ran = 0
    for language, text in blocks(ROOT / "docs" / "tutorial.md"):
        if language == "python":
            proc = subprocess.run([sys.executable, "-c", text], cwd=workdir, env=_env(),
                                  capture_output=True, text=True, timeout=600)
            assert proc.returncode == 0, f"python block:\n{text}\n{proc.stderr[-3000:]}"
            ran += 1
            continue
        if language != "bash":
            continue
        for command, quoted in commands(text):
            for prefix, extra in SMALL.items():
                if command.startswith(prefix):
                    head, sep, comment = command.partition(" #")
                    command = f"{head.rstrip()} {extra}"
            proc = subprocess.run(["bash", "-c", command], cwd=workdir, env=_env(),
                                  capture_output=True, text=True, timeout=600)
            assert proc.returncode == 0, f"{command}\n{proc.stdout[-2000:]}{proc.stderr[-3000:]}"
            printed = {_normalised(line) for line in proc.stdout.splitlines()}
            for line in quoted:
                assert _normalised(line) in printed, (
                    f"{command}: the tutorial quotes\n  {line}\nbut it printed\n"
                    + proc.stdout[-3000:])
            ran += 1
    assert ran >= 8


def test_readme_python_example_runs(workdir):
    code = "\n".join(text for language, text in blocks(ROOT / "README.md")
                     if language == "python")
    assert "load_dict" in code
    proc = subprocess.run([sys.executable, "-c", code + "\nprint(bsdf, glossy)"], cwd=workdir,
                          env=_env(), capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert "amplitude_surface = [0.0002]" in proc.stdout


def test_readme_lists_every_command():
    """The command list of README.md names every sub-command of ``mitsuba-powder``."""
    from mitsuba_powder.cli import build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if a.choices and isinstance(a.choices, dict))
    listing = next(text for language, text in blocks(ROOT / "README.md")
                   if language == "text" and "mitsuba-powder info" in text)
    listed = {shlex.split(line)[1] for line in listing.splitlines()
              if line.startswith("mitsuba-powder ") and not line.split()[1].startswith("-")}
    assert listed == set(sub.choices)


def test_quoted_lines_parse():
    """The block reader: continuation lines, output lines, elisions."""
    got = commands("a \\\n  --b c\n# out 1\n# ... out 2\nd # note\n")
    assert got == [("a --b c", ["out 1", "out 2"]), ("d # note", [])]
