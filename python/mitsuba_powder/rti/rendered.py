"""Relit images of a fit rendered by Mitsuba: the ``scene.xml`` of a maps folder (the relief's
mesh with the powder BSDF and the maps as textures, :mod:`mitsuba_powder.rti.maps`) path
traced under each light, cast shadows and interreflections included (``relight --render``,
the ``powder_rendered`` row of ``compare-maps``).

Light k of gain ``E_k`` is the scene's directional emitter from ``l_k`` of irradiance
``E_k``, or, for lights at a distance r (image widths), its point emitter at
``r l_k (2 W / H)`` of intensity ``E_k (r 2 W / H)^2``
(:func:`mitsuba_powder.rti.lights.point_lights`). The images are the film's linear values,
in the capture's units as :func:`mitsuba_powder.rti.relight` predicts them; pixels outside
the fit's mask are 0.
"""

from __future__ import annotations

import math
import tempfile
from pathlib import Path

import numpy as np

from ..variants import use_variant
from .checks import check_count, check_directions, check_gains
from .lights import LightRig, point_lights
from .result import MapsResult

__all__ = ["RENDER_SPP", "render_maps", "render_result"]

#: Samples per pixel of a rendered relight by default
RENDER_SPP = 64


def render_maps(maps_dir: str | Path, result: MapsResult, directions: np.ndarray,
                gains: np.ndarray | None = None,
                light_distance: float | np.ndarray | None = None,
                spp: int = RENDER_SPP, variant: str = "llvm_ad_rgb", max_depth: int = 4,
                seed: int = 0) -> np.ndarray:
    """Images float32 (K, H, W, 3) of the ``scene.xml`` of ``maps_dir`` (the folder
    ``result`` was read from or written to) under the lights ``directions`` (K, 3).

    Args:
        gains: (K,) irradiances; default :meth:`MapsResult.light_gains`.
        light_distance: image widths, a number or (K,); default the fit's when it is one
            number.
        spp: samples per pixel, >= 1.
        variant: any Mitsuba RGB variant (``scalar_rgb``, ``llvm_ad_rgb``, ``cuda_ad_rgb``).
        max_depth: the path tracer's longest path (2: direct light only; 4: two bounces
            between the relief's faces).
        seed: the sampler's seed of the first light (light k: ``seed + k``).
    """
    import mitsuba as mi

    d = check_directions(directions)
    g = result.light_gains(d) if gains is None else check_gains(gains, len(d))
    spp = check_count("spp", spp, 1)
    max_depth = check_count("max_depth", max_depth, 1)
    if light_distance is None:
        light_distance = (result.light_distance if np.ndim(result.light_distance) == 0
                          else math.inf)
    h, w = result.mask.shape
    scene_file = str(Path(maps_dir) / "scene.xml")
    rig = LightRig(d, light_distance)
    fit_distant = bool(np.all(np.isinf(result.light_distance)))
    if rig.is_distant != fit_distant:
        raise ValueError(f"light_distance = {light_distance!r}: the scene.xml of {maps_dir} "
                         f"has {'a directional' if fit_distant else 'a point'} light (the "
                         f"fit's lights are {'distant' if fit_distant else 'at a distance'}); "
                         "render it with lights of that kind")
    if rig.is_distant:
        params = [{"lx": x, "ly": y, "lz": z, "irradiance": e}
                  for (x, y, z), e in zip(d, g)]
    else:
        pos, inten = point_lights(rig, 2.0 * w / h, g)
        params = [{"px": p[0], "py": p[1], "pz": p[2], "intensity": i}
                  for p, i in zip(pos, inten)]
    out = np.empty((len(d), h, w, 3), dtype=np.float32)
    with use_variant(variant):
        for k, values in enumerate(params):
            defines = {n: repr(float(v)) for n, v in values.items()}
            if result.relief is not None:
                defines["max_depth"] = str(max_depth)
            scene = mi.load_file(scene_file, **defines)
            img = mi.render(scene, spp=spp, seed=seed + k)
            out[k] = np.asarray(img, dtype=np.float32)[..., :3]
    out[:, ~result.mask] = 0.0
    return out


def render_result(result: MapsResult, directions: np.ndarray, **options) -> np.ndarray:
    """:func:`render_maps` of a fit in memory: its maps written to a temporary folder
    (:func:`mitsuba_powder.rti.maps.write_maps`), rendered, the folder removed."""
    from .maps import write_maps

    with tempfile.TemporaryDirectory(prefix="mitsuba-powder-render-") as tmp:
        write_maps(result, tmp)
        return render_maps(tmp, result, directions, **options)
