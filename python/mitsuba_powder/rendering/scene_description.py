"""Scene descriptions as ``render`` reads them: the files a scene names (its inputs, which no
output may replace) and the description with powder properties written into every
``<bsdf type="powder">`` (``render --params/--set``).

Scene files are read by Mitsuba's own parser (:mod:`mitsuba.parser`), so that every file Mitsuba
loads can be edited (comments with ``--``, ``<include>``s, ``<default>``s and ``-D`` values, the
scene versions Mitsuba upgrades), and the powders' properties are edited in the parsed
description before it is instantiated. :func:`xml_property` writes one property as an XML element
for the scenes the package writes itself (``rti.maps``).
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from dataclasses import dataclass
from pathlib import Path

import mitsuba as mi
from mitsuba import mitsuba_ext

__all__ = ["ParsedScene", "parse_scene", "scene_files", "scene_with_properties",
           "xml_property"]


#: Property names given as strings in a scene description (the others are numbers)
_STRING_PROPERTIES = ("grains", "mixing", "material", "specular", "surface_fresnel", "lobes",
                      "sampling", "energy")


def _property_kind(name: str, value) -> tuple[str, object]:
    """One powder property as (element kind, value): ``("string", text)``, ``("float", x)``,
    ``("rgb", (r, g, b))`` or ``("spectrum", (wavelengths, values))`` (nm, -).

    Raises:
        ValueError: a value that is none of these (the property named).
    """
    if name in _STRING_PROPERTIES or (name == "rgb_wavelengths" and isinstance(value, str)):
        return "string", str(value)
    if isinstance(value, dict):
        return "spectrum", _spectrum_pairs(name, value)
    values = list(value) if isinstance(value, (list, tuple)) else [value]
    try:
        if any(isinstance(v, (str, bool)) for v in values):
            raise TypeError
        numbers = [float(v) for v in values]
    except (TypeError, ValueError):
        raise ValueError(f"powder property {name!r} = {value!r}: expected a number (or "
                         "three: R, G, B)") from None
    if len(numbers) == 3:
        if name == "rgb_wavelengths":
            return "string", ", ".join(repr(v) for v in numbers)
        return "rgb", tuple(numbers)
    if len(numbers) != 1:
        raise ValueError(f"powder property {name!r} = {value!r}: expected one number or three "
                         "(R, G, B)")
    return "float", numbers[0]


def xml_property(name: str, value):
    """The scene-description element of one powder property: ``string`` for the named
    choices and ``rgb_wavelengths``, ``rgb`` for three numbers, ``float`` for one,
    ``spectrum`` for an ``irregular`` spectrum dict."""
    kind, v = _property_kind(name, value)
    if kind == "rgb":
        v = ", ".join(repr(x) for x in v)
    elif kind == "spectrum":
        v = ", ".join(f"{w!r}:{x!r}" for w, x in zip(*v))
    elif kind == "float":
        v = repr(v)
    return ET.Element(kind, name=name, value=v)


def _parser_value(name: str, value):
    """One powder property as the value Mitsuba's parser stores for its XML element."""
    kind, v = _property_kind(name, value)
    if kind == "rgb":
        return mi.ScalarColor3f(*v)
    if kind == "spectrum":  # the parser's own spectrum type, not the variant's mi.Spectrum
        return mitsuba_ext.Spectrum(*v)
    return v


def _spectrum_pairs(name: str, value: dict) -> tuple[list[float], list[float]]:
    """(wavelengths, values) of an ``irregular`` spectrum dict (``wavelengths`` and
    ``values``: lists or comma-separated text, as a multi-wavelength ``fit.json`` writes its
    albedo)."""
    def numbers(v) -> list[float]:
        return [float(x) for x in (v.replace(",", " ").split() if isinstance(v, str) else v)]

    try:
        if value.get("type") != "irregular":
            raise ValueError
        wl, vals = numbers(value["wavelengths"]), numbers(value["values"])
        if len(wl) != len(vals) or not wl:
            raise ValueError
    except (KeyError, TypeError, ValueError):
        raise ValueError(f"powder property {name!r} = {value!r}: a spectrum must be "
                         "{'type': 'irregular', 'wavelengths': [...], 'values': [...]} of "
                         "equal lengths") from None
    return wl, vals


#: A property that overrides others in the plugin, and what it overrides: given in the scene
#: but not in the properties, while the properties give what it overrides, it is removed (so
#: that ``radius`` from a fit gives the albedo from the grains, not the scene's albedo)
_OVERRIDES = {
    "albedo": ("radius", "radius2", "fraction2", "grains", "agglomerate_radius",
               "agglomerate_fill", "mixing"),
    "tau_o": ("material", "eta", "k"),
    "eta": ("material",),
    "k": ("material",),
    "material": ("eta", "k"),
    "grains": ("albedo",),
    "radius": ("albedo",),
    "radius2": ("albedo",),
    "fraction2": ("albedo",),
    "agglomerate_radius": ("albedo",),
    "agglomerate_fill": ("albedo",),
    "mixing": ("albedo",),
}


@dataclass
class ParsedScene:
    """A scene description parsed by Mitsuba (:func:`parse_scene`).

    Attributes:
        path: the scene file.
        state: Mitsuba's parsed description (``mitsuba.parser.ParserState``), editable.
        config: the parser configuration it was read with (its variant).
        files: the files of the description: the scene's, then those it includes.
    """

    path: Path
    state: object
    config: object
    files: list[Path]

    def powders(self) -> list:
        """The description's ``powder`` BSDF nodes (``mitsuba.parser.SceneNode``)."""
        return [n for n in self.state.nodes if n.props.plugin_name() == "powder"]

    def folders(self) -> list[Path]:
        """The folders of the description's files, the scene's first (where relative file
        names are looked for)."""
        out: list[Path] = []
        for f in self.files:
            folder = f.resolve().parent
            if folder not in out:
                out.append(folder)
        return out

    def load(self):
        """The scene, instantiated in the variant it was parsed for; relative file names are
        found beside every file of the description (the scene's first)."""
        resolver = mi.file_resolver()
        saved = mi.FileResolver(resolver)
        for folder in reversed(self.folders()):
            resolver.prepend(str(folder))
        try:
            mi.parser.transform_all(self.config, self.state)
            return mi.parser.instantiate(self.config, self.state)
        finally:
            mi.set_file_resolver(saved)


def parse_scene(scene: str | Path, defines: dict[str, str] | None = None) -> ParsedScene:
    """Parse ``scene`` as Mitsuba does (its own parser, the current variant), ``<include>``s
    and ``$name`` values (``<default>``s, ``defines``) resolved.

    Raises:
        RuntimeError: Mitsuba cannot parse it (its message names the file and line).
    """
    scene = Path(scene)
    config = mi.parser.ParserConfig(mi.variant() or "scalar_rgb")
    values = {k: str(v) for k, v in (defines or {}).items()}
    state = mi.parser.parse_file(config, str(scene), **values)
    files = [Path(str(f)) for f in state.files]
    return ParsedScene(scene, state, config, files or [scene])


def scene_with_properties(scene: str | Path | ParsedScene, properties: dict,
                          defines: dict[str, str] | None = None
                          ) -> tuple[ParsedScene, int, list[str]]:
    """The description of ``scene`` with ``properties`` written into every
    ``<bsdf type="powder">`` of the scene and the files it includes (replacing any property of
    the same name), as Mitsuba's parser read it (:func:`parse_scene`).

    Every property then reaches the plugin's constructor, the non-differentiable ones (``eta``,
    ``k``, ``material``, ``lobes``...) included, and is validated there. A scene property that
    would override the given ones is removed: the scene's ``albedo`` when the properties give
    grains (``radius``...) but no albedo, its ``tau_o`` when they give ``eta``/``k`` or a
    ``material`` but no ``tau_o``, its ``eta``/``k`` when they give a ``material``.

    Returns:
        (the edited description (:meth:`ParsedScene.load` instantiates it), the number of
        powder BSDFs changed (0 when the description defines none, e.g. when a plugin creates
        them), the scene properties removed).
    """
    parsed = scene if isinstance(scene, ParsedScene) else parse_scene(scene, defines)
    values = {name: _parser_value(name, value) for name, value in properties.items()}
    drop = {name for name, inputs in _OVERRIDES.items()
            if name not in properties and any(k in properties for k in inputs)}
    removed: list[str] = []
    powders = parsed.powders()
    for node in powders:
        props = node.props
        for name in list(props.keys()):
            if name in values or name in drop:
                del props[name]
                if name in drop and name not in removed:
                    removed.append(name)
        for name, value in values.items():
            props[name] = value
    return parsed, len(powders), removed


def scene_files(scene: str | Path, defines: dict[str, str] | None = None) -> list[Path]:
    """The files a scene description names: the scene, the files it includes and every
    ``filename`` property (``$name`` substituted from its ``<default>``s and ``defines``),
    each resolved beside every file of the description and the current folder (every
    candidate that exists, and the first otherwise). A file Mitsuba cannot parse names only
    itself (Mitsuba reports why when it loads it)."""
    scene = Path(scene)
    try:
        parsed = parse_scene(scene, defines)
    except (RuntimeError, ValueError, OSError):
        return [scene]
    folders = parsed.folders()
    out: list[Path] = list(parsed.files)
    for node in parsed.state.nodes:
        props = node.props
        if "filename" not in props.keys() or props.type("filename") != mi.Properties.Type.String:
            continue
        name = Path(props["filename"])
        candidates = [name] if name.is_absolute() else [f / name for f in folders] + [name]
        found = [c for c in candidates if c.exists()]
        out += found or candidates[:1]
    return out
