"""Unmixing a reflectance spectrum three ways, on the same rows: the powder model and two
baselines (docs/colour.md, "Unmixing against the baselines").

- ``powder``: the reflectance becomes a single-scattering albedo spectrum through the plugin
  (:func:`~mitsuba_powder.plugin.appearance.albedo_for_reflectance`'s inversion, with the
  other plugin properties given; ``tau_o`` must be given, since a mixture's own tau_o depends
  on the fractions), its uncertainty ``sigma / (dR / d rho)``; then today's
  :func:`~mitsuba_powder.fitting.unmix.unmix` (the plugin's Mie mixture rule from the
  materials' optical constants and radii), whose fractions start a refinement on the
  reflectance itself (the plugin's reflectance of the mixture's albedo), with the baselines'
  weights.
- ``hapke``: Hapke's intimate-mixture rule (:mod:`~mitsuba_powder.fitting.mixing_rules`): each
  pure material's albedo from its own reflectance (an endmember spectrum) by inverting Hapke's
  isotropic scatterer, the mixture's albedo their cross-section weighted mean
  (``f_j / r_j``), back to reflectance by the same scatterer.
- ``km``: two-constant Kubelka-Munk: per-pigment K and S from the masstone and a tint with the
  white (population 1) when tints are given, else ``S = 1`` for every pigment (K/S from the
  masstone alone: what the pure spectra determine).

The baselines' fractions are fitted by weighted least squares on the reflectance with the
package's optimiser (:func:`~mitsuba_powder.fitting.optimise.multistart`: Sobol starts,
batched Levenberg-Marquardt, polish; central-difference Jacobian), in the fraction
parametrisation of :mod:`~mitsuba_powder.fitting.unmix` (amounts relative to population 1),
with the same uncertainties ``(J^T W J)^-1`` and warnings. Hapke's rule fits volume fractions
(``M_j / rho_j``), Kubelka-Munk concentrations by mass (the tints are made by mass); both are
reported by mass and by volume (densities of measurements/README.md). Every method's spectral
RMS is that of its fitted reflectance against the measured one on the same wavelengths.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from .._checks import check_each
from ..plugin import registry
from . import mixing_rules as rules
from .optimise import finite_difference_jacobian, multistart, sobol_starts
from .unmix import _covariance, _fractions, _undetermined, unmix

#: the methods of :func:`unmix_reflectance`
METHODS = ("powder", "hapke", "km")
#: albedo values per round of the powder model's reflectance inversion (as ``albedo``)
GRID = 33
#: nodes of the 0/d quadrature and bisection steps (2^-24 in albedo) with energy = "conserving"
SAMPLES, BISECTION_STEPS = 1024, 24
#: Sobol starts of a baseline's fit (beside the given start)
STARTS = 16
#: a fitted fraction below this is reported as the rule's edge (the material left out)
ABSENT = 1e-4
#: log amounts within +-ln(1e6), as :func:`~mitsuba_powder.fitting.unmix.unmix`
_LOG_AMOUNT = math.log(1e6)


@dataclass
class SpectrumUnmixing:
    """Outcome of :func:`unmix_reflectance`.

    Attributes:
        method: ``powder``, ``hapke``, ``km (masstone + tint)`` or ``km (S = 1)``.
        materials: per population.
        mass_fractions, mass_fraction_errors: by mass (None without densities).
        volume_fractions, volume_fraction_errors: of the solid.
        reflectance: the fitted model's reflectance per wavelength.
        rms: RMS of ``reflectance`` minus the measured reflectance.
        chi2, dof: weighted sum of squared reflectance residuals, degrees of freedom.
        warnings: what the data cannot decide, and where the measurement was clipped.
    """

    method: str
    materials: list[str]
    mass_fractions: np.ndarray | None
    mass_fraction_errors: np.ndarray | None
    volume_fractions: np.ndarray | None
    volume_fraction_errors: np.ndarray | None
    reflectance: np.ndarray
    rms: float
    chi2: float
    dof: int
    warnings: list[str] = field(default_factory=list)


def _rebase(x: np.ndarray, cov: np.ndarray, scale: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Fractions ``y_j = x_j a_j / sum_k x_k a_k`` and their covariance (mass from volume with
    ``a`` the densities, volume from mass with their inverses)."""
    t = x * scale
    s = t.sum()
    y = t / s
    jac = (np.diag(scale) * s - np.outer(t, scale)) / (s * s)
    return y, jac @ cov @ jac.T


def _both_bases(materials: list[str], f: np.ndarray, cov: np.ndarray, by: str) -> tuple:
    """(mass, mass errors, volume, volume errors) of fractions ``f`` given ``by`` mass or
    volume with covariance ``cov``; the other basis None without every density."""
    err = np.sqrt(np.maximum(np.diag(cov), 0.0))
    if not all(m in registry.DENSITIES for m in materials):
        return (f, err, None, None) if by == "mass" else (None, None, f, err)
    d = np.array([registry.DENSITIES[m] for m in materials])
    other, cov_o = _rebase(f, cov, d if by == "volume" else 1.0 / d)
    err_o = np.sqrt(np.maximum(np.diag(cov_o), 0.0))
    return (other, err_o, f, err) if by == "volume" else (f, err, other, err_o)


def _check_spectra(wl, reflectance, sigma, endmembers, parts) -> tuple:
    """Float arrays of the measured spectrum and the endmembers, checked."""
    wl = np.atleast_1d(np.asarray(wl, dtype=float))
    r = np.atleast_1d(np.asarray(reflectance, dtype=float))
    sig = np.atleast_1d(np.asarray(sigma, dtype=float))
    if not (wl.ndim == 1 and len(wl) == len(r) == len(sig)):
        raise ValueError(f"wavelengths, reflectance and sigma differ in length ({len(wl)}, "
                         f"{len(r)}, {len(sig)})")
    if not np.all(np.diff(wl) > 0):
        raise ValueError("the wavelengths must increase")
    at = [f" at {w:g} nm" for w in wl]
    check_each("sigma", sig, 0.0, math.inf, "()", at)
    check_each("the reflectance", r, -math.inf, math.inf, "()", at)
    if not 2 <= len(parts) <= registry.MAX_POPULATIONS:
        raise ValueError(f"unmixing {len(parts)} populations; valid range is "
                         f"[2, {registry.MAX_POPULATIONS}]")
    e = None
    if endmembers is not None:
        e = np.atleast_2d(np.asarray(endmembers, dtype=float))
        if e.shape != (len(parts), len(wl)):
            raise ValueError(f"endmembers of shape {e.shape}: one reflectance spectrum per "
                             f"population on the measured wavelengths, ({len(parts)}, "
                             f"{len(wl)})")
    return wl, r, sig, e


class _FractionProblem:
    """Weighted reflectance residuals of a mixing rule ``model(fractions) -> (W,)`` in the log
    amounts of populations 2..n (:func:`~mitsuba_powder.fitting.unmix._fractions`), batched
    for :func:`~mitsuba_powder.fitting.optimise.multistart`."""

    def __init__(self, model, target: np.ndarray, sigma: np.ndarray, n: int, step: float):
        self.model, self.target, self.sigma = model, target, sigma
        self.lower = np.full(n - 1, -_LOG_AMOUNT)
        self.upper = np.full(n - 1, _LOG_AMOUNT)
        self.jacobian = finite_difference_jacobian(self.residuals, self.lower, self.upper, step)

    def residuals(self, y: np.ndarray) -> np.ndarray:
        return np.array([(self.model(_fractions(np.exp(z))[0]) - self.target) / self.sigma
                         for z in np.atleast_2d(y)])


def _fit_rule(method: str, model, parts, by: str, r: np.ndarray, sig: np.ndarray,
              start: np.ndarray, seed: int | None, step: float = 1e-6) -> SpectrumUnmixing:
    """Fit the fractions (by ``by``) of a mixing rule ``model(fractions) -> reflectance`` to
    the reflectance ``r``: from ``start`` and, unless ``seed`` is None, :data:`STARTS` Sobol
    starts; central differences of ``step`` in the log amounts."""
    materials = [m for m, _, _ in parts]
    n = len(parts)
    if not start[0] > 0:
        raise ValueError(f"population 1 ({materials[0]}) needs a start fraction > 0")
    if len(r) <= n - 1:
        raise ValueError(f"{len(r)} wavelengths for {n - 1} free fractions: the fit is not "
                         "determined; give more wavelengths or fewer populations")
    problem = _FractionProblem(model, r, sig, n, step)
    z0 = np.clip(np.log(np.maximum(start[1:] / start[0], 1e-6)), problem.lower, problem.upper)
    starts = z0[None] if seed is None else np.vstack(
        [z0, sobol_starts(problem.lower, problem.upper, STARTS, seed)])
    best = multistart(problem, starts, polish_count=2)
    z = best.y
    res, jac = problem.jacobian(z[None])
    warnings: list[str] = []
    cov_z = _covariance(jac[0], warnings)
    a = np.exp(z)
    f, g = _fractions(a)
    ga = g * a[None, :]
    with np.errstate(invalid="ignore"):  # a singular fit: inf * 0, reported by the callers
        cov_f = ga @ cov_z @ ga.T
    absent = [m for m, v in zip(materials, f) if v < ABSENT]
    if absent:
        warnings.append(f"the fraction of {', '.join(absent)} is below {ABSENT:g}: the rule "
                        "fits best at the edge of what it can mix (without it), where the "
                        "uncertainties are not meaningful")
    if best.agreeing < 2 and len(starts) > 1:
        warnings.append(f"{best.agreeing} start(s) reached the best cost: the optimum may "
                        "not be global")
    warnings += _undetermined(materials, f, np.sqrt(np.maximum(np.diag(cov_f), 0.0)), cov_z,
                              False)
    fitted = model(f)
    return SpectrumUnmixing(method, materials, *_both_bases(materials, f, cov_f, by), fitted,
                            float(np.sqrt(np.mean((fitted - r) ** 2))),
                            float(res[0] @ res[0]), len(r) - (n - 1), warnings)


def _volume_start(parts, by: str) -> np.ndarray:
    """Start volume fractions (:func:`~mitsuba_powder.plugin.grains.volume_fractions`)."""
    from ..plugin.grains import volume_fractions

    return np.array(volume_fractions([(m, f) for m, f, _ in parts], by))


def _mass_start(parts, by: str) -> np.ndarray:
    """Start fractions by mass (by volume where a material has no density: a start only)."""
    materials = [m for m, _, _ in parts]
    if by == "mass":
        return np.array([v for _, v, _ in parts], dtype=float)
    f = _volume_start(parts, by)
    if not all(m in registry.DENSITIES for m in materials):
        return f
    w = f * np.array([registry.DENSITIES[m] for m in materials])
    return w / w.sum()


def unmix_hapke(wl, reflectance, sigma, endmembers, parts, by: str = "volume",
                geometry="0:d", seed: int = 0) -> SpectrumUnmixing:
    """Hapke's intimate-mixture unmixing of a reflectance spectrum (module docstring).

    Args:
        wl, reflectance, sigma: (W,) increasing wavelengths (nm), the mixture's reflectance at
            ``geometry`` and its standard uncertainties.
        endmembers: (n, W) each pure material's reflectance at the same geometry.
        parts: ``(material, start fraction, radius um)`` per population (the radii weight the
            cross-sections); ``by``: how the start fractions are given.
        geometry: ``"0:d"`` or ``(theta_i, theta_o)`` degrees.
    """
    wl, r, sig, e = _check_spectra(wl, reflectance, sigma, endmembers, parts)
    if e is None:
        raise ValueError("Hapke's rule needs the endmembers' reflectance spectra")
    w = rules.hapke_albedo(e, geometry)
    radii = np.array([float(x) for _, _, x in parts])

    def model(f):
        return rules.hapke_reflectance(rules.hapke_mixture_albedo(w, f, radii), geometry)

    return _fit_rule("hapke", model, parts, "volume", r, sig, _volume_start(parts, by), seed)


def unmix_km(wl, reflectance, sigma, endmembers, parts, by: str = "volume", tints=None,
             seed: int = 0) -> SpectrumUnmixing:
    """Two-constant Kubelka-Munk unmixing of a reflectance spectrum (module docstring).

    Args:
        wl, reflectance, sigma, endmembers, parts, by: as :func:`unmix_hapke` (the
            endmembers are the masstones).
        tints: None (``S = 1`` for every pigment), or per population 2..n a pair
            ``(reflectance (W,), mass fraction of the pigment in population 1)``: a tint of
            that pigment with the white, population 1.
    """
    wl, r, sig, e = _check_spectra(wl, reflectance, sigma, endmembers, parts)
    if e is None:
        raise ValueError("Kubelka-Munk needs the endmembers' (masstones') reflectance spectra")
    ratio = rules.km_ratio(e)
    if tints is None:
        k, s, method = ratio, np.ones_like(ratio), "km (S = 1)"
    else:
        if len(tints) != len(parts) - 1:
            raise ValueError(f"{len(tints)} tints for {len(parts) - 1} pigments: give one "
                             "tint with the white (population 1) per population 2..n")
        k, s = ratio.copy(), np.ones_like(ratio)
        for j, (tint, c) in enumerate(tints, start=1):
            tint = np.asarray(tint, dtype=float)
            if tint.shape != (len(wl),):
                raise ValueError(f"the tint of {parts[j][0]} has {tint.shape} values for "
                                 f"{len(wl)} wavelengths")
            k[j], s[j] = rules.km_constants(e[j], tint, c, ratio[0])
        method = "km (masstone + tint)"

    def model(c):
        return rules.km_mixture_reflectance(c, k, s)

    return _fit_rule(method, model, parts, "mass", r, sig, _mass_start(parts, by), seed)


class PowderReflectance:
    """The plugin's reflectance at a geometry as a function of albedo spectra, with the other
    plugin properties fixed: the engine of ``albedo_for_reflectance`` (many albedo sets in one
    evaluation), or, with ``energy = "conserving"`` (whose normalisation needs a spatially
    uniform albedo, which that engine's per-set albedo texture is not), one plugin instance per
    albedo spectrum and the 0/d quadrature of
    :func:`~mitsuba_powder.plugin.appearance.powder_colour` (:data:`SAMPLES` nodes)."""

    def __init__(self, wl: np.ndarray, geometry, properties: dict):
        from ..plugin.appearance import (
            _check_albedo_inputs,
            _geometry,
            _reflectance_of_albedo,
            _visible_wavelengths,
        )

        if "tau_o" not in properties:
            raise ValueError("the powder model's reflectance of a mixture needs tau_o given (a "
                             "property): the mixture's own tau_o depends on its fractions")
        _check_albedo_inputs(wl, np.zeros(len(wl)), GRID, properties)
        self.kind, ti, to = _geometry(geometry)
        self.wl = np.asarray(wl, dtype=float)
        self.properties = dict(properties)
        self.conserving = properties.get("energy") == "conserving"
        if self.conserving:
            if self.kind != "0:d":
                raise ValueError(f"geometry {geometry}: with energy = \"conserving\" the "
                                 "powder model's reflectance is computed for 0:d only")
            _visible_wavelengths(self.wl)
        else:
            self._engine = _reflectance_of_albedo(self.kind, ti, to, self.wl, GRID, properties)

    def _conserving(self, albedo: np.ndarray) -> np.ndarray:
        """(W,) 0/d reflectance of one albedo spectrum, by its own plugin instance."""
        import mitsuba as mi

        from ..plugin.appearance import _groups, _reflectance, _spectral_variant
        from ..variants import use_variant

        # (an irregular spectrum refuses all zeros: 1e-12 reflects nothing measurable)
        values = np.clip(albedo, 1e-12, 1.0)
        spectrum = {"type": "irregular", "wavelengths": ", ".join(map(repr, self.wl.tolist())),
                    "values": ", ".join(map(repr, values.tolist()))}
        with use_variant(_spectral_variant()):
            bsdf = mi.load_dict({"type": "powder", **self.properties, "albedo": spectrum})
            return _reflectance(bsdf, _groups(self.wl), len(self.wl), SAMPLES)

    def __call__(self, albedo: np.ndarray) -> np.ndarray:
        """(k, W) reflectance of (k, W) albedo spectra (any k)."""
        from ..plugin.brf import batch_variant
        from ..variants import use_variant

        a = np.atleast_2d(np.asarray(albedo, dtype=float))
        if self.conserving:
            return np.array([self._conserving(row) for row in a])
        out = []
        with use_variant(batch_variant(self.wl)):
            for i in range(0, len(a), GRID):
                block = np.zeros((GRID, len(self.wl)))
                block[:len(a[i:i + GRID])] = a[i:i + GRID]
                out.append(self._engine(block)[:len(a[i:i + GRID])])
        return np.concatenate(out)

    def albedo(self, target: np.ndarray) -> tuple[np.ndarray, np.ndarray, int]:
        """(albedo, dR/d albedo, clipped): the albedo reproducing ``target`` (the reflectance
        grows with it: :func:`~mitsuba_powder.plugin.appearance._solve_albedo`'s refined grid,
        or bisection where each evaluation is a plugin instance), the slope there, and how
        many targets lay outside the reachable range (read as its nearest end)."""
        from ..plugin.appearance import _solve_albedo
        from ..plugin.brf import batch_variant
        from ..variants import use_variant

        low, high = self(np.stack([np.zeros(len(self.wl)), np.ones(len(self.wl))]))
        clipped = int(np.sum((target < low) | (target > high)))
        t = np.clip(target, low, high)
        if self.conserving:
            lo, hi = np.zeros(len(t)), np.ones(len(t))
            for _ in range(BISECTION_STEPS):
                mid = 0.5 * (lo + hi)
                above = self(mid[None])[0] > t
                lo, hi = np.where(above, lo, mid), np.where(above, mid, hi)
            albedo = 0.5 * (lo + hi)
        else:
            with use_variant(batch_variant(self.wl)):
                albedo = _solve_albedo(self._engine, t, self.wl, GRID, self.kind)
        h = 1e-3
        lo, hi = np.clip(albedo - h, 0.0, 1.0), np.clip(albedo + h, 0.0, 1.0)
        r_lo, r_hi = self(np.stack([lo, hi]))
        return albedo, (r_hi - r_lo) / (hi - lo), clipped


def unmix_powder(wl, reflectance, sigma, parts, by: str = "volume", geometry="0:d",
                 properties: dict | None = None, seed: int = 0) -> SpectrumUnmixing:
    """The powder model's unmixing of a reflectance spectrum (module docstring): today's
    :func:`~mitsuba_powder.fitting.unmix.unmix` on the albedo the plugin inverts from the
    reflectance (its uncertainty ``sigma / (dR / d rho)``), then the fractions refined on the
    reflectance itself, with the weights of the baselines (the inversion is steep where the
    albedo nears 1, and a linearised weight there is not the reflectance's).

    Args:
        wl, reflectance, sigma, parts, by, geometry: as :func:`unmix_hapke` (no endmembers:
            the materials' optical constants and the radii make the model).
        properties: the plugin's other properties (``tau_o`` required; e.g. ``energy``,
            ``extinction``, ``g``).
        seed: of the Sobol scrambling of the albedo's unmixing.
    """
    from ..plugin.grains import mixture_albedo, mixture_properties

    wl, r, sig, _ = _check_spectra(wl, reflectance, sigma, None, parts)
    engine = PowderReflectance(wl, geometry, dict(properties or {}))
    albedo, slope, clipped = engine.albedo(r)
    u = unmix(wl, albedo, sig / np.maximum(slope, 1e-6), parts, by=by, seed=seed)

    def model(f: np.ndarray) -> np.ndarray:
        mix = [(m, float(v), x) for (m, _, x), v in zip(parts, f)]
        return engine(mixture_albedo(mixture_properties(mix, "volume"), wl)[0][None])[0]

    # the plugin computes in float32: differences of 1e-3 in the log amounts
    out = _fit_rule("powder", model, parts, "volume", r, sig, u.fractions, None, 1e-3)
    if clipped:
        out.warnings.append(f"{clipped} reflectance value(s) outside what albedos 0-1 give "
                            "were read as the nearest reachable one by the albedo inversion "
                            "(the start)")
    return out
