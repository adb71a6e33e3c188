"""Colour of a powder from its grains: albedo, efficiencies, tau_o and CIE colour.

Everything optical comes from the C++ plugin (evaluated in a spectral variant): the Mie
albedo rho(lambda), the efficiencies Q_ext and Q_sca, the Fresnel tau_o(lambda) (through
``BSDF.eval_attribute``) and the BRDF integrated into a reflectance spectrum. colour-science
turns the spectrum into CIE XYZ, sRGB and CIELAB under D65.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .._checks import check_range
from ..variants import use_variant
from . import registry

#: Default wavelength grid (nm) of the reported spectra
WAVELENGTHS_NM = np.arange(360.0, 831.0, 5.0)


@dataclass(frozen=True)
class PowderColour:
    """Optical properties and colour of a powder (see :func:`powder_colour`).

    Attributes:
        wavelengths_nm: wavelengths of the spectra, nm.
        albedo: single-scattering albedo rho(lambda) (Q_sca / Q_ext, dimensionless).
        q_ext, q_sca: extinction and scattering efficiencies of the (first) grain population.
        q_ext2, q_sca2: the same for the second population (``None`` with one population).
        tau_o: extrapolation ratio tau_o(lambda) used by the multiple-scattering terms.
        reflectance: directional-hemispherical reflectance for light at normal incidence
            (the integral of f cos(theta_o) over the hemisphere; what an integrating sphere
            measures in 0/d geometry).
        xyz: CIE 1931 XYZ of that reflectance under D65 (Y = 1 for a perfect white); NaN
            unless the wavelengths are a 1, 5, 10 or 20 nm grid covering 380-780 nm.
        srgb: sRGB-encoded colour (IEC 61966-2-1, D65), unclipped; components outside
            [0, 1] are out of the sRGB gamut.
        lab: CIELAB (D65 white), L* in [0, 100].
        properties: the plugin properties used.
    """

    wavelengths_nm: np.ndarray
    albedo: np.ndarray
    q_ext: np.ndarray
    q_sca: np.ndarray
    q_ext2: np.ndarray | None
    q_sca2: np.ndarray | None
    tau_o: np.ndarray
    reflectance: np.ndarray
    xyz: np.ndarray
    srgb: np.ndarray
    lab: np.ndarray
    properties: dict = field(default_factory=dict)

    @property
    def srgb8(self) -> tuple[int, int, int]:
        """sRGB clipped to the gamut and quantised to 8 bits."""
        c = np.clip(self.srgb, 0.0, 1.0)
        return tuple(int(round(v * 255)) for v in c)


def _spectral_variant() -> str:
    if "llvm_ad_spectral" in mi.variants() and dr.has_backend(dr.JitBackend.LLVM):
        from .._llvm import check_llvm

        if check_llvm().usable:
            return "llvm_ad_spectral"
    return "scalar_spectral"


def _groups(wavelengths: np.ndarray) -> np.ndarray:
    """Wavelengths padded to a multiple of 4 (Mitsuba's spectral sample count), (G, 4)."""
    n = len(wavelengths)
    pad = (-n) % 4
    padded = np.concatenate([wavelengths, np.full(pad, wavelengths[-1])])
    return padded.reshape(-1, 4)


def _attribute(bsdf, name: str, groups: np.ndarray, n: int) -> np.ndarray:
    out = []
    for lam in groups:
        si = dr.zeros(mi.SurfaceInteraction3f, 1) if dr.is_jit_v(mi.Float) \
            else mi.SurfaceInteraction3f()
        si.wavelengths = mi.UnpolarizedSpectrum(*[float(v) for v in lam])
        out.append(np.array(bsdf.eval_attribute(name, si), dtype=np.float64).ravel())
    return np.concatenate(out)[:n]


def _reflectance(bsdf, groups: np.ndarray, n: int, samples: int) -> np.ndarray:
    """Directional-hemispherical reflectance at normal incidence.

    At normal incidence the BRDF depends on theta_o only, so the hemispherical integral is
    pi * int_0^1 f du with u = sin^2(theta_o) (midpoint rule, ``samples`` nodes).
    """
    u = (np.arange(samples) + 0.5) / samples
    x = np.sqrt(u).astype(np.float32)
    z = np.sqrt(1.0 - u).astype(np.float32)
    out = []
    for lam in groups:
        if dr.is_jit_v(mi.Float):
            si = dr.zeros(mi.SurfaceInteraction3f, samples)
            si.wi = mi.Vector3f(0.0, 0.0, 1.0)
            si.wavelengths = mi.UnpolarizedSpectrum(*[float(v) for v in lam])
            value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(x, 0.0, z))
            f = np.array(mi.unpolarized_spectrum(value), dtype=np.float64) / z[None, :]
        else:
            f = np.zeros((4, samples))
            for i in range(samples):
                si = mi.SurfaceInteraction3f()
                si.wi = mi.Vector3f(0.0, 0.0, 1.0)
                si.wavelengths = mi.UnpolarizedSpectrum(*[float(v) for v in lam])
                value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(float(x[i]), 0.0,
                                                                     float(z[i])))
                f[:, i] = np.array(mi.unpolarized_spectrum(value)).ravel() / z[i]
        out.append(np.pi * f.mean(axis=1))
    return np.concatenate(out)[:n]


def colour_of_spectrum(wavelengths_nm: np.ndarray, reflectance: np.ndarray
                       ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(XYZ, sRGB, CIELAB) of a reflectance spectrum under D65, CIE 1931 2-degree observer.

    Args:
        wavelengths_nm: regularly spaced wavelengths (step 1, 5, 10 or 20 nm, as ASTM E308
            requires) covering at least 380-780 nm.
        reflectance: reflectance at those wavelengths (dimensionless).

    Raises:
        ValueError: the wavelength grid does not meet these conditions.
    """
    import colour

    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    steps = np.unique(np.round(np.diff(wl), 9))
    if len(steps) != 1 or steps[0] not in (1.0, 5.0, 10.0, 20.0) or wl[0] > 380.0 or \
            wl[-1] < 780.0:
        raise ValueError("colour needs a regular grid with a step of 1, 5, 10 or 20 nm "
                         f"covering 380-780 nm; got {wl[0]:g}-{wl[-1]:g} nm, steps "
                         f"{steps.tolist()}")
    sd = colour.SpectralDistribution(dict(zip(wl, np.asarray(reflectance, float))))
    shape = sd.shape
    cmfs = colour.MSDS_CMFS["CIE 1931 2 Degree Standard Observer"].copy().align(shape)
    illuminant = colour.SDS_ILLUMINANTS["D65"].copy().align(shape)
    # ASTM E308 integrates over its standard 360-780 nm shape and says so in a warning
    with colour.utilities.suppress_warnings(colour_runtime_warnings=True):
        xyz = colour.sd_to_XYZ(sd, cmfs, illuminant) / 100.0
    white = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]
    return np.asarray(xyz), np.asarray(colour.XYZ_to_sRGB(xyz)), np.asarray(
        colour.XYZ_to_Lab(xyz, white))


def _visible_wavelengths(wavelengths_nm) -> np.ndarray:
    """An increasing 1D array of at least 2 wavelengths within 360-830 nm, as float64."""
    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    if wl.ndim != 1 or len(wl) < 2 or np.any(np.diff(wl) <= 0):
        raise ValueError("wavelengths_nm must be an increasing 1D array of at least 2 values")
    if wl[0] < 360.0 or wl[-1] > 830.0:
        raise ValueError(f"wavelengths_nm spans {wl[0]}-{wl[-1]} nm; valid range is 360-830 nm")
    return wl


def _powder_properties(radius: float | None, radius2: float | None, fraction2: float | None,
                       material: str, properties: dict) -> dict:
    """The plugin's properties of :func:`powder_colour` (its defaults filled in)."""
    if radius is None and "albedo" not in properties:
        radius = float(registry.DEFAULTS["radius"])
    props = {"type": "powder", **properties}
    if radius is not None:
        props["radius"] = radius
    if "eta" not in properties:
        props["material"] = material
    if radius2 is not None:
        props.update(radius2=radius2, fraction2=fraction2)
    return props


def powder_colour(
    radius: float | None = None,
    radius2: float | None = None,
    fraction2: float | None = None,
    material: str = str(registry.DEFAULTS["material"]),
    wavelengths_nm: np.ndarray = WAVELENGTHS_NM,
    samples: int = 4096,
    **properties,
) -> PowderColour:
    """Albedo, efficiencies, tau_o, reflectance spectrum and colour of a powder.

    Args:
        radius: grain radius, micrometres (default: the plugin's; none with an ``albedo``
            in ``properties``, which replaces the grains: a radius beside it is an error).
        radius2, fraction2: radius (micrometres) and volume fraction of a second grain
            population (both or neither).
        material: ``"hematite"``, ``"magnetite"`` or a refractiveindex.info YAML path.
        wavelengths_nm: wavelengths of the spectra (nm, regular, within 360-830).
        samples: quadrature nodes of the hemispherical integral.
        **properties: further plugin properties (e.g. ``extinction``, ``g``, ``tau_o``,
            ``eta`` and ``k`` instead of ``material``); the default BRDF is the plugin's.

    Returns:
        A :class:`PowderColour`.

    Raises:
        ValueError: inconsistent arguments; RuntimeError: the plugin rejected a property.
    """
    wavelengths_nm = _visible_wavelengths(wavelengths_nm)
    if (radius2 is None) != (fraction2 is None):
        raise ValueError("give both radius2 and fraction2, or neither")
    check_range("samples", samples, 16)

    props = _powder_properties(radius, radius2, fraction2, material, properties)
    n = len(wavelengths_nm)
    groups = _groups(wavelengths_nm)
    with use_variant(_spectral_variant()):
        bsdf = mi.load_dict(props)
        uses_mie = "albedo" not in properties
        get = lambda name: _attribute(bsdf, name, groups, n)  # noqa: E731
        albedo, tau = get("albedo"), get("tau_o")
        q_ext = get("q_ext") if uses_mie else np.full(n, np.nan)
        q_sca = get("q_sca") if uses_mie else np.full(n, np.nan)
        q_ext2 = get("q_ext2") if uses_mie and radius2 is not None else None
        q_sca2 = get("q_sca2") if uses_mie and radius2 is not None else None
        reflectance = _reflectance(bsdf, groups, n, samples)
    try:
        xyz, srgb, lab = colour_of_spectrum(wavelengths_nm, reflectance)
    except ValueError:  # a grid the colour maths cannot use: spectra only
        xyz = srgb = lab = np.full(3, np.nan)
    return PowderColour(wavelengths_nm, albedo, q_ext, q_sca, q_ext2, q_sca2, tau,
                        reflectance, xyz, srgb, lab, {k: v for k, v in props.items()
                                                      if k != "type"})


# --------------------------------------------------------------------------------------
#  Albedo from a measured reflectance


#: Panels (radians) of the quadrature in theta_o of the 0:d reflectance: finer near the
#: normal, where a narrow back-scattering cone sits at normal incidence
_PANELS = (0.0, 1e-4, 1e-3, 3e-3, 1e-2, 3e-2, 0.1, 0.3, 0.7, 1.1, np.pi / 2)


def mixture_colour(mix, by: str = "volume", wavelengths_nm: np.ndarray = WAVELENGTHS_NM,
                   samples: int = 4096, **properties) -> PowderColour:
    """:func:`powder_colour` of a pigment mixture (docs/model.md, "Several materials").

    Args:
        mix: ``(material, fraction, radius um)`` populations (one to four; built-in materials or
            YAML files), or the same as a string ``hematite:5%:0.1um,kaolinite:95%:1um``
            (:func:`~mitsuba_powder.plugin.grains.parse_mix`).
        by: ``"mass"`` or ``"volume"``: how the fractions are given; mass fractions are
            converted to volume fractions of the solid with the materials' densities
            (:func:`~mitsuba_powder.plugin.grains.volume_fractions`).
        wavelengths_nm, samples, **properties: as :func:`powder_colour` (no grain properties).

    Raises:
        ValueError: a malformed mixture, fractions not summing to 1, no density for a mass
            fraction; RuntimeError: the plugin rejected a property.
    """
    from .grains import mixture_properties, parse_mix

    parts = parse_mix(mix) if isinstance(mix, str) else list(mix)
    props = mixture_properties(parts, by)
    clash = [k for k in props if k in properties]
    if clash:
        raise ValueError(f"{', '.join(clash)} come from the mixture; give them there")
    return powder_colour(wavelengths_nm=wavelengths_nm, samples=samples, **props, **properties)


def hemispherical_nodes(order: int = 16) -> tuple[np.ndarray, np.ndarray]:
    """Nodes theta_o (degrees) and weights of the directional-hemispherical reflectance at
    normal incidence: ``R = sum_k w_k BRF(0, theta_k)`` for
    ``R = (1 / pi) int BRF cos(theta_o) d omega = 2 int_0^{pi/2} BRF cos sin d theta``
    (at normal incidence the BRDF does not depend on the azimuth). Gauss-Legendre of
    ``order`` nodes on each panel of :data:`_PANELS`."""
    x, w = np.polynomial.legendre.leggauss(order)
    theta, weight = [], []
    for a, b in zip(_PANELS[:-1], _PANELS[1:]):
        t = 0.5 * (b - a) * x + 0.5 * (b + a)
        theta.append(t)
        weight.append(0.5 * (b - a) * w * 2.0 * np.cos(t) * np.sin(t))
    return np.degrees(np.concatenate(theta)), np.concatenate(weight)


def _geometry(geometry) -> tuple[str, float, float]:
    """("0:d", 0, 0) or ("brf", theta_i, theta_o) from "0:d", "I:O" or (I, O)."""
    if isinstance(geometry, str):
        text = geometry.strip().lower()
        if text in ("0:d", "0/d"):
            return "0:d", 0.0, 0.0
        parts = text.replace("/", ":").split(":")
        try:
            ti, to = (float(p) for p in parts)
        except ValueError:
            raise ValueError(f"geometry = {geometry!r} is not valid; give '0:d' or "
                             "'THETA_I:THETA_O' in degrees, e.g. '0:45'") from None
    else:
        try:
            ti, to = (float(v) for v in geometry)
        except (TypeError, ValueError):
            raise ValueError(f"geometry = {geometry!r} is not valid; give '0:d' or a pair "
                             "(theta_i, theta_o) in degrees") from None
    if not (0.0 <= ti < 90.0) or not (-90.0 < to < 90.0):
        raise ValueError(f"geometry = {geometry!r}: theta_i must lie in [0, 90) and theta_o "
                         "in (-90, 90) degrees")
    return "brf", ti, to


def albedo_for_reflectance(wavelengths_nm, reflectance, geometry="0:d", grid: int = 33,
                           **properties) -> np.ndarray:
    """The single-scattering albedo per wavelength for which the plugin, with the other
    ``properties``, reproduces a measured reflectance.

    Args:
        wavelengths_nm: (W,) wavelengths, nm.
        reflectance: (W,) target: with ``geometry="0:d"`` the directional-hemispherical
            reflectance at normal incidence (an integrating sphere, 0/d); with a pair
            ``(theta_i, theta_o)`` (degrees, or a string ``"0:45"``) the reflectance factor
            (BRF) in the plane of incidence (``0:45`` of colorimetry).
        geometry: ``"0:d"`` or ``(theta_i, theta_o)``.
        grid: albedo values per refinement round (three rounds).
        **properties: other plugin properties as numbers (``amplitude_volume``, ``g``,
            ``extinction``, ``tau_o`` or ``material``/``eta``/``k`` for tau_o, ``thickness``,
            ``amplitude_surface``, ``correlation_length``, ``specular``, ``sigma``,
            ``lobes``); not ``albedo`` or the grain radius (which the albedo replaces).

    Returns:
        (W,) albedo in [0, 1]: the plugin's reflectance with it equals the target to float
        precision (the reflectance grows with the albedo).

    Raises:
        ValueError: a target the model cannot reach (naming the wavelength, the value and the
            reachable range), a bad geometry, or bad arrays or properties.
    """
    from .brf import batch_variant

    wl, target = _check_albedo_inputs(wavelengths_nm, reflectance, grid, properties)
    kind, ti, to = _geometry(geometry)
    order = np.argsort(wl)
    wl, target = wl[order], target[order]
    reflectances = _reflectance_of_albedo(kind, ti, to, wl, grid, properties)
    with use_variant(batch_variant(wl)):
        result = _solve_albedo(reflectances, target, wl, grid, kind)
    out = np.empty(len(wl))
    out[order] = result
    return out


def _check_albedo_inputs(wavelengths_nm, reflectance, grid: int, properties: dict
                         ) -> tuple[np.ndarray, np.ndarray]:
    """The checks of :func:`albedo_for_reflectance`'s arguments; (wavelengths, targets) as
    float arrays."""
    wl = np.atleast_1d(np.asarray(wavelengths_nm, dtype=np.float64))
    target = np.atleast_1d(np.asarray(reflectance, dtype=np.float64))
    if wl.ndim != 1 or target.shape != wl.shape or len(wl) == 0:
        raise ValueError(f"wavelengths_nm and reflectance must be 1D arrays of the same "
                         f"length; got {wl.shape} and {target.shape}")
    if not np.all(np.isfinite(wl)) or np.any(wl <= 0) or len(np.unique(wl)) != len(wl):
        raise ValueError("wavelengths_nm must be distinct positive finite numbers (nm)")
    if not np.all(np.isfinite(target)):
        raise ValueError("reflectance must be finite")
    bad = [k for k in ("albedo", "radius", "radius2", "fraction2") if k in properties]
    if bad:
        raise ValueError(f"{bad} cannot be given: the albedo is what is solved for")
    check_range("grid", grid, 3)
    return wl, target


def _reflectance_of_albedo(kind: str, ti: float, to: float, wl: np.ndarray, grid: int,
                           properties: dict):
    """The plugin's reflectance at the geometry (``"0:d"``: hemispherical quadrature; else
    the BRF at ``(ti, to)``) as a function of ``grid`` albedo values per wavelength: a callable
    taking albedo (grid, W) and returning the reflectance (grid, W)."""
    from ..io.measurements import Measurements
    from .brf import BatchBRF
    from .grains import GrainOptics

    if kind == "0:d":
        theta, weight = hemispherical_nodes()
    else:
        theta, weight = np.array([to]), np.array([1.0])
    n, w = len(theta), len(wl)
    rows = Measurements(np.full(n * w, ti), np.tile(theta, w), np.zeros(n * w),
                        np.repeat(wl, n), np.zeros(n * w))
    optics = {k: v for k, v in properties.items() if k in ("material", "eta", "k")}
    tau = (np.full(w, float(properties["tau_o"])) if "tau_o" in properties
           else GrainOptics(optics).tau_o(wl))
    fixed = {k: v for k, v in properties.items() if k != "tau_o"}
    engine = BatchBRF(rows, fixed, grid, [])

    def reflectances(albedo: np.ndarray) -> np.ndarray:
        """(grid, W) reflectance of (grid, W) albedo values."""
        brf, _ = engine.evaluate({}, albedo, tau)
        return (brf.reshape(grid, w, n) * weight).sum(axis=2)

    return reflectances


def _solve_albedo(reflectances, target: np.ndarray, wl: np.ndarray, grid: int, kind: str
                  ) -> np.ndarray:
    """The albedo (W,) whose reflectance equals ``target``: three rounds of a ``grid`` of
    albedo values, each within the previous round's bracket (the reflectance grows with the
    albedo), then linear interpolation in the last bracket.

    Raises:
        ValueError: a target outside the reachable range (albedo 0-1).
    """
    w = len(wl)
    lo, hi = np.zeros(w), np.ones(w)
    values = None
    for _ in range(3):
        albedo = lo + np.linspace(0.0, 1.0, grid)[:, None] * (hi - lo)
        values = reflectances(albedo)
        if lo.max() == 0.0 and hi.min() == 1.0:  # first round: the reachable range
            low, high = values[0], values[-1]
            out = (target < low - 1e-7) | (target > high + 1e-7)
            if np.any(out):
                k = int(np.nonzero(out)[0][0])
                raise ValueError(
                    f"reflectance {target[k]:.6g} at {wl[k]:g} nm cannot be reached: with "
                    f"these properties the {'0:d reflectance' if kind == '0:d' else 'BRF'}"
                    f" lies in [{low[k]:.6g}, {high[k]:.6g}] for albedo 0-1")
        # the bracket of each wavelength (the reflectance grows with the albedo)
        idx = np.clip(np.array([np.searchsorted(values[:, j], target[j])
                                for j in range(w)]), 1, grid - 1)
        cols = np.arange(w)
        lo, hi = albedo[idx - 1, cols], albedo[idx, cols]
    r0, r1 = values[idx - 1, cols], values[idx, cols]
    t = np.where(r1 > r0, (target - r0) / np.where(r1 > r0, r1 - r0, 1.0), 0.0)
    return np.clip(lo + np.clip(t, 0.0, 1.0) * (hi - lo), 0.0, 1.0)


def write_spectrum(path, wavelengths_nm, values) -> None:
    """A Mitsuba spectrum file (``<spectrum filename="..."/>``): one ``wavelength value`` line
    per wavelength (nm), increasing."""
    from ..outputs import output_file

    wl = np.asarray(wavelengths_nm, dtype=np.float64)
    order = np.argsort(wl)
    lines = [f"{wl[i]:.6g} {float(values[i]):.9g}" for i in order]
    output_file(path).write_text("\n".join(lines) + "\n")


def reflectance_of_srgb(rgb) -> tuple[np.ndarray, np.ndarray]:
    """A smooth reflectance spectrum (380-780 nm by 5 nm) with the given sRGB colour
    (components in [0, 1], or 0-255 integers), by colour-science's Mallett & Yuksel (2019)
    spectral upsampling of the linear sRGB values."""
    import colour

    c = np.asarray(rgb, dtype=np.float64).reshape(-1)
    if c.shape != (3,) or not np.all(np.isfinite(c)):
        raise ValueError(f"srgb = {rgb!r}: give three numbers R,G,B")
    if np.any(c > 1.0):
        if np.all(c <= 255.0) and np.allclose(c, np.round(c)):
            c = c / 255.0
        else:
            raise ValueError(f"srgb = {rgb!r}: components lie in [0, 1] (or 0-255 integers)")
    if np.any(c < 0.0):
        raise ValueError(f"srgb = {rgb!r}: components must be >= 0")
    linear = colour.models.eotf_sRGB(c)
    sd = colour.recovery.RGB_to_sd_Mallett2019(linear)
    return np.asarray(sd.wavelengths, dtype=np.float64), np.asarray(sd.values, dtype=float)
