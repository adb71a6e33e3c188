"""The checked inputs of a per-pixel RTI fit: the capture (images, lights, mask) and the held
properties, checked once against the fit's options (:func:`check_inputs` ->
:class:`FitInputs`), and the data of a set of its pixels (:meth:`FitInputs.pixels` ->
:class:`FitData`), which every stage of the fit (:mod:`mitsuba_powder.rti.plan`) takes without
checking again."""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .checks import check_directions, check_gains, check_images
from .forward import pixel_light_field
from .lights import check_distance
from .options import FitOptions
from .pixels import PixelData
from .properties import MAP_PROPERTIES, GrainAlbedo, property_map
from .relief import Relief

__all__ = ["MIN_LIGHTS", "FitData", "FitInputs", "check_inputs", "check_lights", "check_mask",
           "check_signal"]


@dataclass(frozen=True, eq=False)
class FitInputs:
    """A capture and held properties checked for a fit with :attr:`options`.

    Attributes:
        images: (K, H, W, 3) float32 linear values.
        d: (K, 3) unit vectors towards the lights.
        mask: (H, W) bool, the pixels to fit.
        gains: (K,) the initial gains (:attr:`GainPolicy.initial
            <mitsuba_powder.rti.gains.GainPolicy.initial>`, default 1).
        maps: held float property of :data:`MAP_PROPERTIES` -> float64 (H, W).
        albedo: (H, W, 3) the held albedo, or None (free, or set by the grains).
        size: (H, W) the held grain size whose grains set the albedo, or None.
        grain: the albedo of the grains of a free or held grain size, or None.
        options: the fit's options.
        relief: the relief of a first fit (:mod:`mitsuba_powder.rti.relief`), whose
            visibility of each light shades the pixels' lights, or None.
    """

    images: np.ndarray
    d: np.ndarray
    mask: np.ndarray
    gains: np.ndarray
    maps: dict[str, np.ndarray]
    albedo: np.ndarray | None
    size: np.ndarray | None
    grain: GrainAlbedo | None
    options: FitOptions
    relief: Relief | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(H, W) pixels."""
        return self.mask.shape

    def pixels(self, sel: np.ndarray, gains: np.ndarray, light_distance: float | np.ndarray,
               options: FitOptions) -> FitData:
        """The data of the pixels ``sel`` (bool (H, W), a subset of :attr:`mask`) under the
        ``gains`` (K,) and lights at ``light_distance`` (checked), with ``options`` (the
        stage's: :attr:`options` with the gain policy it fits with)."""
        obs = np.ascontiguousarray(self.images[:, sel].transpose(1, 0, 2), dtype=np.float32)
        if self.size is not None:
            fixed_albedo = self.grain(self.size[sel])[0]
        else:
            fixed_albedo = None if self.albedo is None else self.albedo[sel]
        field = pixel_light_field(self.d, light_distance, self.shape, sel)
        shadowed = None
        if self.relief is not None:  # the visibility scales each (pixel, light)'s irradiance
            p = int(np.count_nonzero(sel))
            dirs = field[0] if field is not None else np.ascontiguousarray(
                np.broadcast_to(self.d.astype(np.float32), (p,) + self.d.shape))
            vis = self.relief.visibility(self.d if field is None else field[0], sel)
            # lights less than half visible are left out (their factor only needs to be > 0)
            lit = np.maximum(vis, 0.5).astype(np.float64)
            s = lit if field is None else field[1] * lit
            field, shadowed = (dirs, s), vis < 0.5
        return FitData(obs=obs, d=self.d, mask=sel, gains=gains,
                       fixed_maps={n: v[sel] for n, v in self.maps.items()},
                       fixed_albedo=fixed_albedo, grain=self.grain, options=options,
                       field=field, light_distance=light_distance, shadowed=shadowed)

    def shaded(self, relief: Relief, sel: np.ndarray, light_distance: float | np.ndarray,
               rows: int = 64) -> np.ndarray:
        """bool (H, W): the pixels of ``sel`` that ``relief`` shades under at least one of the
        capture's lights (visibility < 1), the lights at ``light_distance``; computed ``rows``
        image rows at a time (the visibilities of a few rows in memory)."""
        out = np.zeros(self.shape, dtype=bool)
        rows = max(1, int(rows))
        for r0 in range(0, self.shape[0], rows):
            part = np.zeros(self.shape, dtype=bool)
            part[r0:r0 + rows] = sel[r0:r0 + rows]
            if not part.any():
                continue
            field = pixel_light_field(self.d, light_distance, self.shape, part)
            vis = relief.visibility(self.d if field is None else field[0], part)
            out[part] = np.any(vis < 1.0, axis=1)
        return out


@dataclass(eq=False)
class FitData:
    """The data of a set of P pixels of a capture, as one stage of a fit fits them."""

    obs: np.ndarray                    # (P, K, 3) float32 observations
    d: np.ndarray                      # (K, 3) unit vectors towards the lights
    mask: np.ndarray                   # (H, W) bool, the pixels (P of them)
    gains: np.ndarray                  # (K,) initial gains (their mean: a calibration)
    fixed_maps: dict[str, np.ndarray]  # held per-pixel float property -> (P,)
    fixed_albedo: np.ndarray | None    # (P, 3) when neither the albedo nor a grain size is free
    grain: GrainAlbedo | None          # the albedo of a free or fixed grain size
    options: FitOptions                # the stage's options
    field: tuple[np.ndarray, np.ndarray] | None = None  # near-field lights: (P, K, 3), (P, K)
    light_distance: float | np.ndarray = math.inf        # r in image widths
    shadowed: np.ndarray | None = None  # (P, K) bool: below the relief's horizon

    @property
    def scale(self) -> float:
        """The mean of the initial gains, held while the gains are fitted (a calibration)."""
        return float(np.mean(self.gains))

    def lights(self, s: slice = slice(None)) -> np.ndarray:
        """The light directions of the pixels ``s``: (K, 3), or (P_s, K, 3) per pixel."""
        return self.d if self.field is None else self.field[0][s]

    def irradiance(self, s: slice = slice(None)) -> np.ndarray | None:
        """The irradiance factors (P_s, K) of the pixels ``s``; None for distant lights."""
        return None if self.field is None else self.field[1][s]

    def light_gains(self, gains: np.ndarray, s: slice = slice(None)) -> np.ndarray:
        """(1, K, 1) or (P_s, K, 1): the gains times the pixels' irradiance factors."""
        if self.field is None:
            return gains[None, :, None]
        return (gains[None, :] * self.field[1][s])[:, :, None]

    @property
    def saturated(self) -> np.ndarray:
        """(P, K): observations with a channel at or above the saturation level."""
        return np.any(self.obs >= self.options.saturation, axis=2)

    @property
    def usable(self) -> np.ndarray:
        """(P, K): observations neither saturated nor below the relief's horizon."""
        return ~self.saturated if self.shadowed is None else ~self.saturated & ~self.shadowed

    def flags(self, predicted: np.ndarray) -> np.ndarray:
        """Weights (P, K): 0 where not :attr:`usable` or where the observed channel mean is
        below the ``predicted`` one (P, K, 3) by more than ``max(shadow_ratio x predicted,
        shadow_floor)``."""
        obs = self.obs.mean(axis=2)
        pred = predicted.mean(axis=2)
        shadow = (pred - obs) > np.maximum(self.options.shadow_ratio * pred,
                                           self.options.shadow_floor)
        return (self.usable & ~shadow).astype(np.float64)

    def pixel_data(self, s: slice, weights: np.ndarray, gains: np.ndarray, layout: list
                   ) -> PixelData:
        """What a per-pixel solver takes of the pixels ``s`` (with the fit's ``weights``
        (P, K) and ``gains`` (K,), the variables ``layout``)."""
        return PixelData(self.obs[s], weights[s], self.lights(s), gains, layout,
                         {n: v[s] for n, v in self.fixed_maps.items()},
                         None if self.fixed_albedo is None else self.fixed_albedo[s],
                         self.grain, self.irradiance(s))


def check_inputs(images: np.ndarray, directions: np.ndarray, options: FitOptions,
                 mask: np.ndarray | None = None) -> FitInputs:
    """Check a capture and the held properties against the fit's ``options``, once.

    Args:
        images: (K, H, W, 3) linear pixel values, 1.0 = the encoding's maximum.
        directions: (K, 3) vectors towards the lights (image frame; normalised here).
        options: the fit's options (:func:`~mitsuba_powder.rti.options.fit_options`).
        mask: bool (H, W) pixels to fit (default all).

    Raises:
        ValueError: naming the input, its value and what was expected.
    """
    imgs = check_images(images)
    k, h, w, _ = imgs.shape
    d = check_directions(directions)
    if len(d) != k:
        raise ValueError(f"directions has {len(d)} rows for {k} images; expected one per image")
    check_lights(d)
    gains = check_gains(options.gains.initial, k)
    mask = check_mask(mask, (h, w))
    check_signal(imgs, mask, options.saturation, options.name("saturation"))
    fixed = options.fixed
    maps = {n: property_map(n, v, (h, w)) for n, v in fixed.items() if n in MAP_PROPERTIES}
    grain = GrainAlbedo(options.grain_name, options.settings) if options.albedo_from_grains \
        else None
    size = property_map(options.grain_name, fixed[options.grain_name], (h, w)) \
        if grain is not None and options.grain_name in fixed else None
    albedo = _held_albedo(fixed["albedo"], (h, w)) if "albedo" in fixed else None
    if not isinstance(options.light_distance, str):
        check_distance(options.light_distance, (h, w), options.name("light_distance"))
    return FitInputs(imgs, d, mask, gains, maps, albedo, size, grain, options)


#: Lights a pixel needs to be fitted: three in different directions give its normal and
#: albedo (Lambertian photometric stereo, the fit's start)
MIN_LIGHTS = 3

#: Directions whose smallest singular value is below this fraction of the largest lie in
#: one plane through the sample: photometric stereo cannot tell the normal's component
#: out of that plane
PLANAR_LIGHTS = 1e-3


def check_lights(d: np.ndarray) -> None:
    """At least :data:`MIN_LIGHTS` unit light directions ``d`` (K, 3), not all in one plane
    through the sample."""
    k = len(d)
    if k < MIN_LIGHTS:
        raise ValueError(f"the capture has {k} light(s); a per-pixel fit needs at least "
                         f"{MIN_LIGHTS}, in directions not all in one plane (each pixel's "
                         "normal and albedo by photometric stereo)")
    sv = np.linalg.svd(d, compute_uv=False)
    if sv[2] < PLANAR_LIGHTS * sv[0]:
        raise ValueError(f"the capture's {k} light directions lie in one plane through the "
                         f"sample (singular values {sv[0]:.3g}, {sv[1]:.3g}, {sv[2]:.3g}); a "
                         "per-pixel fit needs lights out of that plane to find the normal")


def check_signal(images: np.ndarray, mask: np.ndarray, saturation: float,
                 name: str = "saturation") -> np.ndarray:
    """The pixels of ``mask`` that see at least :data:`MIN_LIGHTS` lights with a signal
    (every channel below ``saturation`` and one above 0), bool (H, W); an error when they
    are fewer than half the masked pixels (a saturated or black capture: nothing to fit).
    """
    lit = np.zeros(mask.shape, dtype=np.int32)
    for img in images:  # one image at a time: no (K, H, W) temporaries
        lit += (np.max(img, axis=2) < saturation) & (np.max(img, axis=2) > 0)
    fittable = (lit >= MIN_LIGHTS) & mask
    n, m = int(fittable.sum()), int(mask.sum())
    if 2 * n < m:
        saturated = sum(int(np.sum(np.all(img >= saturation, axis=2)[mask])) for img in images)
        black = sum(int(np.sum(np.all(img <= 0, axis=2)[mask])) for img in images)
        total = len(images) * m
        hint = ("take the capture with a shorter exposure, leave those pixels out of the "
                f"mask, or raise {name} if the encoding's maximum is not saturation"
                if saturated >= black else
                "check that the images are those of the capture and its lights, or leave the "
                "pixels no light reaches out of the mask")
        raise ValueError(
            f"{m - n} of the {m} masked pixels see fewer than {MIN_LIGHTS} lights with a "
            f"signal (of {total} observations, {saturated} are saturated: every channel >= "
            f"{name} = {saturation:g}, and {black} are black: every channel <= 0); nothing "
            f"to fit there: {hint}")
    return fittable


def check_mask(mask: np.ndarray | None, shape: tuple[int, int]) -> np.ndarray:
    """The pixels to fit, bool (H, W) (default all); at least one."""
    if mask is None:
        return np.ones(shape, dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != shape:
        raise ValueError(f"mask has shape {mask.shape}; expected {shape}")
    mask = mask.astype(bool)
    if not mask.any():
        raise ValueError("mask selects no pixel; it needs at least one True")
    return mask


def _held_albedo(value, shape: tuple[int, int]) -> np.ndarray:
    """A held albedo, (3,) or (H, W, 3), as float64 (H, W, 3) in [0, 1]."""
    a = np.asarray(value, dtype=np.float64)
    a = np.broadcast_to(a, shape + (3,)) if a.shape == (3,) else a
    if a.shape != shape + (3,):
        raise ValueError(f"fixed albedo has shape {a.shape}; expected (3,) or "
                         f"({shape[0]}, {shape[1]}, 3)")
    for c in range(3):
        property_map("albedo", a[..., c], shape)
    return a
