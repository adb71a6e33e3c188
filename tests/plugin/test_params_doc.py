"""The plugin's parameter table (powder_param::Table in powder.cpp), the properties its
constructor reads, its doc comment and docs/powder.md name the same properties with the same
defaults and ranges; and the plugin reads every documented property."""

from __future__ import annotations

import re
from pathlib import Path

import mitsuba as mi
import pytest

from helpers import use_variant

ROOT = Path(__file__).resolve().parents[2]
# the plugin's source: powder.cpp (the doc comment), its headers (the parameter table, parsing)
SOURCE = "\n".join(p.read_text() for p in sorted((ROOT / "src" / "bsdfs").glob("powder*")))
DOCS = (ROOT / "docs" / "powder.md").read_text()

_NUMBER = {"Inf": "inf", "0.5 * M_PI": "pi/2"}


def number(token: str) -> str:
    """A range end of the table as the docs (and the plugin's messages, %g) write it."""
    token = token.strip()
    return _NUMBER[token] if token in _NUMBER else f"{float(token):g}"


def table_rows() -> list[dict]:
    """Rows of powder_param::Table: name, documented default, range as written in the docs."""
    body = SOURCE[SOURCE.index("inline constexpr Spec Table[Count]"):]
    body = body[:body.index("};")]
    rows = []
    for m in re.finditer(r'\{\s*"(\w+)",\s*"([^"]*)",\s*[^,]+,\s*"([^"]*)",\s*'
                         r'\{\s*([^,]+),\s*([^,]+),\s*(true|false),\s*(true|false)\s*\},\s*'
                         r'(true|false)\s*\}', body):
        name, _unit, def_doc, lo, hi, lo_c, hi_c, _fit = m.groups()
        rng = ("[" if lo_c == "true" else "(") + number(lo) + ", " + number(hi) + \
            ("]" if hi_c == "true" else ")")
        rows.append({"name": name, "default": def_doc, "range": rng})
    return rows


def doc_comment_entries() -> dict[str, str]:
    """name -> text of each entry of the doc comment's pluginparameters table."""
    block = SOURCE[SOURCE.index(".. pluginparameters::"):SOURCE.index("The dry-powder")]
    entries = {}
    for part in re.split(r"\n \* - ", block)[1:]:
        head, _, rest = part.partition("\n")
        text = " ".join(rest.split())
        for name in head.split(","):
            entries[name.strip()] = text
    return entries


def docs_rows() -> dict[str, list[str]]:
    """name -> cells of docs/powder.md's parameter table."""
    section = DOCS[DOCS.index("## Parameters"):]
    section = section[:section.index("\n\n", section.index("| property"))]
    rows = {}
    for line in section.splitlines()[2:]:
        cells = [c.strip() for c in line.strip().strip("|").split("|")]
        for name in re.findall(r"`(\w+)`", cells[0]):
            rows[name] = cells
    return rows


def properties_read() -> set[str]:
    """Names the constructor reads: the table's, and those named in props.* calls."""
    names = {r["name"] for r in table_rows()}
    names |= set(re.findall(r'props\.(?:has_property|get<[\w:]+>|get_texture<Texture>|type)'
                            r'\("(\w+)"', SOURCE))
    names |= set(re.findall(r'read_spectrum\(props, "(\w+)"\)', SOURCE))
    names |= set(re.findall(r'read_choice<\d+>\(props, "(\w+)"', SOURCE))
    # the material properties of each population (read through these arrays)
    for array in ("PopulationMaterial", "PopulationEta", "PopulationK"):
        body = SOURCE[SOURCE.index(f"{array}[MaxPopulations] = {{"):]
        names |= set(re.findall(r'"(\w+)"', body[:body.index("};")]))
    return names


def test_the_table_is_parsed():
    names = [r["name"] for r in table_rows()]
    assert names[:3] == ["amplitude_volume", "g", "extinction"] and len(names) == 17


def test_doc_comment_lists_exactly_the_properties_read():
    assert set(doc_comment_entries()) == properties_read()


def test_docs_table_lists_exactly_the_properties_read():
    assert set(docs_rows()) == properties_read()


@pytest.mark.parametrize("row", table_rows(), ids=lambda r: r["name"])
def test_defaults_and_ranges_agree(row):
    entry = doc_comment_entries()[row["name"]]
    assert f"Default: {row['default']}" in entry, entry
    assert f"range {row['range']}" in entry, entry
    cells = docs_rows()[row["name"]]
    assert cells[3].startswith(row["default"].split(" (")[0]), cells
    assert row["range"] in cells[4], cells


def test_every_documented_property_is_read(tmp_path):
    """Loading with every documented property set leaves none unreferenced (Mitsuba
    raises on a property nobody queried)."""
    use_variant("llvm_ad_rgb")
    common = {"type": "powder", "amplitude_volume": 0.9, "g": 0.1, "extinction": 0.5,
              "tau_o": 1.0, "thickness": 10.0, "amplitude_surface": 1e-3, "lobes": "all",
              "sampling": "lobes", "wavelength": 650.0, "rgb_wavelengths": "600, 550, 450"}
    mi.load_dict({**common, "specular": "harvey_shack", "correlation_length": 2.0,
                  "sigma": 0.2, "radius": 0.05, "radius2": 0.2, "fraction2": 0.3,
                  "material": "magnetite"})
    mi.load_dict({**common, "specular": "gaussian", "sigma": 0.2, "eta": 2.5, "k": 0.1})
    mi.load_dict({**common, "albedo": 0.5, "energy": "conserving"})
    with pytest.raises(Exception, match="not_a_property"):
        mi.load_dict({**common, "albedo": 0.5, "not_a_property": 1.0})


def test_python_property_list_is_the_plugins():
    """mitsuba_powder.plugin.params.POWDER_PROPERTIES (what render --set accepts) names exactly the
    properties of the plugin's doc comment."""
    from mitsuba_powder.plugin.params import POWDER_PROPERTIES

    assert sorted(POWDER_PROPERTIES) == sorted(doc_comment_entries())
    assert len(set(POWDER_PROPERTIES)) == len(POWDER_PROPERTIES)
