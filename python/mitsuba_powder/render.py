"""Render a scene file that uses the ``powder`` BSDF and write the image."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi

from .outputs import guarding_inputs, output_file
from .params import check_property_names
from .variants import check_variant, use_variant


@dataclass(frozen=True)
class RenderResult:
    """What :func:`render_scene` produced.

    Attributes:
        output: path of the written image.
        width, height: image size in pixels.
        spp: samples per pixel used (the scene's own count when none was asked for).
        variant: Mitsuba variant.
        seconds: wall-clock time of loading and rendering, in seconds.
        applied: the powder properties set (``properties`` of :func:`render_scene`).
        not_applied: those that could not be set (with ``allow_missing``).
        removed: scene properties removed because they would override the given ones (see
            :func:`scene_with_properties`).
    """

    output: Path
    width: int
    height: int
    spp: int | None
    variant: str
    seconds: float
    applied: tuple[str, ...] = ()
    not_applied: tuple[str, ...] = ()
    removed: tuple[str, ...] = ()


def apply_properties(scene, properties: dict) -> tuple[list[str], list[str]]:
    """Set ``properties`` on every ``powder`` BSDF of a loaded scene through ``mi.traverse``.

    Only differentiable parameters can change after loading (``amplitude_volume``, ``g``,
    ``extinction``, ``thickness``, ``amplitude_surface``, ``correlation_length``, ``sigma``,
    ``tau_o`` and ``albedo`` when the scene gives them, ``radius`` when it does not); the
    others (``material``, ``eta``, ``lobes``...) belong in the scene file.

    Returns:
        (names applied, names not applied).

    Raises:
        ValueError: the scene has no ``powder`` BSDF.
    """
    params = mi.traverse(scene)
    keys = list(params.keys())
    prefixes = sorted({k[: -len(".extinction")] for k in keys if k.endswith(".extinction")})
    if not prefixes:
        raise ValueError("the scene has no powder BSDF to apply --params to")
    applied, missing = [], []
    for name, value in properties.items():
        hits = [k for p in prefixes for k in (f"{p}.{name}", f"{p}.{name}.value")
                if k in params]
        if not hits:
            missing.append(name)
            continue
        try:
            numbers = [float(v) for v in (value if isinstance(value, (list, tuple))
                                          else [value])]
        except (TypeError, ValueError):
            raise ValueError(f"powder property {name!r} = {value!r}: expected a number "
                             "(or a list of numbers)") from None
        for key in hits:
            params[key] = type(params[key])(*numbers)
        applied.append(name)
    params.update()
    return applied, missing


#: Property names given as strings in a scene description (the others are numbers)
_STRING_PROPERTIES = ("grains", "mixing", "material", "specular", "surface_fresnel", "lobes",
                      "sampling", "energy")


def _xml_property(name: str, value):
    """The scene-description element of one powder property: ``string`` for the named
    choices and ``rgb_wavelengths``, ``rgb`` for three numbers, ``float`` for one."""
    import xml.etree.ElementTree as ET

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
    import xml.etree.ElementTree as ET

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


def _expanded_tree(scene: Path, depth: int = 0):
    """(root element, folders, files) of a scene file with every ``<include>`` replaced by
    the included file's content (recursively): the folders of the files read, the scene's
    first (Mitsuba resolves relative names there), and the included files."""
    import xml.etree.ElementTree as ET

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
            sub, sub_folders, sub_files = _expanded_tree(path, depth + 1)
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
    import xml.etree.ElementTree as ET

    root, _, _ = _expanded_tree(Path(scene))
    powders = [e for e in root.iter("bsdf") if e.get("type") == "powder"]
    elements = {name: _xml_property(name, value) for name, value in properties.items()}
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


def _load_with_properties(scene: Path, properties: dict, defines: dict) -> tuple:
    """(loaded scene, names applied in the scene description, names left for traverse,
    scene properties removed)."""
    text, count, removed = scene_with_properties(scene, properties)
    if count == 0:
        return mi.load_file(str(scene), **defines), [], list(properties), []
    resolver = mi.file_resolver()
    saved = mi.FileResolver(resolver)
    _, folders, _ = _expanded_tree(scene)
    for folder in reversed(folders):  # relative file names, as load_file does (scene's first)
        resolver.prepend(str(folder))
    try:
        loaded = mi.load_string(text, **defines)
    finally:
        mi.set_file_resolver(saved)
    return loaded, list(properties), [], removed


def scene_files(scene: str | Path, defines: dict[str, str] | None = None) -> list[Path]:
    """The files a scene description names: ``filename`` properties and ``<include>``s, in
    the scene and the files it includes, ``$name`` substituted from its ``<default>``s and
    ``defines``, each resolved beside every file of the description and the current folder
    (every candidate that exists, and the first otherwise). A file that does not parse names
    none (Mitsuba reports it)."""
    import re
    import xml.etree.ElementTree as ET

    scene = Path(scene)
    try:
        root, folders, included = _expanded_tree(scene)
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


def render_scene(
    scene: str | Path,
    output: str | Path,
    variant: str = "scalar_rgb",
    spp: int | None = None,
    defines: dict[str, str] | None = None,
    properties: dict | None = None,
    allow_missing: bool = False,
) -> RenderResult:
    """Render ``scene`` in ``variant`` and write ``output`` (.exr: linear; .png: sRGB 8 bit).

    The caller's Mitsuba variant, if any, is selected again on return (see
    :func:`mitsuba_powder.variants.use_variant`).

    Args:
        scene: scene XML file.
        output: image file to write; its folder is created.
        variant: Mitsuba variant, e.g. ``scalar_rgb``, ``llvm_ad_rgb``, ``scalar_spectral``.
        spp: samples per pixel, overriding the scene's sampler.
        defines: values for the scene's ``<default name=...>`` parameters.
        properties: powder properties, e.g. from a ``fit.json``, written into every
            ``<bsdf type="powder">`` of the scene file and the files it includes before it is
            loaded (:func:`scene_with_properties`: every property, ``eta`` or ``lobes`` too).
            When the description defines no powder BSDF (a plugin creates them), they are set
            after loading where ``mi.traverse`` exposes them (:func:`apply_properties`).
        allow_missing: in that second case, render even when some of ``properties`` cannot be
            set (they are listed in :attr:`RenderResult.not_applied`); by default that is an
            error, since the image would show another powder than the one asked for.

    Raises:
        FileNotFoundError: the scene file does not exist.
        ValueError: unknown variant, unsupported output extension or bad ``spp``; a name in
            ``properties`` that is not a powder property; a property the scene does not expose
            (unless ``allow_missing``).
        RuntimeError: the variant's backend (CUDA, LLVM) cannot run here.
    """
    scene = Path(scene)
    output = Path(output)
    if not scene.is_file():
        raise FileNotFoundError(f"scene file {scene} does not exist")
    check_variant(variant)
    if output.suffix.lower() not in (".exr", ".png", ".jpg", ".hdr", ".pfm"):
        raise ValueError(f"output {output}: extension must be .exr, .png, .jpg, .hdr or .pfm")
    if spp is not None and spp < 1:
        raise ValueError(f"spp = {spp} is out of range; valid range is [1, inf)")
    if properties:
        check_property_names(properties)

    with guarding_inputs(*scene_files(scene, defines)), use_variant(variant):
        output = output_file(output, "output")
        start = time.perf_counter()
        if properties:
            loaded, applied, rest, removed = _load_with_properties(scene, properties,
                                                                   defines or {})
            if rest:  # no powder BSDF in the file itself: set what traverse exposes
                more, missing = apply_properties(loaded, {k: properties[k] for k in rest})
                applied += more
            else:
                missing = []
        else:
            loaded = mi.load_file(str(scene), **(defines or {}))
            applied, missing, removed = [], [], []
        if missing and not allow_missing:
            raise ValueError(
                f"powder properties {', '.join(missing)} cannot be set on {scene}: the scene "
                "does not expose them after loading (only differentiable properties that the "
                "scene gives can change; see mitsuba_powder.render.apply_properties). Set them "
                "in the scene file, or allow rendering without them (allow_missing=True, "
                "--allow-missing)")
        image = mi.render(loaded, spp=spp or 0)
        used_spp = spp or int(loaded.sensors()[0].sampler().sample_count())
        dr.eval(image)  # kernels run asynchronously: wait for them before stopping the clock
        dr.sync_thread()
        seconds = time.perf_counter() - start
        mi.util.write_bitmap(str(output), image, write_async=False)
        height, width = image.shape[0], image.shape[1]
    return RenderResult(output, width, height, used_spp, variant, seconds, tuple(applied),
                        tuple(missing), tuple(removed))
