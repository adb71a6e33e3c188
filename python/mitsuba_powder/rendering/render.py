"""Render a scene file that uses the ``powder`` BSDF and write the image."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi

from .._checks import check_range
from ..outputs import guarding_inputs, output_file
from ..plugin.params import check_property_names
from ..variants import check_variant, use_variant
from .scene_description import parse_scene, scene_files, scene_with_properties

__all__ = ["RenderResult", "apply_properties", "render_scene", "scene_files",
           "scene_with_properties"]


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


def _load_with_properties(scene: Path, properties: dict, defines: dict) -> tuple:
    """(loaded scene, names applied in the scene description, names left for traverse,
    scene properties removed)."""
    parsed, count, removed = scene_with_properties(scene, properties, defines)
    if count == 0:
        return parsed.load(), [], list(properties), []
    return parsed.load(), list(properties), [], removed


def _load(scene: Path, properties: dict | None, defines: dict[str, str]):
    """(the loaded scene, the properties applied, those missing, the scene properties
    removed) of ``scene`` with ``properties`` written into its powders (or set through
    ``mi.traverse`` where the description defines none)."""
    if not properties:
        return parse_scene(scene, defines).load(), [], [], []
    loaded, applied, rest, removed = _load_with_properties(scene, properties, defines)
    missing: list[str] = []
    if rest:  # no powder BSDF in the file itself: set what traverse exposes
        more, missing = apply_properties(loaded, {k: properties[k] for k in rest})
        applied += more
    return loaded, applied, missing, removed


def _check_arguments(scene, output, variant: str, spp: int | None, properties: dict | None
                     ) -> tuple[Path, Path]:
    """:func:`render_scene`'s scene and output paths, its arguments checked."""
    scene = Path(scene)
    output = Path(output)
    if not scene.is_file():
        raise FileNotFoundError(f"scene file {scene} does not exist")
    check_variant(variant)
    if output.suffix.lower() not in (".exr", ".png", ".jpg", ".hdr", ".pfm"):
        raise ValueError(f"output {output}: extension must be .exr, .png, .jpg, .hdr or .pfm")
    if spp is not None:
        check_range("spp", spp, 1)
    if properties:
        check_property_names(properties)
    return scene, output


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
    scene, output = _check_arguments(scene, output, variant, spp, properties)
    with use_variant(variant), guarding_inputs(*scene_files(scene, defines)):
        output = output_file(output, "output")
        start = time.perf_counter()
        loaded, applied, missing, removed = _load(scene, properties, defines or {})
        if missing and not allow_missing:
            raise ValueError(
                f"powder properties {', '.join(missing)} cannot be set on {scene}: the scene "
                "does not expose them after loading (only differentiable properties that the "
                "scene gives can change; see "
                "mitsuba_powder.rendering.render.apply_properties). Set them in the scene file, "
                "or allow rendering without them (allow_missing=True, --allow-missing)")
        image = mi.render(loaded, spp=spp or 0)
        used_spp = spp or int(loaded.sensors()[0].sampler().sample_count())
        dr.eval(image)  # kernels run asynchronously: wait for them before stopping the clock
        dr.sync_thread()
        seconds = time.perf_counter() - start
        mi.util.write_bitmap(str(output), image, write_async=False)
        height, width = image.shape[0], image.shape[1]
    return RenderResult(output, width, height, used_spp, variant, seconds, tuple(applied),
                        tuple(missing), tuple(removed))
