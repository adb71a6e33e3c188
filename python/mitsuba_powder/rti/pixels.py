"""What a per-pixel solver of the RTI fit takes and gives: the data of P pixels under K lights
(:class:`PixelData`, one holder for every solver of
:data:`mitsuba_powder.rti.solvers.SOLVERS`) and the fitted rows (:class:`SolverFit`)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field

import numpy as np

from ..fitting.optimise import ParamSpec
from .properties import GrainAlbedo

__all__ = ["PixelData", "SolverFit"]


@dataclass(frozen=True, eq=False)
class PixelData:
    """The per-pixel least-squares problem of P pixels under K lights.

    The model of pixel p under light k is ``g_k s_pk f(n_p, d_pk) (n_p . d_pk)`` with the gains
    ``g``, the irradiance factors ``s`` (1 for distant lights) and the light directions ``d``
    (one per light, or one per pixel and light at a finite distance); the residuals are
    weighted by ``sqrt(weights)``.

    Attributes:
        observed: (P, K, 3) observations (linear values).
        weights: (P, K) observation weights in {0, 1}.
        directions: (K, 3) unit vectors towards the lights, or (P, K, 3) per pixel.
        gains: (K,) light gains.
        layout: the variables (name, spec) in column order: ``slope_x``, ``slope_y``, then
            ``albedo0..2`` or a grain size, then free properties.
        fixed: held per-pixel properties of the evaluator -> (P,).
        fixed_albedo: (P, 3) when neither the albedo nor a grain size is free.
        grain: the albedo of a free grain size.
        irradiance: (P, K) irradiance factors, or None (distant lights).
    """

    observed: np.ndarray
    weights: np.ndarray
    directions: np.ndarray
    gains: np.ndarray
    layout: Sequence[tuple[str, ParamSpec]]
    fixed: Mapping[str, np.ndarray] = field(default_factory=dict)
    fixed_albedo: np.ndarray | None = None
    grain: GrainAlbedo | None = None
    irradiance: np.ndarray | None = None


@dataclass
class SolverFit:
    """What a solver's ``solve`` gives: the fitted rows ``y`` (P, n) (the layout's columns),
    each pixel's cost (P,), the iterations of the longest pixel and the pixels still
    iterating when the iteration cap stopped them."""

    y: np.ndarray
    cost: np.ndarray
    iterations: int
    at_cap: int = 0
