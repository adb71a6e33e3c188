"""Render a flat powder patch under goniometer geometries and measure its BRF from the image.

The virtual goniometer (the same geometry as ``scenes/gonio.xml``):

- a flat patch (a 200 x 200 rectangle, normal +z) with the ``powder`` BSDF;
- a collimated source at ``wi = (sin theta_i, 0, cos theta_i)``: a ``directional`` emitter of
  irradiance ``E = 1`` (normal to the beam), or, with ``source_radius > 0`` degrees, a distant
  disk of that angular radius with the same irradiance (a source of finite divergence, which
  makes emitter, BSDF and MIS sampling all meaningful);
- per geometry an orthographic sensor looking at the patch from
  ``wo = (sin theta_o cos phi, sin theta_o sin phi, cos theta_o)``, with a box pixel filter,
  so that every pixel is an independent Monte Carlo estimate of the same radiance.

All sensors of one incidence are rendered at once through Mitsuba's ``batch`` sensor, each
image with a guard column on either side that the estimate leaves out (:data:`GUARD_COLUMNS`).
The measured reflectance factor is ``BRF = pi L / (E cos theta_i)``; its Monte Carlo standard
error is the spread of the pixels over the square root of their number. The analytic BRF is
``pi f(wi, wo)`` from the plugin's ``eval`` (averaged over the source disk by quadrature), and
in spectral variants it goes through the film's own spectral-to-sRGB weighting.

Two kinds of values, checked differently (:meth:`GonioResult.deterministic`):

- **deterministic**: a collimated source in an RGB or mono variant (or any value whose
  standard error is exactly 0). Every sample is the same ``f E cos theta_i``: nothing is
  random, the standard error is 0 or float noise, and a z-score would only measure rounding.
  These values are compared with the analytic BRF to a relative tolerance derived from float32
  arithmetic (:meth:`GonioResult.relative_tolerance`).
- **Monte Carlo**: a source of finite size (emitter, BSDF or MIS sampling) or a spectral
  variant (wavelength sampling). These get the z-test, ``|rendered - analytic| <= 3 sigma``.
"""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .._checks import check_range, out_of_range
from ..io.measurements import Measurements, gonio_directions
from ..variants import check_variant, use_variant

SOURCE_DISTANCE = 1.0e4  # scene units; the visible patch is ~3 units wide
CAMERA_DISTANCE = 10.0
PATCH_HALF_SIZE = 100.0
STRATEGIES = ("emitter", "bsdf", "mis")
#: guard columns on each side of every geometry's image in the batch film, left out of the
#: estimate. Without them, a sample near the border of two sub-images of the batch sensor
#: could be traced by one sub-sensor and splatted into the other's border column (float32
#: rounding of the film position, which reaches 5e-4 pixel at x ~ 4000): one sample of the
#: neighbouring geometry in a pixel, a bias of a few 1e-5 of the BRF at grazing geometries
#: (measurements: docs/gonio_validation.md)
GUARD_COLUMNS = 1
#: float32 unit roundoff 2^-24 (relative rounding error of one operation)
FLOAT32_U = 2.0**-24
#: rounding of the plugin's eval and of the final scalings (film division, radiance to BRF),
#: in units of FLOAT32_U: a bound on what a render at exactly the analytic directions adds
#: besides the accumulation, with a margin over what renders show (docs/gonio_validation.md)
EVAL_ULPS = 16.0
#: how far the render's directions are from the analytic ones, per component, in units of
#: FLOAT32_U: the camera ray, the patch's frame and the directional emitter are float32
#: transforms; twice the largest difference seen (docs/gonio_validation.md)
DIRECTION_ULPS = 4.0
#: step (radians) of the one-sided differences of :func:`direction_sensitivity`
SENSITIVITY_STEP = 1e-5


@dataclass
class GonioResult:
    """Rendered and analytic BRF at gonio geometries.

    Attributes:
        theta_i, theta_o, phi: geometries, degrees, shape (N,).
        wavelength: nm per geometry in mono variants, NaN otherwise.
        channels: names of the value columns (``R, G, B`` or ``Y`` for mono).
        rendered: BRF measured on the image, (N, C).
        stderr: its Monte Carlo standard error, (N, C).
        analytic: BRF of the plugin's ``eval`` at the same geometry (and source), (N, C).
        measured: BRF of the measurement file, (N,), when one was given.
        variant, spp, resolution, source_radius, strategy: how it was rendered.
        seconds: wall-clock time of the renders, s.
        sensitivity: ``G``, the sum over the two tangent directions of ``wo`` and of ``wi`` of
            ``|d ln f / d angle|`` (per radian) at the geometry, (N, C): how much a rounding
            of the directions moves the BRF (:func:`direction_sensitivity`); 0 if not given,
            and 0 for the Monte Carlo values of spectral variants (not computed there).
    """

    theta_i: np.ndarray
    theta_o: np.ndarray
    phi: np.ndarray
    wavelength: np.ndarray
    channels: list[str]
    rendered: np.ndarray
    stderr: np.ndarray
    analytic: np.ndarray
    measured: np.ndarray | None = None
    variant: str = ""
    spp: int = 0
    resolution: int = 0
    source_radius: float = 0.0
    strategy: str = "emitter"
    seconds: float = 0.0
    properties: dict = field(default_factory=dict)
    sensitivity: np.ndarray | None = None

    def deterministic(self) -> np.ndarray:
        """True for values without Monte Carlo noise, (N, C): a collimated source in an RGB
        or mono variant (every sample is ``f E cos theta_i`` at the same directions; the
        standard error is 0, or float noise where a pixel's samples were summed in another
        order), and any value whose standard error is exactly 0."""
        by_construction = self.source_radius == 0.0 and "spectral" not in self.variant
        return np.broadcast_to(by_construction, self.stderr.shape) | (self.stderr == 0.0)

    def relative_tolerance(self) -> np.ndarray:
        """Relative difference float32 arithmetic allows between render and analytic BRF,
        (N, C): ``u (spp + EVAL_ULPS + sqrt(3) DIRECTION_ULPS G)`` with ``u = 2^-24``.

        - ``spp u``: a pixel sums its ``spp`` samples in float32 (the error bound of recursive
          summation of ``spp`` terms, ``(spp - 1) u``, plus the division by the weight);
        - ``EVAL_ULPS u`` (16 u): the eval and the scalings;
        - ``sqrt(3) DIRECTION_ULPS G u``: the render's directions differ from the analytic
          ones by up to ``DIRECTION_ULPS`` (4) u per component, at most ``sqrt(3)`` times that
          in angle, and the BRF changes by ``G`` (:attr:`sensitivity`) per radian.
        """
        g = 0.0 if self.sensitivity is None else self.sensitivity
        return FLOAT32_U * (self.spp + EVAL_ULPS + np.sqrt(3.0) * DIRECTION_ULPS * g) * \
            np.ones_like(self.analytic)

    def relative_difference(self) -> np.ndarray:
        """|rendered - analytic| / |analytic|, (N, C)."""
        return np.abs(self.rendered - self.analytic) / np.maximum(np.abs(self.analytic), 1e-30)

    def tolerance(self) -> np.ndarray:
        """Allowed |rendered - analytic|, (N, C): the float32 tolerance
        ``relative_tolerance |analytic|``, plus ``3 sigma_MC`` for Monte Carlo values."""
        floor = self.relative_tolerance() * np.abs(self.analytic)
        return np.where(self.deterministic(), floor, 3.0 * self.stderr + floor)

    def z(self) -> np.ndarray:
        """(rendered - analytic) / sqrt(stderr^2 + (relative_tolerance analytic)^2) for
        Monte Carlo values; NaN for deterministic ones (no noise to measure), (N, C)."""
        scale = np.sqrt(self.stderr**2 + (self.relative_tolerance() * self.analytic) ** 2)
        z = (self.rendered - self.analytic) / np.maximum(scale, 1e-30)
        return np.where(self.deterministic(), np.nan, z)

    def agrees(self) -> np.ndarray:
        """True where the render is within :meth:`tolerance` of the analytic BRF, (N, C)."""
        return np.abs(self.rendered - self.analytic) <= self.tolerance()

    def summary(self) -> dict:
        """Counts and extremes of the agreement (for reports): the deterministic values
        against the float32 tolerance, the Monte Carlo ones by their z."""
        det = self.deterministic()
        mc = ~det
        rel = self.relative_difference()
        tol = self.relative_tolerance()
        ok = self.agrees()
        z = self.z()[mc]
        n_det, n_mc = int(det.sum()), int(mc.sum())
        rel_stderr = self.stderr / np.maximum(np.abs(self.analytic), 1e-30)
        return {
            "geometries": int(len(self.theta_i)), "values": int(det.size),
            "deterministic": {
                "values": n_det,
                "max_relative_difference": float(rel[det].max()) if n_det else None,
                "relative_tolerance_min": float(tol[det].min()) if n_det else None,
                "relative_tolerance_max": float(tol[det].max()) if n_det else None,
                "max_difference_over_tolerance": float((rel[det] / tol[det]).max())
                if n_det else None,
                "beyond_tolerance": int(np.sum(~ok[det])),
                "tolerance": f"u (spp + {EVAL_ULPS:g} + sqrt(3) {DIRECTION_ULPS:g} G), "
                             "u = 2^-24 (float32), G = |d ln f / d angle| summed over the "
                             "tangent directions of wi and wo",
            },
            "monte_carlo": {
                "values": n_mc,
                "max_abs_z": float(np.max(np.abs(z))) if n_mc else None,
                "beyond_3_sigma": int(np.sum(~ok[mc])),
                "expected_beyond_3_sigma_if_gaussian": round(0.0027 * n_mc, 2),
                "median_relative_stderr": float(np.median(rel_stderr[mc])) if n_mc else None,
            },
            "max_relative_difference": float(rel.max()),
        }

    def rows(self) -> list[dict]:
        """One dict per geometry and channel (the CSV rows of :func:`write_gonio_csv`)."""
        out = []
        z = self.z()
        for i in range(len(self.theta_i)):
            for c, name in enumerate(self.channels):
                row = {"theta_i": self.theta_i[i], "theta_o": self.theta_o[i],
                       "phi": self.phi[i], "wavelength": self.wavelength[i], "channel": name,
                       "brf_rendered": self.rendered[i, c], "stderr": self.stderr[i, c],
                       "brf_analytic": self.analytic[i, c], "z": z[i, c]}
                if self.measured is not None:
                    row["brf_measured"] = self.measured[i]
                out.append(row)
        return out


def _transform_look(direction: np.ndarray, distance: float) -> mi.ScalarTransform4f:
    up = [1.0, 0.0, 0.0] if abs(direction[2]) > 0.99 else [0.0, 0.0, 1.0]
    return mi.ScalarTransform4f().look_at(origin=[float(v * distance) for v in direction],
                                          target=[0.0, 0.0, 0.0], up=up)


def film_dict(width: int, height: int) -> dict:
    """An ``hdrfilm`` with a box filter (each sample lands in one pixel only), float32."""
    return {"type": "hdrfilm", "width": width, "height": height, "rfilter": {"type": "box"},
            "pixel_format": "luminance" if "mono" in mi.variant() else "rgb",
            "component_format": "float32"}


def sensor_dict(direction: np.ndarray, resolution: int, spp: int, guard: int = 0) -> dict:
    """An orthographic sensor looking at the patch centre from the unit ``direction``,
    covering 1 x 1 scene units on ``resolution^2`` pixels, and ``guard`` more columns of
    pixels of the same size on each side (``resolution + 2 guard`` columns in all)."""
    width = resolution + 2 * guard
    return {"type": "orthographic",
            "to_world": _transform_look(direction, CAMERA_DISTANCE)
            @ mi.ScalarTransform4f().scale([0.5 * width / resolution, 0.5, 1.0]),
            "film": film_dict(width, resolution),
            "sampler": {"type": "independent", "sample_count": spp}}


def _uniform(value: float) -> dict:
    return {"type": "uniform", "value": float(value)}


def source_dict(wi: np.ndarray, source_radius: float = 0.0, irradiance: float = 1.0) -> dict:
    """Scene-dict entries of the collimated source at direction ``wi`` (unit, to the source).

    ``source_radius = 0``: a directional emitter of irradiance ``irradiance``. Otherwise a disk
    of angular radius ``source_radius`` degrees at :data:`SOURCE_DISTANCE`, radiance chosen so
    that the irradiance normal to ``wi`` is ``irradiance`` (``E = pi L sin^2 alpha``).
    """
    wi = np.asarray(wi, dtype=np.float64)
    if source_radius == 0.0:
        return {"source": {"type": "directional", "direction": [float(-v) for v in wi],
                           "irradiance": _uniform(irradiance)}}
    alpha = np.radians(source_radius)
    radius = SOURCE_DISTANCE * np.tan(alpha)
    radiance = irradiance / (np.pi * np.sin(alpha) ** 2)
    # the disk's normal (+z) must face the patch: look_at maps +z to the viewing direction
    to_world = _transform_look(wi, SOURCE_DISTANCE) @ mi.ScalarTransform4f().scale(
        [radius, radius, 1.0])
    return {"source": {"type": "disk", "to_world": to_world,
                       "emitter": {"type": "area", "radiance": _uniform(radiance)}}}


def _integrator(strategy: str, directional: bool) -> dict:
    if strategy not in STRATEGIES:
        raise ValueError(f"strategy = {strategy!r} is not valid; choose one of {STRATEGIES}")
    if directional and strategy != "emitter":
        raise ValueError(f"strategy = {strategy!r} needs a source that BSDF samples can hit: "
                         "a directional source (source_radius = 0) is a delta light; "
                         "give source_radius > 0 (degrees) or use strategy 'emitter'")
    emitter, bsdf = {"emitter": (1, 0), "bsdf": (0, 1), "mis": (1, 1)}[strategy]
    return {"type": "direct", "emitter_samples": emitter, "bsdf_samples": bsdf}


def patch_dict(properties: dict) -> dict:
    """The powder patch (normal +z) of the virtual goniometer."""
    return {"type": "rectangle",
            "to_world": mi.ScalarTransform4f().scale([PATCH_HALF_SIZE, PATCH_HALF_SIZE, 1.0]),
            "bsdf": {"type": "powder", **properties}}


def _check(variant: str, spp: int, resolution: int, source_radius: float) -> None:
    check_variant(variant)
    check_range("spp", spp, 1)
    check_range("resolution", resolution, 2,
                note="(the error estimate needs several pixels)")
    check_range("source_radius", source_radius, 0.0, 10.0, "[]", unit="degrees")


def _disk_nodes(wi: np.ndarray, source_radius: float, n_r: int = 16, n_psi: int = 32
                ) -> tuple[np.ndarray, np.ndarray]:
    """Directions (K, 3) and weights (K,) of a quadrature over the source disk, the weights
    normalised by ``pi sin^2 alpha`` (so that ``sum w f cos`` is the source-averaged value
    per unit normal irradiance)."""
    if source_radius == 0.0:
        return wi[None, :], np.ones(1)
    alpha = np.radians(source_radius)
    x, wx = np.polynomial.legendre.leggauss(n_r)
    rho = 0.5 * alpha * (x + 1.0)
    w_rho = 0.5 * alpha * wx * np.sin(rho)
    psi = (np.arange(n_psi) + 0.5) * 2.0 * np.pi / n_psi
    up = np.array([1.0, 0.0, 0.0]) if abs(wi[2]) > 0.99 else np.array([0.0, 0.0, 1.0])
    u = np.cross(up, wi)
    u /= np.linalg.norm(u)
    v = np.cross(wi, u)
    r, p = np.meshgrid(rho, psi, indexing="ij")
    d = (np.cos(r)[..., None] * wi + np.sin(r)[..., None] * (
        np.cos(p)[..., None] * u + np.sin(p)[..., None] * v))
    w = np.repeat(w_rho, n_psi) * (2.0 * np.pi / n_psi) / (np.pi * np.sin(alpha) ** 2)
    return d.reshape(-1, 3), w


def film_weights() -> tuple[np.ndarray, np.ndarray]:
    """Spectral variants: wavelengths (nm, 1 nm grid over Mitsuba's CIE range) and the (3, L)
    weights that turn a spectrum sampled on them into the film's linear sRGB value (what
    ``hdrfilm`` estimates: ``M_xyz->srgb int xyz(lambda) s(lambda) dlambda`` times Mitsuba's
    CIE Y normalisation)."""
    lam = np.arange(mi.MI_CIE_MIN, mi.MI_CIE_MAX + 0.5, 1.0)
    if mi.variant().startswith("scalar"):
        xyz = np.array([np.array(mi.cie1931_xyz(float(v))).ravel() for v in lam]).T
    else:
        xyz = np.array(mi.cie1931_xyz(mi.Float(lam)), dtype=np.float64)
    xyz = xyz * mi.MI_CIE_Y_NORMALIZATION
    m = np.array([np.array(mi.xyz_to_srgb(mi.Color3f(*[float(v) for v in e]))).ravel()
                  for e in np.eye(3)]).T
    return lam, m @ xyz


def eval_channels(bsdf, view: np.ndarray, light: np.ndarray) -> np.ndarray:
    """``bsdf.eval`` (f cos theta_light) for (K, 3) view and light directions: (K, C) in
    RGB/mono variants, (K, 3) sRGB film values per unit spectrum in spectral variants."""
    spectral = mi.is_spectral
    if spectral:
        lam, weights = film_weights()
        n_lam = len(lam)
        pad = (-n_lam) % 4
        lam_p = np.concatenate([lam, np.full(pad, lam[-1])]).reshape(-1, 4)
        k, g = view.shape[0], lam_p.shape[0]
        view = np.repeat(view, g, axis=0)
        light = np.repeat(light, g, axis=0)
        lam_lanes = np.tile(lam_p, (k, 1))
    if mi.variant().startswith("scalar"):
        arr = np.array([_eval_scalar(bsdf, view[i], light[i],
                                     lam_lanes[i] if spectral else None)
                        for i in range(view.shape[0])])
    else:
        si = dr.zeros(mi.SurfaceInteraction3f, view.shape[0])
        si.wi = mi.Vector3f(*[view[:, j].astype(np.float32) for j in range(3)])
        if spectral:
            si.wavelengths = mi.UnpolarizedSpectrum(*[lam_lanes[:, j].astype(np.float32)
                                                      for j in range(4)])
        value = bsdf.eval(mi.BSDFContext(), si,
                          mi.Vector3f(*[light[:, j].astype(np.float32) for j in range(3)]))
        if mi.is_polarized:
            value = mi.unpolarized_spectrum(value)
        arr = np.array(value, dtype=np.float64)
        arr = (arr[None, :] if arr.ndim == 1 else arr).T  # (lanes, channels)
    if spectral:
        spec = arr.reshape(k, g * 4)[:, :n_lam]
        white = weights.sum(axis=1)
        return (spec @ weights.T) / white
    return arr


def _eval_scalar(bsdf, view: np.ndarray, light: np.ndarray, lam) -> np.ndarray:
    """One ``eval`` in a scalar variant: the channel values as a 1D array."""
    si = mi.SurfaceInteraction3f()
    si.wi = mi.Vector3f(*[float(v) for v in view])
    if lam is not None:
        si.wavelengths = mi.UnpolarizedSpectrum(*[float(v) for v in lam])
    value = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*[float(v) for v in light]))
    if mi.is_polarized:
        value = mi.unpolarized_spectrum(value)
    return np.atleast_1d(np.array(value, dtype=np.float64)).ravel()


def _tangents(w: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Two unit vectors orthogonal to each unit row of ``w`` and to each other, (K, 3) each."""
    up = np.where(np.abs(w[:, 2:3]) > 0.99, [[1.0, 0.0, 0.0]], [[0.0, 0.0, 1.0]])
    a = np.cross(up, w)
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    return a, np.cross(w, a)


def direction_sensitivity(bsdf, wo: np.ndarray, wi: np.ndarray,
                          step: float = SENSITIVITY_STEP) -> np.ndarray:
    """``G`` (N, C): the sum over the two tangent directions of ``wo`` and the two of ``wi``
    of ``|d ln f / d angle|`` (per radian), each the larger of the two one-sided differences of
    ``step`` radians (so that the cusp of the coherent peak at back-scattering counts its
    slope). ``wo`` (N, 3), ``wi`` one direction (3,)."""
    wi_all = np.repeat(np.asarray(wi, dtype=np.float64)[None, :], len(wo), axis=0)
    base = np.abs(eval_channels(bsdf, wo, wi_all))
    total = np.zeros_like(base)
    for moved in ("wo", "wi"):
        w = wo if moved == "wo" else wi_all
        for t in _tangents(w):
            slope = np.zeros_like(base)
            for sign in (1.0, -1.0):
                wp = w + sign * step * t
                wp /= np.linalg.norm(wp, axis=1, keepdims=True)
                f = (eval_channels(bsdf, wp, wi_all) if moved == "wo"
                     else eval_channels(bsdf, wo, wp))
                slope = np.maximum(slope, np.abs(f - base) / step)
            total += slope
    return total / np.maximum(base, 1e-30)


def _analytic(bsdf, wo: np.ndarray, wi: np.ndarray, source_radius: float) -> np.ndarray:
    """Analytic BRF (N, C) of the patch seen from ``wo`` lit from ``wi`` (one incidence)."""
    nodes, weights = _disk_nodes(wi, source_radius)
    out = []
    for view in wo:
        vals = eval_channels(bsdf, np.repeat(view[None, :], len(nodes), axis=0), nodes)
        out.append(np.pi * (weights[:, None] * vals).sum(axis=0) / wi[2])
    return np.array(out)


def render_gonio(properties: dict, theta_i, theta_o, phi, *, wavelength=None,
                 variant: str = "llvm_ad_rgb", spp: int = 64, resolution: int = 16,
                 source_radius: float = 0.0, strategy: str = "emitter", seed: int = 0,
                 measured: np.ndarray | None = None,
                 progress=None) -> GonioResult:
    """Render the patch at every geometry and measure its BRF on the image.

    Args:
        properties: ``powder`` plugin properties (``mi.load_dict`` form, without ``type``),
            or a function of the wavelength (nm, mono variants) that returns them.
        theta_i, theta_o, phi: geometries in degrees (docs/model.md convention: signed
            ``theta_o``, light at azimuth 0), equal-length sequences.
        wavelength: nm per geometry, mono variants only (the plugin's ``wavelength``);
            default 700 nm.
        variant: Mitsuba variant (``llvm_ad_rgb``, ``llvm_ad_spectral``, ``llvm_ad_mono``...).
        spp: samples per pixel.
        resolution: pixels per side of each geometry's image (``resolution**2`` independent
            estimates).
        source_radius: angular radius of the source, degrees, in [0, 10]; 0 is collimated.
        strategy: ``emitter``, ``bsdf`` or ``mis`` (the last two need ``source_radius > 0``).
        seed: sampler seed.
        measured: measured BRF per geometry, carried into the result.
        progress: called with a line of text after each incidence.

    Returns:
        :class:`GonioResult`.
    """
    _check(variant, spp, resolution, source_radius)
    ti, to, ph = (np.atleast_1d(np.asarray(a, dtype=np.float64)) for a in
                  (theta_i, theta_o, phi))
    _check_geometries(ti, to, ph)
    mono = "mono" in variant
    lam = _wavelengths(wavelength, variant, ti.shape)
    integrator = _integrator(strategy, source_radius == 0.0)
    wi_all, wo_all = gonio_directions(ti, to, ph)
    channels = ["Y"] if mono else ["R", "G", "B"]
    n_c = len(channels)
    rendered, stderr, analytic, sensitivity = (np.empty((len(ti), n_c)) for _ in range(4))
    seconds, used = 0.0, {}
    lam_key = np.nan_to_num(lam, nan=-1.0)  # NaN (no wavelength) != NaN in a set
    keys = sorted(set(zip(lam_key.tolist(), ti.tolist(), strict=True)))
    with use_variant(variant):
        for lam_k, ti_k in keys:
            idx = np.nonzero((ti == ti_k) & (lam_key == lam_k))[0]
            props = _properties_at(properties, lam_k, mono, used)
            wi = wi_all[idx[0]]
            pix, bsdf, took = _render_group(props, wi, wo_all[idx], integrator, source_radius,
                                            resolution, spp, seed, n_c)
            seconds += took
            rendered[idx], stderr[idx] = _brf_of_pixels(pix, wi)
            analytic[idx] = _analytic(bsdf, wo_all[idx], wi, source_radius)
            sensitivity[idx] = _sensitivity(bsdf, wo_all[idx], wi, stderr[idx])
            if progress is not None:
                where = f"{lam_k:g} nm, " if mono else ""
                progress(f"{where}theta_i {ti_k:g}: {len(idx)} geometries rendered")
    return GonioResult(ti, to, ph, lam, channels, rendered, stderr, analytic,
                       None if measured is None else np.asarray(measured, dtype=np.float64),
                       variant, spp, resolution, source_radius, strategy, seconds,
                       used["all"] if "all" in used else used, sensitivity)


def _properties_at(properties, lam: float, mono: bool, used: dict) -> dict:
    """The plugin properties at the wavelength ``lam`` (nm; mono variants), recorded in
    ``used`` (by wavelength, or ``all``)."""
    props = dict(properties(lam) if callable(properties) else properties)
    used[f"{lam:g}" if mono else "all"] = dict(props)
    if mono:
        props["wavelength"] = float(lam)
    return props


def _check_geometries(ti: np.ndarray, to: np.ndarray, ph: np.ndarray) -> None:
    """Equal-length, non-empty angle arrays (degrees) in the valid ranges."""
    if not (len(ti) == len(to) == len(ph)) or len(ti) == 0:
        raise ValueError("theta_i, theta_o and phi must be non-empty and of equal length")
    for name, values, lo, hi, lo_in in (("theta_i", ti, 0.0, 90.0, True),
                                         ("theta_o", to, -90.0, 90.0, False),
                                         ("phi", ph, -360.0, 360.0, True)):
        ok = np.isfinite(values) & (values >= lo if lo_in else values > lo) & (
            values < hi if name != "phi" else values <= hi)
        if not ok.all():
            bad = float(values[~ok][0])
            valid = f"{'[' if lo_in else '('}{lo:g}, {hi:g}{']' if name == 'phi' else ')'}"
            raise ValueError(out_of_range(f"{name} = {bad:g} degrees", valid))


def _wavelengths(wavelength, variant: str, shape: tuple) -> np.ndarray:
    """The wavelength (nm) per geometry: 700 nm by default in mono variants, NaN (every
    channel) in the others, which take no wavelength."""
    mono = "mono" in variant
    if wavelength is None:
        return np.full(shape, 700.0 if mono else np.nan)
    if not mono:
        raise ValueError(f"wavelength applies to mono variants only (variant = "
                         f"{variant!r}): RGB and spectral variants render every channel")
    return np.broadcast_to(np.asarray(wavelength, dtype=np.float64), shape).copy()


def _render_group(props: dict, wi: np.ndarray, wo: np.ndarray, integrator: dict,
                  source_radius: float, resolution: int, spp: int, seed: int, n_c: int):
    """Render the views ``wo`` (K, 3) of one incidence ``wi`` in one batch sensor.

    Returns:
        (pixels (K, resolution**2, n_c) without the guard columns, the patch's BSDF, the
        seconds the render took).
    """
    width = resolution + 2 * GUARD_COLUMNS
    scene = mi.load_dict({
        "type": "scene", "integrator": integrator, "patch": patch_dict(props),
        **source_dict(wi, source_radius),
        "sensor": {"type": "batch",
                   "film": film_dict(width * len(wo), resolution),
                   "sampler": {"type": "independent", "sample_count": spp},
                   **{f"s{j}": sensor_dict(view, resolution, spp, GUARD_COLUMNS)
                      for j, view in enumerate(wo)}},
    })
    start = time.perf_counter()
    image = mi.render(scene, seed=seed)
    dr.sync_thread()
    img = np.array(image, dtype=np.float64)
    seconds = time.perf_counter() - start
    pix = img.reshape(resolution, len(wo), width, -1)[
        :, :, GUARD_COLUMNS:GUARD_COLUMNS + resolution, :n_c]
    pix = np.moveaxis(pix, 1, 0).reshape(len(wo), resolution * resolution, n_c)
    bsdf = next(s.bsdf() for s in scene.shapes() if s.id() == "patch")
    return pix, bsdf, seconds


def _brf_of_pixels(pix: np.ndarray, wi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """BRF (K, C) and its standard error from the pixels (K, P, C) of views lit from ``wi``."""
    # irradiance 1 normal to the beam; in spectral variants the film sees it as the
    # sRGB value of a unit spectrum
    white = film_weights()[1].sum(axis=1) if mi.is_spectral else np.ones(3)
    scale = np.pi / wi[2] / white[:pix.shape[2]]
    return scale * pix.mean(axis=1), scale * pix.std(axis=1, ddof=1) / np.sqrt(pix.shape[1])


def _sensitivity(bsdf, wo: np.ndarray, wi: np.ndarray, stderr: np.ndarray) -> np.ndarray:
    """:func:`direction_sensitivity` (K, C) where it is needed, else 0."""
    # G sets the float32 tolerance of the deterministic values; spectral variants
    # (Monte Carlo in wavelength, and slow to differentiate in scalar_spectral) only
    # need it where a standard error is exactly 0
    out = np.zeros(stderr.shape)
    need = (np.arange(len(wo)) if not mi.is_spectral
            else np.nonzero((stderr == 0.0).any(axis=1))[0])
    if len(need):
        out[need] = direction_sensitivity(bsdf, wo[need], wi)
    return out


def render_measurements(properties, data: Measurements, **kwargs) -> GonioResult:
    """:func:`render_gonio` at the geometries and wavelengths of a measurement file (mono
    variant; the default ``llvm_ad_mono``), carrying the measured BRF into the result."""
    kwargs.setdefault("variant", "llvm_ad_mono")
    if "mono" not in kwargs["variant"]:
        raise ValueError(f"variant = {kwargs['variant']!r}: comparing with measurements "
                         "needs a mono variant (the plugin renders at each measured "
                         "wavelength), e.g. llvm_ad_mono")
    return render_gonio(properties, data.theta_i, data.theta_o, data.phi,
                        wavelength=data.wavelength, measured=data.brf, **kwargs)
