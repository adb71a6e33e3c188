"""Independent double-precision reference for the grain models of docs/model.md ("Grain models
(property `grains`)"): effective-medium mixing (Bruggeman, Maxwell Garnett), the Mie albedo of
an agglomerate, Hapke's equivalent-slab albedo (one or two populations) and the crystallite size
parameter. Written from docs/model.md only, with NumPy and miepython (which uses ``n - ik``).

Units: wavelengths in nanometres (``wl_nm``) as in Mitsuba, every length in micrometres.
Complex indices follow docs/model.md's ``n + ik`` convention (``k >= 0`` absorbs).
"""

from __future__ import annotations

import miepython
import numpy as np

#: The effective-medium rules of the ``mixing`` property
MIXINGS = ("bruggeman", "maxwell_garnett")


def bruggeman_eps(eps_i: complex, f: float) -> complex:
    """Bruggeman effective permittivity (dimensionless) of a fraction ``f`` (volume, 0 < f <= 1)
    of material with permittivity ``eps_i`` in air (eps = 1).

    Solves ``2 eps^2 - b eps - eps_i = 0``, ``b = (3 f - 1) eps_i + (2 - 3 f)`` and keeps the
    root with ``Im(eps) >= 0``. Taken here as the root with the larger imaginary part (the one
    continuously connected to ``eps_i`` at f = 1 and to 1 at f -> 0; at f = 1 with Re(eps_i) < 0
    the other root, -1/2, also has Im = 0). When both roots are real (``eps_i`` real) the one with
    ``Re(eps) > 0`` (their product is ``-eps_i / 2 < 0``, so exactly one is positive).
    """
    eps_i = complex(eps_i)
    b = (3.0 * f - 1.0) * eps_i + (2.0 - 3.0 * f)
    disc = np.sqrt(complex(b * b + 8.0 * eps_i))
    r1, r2 = (b + disc) / 4.0, (b - disc) / 4.0
    if r1.imag == r2.imag:  # both real
        return complex(r1 if r1.real > r2.real else r2)
    return complex(r1 if r1.imag > r2.imag else r2)


def maxwell_garnett_eps(eps_i: complex, f: float) -> complex:
    """Maxwell Garnett effective permittivity (dimensionless) of inclusions of permittivity
    ``eps_i`` at volume fraction ``f`` (0 < f <= 1) in air:
    ``eps = (1 + 2 f beta) / (1 - f beta)``, ``beta = (eps_i - 1) / (eps_i + 2)``."""
    eps_i = complex(eps_i)
    beta = (eps_i - 1.0) / (eps_i + 2.0)
    return (1.0 + 2.0 * f * beta) / (1.0 - f * beta)


def effective_index(index: complex, f: float, mixing: str = "bruggeman") -> complex:
    """Effective refractive index ``sqrt(eps)`` (Im >= 0, dimensionless) of an agglomerate of
    fill ``f`` of a material with index ``index = n + ik``, by the rule ``mixing``."""
    eps_i = complex(index) ** 2
    if mixing == "bruggeman":
        eps = bruggeman_eps(eps_i, f)
    elif mixing == "maxwell_garnett":
        eps = maxwell_garnett_eps(eps_i, f)
    else:
        raise ValueError(f"mixing = {mixing!r}; valid values are {MIXINGS}")
    m = complex(np.sqrt(complex(eps)))
    if m.imag < 0.0:  # not reached for Im(eps) >= 0 (principal root), kept as a guard
        m = -m
    return m


def mie_efficiencies(index: complex, x: float) -> tuple[float, float]:
    """(Q_ext, Q_sca) of a sphere of index ``n + ik`` in air at size parameter ``x``
    (dimensionless), from miepython (which takes ``n - ik``)."""
    qext, qsca = miepython.efficiencies_mx(np.conj(complex(index)), float(x))[:2]
    return float(qext), float(qsca)


def agglomerate_albedo(index: complex, agglomerate_radius_um: float, fill: float,
                       wl_nm: float, mixing: str = "bruggeman") -> float:
    """Single-scattering albedo Q_sca / Q_ext (dimensionless) of an agglomerate: a sphere of
    radius ``agglomerate_radius_um`` (um) with the effective index of fill ``fill`` of the
    material ``index``, at the wavelength ``wl_nm`` (nm)."""
    m = effective_index(index, fill, mixing)
    x = 2.0 * np.pi * agglomerate_radius_um / (wl_nm * 1e-3)
    qext, qsca = mie_efficiencies(m, x)
    return qsca / qext


def sphere_albedo(index: complex, radius_um: float, wl_nm: float) -> float:
    """Isolated-sphere Mie albedo Q_sca / Q_ext (dimensionless), radius in um, wavelength nm."""
    qext, qsca = mie_efficiencies(index, 2.0 * np.pi * radius_um / (wl_nm * 1e-3))
    return qsca / qext


def slab_albedo(index: complex, diameter_um: float, wl_nm: float) -> float:
    """Hapke's equivalent-slab albedo (dimensionless) of a grain of size ``diameter_um`` (um,
    D = 2 r) and index ``n + ik`` (n > 1) at the wavelength ``wl_nm`` (nm), as docs/model.md:

    ``rho = S_e + (1 - S_e) (1 - S_i) Theta / (1 - S_i Theta)``, ``Theta = exp(-alpha <D>)``,
    ``alpha = 4 pi k / lam``, ``<D> = (2/3) [n^2 - (1/n) (n^2 - 1)^(3/2)] D``.
    """
    n, k = float(complex(index).real), float(complex(index).imag)
    if not n > 1.0:
        raise ValueError(f"slab albedo needs n > 1, got n = {n}")
    lam = wl_nm * 1e-3
    alpha = 4.0 * np.pi * k / lam
    d_mean = (2.0 / 3.0) * (n * n - (n * n - 1.0) ** 1.5 / n) * diameter_um
    theta = np.exp(-alpha * d_mean)
    r0 = ((n - 1.0) ** 2 + k * k) / ((n + 1.0) ** 2 + k * k)
    s_e = 0.0587 + 0.8543 * r0 + 0.0870 * r0 * r0
    s_i = 1.0 - (0.9413 - 0.8543 * r0 - 0.0870 * r0 * r0) / n
    return float(s_e + (1.0 - s_e) * (1.0 - s_i) * theta / (1.0 - s_i * theta))


def slab_albedo_two(index: complex, r1: float, r2: float, f2: float, wl_nm: float) -> float:
    """Equivalent-slab albedo (dimensionless) of two populations of radii ``r1``, ``r2`` (um,
    D_j = 2 r_j) with volume fraction ``f2`` of the second, at ``wl_nm`` (nm): docs/model.md's
    mixing formula with ``Q_ext = 1, Q_sca = rho_j`` and weights ``f_j / r_j``."""
    w1, w2 = (1.0 - f2) / r1, f2 / r2
    rho1 = slab_albedo(index, 2.0 * r1, wl_nm)
    rho2 = slab_albedo(index, 2.0 * r2, wl_nm)
    return (w1 * rho1 + w2 * rho2) / (w1 + w2)


def crystallite_size_parameter(index: complex, radius_um: float, wl_nm: float) -> float:
    """Size parameter ``2 pi r |n + ik| / lam`` (dimensionless) of a crystallite of radius
    ``radius_um`` (um) at ``wl_nm`` (nm): mixing rules hold below about 0.5."""
    return float(2.0 * np.pi * radius_um * abs(complex(index)) / (wl_nm * 1e-3))
