"""Scene descriptions as ``render`` reads them: the files a scene names (its inputs, which no
output may replace) and the description with powder properties written into every
``<bsdf type="powder">`` (``render --params/--set``), ``<include>``s read in."""

from __future__ import annotations

import xml.etree.ElementTree as ET
from pathlib import Path

__all__ = ["expanded_tree", "scene_files", "scene_with_properties", "xml_property"]


#: Property names given as strings in a scene description (the others are numbers)
_STRING_PROPERTIES = ("grains", "mixing", "material", "specular", "surface_fresnel", "lobes",
                      "sampling", "energy")


def xml_property(name: str, value):
    """The scene-description element of one powder property: ``string`` for the named
    choices and ``rgb_wavelengths``, ``rgb`` for three numbers, ``float`` for one."""
    if name in _STRING_PROPERTIES:
        return ET.Element("string", name=name, value=str(value))
    if name == "rgb_wavelengths" and isinstance(value, str):
        return ET.Element("string", name=name, value=value)
    if isinstance(value, dict):
        return _xml_spectrum(name, value)
    values = list(value) if isinstance(value, (list, tuple)) else [value]
    try:
        if any(isinstance(v, (str, bool)) for v in values):
            raise TypeError
        numbers = [float(v) for v in values]
    except (TypeError, ValueError):
        raise ValueError(f"powder property {name!r} = {value!r}: expected a number (or "
                         "three: R, G, B)") from None
    if len(numbers) == 3:
        text = ", ".join(repr(v) for v in numbers)
        return ET.Element("string" if name == "rgb_wavelengths" else "rgb", name=name,
                          value=text)
    if len(numbers) != 1:
        raise ValueError(f"powder property {name!r} = {value!r}: expected one number or three "
                         "(R, G, B)")
    return ET.Element("float", name=name, value=repr(numbers[0]))


def _xml_spectrum(name: str, value: dict):
    """A ``<spectrum>`` of ``(wavelength, value)`` pairs from an ``irregular`` spectrum dict
    (``wavelengths`` and ``values``: lists or comma-separated text, as a multi-wavelength
    ``fit.json`` writes its albedo)."""
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
    text = ", ".join(f"{w!r}:{v!r}" for w, v in zip(wl, vals))
    return ET.Element("spectrum", name=name, value=text)


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
    "agglomerate_radius": ("albedo",),
    "agglomerate_fill": ("albedo",),
    "mixing": ("albedo",),
}


def expanded_tree(scene: Path, depth: int = 0):
    """(root element, folders, files) of a scene file with every ``<include>`` replaced by
    the included file's content (recursively): the folders of the files read, the scene's
    first (Mitsuba resolves relative names there), and the included files."""
    if depth > 16:
        raise ValueError(f"{scene}: <include> nested more than 16 deep")
    root = ET.parse(scene).getroot()
    folders, files = [scene.resolve().parent], []
    for parent in list(root.iter()):
        for child in reversed(list(parent)):  # from the end: indices before stay valid
            if child.tag != "include" or not child.get("filename"):
                continue
            i = list(parent).index(child)
            name = Path(child.get("filename"))
            path = name if name.is_absolute() else scene.parent / name
            if not path.is_file():
                continue  # Mitsuba reports it when it loads the scene
            sub, sub_folders, sub_files = expanded_tree(path, depth + 1)
            files += [path, *sub_files]
            parent.remove(child)
            for k, element in enumerate(list(sub)):
                parent.insert(i + k, element)
            folders += [f for f in sub_folders if f not in folders]
    return root, folders, files


def scene_with_properties(scene: str | Path, properties: dict
                          ) -> tuple[str, int, list[str]]:
    """The scene description of ``scene`` with ``properties`` written into every
    ``<bsdf type="powder">`` element of the file (replacing any element of the same name).

    Every property then reaches the plugin's constructor, the non-differentiable ones (``eta``,
    ``k``, ``material``, ``lobes``...) included, and is validated there. A scene property that
    would override the given ones is removed: the scene's ``albedo`` when the properties give
    grains (``radius``...) but no albedo, its ``tau_o`` when they give ``eta``/``k`` or a
    ``material`` but no ``tau_o``, its ``eta``/``k`` when they give a ``material``.

    Included files (``<include>``) are read into the description first, so that their powders
    get the properties too.

    Returns:
        (the XML text, the number of powder BSDFs changed (0 when the description defines
        none, e.g. when a plugin creates them), the scene properties removed).
    """
    root, _, _ = expanded_tree(Path(scene))
    powders = [e for e in root.iter("bsdf") if e.get("type") == "powder"]
    elements = {name: xml_property(name, value) for name, value in properties.items()}
    drop = {name for name, inputs in _OVERRIDES.items()
            if name not in properties and any(k in properties for k in inputs)}
    removed: list[str] = []
    for bsdf in powders:
        for child in list(bsdf):
            name = child.get("name")
            if name in elements or name in drop:
                bsdf.remove(child)
                if name in drop and name not in removed:
                    removed.append(name)
        for element in elements.values():
            bsdf.append(element)
    return ET.tostring(root, encoding="unicode"), len(powders), removed


def scene_files(scene: str | Path, defines: dict[str, str] | None = None) -> list[Path]:
    """The files a scene description names: ``filename`` properties and ``<include>``s, in
    the scene and the files it includes, ``$name`` substituted from its ``<default>``s and
    ``defines``, each resolved beside every file of the description and the current folder
    (every candidate that exists, and the first otherwise). A file that does not parse names
    none (Mitsuba reports it)."""
    import re
    scene = Path(scene)
    try:
        root, folders, included = expanded_tree(scene)
    except (ET.ParseError, OSError, ValueError):
        return [scene]
    values = {e.get("name"): e.get("value", "") for e in root.iter("default")}
    values.update(defines or {})

    def substituted(text: str) -> str:
        return re.sub(r"\$(\w+)", lambda m: str(values.get(m.group(1), m.group(0))), text)

    names = [e.get("value") for e in root.iter() if e.get("name") == "filename"]
    out: list[Path] = [scene, *included]
    for text in names:
        if not text:
            continue
        name = Path(substituted(text))
        candidates = [name] if name.is_absolute() else [f / name for f in folders] + [name]
        found = [c for c in candidates if c.exists()]
        out += found or candidates[:1]
    return out
