"""Per-pixel powder maps fitted to an RTI capture (:class:`MapsResult`) and the fitted surface
relit under new lights (:func:`relight`)."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .checks import check_directions
from .forward import MAX_LANES, VARIANT, near_field, render_capture
from .gains import GainModel
from .properties import GRAIN_MAPS
from .relief import Relief

__all__ = ["MapsResult", "relight"]


@dataclass
class MapsResult:
    """Per-pixel powder maps fitted to an RTI capture (:func:`mitsuba_powder.rti.fit_maps`).

    Attributes:
        normals: float32 (H, W, 3) unit normals (image frame), NaN outside the mask.
        albedo: float32 (H, W, 3) single-scattering albedo per channel.
        maps: property -> float32 (H, W) map, for every free and every per-pixel fixed float
            property (plugin units).
        settings: plugin properties held for every pixel (scalars and strings).
        residual_rms: float32 (H, W) RMS of the used residuals (linear units); NaN where
            fewer observations were used than the pixel has variables (not determined).
        gains: (K,) fitted (or given) light irradiances, mean 1 when fitted.
        used: bool (K, H, W): observations in the loss (not shadowed, not saturated).
        free: the free properties (besides the normal).
        mask: bool (H, W) fitted pixels.
        variant: the Mitsuba variant.
        fit_settings: the fit's options and diagnostics (iterations, seconds, ...).
        light_distance: the lights' distance from the image's centre in image widths (a
            number or (K,), given or fitted; ``inf``: distant lights): relit images use it.
        gain_model: the gains as a smooth function of the light direction (with the fitted
            lights' residuals): the gain of a light when none is given; None: the exposure.
        exposure: the lights' irradiance scale (given or fitted): the gain of a light when
            none is given and there is no gain model.
        relief: the relief integrated from the normals with its horizon map
            (:mod:`mitsuba_powder.rti.relief`; fits with ``shadows="relief"`` or ``"auto"``
            (the default), and fit-maps' ``ratio`` fits, unused by the fit): relit images of
            a fit that used it (``fit_settings["shadows"] == "relief"``) are shaded by it;
            None: no cast shadows.
    """

    normals: np.ndarray
    albedo: np.ndarray
    maps: dict[str, np.ndarray]
    settings: dict
    residual_rms: np.ndarray
    gains: np.ndarray
    used: np.ndarray
    free: list[str]
    mask: np.ndarray
    variant: str = VARIANT
    fit_settings: dict = field(default_factory=dict)
    light_distance: float | np.ndarray = math.inf
    gain_model: GainModel | None = None
    exposure: float = 1.0
    relief: Relief | None = None

    @property
    def n_parameters(self) -> int:
        """Fitted numbers per pixel: 2 (normal) + 3 (albedo, if free) + 1 per other property."""
        return 2 + sum(3 if n == "albedo" else 1 for n in self.free)

    def as_maps(self) -> dict:
        """The maps as :func:`mitsuba_powder.rti.render_capture` takes them (pixels outside
        the mask get n = z and the median values)."""
        normals = np.where(self.mask[..., None], self.normals, np.array([0.0, 0.0, 1.0]))
        albedo = np.where(self.mask[..., None], self.albedo,
                          np.nanmedian(self.albedo[self.mask], axis=0))
        out: dict = {"normal": normals}
        if not any(name in self.maps for name in GRAIN_MAPS):  # else the grains set it
            out["albedo"] = np.clip(albedo, 0.0, 1.0)
        for k, v in self.maps.items():
            out[k] = np.where(self.mask, v, np.nanmedian(v[self.mask]))
        out.update(self.settings)
        return out

    def predict(self, directions: np.ndarray, gains: np.ndarray | None = None,
                light_distance: float | np.ndarray | None = None,
                shadows: bool | None = None) -> np.ndarray:
        """Relit images float32 (K', H, W, 3) under ``directions`` (K', 3); see :func:`relight`.
        """
        return relight(self, directions, gains, light_distance=light_distance,
                       shadows=shadows)

    def light_gains(self, directions: np.ndarray) -> np.ndarray:
        """(K',) gains of lights at ``directions``: the gain model's (a fitted light's own
        gain, the smooth trend for another), or the exposure without a gain model."""
        if self.gain_model is None:
            return np.full(len(directions), float(self.exposure))
        return self.gain_model.evaluate(directions)


def relight(result: MapsResult, directions: np.ndarray, gains: np.ndarray | None = None,
            max_lanes: int = MAX_LANES, light_distance: float | np.ndarray | None = None,
            shadows: bool | None = None) -> np.ndarray:
    """The fitted surface under new lights: :func:`mitsuba_powder.rti.render_capture` with the
    fitted maps.

    Args:
        result: a :func:`mitsuba_powder.rti.fit_maps` result.
        directions: (K', 3) vectors towards the lights.
        gains: (K',) light irradiances; default: :meth:`MapsResult.light_gains` (the fit's
            gain model at these directions, the exposure without one).
        light_distance: the new lights' distance in image widths (a number or (K',));
            default: the fit's when it is one number (``inf`` for per-light distances).
        shadows: shade each pixel by the lights' visibility over the fit's relief (cast
            shadows, :mod:`mitsuba_powder.rti.relief`); default: when the fit was made with
            them (``fit_settings["shadows"] == "relief"``: ``shadows="relief"``, or
            ``"auto"`` where it chose the relief); a relief kept by a fit without them is
            used when asked.

    Returns:
        float32 (K', H, W, 3) radiance (the capture's linear units); 0 outside the mask.
    """
    if light_distance is None:
        light_distance = (result.light_distance if np.ndim(result.light_distance) == 0
                          else math.inf)
    if gains is None:
        gains = result.light_gains(directions)
    out = render_capture(result.as_maps(), directions, gains, result.variant, max_lanes,
                         light_distance)
    if shadows is None:
        shadows = result.relief is not None and result.fit_settings.get("shadows") == "relief"
    if shadows:
        if result.relief is None:
            raise ValueError("shadows = True needs a fit with a relief (shadows='relief')")
        field = near_field(check_directions(directions), light_distance, result.mask.shape)
        vis = result.relief.visibility(check_directions(directions) if field is None
                                       else field[0])
        out *= vis.T.reshape(out.shape[:3])[..., None]
    out[:, ~result.mask] = 0.0
    return out
