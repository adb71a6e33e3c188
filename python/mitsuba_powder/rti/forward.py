"""The per-pixel forward model of an RTI capture: every pixel of a powder surface under every
light, in one plugin evaluation.

An RTI capture is a fixed camera and K photographs, each lit from one known direction
(:mod:`mitsuba_powder.rti.capture` reads them).

**Frame.** The image frame: x to the image's right, y to its top, z towards the camera. Arrays
are (H, W) with row 0 at the top of the image. Light directions ``l_k`` (K, 3) are unit vectors
towards the (distant) lights; the camera looks straight down the -z axis (orthographic), so the
direction towards the viewer is ``v = (0, 0, 1)`` at every pixel.

**Forward model** (:func:`render_capture`). At a pixel with unit normal ``n`` (``n_z > 0``) and
powder properties ``theta``, under light k of irradiance ``E_k`` (W/m^2, measured on a plane
perpendicular to ``l_k``; the light's *gain*), the pixel value is the reflected radiance

    ``L_k = E_k f(l_k, v; theta) max(n . l_k, 0)``            [W/(m^2 sr)]

with ``f`` the powder BRDF (1/sr) in the pixel's local frame ``mi.Frame3f(n)`` (Mitsuba's
tangent frame of ``n``; the model is isotropic, so the tangent choice does not matter). It is
evaluated exactly as Mitsuba's renderer does: ``bsdf.eval(ctx, si, wo)`` with
``si.wi = to_local(v)`` and ``wo = to_local(l_k)``, which returns ``f cos(theta_o) =
f (n . l_k)``; the model (``energy="paper"``) is reciprocal, so this equals ``f(wi = l_k, wo =
v) (n . l_k)`` in docs/model.md's naming (checked in ``tests/rti/test_rti_fit.py``). A pixel
whose light lies below its tangent plane (``n . l_k <= 0``, attached shadow) is 0; ``n . v > 0``
always holds here because every normal faces the camera. Values are "radiance for unit
irradiance" when ``E_k = 1``; a Lambertian white (``f = 1/pi``) at normal incidence gives
``1/pi``. In RGB variants each channel is the model at the plugin's ``rgb_wavelengths``.

All pixels x lights are one plugin evaluation: lane ``p K + k`` is pixel p under light k, the
per-pixel properties reach the lanes by ``dr.gather`` from per-pixel arrays assigned through
``mi.traverse`` (as :class:`mitsuba_powder.plugin.brf.BatchBRF` does per parameter set), the
albedo as a per-lane ``albedo.value`` colour. Evaluations are chunked over pixels when pixels x
lights exceeds ``max_lanes``.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from ..plugin.brf import forward_grad
from ..variants import use_variant
from .checks import check_count, check_directions, check_gains, check_normals
from .lights import LightRig, check_distance, light_field, pixel_coordinates
from .properties import (
    MAP_GRAIN_SETTINGS,
    MAP_PROPERTIES,
    SPECS,
    GrainAlbedo,
    grain_map_name,
    property_map,
)

__all__ = ["MAX_LANES", "PixelEvaluator", "VARIANT", "check_rgb_variant", "near_field",
           "normals_of_slopes", "pixel_chunks", "pixel_light_field", "render_capture",
           "slopes_of_normals"]

#: Default limit of pixels x lights per plugin evaluation (bounds memory: the float64
#: Jacobian of a chunk takes 24 x lanes x variables bytes)
MAX_LANES = 1 << 21

#: The default Mitsuba variant of the RTI fit (an RGB variant with AD)
VARIANT = "llvm_ad_rgb"


def check_rgb_variant(variant: str) -> str:
    """``variant`` if it is an RGB variant's name (RTI maps have three channels)."""
    if not isinstance(variant, str) or "rgb" not in variant:
        raise ValueError(f"variant = {variant!r}: RTI maps need an RGB variant (e.g. "
                         "llvm_ad_rgb or cuda_ad_rgb)")
    return variant


class PixelEvaluator:
    """One plugin instance that evaluates ``f (n . l)`` of P pixels under K lights per launch.

    Args:
        varying: float properties given per pixel.
        settings: plugin properties held for every pixel (numbers or strings), e.g.
            ``{"lobes": "single,multiple", "g": 0.2}``.
        variant: an RGB variant of Mitsuba (``llvm_ad_rgb``, ``cuda_ad_rgb``).
    """

    def __init__(self, varying: Sequence[str], settings: Mapping, variant: str):
        check_rgb_variant(variant)
        if settings.get("energy", "paper") != "paper":
            raise ValueError(f"energy = {settings['energy']!r}: per-pixel maps need energy = "
                             "'paper' (the only valid value here: 'conserving' tabulates its "
                             "normalisation for one value of each parameter, not one per "
                             "pixel)")
        self.variant = variant
        self.varying = list(varying)
        props = {k: v for k, v in settings.items()
                 if k not in ("type", "albedo") + MAP_GRAIN_SETTINGS}
        for name in self.varying:  # present at load so that mi.traverse exposes them
            props.setdefault(name, SPECS[name].start)
            if name == "thickness":
                props[name] = 1.0
        with use_variant(variant):
            self.bsdf = mi.load_dict({"type": "powder", **props,
                                      "albedo": {"type": "rgb", "value": [0.5, 0.5, 0.5]}})
            self.params = mi.traverse(self.bsdf)
            missing = [n for n in self.varying if n not in self.params]
            if missing:
                raise ValueError(f"properties {missing} are not differentiable with these "
                                 f"settings ({dict(settings)}); see docs/powder.md (e.g. "
                                 "correlation_length needs specular = 'harvey_shack', sigma "
                                 "needs 'gaussian')")

    def __call__(self, slopes: np.ndarray, albedo: np.ndarray, values: Mapping[str, np.ndarray],
                 directions: np.ndarray, derivatives: Sequence[str] = ()
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """``f (n . l)`` (P, K, 3) float64 and its derivatives.

        Args:
            slopes: (P, 2) normal slopes ``(n_x / n_z, n_y / n_z)``.
            albedo: (P, 3) single-scattering albedo per channel.
            values: varying property -> (P,) values.
            directions: (K, 3) unit vectors towards the lights (image frame), or (P, K, 3)
                one set per pixel (lights at a finite distance, :mod:`.lights`).
            derivatives: any of ``slope_x``, ``slope_y``, ``albedo`` and the varying
                properties; ``albedo`` gives d(channel c)/d(albedo c) (the channels are
                independent).
        """
        p, k = len(slopes), directions.shape[-2]
        grads: dict[str, np.ndarray] = {}
        with use_variant(self.variant):
            pix = dr.arange(mi.UInt32, p * k) // k
            light = dr.arange(mi.UInt32, p * k) % k
            sources: dict[str, object] = {
                "slope_x": mi.Float(slopes[:, 0].astype(np.float32)),
                "slope_y": mi.Float(slopes[:, 1].astype(np.float32)),
                "albedo": mi.Color3f(*[mi.Float(albedo[:, c].astype(np.float32))
                                       for c in range(3)]),
            }
            for name in self.varying:
                sources[name] = mi.Float(np.asarray(values[name], np.float32).reshape(p))
            for name in derivatives:
                dr.enable_grad(sources[name])
            lanes = {name: dr.gather(type(src), src, pix) for name, src in sources.items()}
            if directions.ndim == 3:  # per pixel: lane p K + k is C order of (P, K)
                lights = mi.Vector3f(*[mi.Float(np.ascontiguousarray(
                    directions[..., c], dtype=np.float32).reshape(-1)) for c in range(3)])
            else:
                table = mi.Vector3f(*[mi.Float(directions[:, c].astype(np.float32))
                                      for c in range(3)])
                lights = dr.gather(mi.Vector3f, table, light)
            dr.eval(lanes)  # one launch for every gather
            out = self._eval(lanes, lights, p * k)
            value = np.array(out, dtype=np.float64).reshape(3, p, k).transpose(1, 2, 0)
            for name in derivatives:
                grads[name] = forward_grad(sources[name], out).reshape(3, p, k
                                                                        ).transpose(1, 2, 0)
                dr.disable_grad(sources[name])
        return value, grads

    def _eval(self, lanes: Mapping[str, object], lights, count: int):
        """The plugin's ``f (n . l)`` (a colour per lane) with the lanes' properties assigned;
        in the evaluator's variant."""
        for name in self.varying:
            self.params[name] = lanes[name]
        self.params["albedo.value"] = lanes["albedo"]
        self.params.update()
        n = dr.normalize(mi.Vector3f(lanes["slope_x"], lanes["slope_y"], 1.0))
        frame = mi.Frame3f(n)
        si = dr.zeros(mi.SurfaceInteraction3f, count)
        si.wi = frame.to_local(mi.Vector3f(0.0, 0.0, 1.0))  # towards the camera
        wo = frame.to_local(lights)
        out = self.bsdf.eval(mi.BSDFContext(), si, wo)
        dr.eval(out)
        return out


def pixel_chunks(count: int, lights: int, max_lanes: int) -> list[slice]:
    """Pixel ranges of at most ``max_lanes // lights`` pixels (at least one)."""
    step = max(1, int(max_lanes) // max(lights, 1))
    return [slice(s, min(s + step, count)) for s in range(0, count, step)]


def slopes_of_normals(normals: np.ndarray) -> np.ndarray:
    """(..., 3) normals with n_z > 0 -> (..., 2) slopes (n_x / n_z, n_y / n_z)."""
    return normals[..., :2] / normals[..., 2:3]


def normals_of_slopes(slopes: np.ndarray) -> np.ndarray:
    """(..., 2) slopes -> (..., 3) unit normals."""
    n = np.concatenate([slopes, np.ones(slopes.shape[:-1] + (1,))], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _albedo_map(maps: Mapping, grain: str, shape: tuple[int, int]) -> np.ndarray:
    """The albedo (H, W, 3) of ``maps``: given per pixel or as (3,), or the grains' of a
    per-pixel grain size ``grain``; range-checked."""
    if grain in maps:
        size = property_map(grain, maps[grain], shape)
        rho, _ = GrainAlbedo(grain, {k: v for k, v in maps.items()
                                     if k not in ("normal", "albedo", grain)
                                     and np.ndim(v) == 0})(size.ravel())
        albedo = rho.reshape(shape + (3,))
    else:
        albedo = np.asarray(maps["albedo"], dtype=np.float64)
    if albedo.shape == (3,):
        albedo = np.broadcast_to(albedo, shape + (3,))
    if albedo.shape != shape + (3,):
        raise ValueError(f"albedo has shape {albedo.shape}; expected (3,) or {shape + (3,)}")
    for c in range(3):
        property_map("albedo", albedo[..., c], shape)
    return albedo


def _split_maps(maps: Mapping, shape: tuple[int, int]
                ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], dict]:
    """maps -> normals (H, W, 3), albedo (H, W, 3), per-pixel float properties, settings."""
    grain = grain_map_name(maps)
    if "normal" not in maps or ("albedo" not in maps and grain not in maps):
        raise ValueError(f"maps has keys {sorted(maps)}; it needs 'normal' (H, W, 3) and "
                         f"'albedo' (H, W, 3) or (3,), or '{grain}' (H, W) or a number")
    normals = check_normals(maps["normal"], shape)
    if grain in maps and "albedo" in maps:
        raise ValueError(f"maps has both 'albedo' and '{grain}': the grains set the albedo; "
                         "give one of them")
    albedo = _albedo_map(maps, grain, shape)
    values, settings = {}, {}
    for key, value in maps.items():
        if key in ("normal", "albedo", grain):
            continue  # a grain size is turned into the albedo above
        if key in MAP_PROPERTIES:
            values[key] = property_map(key, value, shape)
        elif np.ndim(value) != 0 and key in MAP_GRAIN_SETTINGS:
            raise ValueError(f"maps[{key!r}]: only {grain} may vary per pixel among the grain "
                             "properties (give the others as numbers)")
        else:
            settings[key] = value
    return normals, albedo, values, settings


def near_field(directions: np.ndarray, light_distance: float | np.ndarray,
               shape: tuple[int, int], mask: np.ndarray | None = None
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """Per-pixel light directions and irradiance factors of lights at ``light_distance``
    (checked: :func:`mitsuba_powder.rti.lights.check_distance`).

    Args:
        directions: (K, 3) unit vectors from the image's centre towards the lights.
        light_distance: r in image widths (a number or (K,)); ``inf``: distant lights.
        shape: (H, W) pixels of the image (pixel coordinates and the least valid distance).
        mask: bool (H, W): only these pixels (in C order); default all.

    Returns:
        None for distant lights (the (K, 3) directions hold at every pixel), else float32
        (P, K, 3) directions and float64 (P, K) irradiance factors ``s`` (1 at the
        image's centre).
    """
    check_distance(light_distance, shape, "light_distance")
    return pixel_light_field(directions, light_distance, shape, mask)


def pixel_light_field(directions: np.ndarray, light_distance: float | np.ndarray,
                      shape: tuple[int, int], mask: np.ndarray | None = None
                      ) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`near_field` of a distance already checked for the image."""
    rig = LightRig(directions, light_distance)
    if rig.is_distant:
        return None
    xy = pixel_coordinates(shape)
    xy = xy.reshape(-1, 2) if mask is None else xy[mask]
    dirs, s = light_field(rig, xy)
    # float32 directions: the plugin evaluates in float32, and they take 12 bytes a lane
    return (np.ascontiguousarray(dirs.transpose(1, 0, 2), dtype=np.float32),
            np.ascontiguousarray(s.T))


def render_capture(maps: Mapping, directions: np.ndarray, gains: np.ndarray | None = None,
                   variant: str = VARIANT, max_lanes: int = MAX_LANES,
                   light_distance: float | np.ndarray = math.inf) -> np.ndarray:
    """Render an RTI capture of a powder surface from per-pixel maps (the forward model).

    Args:
        maps: ``normal`` (H, W, 3) unit normals with n_z > 0 (image frame: x right, y up, z to
            the camera); ``albedo`` (H, W, 3) or (3,) single-scattering albedo per channel in
            [0, 1], or a grain size of :data:`~mitsuba_powder.rti.properties.GRAIN_MAPS`
            ((H, W) or a number) whose grains set it; any of
            :data:`~mitsuba_powder.rti.properties.MAP_PROPERTIES` as (H, W) maps or scalars in
            the plugin's units (extinction 1/um, lengths um, ``amplitude_surface`` um^2); other
            plugin settings (``lobes``, ``specular``, ``material``, ``rgb_wavelengths``, ...)
            as values for every pixel.
        directions: (K, 3) vectors towards the lights (normalised here).
        gains: (K,) irradiance of each light, W/m^2 on a plane perpendicular to it (default 1).
        variant: an RGB variant.
        max_lanes: pixels x lights per plugin evaluation at most (memory bound).
        light_distance: the lights' distance from the image's centre in image widths (a
            number or (K,)), beyond the image's half-diagonal; ``inf`` (default): distant
            lights. A finite distance gives each pixel x its own direction ``d_k(x)`` and
            irradiance ``E_k s_k(x)`` (:mod:`mitsuba_powder.rti.lights`).

    Returns:
        float32 (K, H, W, 3) radiance ``E_k f(l_k, v) max(n . l_k, 0)``, W/(m^2 sr) (the
        module docstring gives the exact definition; ``E_k s_k(x)`` and ``d_k(x)`` for lights
        at a finite distance).
    """
    d = check_directions(directions)
    if "normal" not in maps:
        raise ValueError(f"maps has keys {sorted(maps)}; it needs 'normal' (H, W, 3)")
    shape = tuple(np.shape(maps["normal"])[:2])
    normals, albedo, values, settings = _split_maps(maps, shape)
    g = check_gains(gains, len(d))
    max_lanes = check_count("max_lanes", max_lanes, 1)
    field_ = near_field(d, light_distance, shape)
    ev = PixelEvaluator(list(values), settings, variant)
    slopes = slopes_of_normals(normals).reshape(-1, 2)
    alb = albedo.reshape(-1, 3)
    flat = {k: v.ravel() for k, v in values.items()}
    out = np.empty((len(d),) + shape + (3,), dtype=np.float32)
    view = out.reshape(len(d), -1, 3)
    for s in pixel_chunks(len(slopes), len(d), max_lanes):
        part = {k: v[s] for k, v in flat.items()}
        if field_ is None:
            value, _ = ev(slopes[s], alb[s], part, d)
            view[:, s] = (value * g[None, :, None]).transpose(1, 0, 2)
        else:
            value, _ = ev(slopes[s], alb[s], part, field_[0][s])
            view[:, s] = (value * (g[None, :] * field_[1][s])[:, :, None]).transpose(1, 0, 2)
    return out
