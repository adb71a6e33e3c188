"""Independent double-precision reference for the grains of docs/model.md: the Mie efficiencies
and albedo of spheres (one or two populations), effective-medium mixing (Bruggeman, Maxwell
Garnett) and the Mie albedo of an agglomerate, Hapke's equivalent-slab albedo (one or two
populations), the crystallite size parameter, the extrapolation ratio tau_o from Fresnel
("Extrapolation ratio tau_o") and an independent reader of the bundled optical constants.
Written from docs/model.md only, with NumPy, SciPy and miepython (which uses ``n - ik``).

tau_o is integrated twice, by genuinely different methods, each the reference of its own
tests: :func:`tau_o_fresnel` by adaptive quadrature split at the critical angle (the
reference fit's, checked against docs/model.md's values), :func:`tau_o_trapezoid` by a
trapezoid rule on a uniform grid of 2e6 intervals (the plugin's tau_o is checked against it
to 1e-6). Both use the one Fresnel reflectance :func:`fresnel_inside`.

Units: wavelengths in nanometres (``wl_nm``) as in Mitsuba, every length in micrometres.
Complex indices follow docs/model.md's ``n + ik`` convention (``k >= 0`` absorbs).
"""

from __future__ import annotations

import math
from pathlib import Path

import miepython
import numpy as np
from scipy import integrate

#: The optical constants bundled with the package (refractiveindex.info YAML tables)
OPTICAL_CONSTANTS = Path(__file__).resolve().parents[2] / "python" / "mitsuba_powder" / "data" / \
    "optical_constants"

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


def mie_albedo(index: complex, radius_um: float, wl_nm: float, radius2: float | None = None,
               fraction2: float = 0.0) -> float:
    """Mie albedo (dimensionless) of spheres of index ``n + ik`` and radius ``radius_um`` (um) at
    the wavelength ``wl_nm`` (nm): Q_sca / Q_ext of the isolated sphere, or, with a second
    population of radius ``radius2`` (um) and volume fraction ``fraction2``, docs/model.md's
    mixing ``(w1 Q_sca1 + w2 Q_sca2) / (w1 Q_ext1 + w2 Q_ext2)``, ``w_j = f_j / r_j``."""
    x1 = 2 * np.pi * radius_um / (wl_nm * 1e-3)
    e1, s1 = mie_efficiencies(index, x1)
    if radius2 is None:
        return s1 / e1
    e2, s2 = mie_efficiencies(index, 2 * np.pi * radius2 / (wl_nm * 1e-3))
    w1, w2 = (1 - fraction2) / radius_um, fraction2 / radius2
    return (w1 * s1 + w2 * s2) / (w1 * e1 + w2 * e2)


def mixture_albedo(populations: list[tuple[complex, float, float]], wl_nm: float) -> float:
    """Mie albedo (dimensionless) of a mixture of populations ``(index n + ik, radius um, volume
    fraction of the solid)`` at the wavelength ``wl_nm`` (nm), docs/model.md's "Several
    materials": ``sum_j (f_j / r_j) Q_sca,j / sum_j (f_j / r_j) Q_ext,j``, each Q by miepython
    with that population's index."""
    num = den = 0.0
    for index, radius, fraction in populations:
        qext, qsca = mie_efficiencies(index, 2 * np.pi * radius / (wl_nm * 1e-3))
        num += fraction / radius * qsca
        den += fraction / radius * qext
    return num / den


def bruggeman_mixture(indices: list[complex], fractions: list[float]) -> complex:
    """Bruggeman effective index ``sqrt(eps)`` of materials ``n + ik`` at volume fractions summing
    to 1 (docs/model.md, "The mixture's index for tau_o"): the roots of the polynomial
    ``sum_j f_j (eps_j - eps) prod_{k != j} (eps_k + 2 eps)`` by ``numpy.roots``, the one with
    ``Im(eps) >= 0`` and ``Re(eps) > 0`` nearest the volume average of the ``eps_j`` (a method
    independent of the plugin's Newton iteration)."""
    eps = [complex(m) ** 2 for m in indices]
    poly = np.zeros(1, dtype=complex)
    for j, (e_j, f_j) in enumerate(zip(eps, fractions)):
        term = np.array([f_j * -1.0, f_j * e_j], dtype=complex)  # f_j (e_j - eps)
        for k, e_k in enumerate(eps):
            if k != j:
                term = np.polymul(term, np.array([2.0, e_k], dtype=complex))
        poly = np.polyadd(poly, term)
    roots = np.roots(poly)
    ok = [r for r in roots if r.imag >= -1e-12 * abs(r) and r.real > 0]
    mean = sum(f * e for f, e in zip(fractions, eps))
    root = min(ok, key=lambda r: abs(r - mean))
    return complex(np.sqrt(complex(root)))


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


def fresnel_inside(cos_theta: np.ndarray, n: float) -> np.ndarray:
    """Unpolarised Fresnel reflectance for light inside a medium of real index ``n`` hitting
    the boundary with air at incidence ``theta`` (1 beyond the critical angle).

    Args:
        cos_theta: cosine of the incidence angle inside the medium, in [0, 1].
        n: real refractive index of the medium (>= 1).

    Returns:
        R(theta), same shape as ``cos_theta``.
    """
    cos_i = np.asarray(cos_theta, dtype=np.float64)
    sin_t2 = n * n * (1.0 - cos_i * cos_i)  # Snell: sin(theta_t) = n sin(theta_i)
    total = sin_t2 >= 1.0
    cos_t = np.sqrt(np.clip(1.0 - sin_t2, 0.0, 1.0))
    with np.errstate(divide="ignore", invalid="ignore"):
        r_s = (n * cos_i - cos_t) / (n * cos_i + cos_t)
        r_p = (cos_i - n * cos_t) / (cos_i + n * cos_t)
    r = 0.5 * (r_s * r_s + r_p * r_p)
    return np.where(total, 1.0, np.nan_to_num(r, nan=1.0))


def _rbar(c1: float, c2: float) -> float:
    """Rbar = (3 C2 + 2 C1) / (3 C2 - 2 C1 + 2) (docs/model.md Eq. 11, Zhu, Pine and Weitz 1991)
    from the moments C_1, C_2 of the Fresnel reflectance."""
    return (3.0 * c2 + 2.0 * c1) / (3.0 * c2 - 2.0 * c1 + 2.0)


def _tau_o(rbar: float) -> float:
    """tau_o = (2/3) (1 + Rbar) / (1 - Rbar) (dimensionless)."""
    return (2.0 / 3.0) * (1.0 + rbar) / (1.0 - rbar)


def fresnel_moments(n: float) -> tuple[float, float]:
    """C_1 and C_2 of docs/model.md: ``C_j = int_0^{pi/2} R(theta) cos^j(theta) sin(theta) dtheta``,
    integrated with adaptive quadrature split at the critical angle (where R has a kink);
    beyond it R = 1 and the integral is closed-form, ``cos^{j+1}(theta_c) / (j + 1)``."""
    if not (math.isfinite(n) and n >= 1.0):
        raise ValueError(f"eta (real refractive index) must be a finite number >= 1, got {n}")
    theta_c = math.asin(1.0 / n)
    moments = []
    for j in (1, 2):
        inside, _ = integrate.quad(
            lambda t, j=j: float(fresnel_inside(math.cos(t), n)) * math.cos(t) ** j * math.sin(t),
            0.0, theta_c, epsabs=1e-13, epsrel=1e-12, limit=200)
        moments.append(inside + math.cos(theta_c) ** (j + 1) / (j + 1))
    return moments[0], moments[1]


def rbar_fresnel(n: float) -> float:
    """Rbar of grains of real index ``n`` from the adaptive quadrature :func:`fresnel_moments`."""
    return _rbar(*fresnel_moments(n))


def tau_o_fresnel(n: float) -> float:
    """Extrapolation ratio tau_o = (2/3) (1 + Rbar) / (1 - Rbar) for grains of real index ``n``
    (dimensionless; 2/3 at n = 1), Rbar by adaptive quadrature (:func:`rbar_fresnel`)."""
    return _tau_o(rbar_fresnel(n))


def tau_o_trapezoid(n: float) -> float:
    """docs/model.md's tau_o (dimensionless) for grains of real index ``n`` by a different
    quadrature than :func:`tau_o_fresnel`: the trapezoid rule in theta on 2e6 intervals."""
    theta = np.linspace(0.0, np.pi / 2, 2_000_001)
    ci = np.cos(theta)
    r = fresnel_inside(ci, n)
    c1 = np.trapezoid(r * ci * np.sin(theta), theta)
    c2 = np.trapezoid(r * ci**2 * np.sin(theta), theta)
    return _tau_o(_rbar(c1, c2))


def read_yaml_nk(path: Path) -> np.ndarray:
    """Independent reader of a refractiveindex.info table: rows (wavelength um, n, k)."""
    rows, inside = [], False
    for line in path.read_text().splitlines():
        if line.strip().startswith("data:"):
            inside = True
            continue
        if inside:
            parts = line.split()
            if len(parts) != 3:
                break
            rows.append([float(p) for p in parts])
    return np.array(rows)


def hematite_nk(wl_nm: np.ndarray) -> np.ndarray:
    """Orientation-averaged hematite index n + ik at wavelengths in nm (test reference)."""
    o = read_yaml_nk(OPTICAL_CONSTANTS / "hematite_Querry-o.yml")
    e = read_yaml_nk(OPTICAL_CONSTANTS / "hematite_Querry-e.yml")
    wl_um = np.asarray(wl_nm) * 1e-3
    # the plugin averages on the o grid then interpolates; do the same
    grid = o[:, 0][(o[:, 0] >= e[0, 0]) & (o[:, 0] <= e[-1, 0])]
    n_avg = (2 * np.interp(grid, o[:, 0], o[:, 1]) + np.interp(grid, e[:, 0], e[:, 1])) / 3
    k_avg = (2 * np.interp(grid, o[:, 0], o[:, 2]) + np.interp(grid, e[:, 0], e[:, 2])) / 3
    return np.interp(wl_um, grid, n_avg) + 1j * np.interp(wl_um, grid, k_avg)
