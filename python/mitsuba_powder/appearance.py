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

from .variants import use_variant

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
        from ._llvm import check_llvm

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


def powder_colour(
    radius: float = 0.017,
    radius2: float | None = None,
    fraction2: float | None = None,
    material: str = "hematite",
    wavelengths_nm: np.ndarray = WAVELENGTHS_NM,
    samples: int = 4096,
    **properties,
) -> PowderColour:
    """Albedo, efficiencies, tau_o, reflectance spectrum and colour of a powder.

    Args:
        radius: grain radius, micrometres.
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
    wavelengths_nm = np.asarray(wavelengths_nm, dtype=np.float64)
    if wavelengths_nm.ndim != 1 or len(wavelengths_nm) < 2 or np.any(np.diff(wavelengths_nm)
                                                                       <= 0):
        raise ValueError("wavelengths_nm must be an increasing 1D array of at least 2 values")
    if wavelengths_nm[0] < 360.0 or wavelengths_nm[-1] > 830.0:
        raise ValueError(f"wavelengths_nm spans {wavelengths_nm[0]}-{wavelengths_nm[-1]} nm; "
                         "valid range is 360-830 nm")
    if (radius2 is None) != (fraction2 is None):
        raise ValueError("give both radius2 and fraction2, or neither")
    if samples < 16:
        raise ValueError(f"samples = {samples} is out of range; valid range is [16, inf)")

    props = {"type": "powder", "radius": radius, **properties}
    if "eta" not in properties:
        props["material"] = material
    if radius2 is not None:
        props.update(radius2=radius2, fraction2=fraction2)

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
