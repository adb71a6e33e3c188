"""A reference target in the frame (a white or grey card, Spectralon) calibrates an RTI
capture: each light's irradiance and so the exposure, as calibrated RTI does
(``--reference x0,y0,x1,y1[:REFLECTANCE]``).

The card is taken as a Lambertian reflector of known reflectance ``R`` (default
:data:`DEFAULT_REFLECTANCE`) lying flat in the sample's plane (its normal towards the camera,
``n = z``). Under light k of irradiance ``E_k`` its pixels read ``E_k R / pi l_k,z``, so

    E_k = pi m_k / (R l_k,z)

with ``m_k`` the mean over the card's pixels and channels of the observations not saturated
(any channel at or above the fit's saturation level). A light that grazes the card
(``l_k,z`` below :data:`MIN_LZ`, about 3 degrees) or saturates all of it gives no estimate: it
gets the median of the others' (and is counted). The exposure is the lights' mean irradiance
and the gains relative to it are held in the fit (``gains="fixed"``): the powder's albedo is
then on the card's absolute scale. The card's pixels are left out of the fit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .._checks import check_range

__all__ = ["DEFAULT_REFLECTANCE", "MIN_LZ", "Reference", "calibrate", "parse_reference"]

#: The card's reflectance when none is given (a white reference card; Spectralon is ~0.99)
DEFAULT_REFLECTANCE = 0.99
#: Lights at lz below this (about 3 degrees of elevation) give the card no usable irradiance
MIN_LZ = 0.05


@dataclass(frozen=True)
class Reference:
    """A reference card: its box in pixels (``x0 <= x < x1`` columns from the left,
    ``y0 <= y < y1`` rows from the top, as ``compare-photo --region``) and reflectance."""

    box: tuple[int, int, int, int]
    reflectance: float = DEFAULT_REFLECTANCE

    def mask(self, shape: tuple[int, int], name: str = "--reference") -> np.ndarray:
        """The card's pixels, bool (H, W); a box outside the image is an error naming it."""
        h, w = shape
        x0, y0, x1, y1 = self.box
        if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
            raise ValueError(f"{name} = {x0},{y0},{x1},{y1} is out of range; valid: 0 <= x0 < "
                             f"x1 <= {w}, 0 <= y0 < y1 <= {h} (pixels of the {w} x {h} image)")
        out = np.zeros((h, w), dtype=bool)
        out[y0:y1, x0:x1] = True
        return out


def parse_reference(text: str, name: str = "--reference") -> Reference:
    """``x0,y0,x1,y1[:REFLECTANCE]`` -> :class:`Reference` (reflectance in (0, 1])."""
    box_text, _, refl_text = str(text).partition(":")
    try:
        box = tuple(int(v) for v in box_text.split(","))
    except ValueError:
        box = ()
    if len(box) != 4:
        raise ValueError(f"{name} = {text!r}: expected x0,y0,x1,y1[:REFLECTANCE] (the card's "
                         "pixels, whole numbers, and its reflectance in (0, 1])")
    refl = (DEFAULT_REFLECTANCE if not refl_text else
            check_range(f"{name} reflectance", refl_text, 0.0, 1.0, "(]"))
    return Reference(box, refl)


def calibrate(images: np.ndarray, directions: np.ndarray, reference: Reference,
              saturation: float = 0.99, name: str = "--reference") -> dict:
    """The lights' irradiances from the card (module docstring).

    Args:
        images: (K, H, W, C) linear values; directions: (K, 3) unit vectors to the lights.

    Returns:
        dict: ``irradiance`` (K,), ``exposure`` (their mean), ``gains`` (K,) relative to it,
        ``estimated`` (K,) bool (from the card, else the others' median), ``pixels``.

    Raises:
        ValueError: no light gives the card an irradiance (all grazing or saturated).
    """
    sel = reference.mask(images.shape[1:3], name)
    card = np.asarray(images[:, sel], dtype=np.float64)              # (K, P, C)
    ok = ~np.any(card >= saturation, axis=2)                           # (K, P)
    d = np.asarray(directions, dtype=np.float64)
    lz = d[:, 2] / np.linalg.norm(d, axis=1)
    count = ok.sum(axis=1)
    mean = np.where(count > 0, np.sum(card.mean(axis=2) * ok, axis=1) / np.maximum(count, 1),
                    np.nan)
    estimated = (lz >= MIN_LZ) & (count >= max(1, 0.5 * sel.sum())) & (mean > 0)
    if not estimated.any():
        raise ValueError(f"{name}: no light gives the card an irradiance (every light grazes "
                         f"it, lz < {MIN_LZ}, or saturates half of its pixels or more); "
                         "choose a card region that is lit and not clipped")
    e = np.full(len(d), np.nan)
    e[estimated] = math.pi * mean[estimated] / (reference.reflectance * lz[estimated])
    e[~estimated] = float(np.median(e[estimated]))
    exposure = float(np.mean(e))
    return {"irradiance": e, "exposure": exposure, "gains": e / exposure,
            "estimated": estimated, "pixels": int(sel.sum()),
            "box": list(reference.box), "reflectance": reference.reflectance}
