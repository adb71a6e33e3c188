"""Render a scene file that uses the ``powder`` BSDF and write the image."""

from __future__ import annotations

import time
from dataclasses import dataclass
from pathlib import Path

import drjit as dr
import mitsuba as mi

from .variants import check_variant, use_variant


@dataclass(frozen=True)
class RenderResult:
    """What :func:`render_scene` produced.

    Attributes:
        output: path of the written image.
        width, height: image size in pixels.
        spp: samples per pixel used (``None`` when the scene's own count was used).
        variant: Mitsuba variant.
        seconds: wall-clock time of loading and rendering, in seconds.
    """

    output: Path
    width: int
    height: int
    spp: int | None
    variant: str
    seconds: float
    applied: tuple[str, ...] = ()
    not_applied: tuple[str, ...] = ()


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


def render_scene(
    scene: str | Path,
    output: str | Path,
    variant: str = "scalar_rgb",
    spp: int | None = None,
    defines: dict[str, str] | None = None,
    properties: dict | None = None,
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
        properties: powder properties set on every powder BSDF after loading (see
            :func:`apply_properties`), e.g. from a ``fit.json``.

    Raises:
        FileNotFoundError: the scene file does not exist.
        ValueError: unknown variant, unsupported output extension or bad ``spp``.
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

    with use_variant(variant):
        start = time.perf_counter()
        loaded = mi.load_file(str(scene), **(defines or {}))
        applied, missing = apply_properties(loaded, properties) if properties else ([], [])
        image = mi.render(loaded, spp=spp or 0)
        dr.eval(image)  # kernels run asynchronously: wait for them before stopping the clock
        dr.sync_thread()
        seconds = time.perf_counter() - start
        output.parent.mkdir(parents=True, exist_ok=True)
        mi.util.write_bitmap(str(output), image, write_async=False)
        height, width = image.shape[0], image.shape[1]
    return RenderResult(output, width, height, spp, variant, seconds, tuple(applied),
                        tuple(missing))
