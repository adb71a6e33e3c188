"""Per-pixel powder maps fitted to an RTI capture (:class:`MapsResult`) and the fitted surface
relit under new lights (:func:`relight`)."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from .forward import MAX_LANES, VARIANT, render_capture
from .properties import GRAIN_MAPS

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

    def predict(self, directions: np.ndarray, gains: np.ndarray | None = None) -> np.ndarray:
        """Relit images float32 (K', H, W, 3) under ``directions`` (K', 3); see :func:`relight`.
        """
        return relight(self, directions, gains)


def relight(result: MapsResult, directions: np.ndarray, gains: np.ndarray | None = None,
            max_lanes: int = MAX_LANES) -> np.ndarray:
    """The fitted surface under new lights: :func:`mitsuba_powder.rti.render_capture` with the
    fitted maps.

    Args:
        result: a :func:`mitsuba_powder.rti.fit_maps` result.
        directions: (K', 3) vectors towards the lights.
        gains: (K',) light irradiances (default 1: the fit's mean gain).

    Returns:
        float32 (K', H, W, 3) radiance (the capture's linear units); 0 outside the mask.
    """
    out = render_capture(result.as_maps(), directions, gains, result.variant, max_lanes)
    out[:, ~result.mask] = 0.0
    return out
