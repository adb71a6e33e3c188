"""Other people's mixing rules for pigment mixtures, the baselines of unmixing
(:mod:`mitsuba_powder.fitting.unmix_baselines`, docs/colour.md, "Unmixing against the
baselines").

Like :mod:`mitsuba_powder.fitting.baselines`, these are NumPy functions written from the
published formulas; they are not part of the powder plugin.

**Hapke's intimate-mixture rule** (Hapke 2012, *Theory of Reflectance and Emittance
Spectroscopy*, 2nd ed., ch. 10, "mixtures"; used for unmixing by Mustard & Pieters 1989,
JGR 94, 13619): the single-scattering albedo of an intimate mixture is the cross-section
weighted mean of the components' albedos,
``w = sum_j (M_j / (rho_j D_j)) Q_S,j / sum_j (M_j / (rho_j D_j)) Q_E,j`` with ``M_j`` the mass
fraction, ``rho_j`` the solid density and ``D_j`` the grain diameter; with ``Q_E = 1`` (grains
large against the wavelength, diffraction not counted as scattering) and ``Q_S,j = w_j``. As
``M_j / rho_j`` is proportional to the volume fraction ``f_j``, the weights are ``f_j / r_j``
(:func:`hapke_mixture_albedo`). The components' albedos ``w_j`` come from their own
reflectance through Hapke's isotropic scatterer with the first approximation of Chandrasekhar's
H function, ``H(x) = (1 + 2x) / (1 + 2 gamma x)``, ``gamma = sqrt(1 - w)`` (Hapke 1981,
JGR 86, 3039; Hapke 2012, ch. 8): the directional-hemispherical reflectance
``r_h(mu0) = 1 - gamma H(mu0) = (1 - gamma) / (1 + 2 gamma mu0)`` (geometry ``0:d``, inverted
in closed form) and the bidirectional reflectance factor
``REFF = pi r / mu0 = (w / 4) H(mu0) H(mu) / (mu0 + mu)`` (a pair ``(theta_i, theta_o)``,
inverted by bisection: it grows with ``w``). No opposition effect, isotropic phase function.

**Two-constant Kubelka-Munk** (Kubelka & Munk 1931; Duncan 1940, Proc. Phys. Soc. 52, 390,
for the mixture rule; the colorant formulation of Allen 1980, in *Color Theory and Colorant
Formulation*): an opaque layer reflects ``R_inf = 1 + K/S - sqrt((K/S)^2 + 2 K/S)``
(:func:`km_reflectance`), inverted by ``K/S = (1 - R)^2 / (2 R)`` (:func:`km_ratio`); a
mixture of pigments at concentrations ``c_j`` has ``K = sum c_j K_j`` and ``S = sum c_j S_j``
(:func:`km_mixture_reflectance`). Only ``K/S`` of a pure pigment follows from its masstone;
the two constants separately need a second swatch, a tint of the pigment with a white of known
``K_w / S_w`` at mass fraction ``c``, with the white's ``S_w = 1`` as the unit
(:func:`km_constants`). Without tints, ``S_j = 1`` for every pigment (the one-constant
reading): the mixture's ``K/S`` is then ``sum c_j (K/S)_j``.
"""

from __future__ import annotations

import math

import numpy as np

from .._checks import check_range

#: the smallest S of :func:`km_constants` (relative to the white's S = 1)
S_FLOOR = 1e-6
#: bisection steps of the bidirectional Hapke inversion (2^-60: to float64 precision)
_BISECTION_STEPS = 60


def hapke_geometry(geometry) -> tuple[float, float] | None:
    """None for ``"0:d"``, else ``(mu0, mu)`` of ``"THETA_I:THETA_O"`` or a pair in degrees.

    Raises:
        ValueError: a geometry that is neither (the message of
            :func:`mitsuba_powder.plugin.appearance._geometry`).
    """
    from ..plugin.appearance import _geometry

    kind, ti, to = _geometry(geometry)
    if kind == "0:d":
        return None
    return math.cos(math.radians(ti)), math.cos(math.radians(to))


def _h(x: float, gamma: np.ndarray) -> np.ndarray:
    """Hapke's (1981) first approximation of Chandrasekhar's H function."""
    return (1.0 + 2.0 * x) / (1.0 + 2.0 * gamma * x)


def hapke_reflectance(w, geometry="0:d") -> np.ndarray:
    """The reflectance of a half-space of isotropic scatterers of single-scattering albedo ``w``
    (in [0, 1]): ``0:d`` the directional-hemispherical reflectance at normal incidence
    ``(1 - gamma) / (1 + 2 gamma)``; a pair ``(theta_i, theta_o)`` the bidirectional
    reflectance factor ``(w / 4) H(mu0) H(mu) / (mu0 + mu)``."""
    w = np.asarray(w, dtype=float)
    gamma = np.sqrt(np.clip(1.0 - w, 0.0, 1.0))
    g = hapke_geometry(geometry)
    if g is None:
        return (1.0 - gamma) / (1.0 + 2.0 * gamma)
    mu0, mu = g
    return w / 4.0 * _h(mu0, gamma) * _h(mu, gamma) / (mu0 + mu)


def hapke_albedo(reflectance, geometry="0:d") -> np.ndarray:
    """The inverse of :func:`hapke_reflectance`: the albedo ``w`` of each reflectance.
    ``0:d``: ``gamma = (1 - r) / (1 + 2 r)``, ``w = 1 - gamma^2``; a pair: bisection in
    ``w`` (the reflectance factor grows with it).

    Raises:
        ValueError: a reflectance outside what albedos 0 to 1 give (``[0, 1]`` for ``0:d``),
            naming the first such value.
    """
    r = np.asarray(reflectance, dtype=float)
    g = hapke_geometry(geometry)
    top = 1.0 if g is None else float(hapke_reflectance(1.0, geometry))
    bad = ~(np.isfinite(r) & (r >= 0.0) & (r <= top))
    if np.any(bad):
        raise ValueError(f"reflectance {r[bad].ravel()[0]:g} is out of range; valid range is "
                         f"[0, {top:.6g}] (Hapke's isotropic scatterer, albedo 0-1, "
                         f"geometry {geometry})")
    if g is None:
        gamma = (1.0 - r) / (1.0 + 2.0 * r)
        return 1.0 - gamma * gamma
    lo, hi = np.zeros_like(r), np.ones_like(r)
    for _ in range(_BISECTION_STEPS):
        mid = 0.5 * (lo + hi)
        above = hapke_reflectance(mid, geometry) > r
        hi, lo = np.where(above, mid, hi), np.where(above, lo, mid)
    return 0.5 * (lo + hi)


def hapke_mixture_albedo(albedos, volume_fractions, radii) -> np.ndarray:
    """Hapke's intimate mixture: ``w = sum_j (f_j / r_j) w_j / sum_j (f_j / r_j)``.

    Args:
        albedos: (n, W) the components' single-scattering albedos.
        volume_fractions: (n,) volume fractions of the solid (``M_j / rho_j``, normalised).
        radii: (n,) grain radii (any one unit).

    Raises:
        ValueError: shapes that disagree, a negative fraction, fractions summing to 0, or a
            radius that is not positive.
    """
    w = np.atleast_2d(np.asarray(albedos, dtype=float))
    f = np.asarray(volume_fractions, dtype=float).ravel()
    r = np.asarray(radii, dtype=float).ravel()
    if not (len(w) == len(f) == len(r)):
        raise ValueError(f"{len(w)} albedo spectra, {len(f)} fractions and {len(r)} radii: "
                         "give one of each per component")
    if np.any(f < 0.0) or not f.sum() > 0.0:
        raise ValueError(f"volume fractions {f.tolist()}: each must be >= 0, not all 0")
    for value in r:
        check_range("radius", value, 0.0, closed="()")
    u = f / r
    return (u[:, None] * w).sum(axis=0) / u.sum()


def km_reflectance(k_over_s) -> np.ndarray:
    """Kubelka-Munk's reflectance of an opaque layer, ``R_inf = 1 + a - sqrt(a^2 + 2a)`` with
    ``a = K/S >= 0`` (written ``1 / (1 + a + sqrt(a^2 + 2a))`` to keep its precision where
    ``a`` is large)."""
    a = np.asarray(k_over_s, dtype=float)
    return 1.0 / (1.0 + a + np.sqrt(a * a + 2.0 * a))


def km_ratio(reflectance) -> np.ndarray:
    """``K/S = (1 - R)^2 / (2 R)`` of an opaque layer of reflectance ``R`` in (0, 1].

    Raises:
        ValueError: a reflectance outside (0, 1], naming the first such value.
    """
    r = np.asarray(reflectance, dtype=float)
    bad = ~(np.isfinite(r) & (r > 0.0) & (r <= 1.0))
    if np.any(bad):
        raise ValueError(f"reflectance {r[bad].ravel()[0]:g} is out of range; valid range is "
                         "(0, 1] (Kubelka-Munk's opaque layer)")
    return (1.0 - r) ** 2 / (2.0 * r)


def km_constants(masstone, tint, tint_fraction: float, white_ratio) -> tuple[np.ndarray,
                                                                             np.ndarray]:
    """A pigment's (K, S) from its masstone reflectance and that of a tint with a white
    (two-constant Kubelka-Munk, the white's ``S_w = 1`` as the unit).

    With ``m = (K/S)`` of the masstone, ``t = (K/S)`` of the tint (mass fraction ``c`` of the
    pigment) and ``k_w = (K/S)`` of the white: ``t = (c K + (1 - c) k_w) / (c S + 1 - c)`` and
    ``K = m S`` give ``S = (1 - c)(t - k_w) / (c (m - t))``, kept above :data:`S_FLOOR` (a
    tint as white as the white, ``t <= k_w``, means a pigment that neither scatters nor absorbs
    beside it). Where the pigment absorbs no more than its tint (``m - t <= 1e-9 max(m, 1)``;
    e.g. where neither absorbs) the two swatches cannot separate K from S and ``S = 1`` is
    taken (K = m).

    Args:
        masstone: (W,) reflectance of the pure pigment.
        tint: (W,) reflectance of the tint.
        tint_fraction: the pigment's mass fraction in the tint, in (0, 1).
        white_ratio: (W,) ``K/S`` of the white.

    Returns:
        (K, S), each (W,), ``S > 0``.
    """
    c = check_range("tint_fraction", tint_fraction, 0.0, 1.0, closed="()")
    m, t = km_ratio(masstone), km_ratio(tint)
    kw = np.asarray(white_ratio, dtype=float)
    determined = m - t > 1e-9 * np.maximum(m, 1.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        s = np.where(determined, np.maximum((1.0 - c) * (t - kw) / (c * (m - t)), S_FLOOR),
                     1.0)
    return m * s, s


def km_mixture_reflectance(concentrations, k, s) -> np.ndarray:
    """Two-constant Kubelka-Munk: ``R_inf`` of ``K = sum c_j K_j``, ``S = sum c_j S_j``.

    Args:
        concentrations: (n,) the pigments' concentrations (>= 0, not all 0; mass fractions
            when the constants come from tints made by mass).
        k, s: (n, W) the pigments' constants (``S > 0``).
    """
    c = np.asarray(concentrations, dtype=float).ravel()
    k, s = np.atleast_2d(k), np.atleast_2d(s)
    if not (len(c) == len(k) == len(s)):
        raise ValueError(f"{len(c)} concentrations for {len(k)} K and {len(s)} S spectra")
    if np.any(c < 0.0) or not c.sum() > 0.0:
        raise ValueError(f"concentrations {c.tolist()}: each must be >= 0, not all 0")
    return km_reflectance((c[:, None] * k).sum(axis=0) / (c[:, None] * s).sum(axis=0))
