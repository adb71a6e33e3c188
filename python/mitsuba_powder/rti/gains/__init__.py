"""Per-light gains, in one home.

The K lights of an RTI capture differ in brightness: light k reaches the sample with the
irradiance ``E_k``, its *gain* (relative to the mean of the initial gains, which is a
calibration: only the gains relative to it are fitted). Everything about them is here:

* :mod:`.policy`: how a fit finds them (:class:`GainPolicy`: fitted or held, their start, the
  trend, the pixel subsample they are fitted on before the maps) and that subsample
  (:func:`gain_sample`); the fit's plan (:mod:`mitsuba_powder.rti.plan`) and the tiled fit
  (:mod:`mitsuba_powder.rti.tiles`) fit them on a subsample with
  :meth:`GainPolicy.on_subsample` and hold them with :meth:`GainPolicy.held`;
* :mod:`.step`: their Gauss-Newton step in the fit's alternation, every pixel's variables
  eliminated (:func:`gain_system`, :func:`gain_step`; the gains of lights that see too
  little, :func:`uninformed_lights`, are held); each per-pixel solver gives its
  pixels' part of that reduced system (``model(rows, gain_terms=True)``);
* :mod:`.trend`: the gains as a smooth function of the light's direction
  (:class:`GainTrend`: how a fit extends them to lights it did not fit; :class:`GainModel`,
  :func:`fit_gain_model`).
"""

from __future__ import annotations

import warnings

from .policy import GAIN_MODES, GAIN_PIXELS, GainPolicy, gain_policy, gain_sample
from .step import MIN_INFORMATION, gain_step, gain_system, uninformed_lights
from .trend import (
    GAIN_MODEL_MODES,
    MAX_AZIMUTH_ORDER,
    MAX_DEGREE,
    GainModel,
    GainTrend,
    fit_gain_model,
    gain_basis,
)

__all__ = ["GAIN_MODEL_MODES", "GAIN_MODES", "GAIN_PIXELS", "MAX_AZIMUTH_ORDER", "MAX_DEGREE",
           "MIN_INFORMATION", "GainModel", "GainPolicy", "GainTrend", "fit_gain_model",
           "gain_basis", "gain_policy", "gain_sample", "gain_step", "gain_system",
           "uninformed_lights"]


def __getattr__(name: str):
    """``GainOptions``: the old name of :class:`GainTrend`, for one release."""
    if name == "GainOptions":
        warnings.warn("mitsuba_powder.rti.gains.GainOptions is renamed GainTrend (how the "
                      "fitted gains extend to lights not fitted); the old name goes in the "
                      "next release", DeprecationWarning, stacklevel=2)
        return GainTrend
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
