"""The variables of a goniometric fit: which plugin properties may be fitted and in what range
(:data:`FITTABLE`), and the layout of one fit's variables (:class:`VariableLayout`): one per
free property, the albedo once per wavelength when several are fitted, bounds (the extinction
bounded by the EBS regime) and the optimiser's scaling (log10 for scale parameters)."""

from __future__ import annotations

import math

import numpy as np

from ..plugin.grains import DEFAULT_FILL, GRAIN_VARIABLES
from .optimise import ParamSpec

FITTABLE: dict[str, ParamSpec] = {
    # A_v stays near 1 for real powders (docs/model.md); a wide range opens a degenerate valley
    # where a tiny albedo (small grains) is traded against a huge A_v
    "amplitude_volume": ParamSpec(0.05, 5.0, True, 1.0),
    "g": ParamSpec(-0.95, 0.95, False, 0.0),
    "extinction": ParamSpec(1e-3, 1e3, True, 1.0),
    "radius": ParamSpec(3e-3, 3.0, True, 0.05),
    "radius2": ParamSpec(3e-3, 3.0, True, 0.5),
    "fraction2": ParamSpec(0.0, 1.0, False, 0.5),
    "radius3": ParamSpec(3e-3, 3.0, True, 0.5),
    "fraction3": ParamSpec(0.0, 1.0, False, 0.2),
    "radius4": ParamSpec(3e-3, 3.0, True, 0.5),
    "fraction4": ParamSpec(0.0, 1.0, False, 0.1),
    "agglomerate_radius": ParamSpec(1e-2, 3.0, True, 0.15),
    "agglomerate_fill": ParamSpec(0.05, 1.0, False, DEFAULT_FILL),
    "albedo": ParamSpec(0.0, 1.0, False, 0.8),
    "tau_o": ParamSpec(1e-2, 1e2, True, 2.0 / 3.0),
    "thickness": ParamSpec(1e-2, 1e4, True, 100.0),
    "amplitude_surface": ParamSpec(1e-9, 0.1, True, 1e-5),
    "correlation_length": ParamSpec(1e-2, 1e2, True, 1.0),
    "sigma": ParamSpec(1e-3, 1.5, True, 0.1),
}

#: Enhanced back-scattering theory holds while the cone is narrow: ``--regime ebs`` bounds
#: the extinction so that kappa / k0 stays at most this at every fitted wavelength
EBS_KAPPA_OVER_K0 = 0.25

#: Regimes of :func:`mitsuba_powder.fitting.fit.fit`
REGIMES = ("ebs", "free")


def extinction_limit(wavelengths: np.ndarray) -> float:
    """The largest extinction (1/um) of the EBS regime: kappa / k0 <= :data:`EBS_KAPPA_OVER_K0`
    at every wavelength (nm), k0 = 2 pi / lambda; the longest wavelength has the smallest k0."""
    return EBS_KAPPA_OVER_K0 * 2.0 * math.pi / (1e-3 * float(np.max(wavelengths)))


class VariableLayout:
    """The optimiser's variables ``y`` of a fit and their plugin values ``x``.

    Attributes:
        names: per variable, (property, wavelength in nm or None); ``albedo`` has one variable
            per wavelength when several are fitted.
        specs: per variable, its :class:`ParamSpec` (the extinction's upper bound lowered to
            :attr:`extinction_limit` in the EBS regime).
        lower, upper: bounds in ``y``.
        extinction_limit: the EBS regime's extinction limit, 1/um (also with ``regime="free"``,
            where it bounds nothing).
    """

    def __init__(self, free: list[str], wavelengths: np.ndarray, regime: str):
        self.names: list[tuple[str, float | None]] = []
        for n in free:
            if n == "albedo" and len(wavelengths) > 1:
                self.names += [(n, float(w)) for w in wavelengths]
            else:
                self.names.append((n, None))
        self.specs = [FITTABLE[n] for n, _ in self.names]
        self.extinction_limit = extinction_limit(wavelengths)
        if regime == "ebs":
            self.specs = [ParamSpec(s.lower, min(s.upper, self.extinction_limit), s.log,
                                    min(s.start, self.extinction_limit))
                          if n == "extinction" else s
                          for s, (n, _) in zip(self.specs, self.names)]
        self.lower = np.array([s.to_y(s.lower) for s in self.specs], dtype=np.float64)
        self.upper = np.array([s.to_y(s.upper) for s in self.specs], dtype=np.float64)

    def index(self, name: str) -> int:
        """The variable of property ``name`` (the first, for a per-wavelength albedo)."""
        return [n for n, _ in self.names].index(name)

    def columns(self, name: str) -> list[int]:
        """Every variable of property ``name``."""
        return [j for j, (n, _) in enumerate(self.names) if n == name]

    def x_of(self, y: np.ndarray) -> np.ndarray:
        """Plugin values (B, p) of optimiser variables ``y`` (B, p) or (p,)."""
        y = np.atleast_2d(y)
        return np.stack([s.to_x(y[:, j]) for j, s in enumerate(self.specs)], axis=1)

    def y_of(self, x: np.ndarray) -> np.ndarray:
        """Optimiser variables (B, p) of plugin values ``x`` (B, p) or (p,)."""
        x = np.atleast_2d(np.asarray(x, dtype=np.float64))
        return np.stack([s.to_y(x[:, j]) for j, s in enumerate(self.specs)], axis=1)

    def start(self) -> np.ndarray:
        """The default start (each property's :class:`ParamSpec` start), (p,)."""
        return self.y_of(np.array([s.start for s in self.specs]))[0]

    def hold_grains(self) -> np.ndarray:
        """(p,) booleans: the grain variables."""
        return np.array([n in GRAIN_VARIABLES for n, _ in self.names])

    def properties(self, x: np.ndarray, fixed: dict, lam: float | None = None) -> dict:
        """Plugin properties (mono form at wavelength ``lam``): ``fixed`` and the values of
        variables ``x`` (p,)."""
        d = dict(fixed)
        for j, (name, w) in enumerate(self.names):
            if w is None or w == lam:
                d[name] = float(x[j])
        return d
