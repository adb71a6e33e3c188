"""The documentation's pointers lead somewhere: no file of the repository names the
specification by a file name the repository does not contain (the specification is
docs/model.md; it used to be a file outside the repository), and the relative links of
README.md and docs/*.md point to files (and headings) that exist."""

from __future__ import annotations

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]

#: the old name of the specification, which a clone does not contain (built here so that this
#: file does not name it itself)
OLD_SPEC = "MODEL" + ".md"


MARKDOWN = ["README.md", *sorted(str(p.relative_to(ROOT)) for p in (ROOT / "docs").glob("*.md"))]

INLINE_LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
REFERENCE_DEFINITION = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$", re.MULTILINE)
FENCE = re.compile(r"^(```|~~~).*?^\1[^\n]*$", re.MULTILINE | re.DOTALL)
INLINE_CODE = re.compile(r"`[^`\n]*`")


def repository_files() -> list[str]:
    """Tracked files, and new files that git does not ignore (so that a file is checked before
    it is committed)."""
    try:
        out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard",
                              "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        pytest.skip("not a git checkout (git ls-files failed)")
    return sorted({name for name in out.decode("utf-8", "replace").split("\0") if name})


def read_text(path: Path) -> str | None:
    """The file's text, or None for a binary file (a NUL byte, or not UTF-8)."""
    data = path.read_bytes()
    if b"\0" in data:
        return None
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError:
        return None


def test_no_file_names_a_specification_the_repository_lacks():
    files = repository_files()
    if any(Path(name).name == OLD_SPEC for name in files):
        pytest.skip(f"the repository contains a file named {OLD_SPEC}")
    offenders = []
    for name in files:
        path = ROOT / name
        if not path.is_file():  # deleted in the working tree
            continue
        text = read_text(path)
        if text is None:
            continue
        for lineno, line in enumerate(text.splitlines(), start=1):
            if OLD_SPEC in line:
                offenders.append(f"{name}:{lineno}: {line.strip()}")
    assert not offenders, (f"{len(offenders)} lines name {OLD_SPEC}, which is not in the "
                           "repository (the specification is docs/model.md):\n"
                           + "\n".join(offenders))


def github_slug(heading: str) -> str:
    """GitHub's anchor for a markdown heading: lower case, markup and punctuation removed
    (letters, digits, spaces, hyphens and underscores kept), spaces to hyphens."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading)  # links: their text
    text = text.replace("`", "").strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(text: str) -> set[str]:
    """Anchors of the headings of a markdown text (duplicates numbered as GitHub does)."""
    seen: dict[str, int] = {}
    out = set()
    for match in re.finditer(r"^#{1,6}\s+(.*?)\s*#*\s*$", FENCE.sub("", text), re.MULTILINE):
        slug = github_slug(match.group(1))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        out.add(slug if n == 0 else f"{slug}-{n}")
    return out


def links(text: str) -> list[str]:
    """Targets of the inline links, images and reference definitions, outside code."""
    prose = INLINE_CODE.sub("", FENCE.sub("", text))
    return ([m.group(1) for m in INLINE_LINK.finditer(prose)]
            + [m.group(1) for m in REFERENCE_DEFINITION.finditer(prose)])


@pytest.mark.parametrize("name", MARKDOWN)
def test_relative_markdown_links_point_to_existing_files(name):
    path = ROOT / name
    text = path.read_text(encoding="utf-8")
    broken = []
    for target in links(text):
        if re.match(r"^[a-zA-Z][a-zA-Z0-9+.-]*:", target):  # http:, https:, mailto:, ...
            continue
        file_part, _, anchor = target.partition("#")
        file_part = file_part.split("?")[0]
        dest = path if not file_part else (path.parent / file_part)
        if not dest.exists():
            broken.append(f"{target}: no file {dest}")
            continue
        if anchor and dest.suffix == ".md" and dest.is_file():
            if anchor.lower() not in anchors(dest.read_text(encoding="utf-8")):
                broken.append(f"{target}: no heading with anchor #{anchor} in "
                              f"{dest.relative_to(ROOT)}")
    assert not broken, f"{name}: broken relative links:\n" + "\n".join(broken)


def test_link_parser_finds_links_and_skips_code():
    text = ("see [a](a.md) and ![fig](figures/x.png \"title\"), not `[b](b.md)`\n"
            "```\n[c](c.md)\n```\n[ref]: other.md#part\n")
    assert links(text) == ["a.md", "figures/x.png", "other.md#part"]
    assert github_slug("Energy: the regime of the theory and the two modes") == \
        "energy-the-regime-of-the-theory-and-the-two-modes"
    assert github_slug("Grain models (`grains`)") == "grain-models-grains"
    assert anchors("# A\n## A\n") == {"a", "a-1"}
