"""Per-light gains as a smooth function of the light's direction, plus regularised residuals.

The per-light gains ``g_k`` that the per-pixel fit finds (the irradiance of light k relative
to the dome's mean, a calibration of the dome) fall smoothly with the light's elevation on
real domes (a lamp's beam pattern, a mis-measured elevation, a dome that is not a sphere). A
light that was not fitted (a new ``.lp`` file, a held-out light) has no gain of its own; this
module gives it the gain of the trend at its direction.

**Model.** In log gain (a relative change: ``ln g ~ g - 1`` for gains near 1; the model stays
positive wherever it is evaluated):

    ``ln g(l) = sum_j c_j B_j(l)``,    ``ln g_k = sum_j c_j B_j(l_k) + delta_k``

for the fitted lights, with ``delta_k`` a per-light residual (log) gain pulled towards 0 by a
ridge penalty. The basis ``B`` of :func:`gain_basis`, in the unit direction ``l = (l_x,
l_y, l_z)`` (image frame, z towards the camera, ``l_z = sin(elevation)``):

* ``1, l_z, l_z^2, ..., l_z^degree`` (default degree 2): a polynomial in ``sin(elevation)``,
  not in the elevation itself, because a polynomial in ``l_z`` is a polynomial in the
  direction's components: smooth everywhere on the sphere, the zenith included (one in the
  elevation has a cone-shaped kink there), and the cosine of the incidence on the mean
  surface, through which most calibration errors act;
* ``azimuth_order`` 1 adds ``l_x, l_y`` (a dome tilted or off-centre), 2 adds also
  ``l_x^2 - l_y^2, 2 l_x l_y``: ``cos^m(elevation)`` times ``cos(m phi), sin(m phi)``, smooth
  at the zenith as well.

Outside the range of ``l_z`` of the fitted lights the polynomial in ``l_z`` is held at its end
values (``extrapolate=False``, the default): a low light below the dome's lowest ring gets the
lowest ring's trend, not a polynomial's runaway.

**Fit** (:func:`fit_gain_model`): weighted least squares jointly in ``c`` and ``delta``,

    ``min sum_k w_k (ln g_k - B_k c - delta_k)^2 + strength sum_k delta_k^2``

with the weights ``w_k >= 0`` normalised to mean 1 (e.g. ``1 / var(ln g_k)`` or the number of
observations of light k). For a given ``c`` the residuals are ``delta_k = w_k r_k / (w_k +
strength)`` (``r_k`` the log deviation from the trend): a light of weight w keeps the
fraction ``w / (w + strength)`` of its deviation. Eliminating them, ``c`` is the weighted
fit with weights ``w_k strength / (w_k + strength)``, i.e. ``1 / (sigma_k^2 + tau^2)`` for
gains of log standard error ``sigma_k`` and a spread ``tau`` of the lights about the trend
(``strength = sigma^2 / tau^2`` in units of the mean weight; dimensionless). ``strength =
inf`` (default): no residuals, the gains are the trend; ``strength = 0``: free residuals (the
fitted lights keep their gains exactly) and ``c`` the unweighted fit of the lights of weight
> 0.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..._checks import check_range, out_of_range
from ..lights import unit_directions

__all__ = ["GAIN_MODEL_MODES", "MAX_AZIMUTH_ORDER", "MAX_DEGREE", "GainModel", "GainTrend",
           "fit_gain_model", "gain_basis"]

#: Highest polynomial degree in l_z (a dome has a handful of rings)
MAX_DEGREE = 6
#: Highest azimuthal order
MAX_AZIMUTH_ORDER = 2
#: The ``kind`` tag of a serialised model
KIND = "mitsuba-powder gain model"


def _order(name: str, value, upper: int) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or \
            not 0 <= value <= upper:
        raise ValueError(out_of_range(f"{name} = {value!r}", f"the whole numbers 0-{upper}"))
    return int(value)


def gain_basis(directions: np.ndarray, degree: int = 2, azimuth_order: int = 0,
               lz_range: tuple[float, float] | None = None) -> np.ndarray:
    """Design matrix float64 (K, n) of the gain model at K directions (module docstring).

    Args:
        directions: (K, 3) vectors towards the lights (normalised here).
        degree: polynomial degree in ``l_z``, 0-:data:`MAX_DEGREE`.
        azimuth_order: 0, 1 (``l_x, l_y``) or 2 (also ``l_x^2 - l_y^2, 2 l_x l_y``).
        lz_range: (low, high): ``l_z`` is clamped into it for the polynomial terms (None: not
            clamped).

    Returns:
        columns ``1, l_z, ..., l_z^degree`` then the azimuthal ones; n = degree + 1 + 2
        azimuth_order.
    """
    d = unit_directions(directions)
    degree = _order("degree", degree, MAX_DEGREE)
    azimuth_order = _order("azimuth_order", azimuth_order, MAX_AZIMUTH_ORDER)
    t = d[:, 2] if lz_range is None else np.clip(d[:, 2], *lz_range)
    cols = [t**j for j in range(degree + 1)]
    if azimuth_order >= 1:
        cols += [d[:, 0], d[:, 1]]
    if azimuth_order >= 2:
        cols += [d[:, 0] ** 2 - d[:, 1] ** 2, 2.0 * d[:, 0] * d[:, 1]]
    return np.stack(cols, axis=1)


@dataclass(frozen=True, eq=False)
class GainModel:
    """A fitted gain model (module docstring); build it with :func:`fit_gain_model`.

    Attributes:
        coefficients: float64 (n,) ``c`` of ``ln g`` on :func:`gain_basis`'s columns.
        degree, azimuth_order: the basis.
        lz_range: (low, high) ``l_z`` of the fitted lights (the polynomial is held at its
            ends outside unless ``extrapolate``).
        strength: the ridge strength of the residuals (``inf``: none).
        directions: float64 (K, 3) the fitted lights' unit directions.
        residuals: float64 (K,) their log residual gains ``delta_k`` (0 when strength = inf).
    """

    coefficients: np.ndarray
    degree: int
    azimuth_order: int
    lz_range: tuple[float, float]
    strength: float
    directions: np.ndarray
    residuals: np.ndarray

    def log_basis(self, directions: np.ndarray, extrapolate: bool = False) -> np.ndarray:
        """(K', n) ``d ln g / d c`` at directions (the basis, clamped unless extrapolating)."""
        return gain_basis(directions, self.degree, self.azimuth_order,
                          None if extrapolate else self.lz_range)

    def trend(self, directions: np.ndarray, extrapolate: bool = False) -> np.ndarray:
        """(K',) the smooth gain ``exp(B c)`` at directions (no residual)."""
        return np.exp(self.log_basis(directions, extrapolate) @ self.coefficients)

    def matches(self, directions: np.ndarray, match_degrees: float = 0.01) -> np.ndarray:
        """(K',) index of the fitted light within ``match_degrees`` of each direction (the
        nearest), -1 where none is."""
        d = unit_directions(directions)
        cos = d @ self.directions.T
        best = np.argmax(cos, axis=1)
        near = cos[np.arange(len(d)), best] >= math.cos(math.radians(match_degrees))
        return np.where(near, best, -1)

    def evaluate(self, directions: np.ndarray, match_degrees: float = 0.01,
                 extrapolate: bool = False) -> np.ndarray:
        """(K',) gains for lights at ``directions``: the trend, times ``exp(delta_k)`` where a
        direction is a fitted light's (within ``match_degrees``): a relight under the
        capture's own lights reproduces the fitted gains, a new light gets the trend."""
        idx = self.matches(directions, match_degrees)
        delta = np.where(idx >= 0, self.residuals[np.maximum(idx, 0)], 0.0)
        return self.trend(directions, extrapolate) * np.exp(delta)

    def gains(self) -> np.ndarray:
        """(K,) the fitted lights' gains: ``exp(B_k c + delta_k)``."""
        return self.trend(self.directions) * np.exp(self.residuals)

    def jacobian(self, directions: np.ndarray, match_degrees: float = 0.01,
                 extrapolate: bool = False) -> np.ndarray:
        """(K', n) ``d g / d c`` of :meth:`evaluate` (``g B``)."""
        g = self.evaluate(directions, match_degrees, extrapolate)
        return g[:, None] * self.log_basis(directions, extrapolate)

    def scaled(self, factor: float) -> GainModel:
        """The model with every gain multiplied by ``factor`` > 0 (``ln factor`` added to the
        constant term), e.g. to restore the gains' mean."""
        f = float(factor)
        if not (math.isfinite(f) and f > 0):
            raise ValueError(out_of_range(f"factor = {factor!r}", "(0, inf)"))
        c = self.coefficients.copy()
        c[0] += math.log(f)
        return GainModel(c, self.degree, self.azimuth_order, self.lz_range, self.strength,
                         self.directions, self.residuals)

    def to_dict(self) -> dict:
        """A JSON-ready description (for ``fit.json``; ``strength`` inf is written as None)."""
        return {"kind": KIND,
                "basis": "ln g = sum_j c_j B_j(l): 1, lz, ..., lz^degree (lz clamped to "
                         "lz_range), then lx, ly (azimuth_order >= 1), lx^2 - ly^2, 2 lx ly "
                         "(azimuth_order 2)",
                "degree": self.degree, "azimuth_order": self.azimuth_order,
                "coefficients": [float(c) for c in self.coefficients],
                "lz_range": [float(v) for v in self.lz_range],
                "strength": None if math.isinf(self.strength) else float(self.strength),
                "directions": self.directions.tolist(),
                "residuals": [float(v) for v in self.residuals]}

    @classmethod
    def from_dict(cls, data: dict) -> GainModel:
        """The model of :meth:`to_dict`'s output.

        Raises:
            ValueError: a missing key or a value out of range (the key is named).
        """
        if not isinstance(data, dict) or data.get("kind") != KIND:
            kind = data.get("kind") if isinstance(data, dict) else type(data).__name__
            raise ValueError(f"gain model: kind = {kind!r}; expected {KIND!r}")
        missing = [k for k in ("degree", "azimuth_order", "coefficients", "lz_range",
                               "strength", "directions", "residuals") if k not in data]
        if missing:
            raise ValueError(f"gain model: keys {missing} are missing")
        degree = _order("degree", data["degree"], MAX_DEGREE)
        order = _order("azimuth_order", data["azimuth_order"], MAX_AZIMUTH_ORDER)
        c = np.asarray(data["coefficients"], dtype=np.float64)
        if c.shape != (degree + 1 + 2 * order,) or not np.all(np.isfinite(c)):
            raise ValueError(f"gain model: coefficients {c.tolist()}; expected "
                             f"{degree + 1 + 2 * order} finite numbers")
        lo, hi = (float(v) for v in data["lz_range"])
        if not -1.0 <= lo <= hi <= 1.0:
            raise ValueError(out_of_range(f"gain model: lz_range = {[lo, hi]}",
                                          "-1 <= low <= high <= 1"))
        strength = math.inf if data["strength"] is None else float(data["strength"])
        if not strength >= 0:
            raise ValueError(out_of_range(f"gain model: strength = {data['strength']!r}",
                                          "[0, inf]", "(None: inf)"))
        d = unit_directions(data["directions"], "gain model: directions")
        res = np.asarray(data["residuals"], dtype=np.float64)
        if res.shape != (len(d),) or not np.all(np.isfinite(res)):
            raise ValueError(f"gain model: residuals of shape {res.shape}; expected "
                             f"({len(d)},) finite numbers, one per direction")
        return cls(c, degree, order, (lo, hi), strength, d, res)


def fit_gain_model(directions: np.ndarray, gains: np.ndarray, weights: np.ndarray | None = None,
                   degree: int = 2, azimuth_order: int = 0, strength: float = math.inf
                   ) -> GainModel:
    """Fit the smooth gain model (and residual gains) to per-light gains (module docstring).

    Args:
        directions: (K, 3) vectors towards the fitted lights.
        gains: (K,) their gains, > 0.
        weights: (K,) relative weights >= 0 of ``ln g_k`` (normalised to mean 1 here; a light
            of weight 0 does not inform the trend and keeps no residual); default all 1.
        degree: polynomial degree in ``l_z``; the lights of weight > 0 need at least
            ``degree + 1`` distinct elevations.
        azimuth_order: 0-2 (module docstring).
        strength: ridge strength of the residual gains, [0, inf] in units of the mean weight
            (inf: gains = trend; 0: residuals free).

    Returns:
        A :class:`GainModel`.

    Raises:
        ValueError: shapes, gains <= 0, weights < 0 or all 0, fewer lights than coefficients,
            too few distinct elevations for the degree, directions that do not determine the
            azimuthal terms.
    """
    d, g, w, lam = _checked_data(directions, gains, weights, strength)
    used = w > 0
    t = d[used, 2]
    lz_range = (float(t.min()), float(t.max()))
    basis = gain_basis(d, degree, azimuth_order, lz_range)
    _check_determined(basis, t, used, degree, azimuth_order)
    if math.isinf(lam):
        eff = w
    elif lam == 0:
        eff = used.astype(np.float64)
    else:
        eff = w * lam / (w + lam)
    y = np.log(g)
    a = basis[used] * np.sqrt(eff[used])[:, None]
    norms = np.linalg.norm(a, axis=0)
    scale = np.where(norms > 0, norms, 1.0)  # a zero column is caught by the rank test
    _check_rank(a / scale, int(used.sum()), degree, azimuth_order)
    c = np.linalg.lstsq(a / scale, y[used] * np.sqrt(eff[used]), rcond=None)[0] / scale
    r = y - basis @ c
    if math.isinf(lam):
        delta = np.zeros(len(d))
    else:
        delta = np.where(used, w * r / np.where(used, w + lam, 1.0), 0.0)
    return GainModel(c, int(degree), int(azimuth_order), lz_range, lam, d, delta)


def _checked_data(directions: np.ndarray, gains: np.ndarray, weights: np.ndarray | None,
                  strength: float) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """:func:`fit_gain_model`'s unit directions, gains, weights (mean 1) and strength."""
    d = unit_directions(directions)
    g = np.asarray(gains, dtype=np.float64)
    if g.shape != (len(d),):
        raise ValueError(f"gains has shape {g.shape}; expected ({len(d)},), one per direction")
    if not np.all(np.isfinite(g) & (g > 0)):
        k = int(np.flatnonzero(~(np.isfinite(g) & (g > 0)))[0])
        raise ValueError(out_of_range(f"gains[{k}] = {float(g[k])!r}", "(0, inf)"))
    w = np.ones(len(d)) if weights is None else np.asarray(weights, dtype=np.float64)
    if w.shape != (len(d),):
        raise ValueError(f"weights has shape {w.shape}; expected ({len(d)},)")
    if not np.all(np.isfinite(w) & (w >= 0)) or not np.any(w > 0):
        raise ValueError(f"weights = {w.tolist()}: expected finite values >= 0, not all 0")
    lam = float(strength)
    if not lam >= 0:
        raise ValueError(out_of_range(f"strength = {strength!r}", "[0, inf]"))
    return d, g, w / np.mean(w), lam


def _check_determined(basis: np.ndarray, lz: np.ndarray, used: np.ndarray, degree: int,
                      azimuth_order: int) -> None:
    """Enough lights of weight > 0 (``used``), at enough distinct elevations ``lz``."""
    n = basis.shape[1]
    if used.sum() < n:
        raise ValueError(f"a gain model of degree {degree} in lz and azimuth order "
                         f"{azimuth_order} has {n} coefficients; {int(used.sum())} lights of "
                         f"weight > 0 are too few (it needs >= {n})")
    levels = np.unique(np.round(lz, 6))
    if len(levels) <= degree:
        raise ValueError(f"degree = {degree} in lz needs lights at >= {degree + 1} distinct "
                         f"elevations; the lights of weight > 0 have {len(levels)} (lz = "
                         f"{', '.join(f'{v:.4g}' for v in levels)}); lower the degree")


def _check_rank(a: np.ndarray, lights: int, degree: int, azimuth_order: int) -> None:
    """The weighted, column-scaled design matrix ``a`` has full column rank."""
    sv = np.linalg.svd(a, compute_uv=False)
    if sv[-1] <= 1e-10 * sv[0]:
        rank = int(np.sum(sv > 1e-10 * sv[0]))
        raise ValueError(f"the {lights} light directions determine only {rank} of the "
                         f"{a.shape[1]} functions of the gain model (degree {degree}, azimuth "
                         f"order {azimuth_order}); lower the degree or the azimuth order")


#: How the per-pixel fit uses the gain model: ``none`` (no model: a light not fitted has gain 1,
#: the gains' mean; the default, since on real captures the gains also absorb shadows and model
#: error at grazing light and their trend relit held-out lights worse than 1: docs/rti.md),
#: ``free`` (every fitted light keeps its own gain; the model gives the gain of a light not
#: fitted) or ``smooth`` (the gains are the model's, with residuals regularised by the spread)
GAIN_MODEL_MODES = ("none", "free", "smooth")


@dataclass(frozen=True)
class GainTrend:
    """How :func:`mitsuba_powder.rti.fit_maps` extends its fitted per-light gains to lights it
    did not fit (and, ``smooth``, regularises them): the gains' trend in the light direction.

    Attributes:
        mode: ``none``, ``free`` or ``smooth`` (:data:`GAIN_MODEL_MODES`).
        degree: polynomial degree in ``l_z`` (lowered to what the lights' elevations
            determine).
        azimuth_order: 0-2 (module docstring).
        spread: ``smooth`` only: the relative spread ``tau`` of the lights' gains about the
            trend (e.g. 0.02 = 2 %), > 0; None: the gains are the trend exactly.
    """

    mode: str = "none"
    degree: int = 2
    azimuth_order: int = 0
    spread: float | None = None

    def __post_init__(self) -> None:
        if self.mode not in GAIN_MODEL_MODES:
            raise ValueError(f"gain_model = {self.mode!r} is not valid; choose one of "
                             f"{GAIN_MODEL_MODES}")
        _order("gain_degree", self.degree, MAX_DEGREE)
        _order("gain_azimuth_order", self.azimuth_order, MAX_AZIMUTH_ORDER)
        if self.spread is not None:
            tau = check_range("gain_spread", self.spread, 0.0, math.inf, "()",
                              note="(a relative spread, e.g. 0.02), or None")
            object.__setattr__(self, "spread", tau)
            if self.mode != "smooth":
                raise ValueError(f"gain_spread = {self.spread!r} needs gain_model = 'smooth' "
                                 f"(it is {self.mode!r})")

    def strength(self, raw_weights: np.ndarray | None) -> float:
        """The ridge strength of :func:`fit_gain_model` for the gains' raw weights (the
        Gauss-Newton information of ``ln g_k``): 0 (``free``), inf (``smooth`` without a
        spread) or ``1 / (tau^2 mean(w))``."""
        if self.mode in ("none", "free"):
            return 0.0
        if self.spread is None or raw_weights is None:
            return math.inf
        return 1.0 / (float(self.spread) ** 2 * max(float(np.mean(raw_weights)), 1e-300))

    def fit(self, directions: np.ndarray, gains: np.ndarray,
            information: np.ndarray | None = None) -> GainModel:
        """The gain model of fitted ``gains``, weighted by ``g_k^2 information_k`` (the
        information of ``ln g_k``; all 1 when None), at the highest degree up to
        :attr:`degree` that the lights determine."""
        w = None if information is None else np.maximum(gains**2 * information, 0.0)
        if w is not None and not np.any(w > 0):
            w = None
        strength = self.strength(w)
        for degree in range(self.degree, -1, -1):
            for order in range(self.azimuth_order, -1, -1):
                try:
                    return fit_gain_model(directions, gains, w, degree, order, strength)
                except ValueError:
                    if degree == 0 and order == 0:
                        raise
        raise AssertionError("unreachable")

    def smooth(self, directions: np.ndarray, gains: np.ndarray, information: np.ndarray,
               scale: float) -> np.ndarray:
        """``smooth`` mode: the gains replaced by the model's (trend and regularised
        residuals), their mean restored to ``scale``."""
        model = self.fit(directions, gains, information)
        new = model.gains()
        return new * (scale / float(np.mean(new)))

    def settings(self) -> dict:
        """JSON-ready options (for ``fit.json``)."""
        return {"mode": self.mode, "degree": self.degree,
                "azimuth_order": self.azimuth_order, "spread": self.spread}
