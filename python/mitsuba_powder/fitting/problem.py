"""The least-squares problem of a goniometric fit, batched over parameter sets (the
:class:`~mitsuba_powder.fitting.optimise.BatchProblem` the optimiser takes).

Three parts: the variables (:class:`~mitsuba_powder.fitting.variables.VariableLayout`), where the
albedo comes from (:func:`albedo_source`: fixed, free per wavelength, or from the grains by Mie
theory with its derivatives), and the residual engine (:class:`Problem`): weighted residuals of
the plugin's BRF and their Jacobian in the optimiser's variables.
"""

from __future__ import annotations

import numpy as np

from ..io.measurements import Measurements
from ..plugin import registry
from ..plugin.brf import BatchBRF, engine_properties
from ..plugin.grains import GRAIN_VARIABLES, POPULATION_MATERIALS, GrainOptics
from .variables import FITTABLE, REGIMES, VariableLayout

#: The plugin's default radius (um), used when neither fitted nor given
DEFAULT_RADIUS = float(registry.DEFAULTS["radius"])

#: Properties that only configure the grain model (not fitted)
GRAIN_SETTINGS = ("grains", "mixing")

#: Entries of the grain albedo cache, at most (one per distinct set of grain values)
_RHO_CACHE_SIZE = 100000


def _check_free(free: list[str], fixed: dict) -> None:
    unknown = [n for n in free if n not in FITTABLE]
    if unknown:
        raise ValueError(f"cannot fit {unknown}: fittable properties are {', '.join(FITTABLE)}")
    if len(set(free)) != len(free) or not free:
        raise ValueError(f"free properties must be distinct and non-empty, got {free}")
    clash = [n for n in free if n in fixed]
    if clash:
        raise ValueError(f"{clash} are both free and fixed (--set)")
    given = set(free) | set(fixed)
    for j in range(2, registry.MAX_POPULATIONS + 1):
        pair = (f"radius{j}", f"fraction{j}")
        if any(n in given for n in pair) and not all(n in given for n in pair):
            raise ValueError(f"population {j} needs radius{j} and fraction{j} (free or fixed)")
        if j > 2 and f"radius{j}" in given and f"radius{j - 1}" not in given:
            raise ValueError(f"population {j} needs population {j - 1} (radius{j - 1}, "
                             f"fraction{j - 1}): populations are numbered 2, 3, 4 without gaps")
    mixed = any(k in fixed for k in POPULATION_MATERIALS)
    free_fractions = [n for n in free if n.startswith("fraction")]
    if mixed and free_fractions and "tau_o" not in given:
        raise ValueError(f"{free_fractions} are free and the populations are of different "
                         "materials: tau_o (from the mixture's Bruggeman index) would change "
                         "with them; give tau_o or fit it (--set tau_o=... or --free tau_o)")
    specular = fixed.get("specular", "harvey_shack")
    unused = {"harvey_shack": "sigma", "gaussian": "correlation_length"}.get(specular)
    if unused in free:
        raise ValueError(f"{unused} has no effect with specular = {specular!r}: fit "
                         f"{'correlation_length' if unused == 'sigma' else 'sigma'} instead, or "
                         f"set specular={'gaussian' if unused == 'sigma' else 'harvey_shack'}")
    grains = [n for n in GRAIN_VARIABLES + GRAIN_SETTINGS if n in free or n in fixed]
    if ("albedo" in free or "albedo" in fixed) and grains:
        raise ValueError(f"albedo and {grains} cannot be used together: a given albedo "
                         "replaces the one Mie theory computes from the grains")
    _check_grain_model(free, fixed)
    if "albedo" in fixed and not isinstance(fixed["albedo"], (int, float)):
        raise ValueError(f"albedo = {fixed['albedo']!r}: a fit takes a fixed albedo as one "
                         "number in [0, 1]")
    for name, value in fixed.items():
        if registry.interval(name) is not None:  # the plugin's range, its own rule
            registry.check_value(name, value, "fixed ")


def _check_grain_model(free: list[str], fixed: dict) -> None:
    """The grain properties each model takes (the plugin's rules, from its registry)."""
    registry.check_grain_model(fixed.get("grains", registry.DEFAULTS["grains"]),
                               set(free) | set(fixed), free)


# ----------------------------------------------------------------- albedo sources


class FixedAlbedo:
    """One given albedo at every wavelength."""

    mode = "fixed"

    def __init__(self, value: float, wavelengths: np.ndarray):
        self.value = float(value)
        self.count = len(wavelengths)

    def albedo(self, x: np.ndarray, derivatives: bool) -> tuple[np.ndarray, None]:
        """rho (B, W) of parameter sets ``x`` (B, p); no grain derivatives."""
        return np.full((len(x), self.count), self.value), None


class FreeAlbedo:
    """The albedo is a variable (one per wavelength when several are fitted)."""

    mode = "free"

    def __init__(self, layout: VariableLayout, wavelengths: np.ndarray):
        self.columns = layout.columns("albedo")
        self.count = len(wavelengths)

    def albedo(self, x: np.ndarray, derivatives: bool) -> tuple[np.ndarray, None]:
        """rho (B, W): the albedo variables of parameter sets ``x`` (B, p)."""
        return x[:, self.columns].reshape(len(x), self.count), None


class GrainAlbedo:
    """The albedo from the grains by Mie theory (:class:`GrainOptics`), with its derivatives
    with respect to the :data:`GRAIN_VARIABLES`; values are cached per set of grain values
    (the global phase holds the grains, so most parameter sets share them)."""

    mode = "grains"

    def __init__(self, grains: GrainOptics, layout: VariableLayout, free: list[str],
                 fixed: dict, wavelengths: np.ndarray):
        self.grains = grains
        self.layout = layout
        self.free = free
        self.fixed = fixed
        self.wavelengths = wavelengths
        self.grain_free = [n for n in GRAIN_VARIABLES if n in free]
        self._cache: dict[tuple, tuple[np.ndarray, np.ndarray | None]] = {}

    def grain_values(self, x: np.ndarray) -> tuple[np.ndarray | None, ...]:
        """The :data:`GRAIN_VARIABLES` per parameter set (None where absent)."""
        out = []
        for name in GRAIN_VARIABLES:
            if name in self.free:
                out.append(x[:, self.layout.index(name)])
            elif name in self.fixed:
                out.append(np.full(len(x), float(self.fixed[name])))
            else:
                out.append(None)
        if out[0] is None:  # the plugin's default radius
            out[0] = np.full(len(x), DEFAULT_RADIUS)
        return tuple(out)

    def albedo(self, x: np.ndarray, derivatives: bool) -> tuple[np.ndarray, np.ndarray]:
        """rho (B, W) and d rho / d(:data:`GRAIN_VARIABLES`) (B, W, 9; zero unless
        ``derivatives`` and some grain variable is free)."""
        b, w = len(x), len(self.wavelengths)
        grain = self.grain_values(x)
        rho = np.empty((b, w))
        deriv = np.zeros((b, w, len(GRAIN_VARIABLES)))
        need = derivatives and bool(self.grain_free)
        missing = []
        for i in range(b):
            key = tuple(None if v is None else float(v[i]) for v in grain) + (need,)
            if key in self._cache:
                rho[i], d = self._cache[key]
                if d is not None:
                    deriv[i] = d
            else:
                missing.append((i, key))
        if missing:
            idx = np.array([i for i, _ in missing])
            r1, r2, f2, ra, fill, r3, f3, r4, f4 = (None if v is None else v[idx]
                                                    for v in grain)
            values, d = self.grains.albedo(self.wavelengths, r1, r2, f2, derivatives=need,
                                           agglomerate_radius=ra, agglomerate_fill=fill,
                                           radius3=r3, fraction3=f3, radius4=r4,
                                           fraction4=f4)
            for k, (i, key) in enumerate(missing):
                rho[i] = values[k]
                if d is not None:
                    deriv[i] = d[k]
                if len(self._cache) < _RHO_CACHE_SIZE:
                    self._cache[key] = (values[k], None if d is None else d[k])
        return rho, deriv


def albedo_source(layout: VariableLayout, free: list[str], fixed: dict, grains: GrainOptics,
                  wavelengths: np.ndarray) -> FixedAlbedo | FreeAlbedo | GrainAlbedo:
    """Where the albedo of a fit comes from: free, fixed, else the grains."""
    if "albedo" in free:
        return FreeAlbedo(layout, wavelengths)
    if "albedo" in fixed:
        return FixedAlbedo(fixed["albedo"], wavelengths)
    return GrainAlbedo(grains, layout, free, fixed, wavelengths)


# ----------------------------------------------------------------- residual engine


class Problem:
    """The least-squares problem in the optimiser's variables ``y`` (log10 for scale
    parameters), batched over parameter sets (see
    :class:`mitsuba_powder.fitting.optimise.BatchProblem`).

    Variables (:attr:`layout`): one per free property; ``albedo`` once per wavelength when
    several are fitted. The albedo comes from :attr:`albedo_source`; the plugin's BRF and its
    forward-mode derivatives from :class:`~mitsuba_powder.plugin.brf.BatchBRF`.
    """

    def __init__(self, data: Measurements, free: list[str], fixed: dict,
                 regime: str = "ebs"):
        _check_free(free, fixed)
        if regime not in REGIMES:
            raise ValueError(f"regime = {regime!r} is not valid; valid values are "
                             f"{', '.join(REGIMES)}")
        self.data = data
        self.free = list(free)
        self.fixed = dict(fixed)
        self.regime = regime
        self.wavelengths = data.wavelengths()
        self.row_wavelength = np.searchsorted(self.wavelengths, data.wavelength)
        self.layout = VariableLayout(self.free, self.wavelengths, regime)
        self.weights = 1.0 / data.sigma if data.sigma is not None else np.ones(len(data))
        self.target = data.brf
        # float properties the plugin takes per parameter set
        self.varying = [n for n in self.free if n != "albedo" and n not in GRAIN_VARIABLES]
        self.grain_free = [n for n in GRAIN_VARIABLES if n in self.free]
        self.engine_properties = engine_properties(self.fixed)
        self.grains = GrainOptics(self.fixed)
        self.albedo_source = albedo_source(self.layout, self.free, self.fixed, self.grains,
                                           self.wavelengths)
        self.tau_o = (np.full(len(self.wavelengths), float(self.fixed["tau_o"]))
                      if "tau_o" in self.fixed else
                      None if "tau_o" in self.free else self.grains.tau_o(
                          self.wavelengths, {k: v for k, v in self.fixed.items()
                                             if k.startswith("fraction")}))
        # False while the global phase holds the grains: no Mie derivatives needed
        self.grain_derivatives = True
        self._engines: dict[int, BatchBRF] = {}
        self.evaluations = 0

    # ----------------------------------------------------------- variables

    @property
    def names(self) -> list[tuple[str, float | None]]:
        return self.layout.names

    @property
    def specs(self) -> list:
        return self.layout.specs

    @property
    def lower(self) -> np.ndarray:
        return self.layout.lower

    @property
    def upper(self) -> np.ndarray:
        return self.layout.upper

    @property
    def extinction_limit(self) -> float:
        return self.layout.extinction_limit

    @property
    def albedo_mode(self) -> str:
        """``"free"``, ``"fixed"`` or ``"grains"``."""
        return self.albedo_source.mode

    def index(self, name: str) -> int:
        return self.layout.index(name)

    def x_of(self, y: np.ndarray) -> np.ndarray:
        return self.layout.x_of(y)

    def y_of(self, x: np.ndarray) -> np.ndarray:
        return self.layout.y_of(x)

    def start(self) -> np.ndarray:
        """The default start (each property's :class:`ParamSpec` start), (p,)."""
        return self.layout.start()

    def hold_grains(self) -> np.ndarray:
        """(p,) booleans: the grain variables."""
        return self.layout.hold_grains()

    # ----------------------------------------------------------- evaluation

    def _engine(self, batch: int) -> BatchBRF:
        if batch not in self._engines:
            self._engines[batch] = BatchBRF(self.data, self.engine_properties, batch,
                                            self.varying)
        return self._engines[batch]

    def albedo(self, x: np.ndarray, derivatives: bool) -> tuple[np.ndarray, np.ndarray | None]:
        """rho (B, W) and, for grains, d rho / d(:data:`GRAIN_VARIABLES`) (B, W, 5)."""
        return self.albedo_source.albedo(x, derivatives and self.grain_derivatives)

    def _jacobian_column(self, j: int, x: np.ndarray, grads: dict,
                         drho: np.ndarray | None) -> np.ndarray:
        """d BRF / d y_j (B, N), unweighted."""
        name, lam = self.names[j]
        dxdy = self.specs[j].dx_dy(x[:, j])[:, None]
        if name in self.varying:
            col = grads[name]
        elif name == "albedo":
            col = grads["albedo"] if lam is None else grads["albedo"] * (
                self.data.wavelength == lam)[None, :]
        else:  # a grain variable: chain rule through rho at each row's wavelength
            k = GRAIN_VARIABLES.index(name)
            col = grads["albedo"] * drho[:, self.row_wavelength, k]
        return col * dxdy

    def _evaluate(self, y: np.ndarray, derivatives: bool):
        y = np.atleast_2d(np.asarray(y, dtype=np.float64))
        x = self.x_of(y)
        rho, drho = self.albedo(x, derivatives)
        values = {n: x[:, self.index(n)] for n in self.varying}
        brf, grads = self._engine(len(x)).evaluate(values, rho, self.tau_o, derivatives)
        self.evaluations += 1
        res = (brf - self.target[None, :]) * self.weights[None, :]
        if not derivatives:
            return res, None
        jac = np.zeros(res.shape + (len(self.names),))
        for j in range(len(self.names)):
            jac[:, :, j] = self._jacobian_column(j, x, grads, drho) * self.weights[None, :]
        return res, jac

    def residuals(self, y: np.ndarray) -> np.ndarray:
        """Weighted residuals (B, N) of parameter sets y (B, p)."""
        return self._evaluate(y, False)[0]

    def jacobian(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Weighted residuals (B, N) and their Jacobian (B, N, p) with respect to y."""
        return self._evaluate(y, True)

    # ----------------------------------------------------------- results

    def properties(self, x: np.ndarray, lam: float | None = None) -> dict:
        """Plugin properties (mono form at wavelength ``lam``) of variables ``x`` (p,)."""
        return self.layout.properties(x, self.fixed, lam)
