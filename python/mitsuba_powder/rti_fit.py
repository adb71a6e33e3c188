"""Per-pixel powder maps from an RTI capture: forward model, fit, relighting, synthetic captures.

An RTI capture is a fixed camera and K photographs, each lit from one known direction
(:mod:`mitsuba_powder.rti` reads them). This module fits the powder plugin to every pixel at
once, with no Python loop over pixels.

**Frame.** The image frame: x to the image's right, y to its top, z towards the camera. Arrays
are (H, W) with row 0 at the top of the image. Light directions ``l_k`` (K, 3) are unit vectors
towards the (distant) lights; the camera looks straight down the -z axis (orthographic), so the
direction towards the viewer is ``v = (0, 0, 1)`` at every pixel.

**Forward model** (:func:`render_capture`). At a pixel with unit normal ``n`` (``n_z > 0``) and
powder properties ``theta``, under light k of irradiance ``E_k`` (W/m^2, measured on a plane
perpendicular to ``l_k``; the light's *gain*), the pixel value is the reflected radiance

    ``L_k = E_k f(l_k, v; theta) max(n . l_k, 0)``            [W/(m^2 sr)]

with ``f`` the powder BRDF (1/sr) in the pixel's local frame ``mi.Frame3f(n)`` (Mitsuba's
tangent frame of ``n``; the model is isotropic, so the tangent choice does not matter). It is
evaluated exactly as Mitsuba's renderer does: ``bsdf.eval(ctx, si, wo)`` with
``si.wi = to_local(v)`` and ``wo = to_local(l_k)``, which returns ``f cos(theta_o) =
f (n . l_k)``; the model (``energy="paper"``) is reciprocal, so this equals ``f(wi = l_k, wo =
v) (n . l_k)`` in docs/model.md's naming (checked in ``tests/test_rti_fit.py``). A pixel whose light
lies below its tangent plane (``n . l_k <= 0``, attached shadow) is 0; ``n . v > 0`` always
holds here because every normal faces the camera. Values are "radiance for unit irradiance"
when ``E_k = 1``; a Lambertian white (``f = 1/pi``) at normal incidence gives ``1/pi``. In RGB
variants each channel is the model at the plugin's ``rgb_wavelengths``.

All pixels x lights are one plugin evaluation: lane ``p K + k`` is pixel p under light k, the
per-pixel properties reach the lanes by ``dr.gather`` from per-pixel arrays assigned through
``mi.traverse`` (as :class:`mitsuba_powder.model.BatchBRF` does per parameter set), the albedo as
a per-lane ``albedo.value`` colour. Evaluations are chunked over pixels when pixels x lights
exceeds ``max_lanes``.

**Fit** (:func:`fit_maps`). Variables per pixel: the normal as the slopes ``(a, b) = (n_x/n_z,
n_y/n_z)`` (``n = (a, b, 1)/|(a, b, 1)|``: smooth everywhere, no singularity at ``n = z``),
the albedo per channel, and the free powder properties (log10 for positive scale properties,
as in :data:`mitsuba_powder.fit.FITTABLE`). The loss of a pixel is
``sum_{k, c} w_{k} (E_k f_c max(n . l_k, 0) - I_{k, c})^2`` with ``w_k`` in {0, 1}: observations
flagged as saturated (any channel >= ``saturation``) or shadowed (observed far below the
model's prediction) get ``w = 0``. It is minimised by
:func:`mitsuba_powder.optimise.batch_levenberg_marquardt` with B = pixels (all pixels of a
chunk in each Dr.Jit launch; Jacobian columns by forward-mode AD, one pass per variable and one
pass for the three albedo channels together). Starts: normal and albedo from Lambertian
photometric stereo (weighted least squares per pixel, vectorised), the Lambertian albedo mapped
to the powder's single-scattering albedo through a table of the model; a free grain size from
a search over 40 sizes (x 5 extinctions when ``extinction`` is free, with ``amplitude_volume``
in closed form when it is free: :func:`_grain_start`); other properties at their defaults.
Per-light gains ``E_k`` shared by all pixels alternate with the per-pixel fit: closed-form
least squares given the per-pixel models, normalised to mean 1 (the overall scale
goes into the albedo and ``amplitude_volume``).

**What a dome of lights determines.** Cramer-Rao bounds (1-sigma, from the Jacobian at the
truth) per pixel with 1 % noise, 40 lights at elevations 10-80 degrees, a camera at the zenith,
the four regions of :data:`SYNTHETIC_REGIONS`, flat and tilted normals, all ten parameters free
-> the default seven:

* normal: 0.2-1.0 degrees -> identifiable;
* albedo per channel: 8-160 % with ``amplitude_volume`` and ``g`` free (condition number of
  J^T J 1e5-6e7), 0.03-7 % once they are held -> identifiable given A_v and g;
* ``amplitude_volume``: 50-360 % (an overall scale of the volume terms, traded against the
  albedo: L1 ~ rho and L2 ~ rho^2 differ too little in angular shape) -> not identifiable;
* ``g``: 20-500 % (the camera sees scattering angles 100-170 degrees only) -> not identifiable;
* ``extinction``: 30-450 % (it sets only the coherent cone, kappa / k0 wide, around the
  retro-reflection direction; the nearest light is 10 degrees away) and the finite-thickness
  factor -> not identifiable;
* ``amplitude_surface``, ``correlation_length``: 10-40 % (the lobe is seen by a few lights)
  -> weakly identifiable, but the lobe must be modelled: without it normals and albedo are
  biased where it is strong.

Fits of the synthetic capture agree: with ``amplitude_volume``, ``g`` and ``extinction`` free
the residual is at the noise level but region medians are off by 10-100 % (albedo by up to
23 %); with them held at the truth, albedo medians are within 1 % and normals within 0.5
degrees (median). Hence :data:`DEFAULT_FREE`: normal (2), albedo (3), ``amplitude_surface``,
``correlation_length``: 7 numbers per pixel; the others are held (at the plugin's defaults or
as given in ``fixed``), and the albedo is then relative to them.

Two changes make ``amplitude_volume`` and ``extinction`` identifiable: a grain size free
instead of the albedo (``free=["radius", ...]``: the grains set all three channels, so A_v
no longer trades against the albedo's scale) and lights near the camera, which sample the
coherent cone (:func:`synthetic_capture` ``near_camera``). Bounds per pixel with normal,
radius, A_v and extinction free (``docs/scripts/rti_identifiability.py``, images exposed to
0.9): radius 0.2-10 %, A_v 0.4-16 %, extinction 3.7-14 % with 8 of 40 lights at 82-88
degrees, against 6.9-44 % for the extinction on the 10-80 degree dome, where a fit can also
land on a second solution at the noise level; with the near-camera lights, region medians of
the synthetic capture are within 4 % (``tests/test_rti_fit.py``, docs/rti.md).

**Scale.** The overall scale of the gains is not fitted: it is a calibration (the mean of
``initial_gains``, default 1, e.g. from a white reference); only the gains relative to it are.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field

import drjit as dr
import mitsuba as mi
import numpy as np

from .fit import FITTABLE
from .model import forward_grad
from .optimise import ParamSpec, batch_levenberg_marquardt
from .variants import use_variant

__all__ = ["DEFAULT_FREE", "MAP_PROPERTIES", "MapsResult", "dome_directions", "fit_maps",
           "lambertian_start", "max_correlation_length", "relight", "render_capture",
           "synthetic_capture", "synthetic_maps"]

#: Float properties of the plugin that may vary per pixel (maps (H, W) or scalars)
MAP_PROPERTIES = ("amplitude_volume", "g", "extinction", "tau_o", "thickness",
                  "amplitude_surface", "correlation_length", "sigma")

#: Grain sizes that may vary per pixel instead of the albedo: the albedo per channel is then
#: the grains' (``radius`` of spheres or slab grains, ``agglomerate_radius``), from
#: :class:`GrainAlbedo`
GRAIN_MAPS = ("radius", "agglomerate_radius")

#: Properties the fit can free besides the normal and the albedo (per channel)
FREE_PROPERTIES = ("albedo",) + MAP_PROPERTIES + GRAIN_MAPS

#: Default free set (besides the normal): see the module docstring and docs for the evidence
DEFAULT_FREE = ["albedo", "amplitude_surface", "correlation_length"]

#: Bounds and starts of the fitted properties (the goniometric fit's, with the albedo kept
#: strictly inside (0, 1) and a surface amplitude that can vanish)
SPECS: dict[str, ParamSpec] = {
    **{k: FITTABLE[k] for k in MAP_PROPERTIES},
    "albedo": ParamSpec(1e-3, 0.999, False, 0.8),
    "amplitude_surface": ParamSpec(1e-9, 1e-2, True, 1e-5),
    # a lobe wide enough (1/e half width ~ 25 degrees) to reach the dome's lights from the
    # start: from the goniometric 1 um, LM drifts to an invisible needle. The upper bound is
    # lowered further to the dome's resolution by :func:`max_correlation_length` (held-out
    # lights of the synthetic capture, RMS / noise: bound 3 um -> 578, 1.5 -> 1.43, the
    # dome's 0.86 -> 1.13)
    "correlation_length": ParamSpec(0.05, 1.5, True, 0.4),
    **{k: FITTABLE[k] for k in GRAIN_MAPS},
}


#: Plugin properties that describe the grains: the evaluator takes the albedo per pixel
#: instead (``material``, ``eta``, ``k`` stay: they set tau_o)
GRAIN_SETTINGS = ("grains", "mixing", "agglomerate_fill", "agglomerate_radius", "radius",
                  "radius2", "fraction2")


def grain_map_name(settings: Mapping) -> str:
    """The per-pixel grain size of these settings: ``agglomerate_radius`` for agglomerates,
    else ``radius``."""
    return "agglomerate_radius" if settings.get("grains") == "agglomerate" else "radius"


class GrainAlbedo:
    """The albedo per RGB channel of grains whose size varies per pixel: rho(r) and d rho / d r
    at the plugin's ``rgb_wavelengths``, by cubic Hermite interpolation in ln r of a table of
    the plugin's own double-precision albedo (:class:`mitsuba_powder.grain_optics.GrainOptics`,
    the C++ grain models) over the fittable range of the size (:data:`SPECS`), 3000 nodes.
    ``max_error`` is the largest relative difference from direct theory at the midpoints of the
    table's intervals (measured when built).

    Args:
        name: ``radius`` (``grains`` = ``sphere`` or ``slab``) or ``agglomerate_radius``.
        settings: the plugin properties held for every pixel (``material``, ``eta``/``k``,
            ``grains``, ``agglomerate_fill``, ``mixing``, ``rgb_wavelengths``).
    """

    NODES = 3000

    def __init__(self, name: str, settings: Mapping):
        from .grain_optics import GrainOptics

        if name not in GRAIN_MAPS:
            raise ValueError(f"{name!r} is not a per-pixel grain size; choose among "
                             f"{GRAIN_MAPS}")
        model = settings.get("grains", "sphere")
        if (name == "agglomerate_radius") != (model == "agglomerate"):
            need = "agglomerate" if name == "agglomerate_radius" else "sphere or slab"
            raise ValueError(f"a per-pixel {name} needs grains = {need} (got grains = "
                             f"{model!r})")
        self.name = name
        wl = settings.get("rgb_wavelengths", (611.3, 549.1, 464.3))
        if isinstance(wl, str):
            wl = [float(v) for v in wl.replace(",", " ").split()]
        self.wavelengths = [float(v) for v in wl]
        optics = GrainOptics(dict(settings))
        spec = SPECS[name]
        self.u0, self.u1 = math.log(spec.lower), math.log(spec.upper)
        self.du = (self.u1 - self.u0) / (self.NODES - 1)
        nodes = np.exp(self.u0 + self.du * np.arange(self.NODES))
        mids = np.exp(self.u0 + self.du * (np.arange(self.NODES - 1) + 0.5))

        def table(r: np.ndarray, derivatives: bool):
            crystallite = float(settings.get("radius", 0.017))
            if name == "radius":
                return optics.albedo(self.wavelengths, r, derivatives=derivatives)
            return optics.albedo(self.wavelengths, np.full(len(r), crystallite),
                                 derivatives=derivatives, agglomerate_radius=r,
                                 agglomerate_fill=settings.get("agglomerate_fill"))

        rho, d = table(nodes, True)
        column = 0 if name == "radius" else 3
        self.rho = rho                                   # (N, 3)
        self.drho_du = d[:, :, column] * nodes[:, None]  # d rho / d ln r
        exact = table(mids, False)[0]
        approx, _ = self(mids)
        self.max_error = float(np.max(np.abs(approx / exact - 1.0)))

    def __call__(self, r: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(rho (P, 3), d rho / d r (P, 3)) at sizes r (P,) in um (inside the fittable range).
        """
        r = np.asarray(r, dtype=np.float64)
        t = np.clip((np.log(r) - self.u0) / self.du, 0.0, self.NODES - 1 - 1e-9)
        j = np.minimum(t.astype(np.int64), self.NODES - 2)
        s = (t - j)[:, None]
        h00, h10 = (1 + 2 * s) * (1 - s) ** 2, s * (1 - s) ** 2
        h01, h11 = s * s * (3 - 2 * s), s * s * (s - 1)
        p0, p1, m0, m1 = self.rho[j], self.rho[j + 1], self.drho_du[j], self.drho_du[j + 1]
        rho = h00 * p0 + h10 * self.du * m0 + h01 * p1 + h11 * self.du * m1
        # derivative of the interpolant with respect to ln r, then r
        d00, d10 = 6 * s * s - 6 * s, 3 * s * s - 4 * s + 1
        d01, d11 = -6 * s * s + 6 * s, 3 * s * s - 2 * s
        drho = (d00 * p0 / self.du + d10 * m0 + d01 * p1 / self.du + d11 * m1) / r[:, None]
        return rho, drho

#: Grain sizes tried per pixel for the start of a per-pixel grain size (log grid)
START_SIZES = 40

#: Largest normal slope |n_x / n_z|, |n_y / n_z| (tilt up to 85 degrees along an axis)
SLOPE_LIMIT = 11.4

#: Default limit of pixels x lights per plugin evaluation (bounds memory: the float64
#: Jacobian of a chunk takes 24 x lanes x variables bytes)
MAX_LANES = 1 << 21

#: Gain modes of :func:`fit_maps`
GAIN_MODES = ("fit", "fixed")

#: The camera direction in the image frame
VIEW = np.array([0.0, 0.0, 1.0])

VARIANT = "llvm_ad_rgb"


# ---------------------------------------------------------------------------
#  Input checks
# ---------------------------------------------------------------------------

def _check_directions(directions: np.ndarray, name: str = "directions") -> np.ndarray:
    """(K, 3) finite non-zero vectors -> unit float64 vectors."""
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] < 1:
        raise ValueError(f"{name} has shape {d.shape}; expected (K, 3) with K >= 1")
    if not np.all(np.isfinite(d)):
        k = int(np.nonzero(~np.all(np.isfinite(d), axis=1))[0][0])
        raise ValueError(f"{name}[{k}] = {d[k].tolist()} is not finite")
    norm = np.linalg.norm(d, axis=1)
    if np.any(norm == 0):
        k = int(np.nonzero(norm == 0)[0][0])
        raise ValueError(f"{name}[{k}] = {d[k].tolist()} is a zero vector; a light direction "
                         "needs a length > 0")
    return d / norm[:, None]


def _check_range(name: str, value: float, lower: float, upper: float,
                 open_lower: bool = False, open_upper: bool = False) -> float:
    """A finite number in [lower, upper] (open ends as asked)."""
    try:
        v = float(value)
    except (TypeError, ValueError):
        raise ValueError(f"{name} = {value!r} is not a number") from None
    lo_ok = v > lower if open_lower else v >= lower
    hi_ok = v < upper if open_upper else v <= upper
    if not (math.isfinite(v) or (upper == math.inf and v == math.inf)) or not (lo_ok and hi_ok):
        raise ValueError(f"{name} = {value!r} is out of range; valid range is "
                         f"{'(' if open_lower else '['}{lower:g}, {upper:g}"
                         f"{')' if open_upper else ']'}")
    return v


def _check_count(name: str, value, lower: int, upper: float = math.inf) -> int:
    """A whole number in [lower, upper] (2.5 is an error, not 2)."""
    v = _check_range(name, value, lower, upper)
    if not math.isfinite(v) or v != math.floor(v):
        raise ValueError(f"{name} = {value!r} is not a whole number; valid range is "
                         f"[{lower:g}, {upper:g}]")
    return int(v)


def _check_normals(normals: np.ndarray, shape: tuple[int, int], name: str = "normal"
                   ) -> np.ndarray:
    """(H, W, 3) unit normals facing the camera -> float64 normalised."""
    n = np.asarray(normals, dtype=np.float64)
    if n.shape != shape + (3,):
        raise ValueError(f"{name} has shape {n.shape}; expected {shape + (3,)}")
    bad = ~np.all(np.isfinite(n), axis=-1) | (n[..., 2] <= 0)
    if np.any(bad):
        i, j = (int(x[0]) for x in np.nonzero(bad))
        raise ValueError(f"{name}[{i}, {j}] = {n[i, j].tolist()}: a normal must be finite and "
                         "face the camera; valid range is n_z > 0")
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def _property_map(name: str, value, shape: tuple[int, int]) -> np.ndarray:
    """A float property given as a scalar or an (H, W) map -> float64 (H, W), range-checked
    against :data:`SPECS`' physical range (the plugin's)."""
    arr = np.asarray(value, dtype=np.float64)
    if arr.ndim == 0:
        arr = np.full(shape, float(arr))
    if arr.shape != shape:
        raise ValueError(f"{name} has shape {arr.shape}; expected a scalar or {shape}")
    lower, upper, lo_open, hi_open = _PHYSICAL[name]
    lo_ok = arr > lower if lo_open else arr >= lower
    hi_ok = arr < upper if hi_open else arr <= upper
    bad = ~(lo_ok & hi_ok) | np.isnan(arr)
    if np.any(bad):
        i, j = (int(x[0]) for x in np.nonzero(bad))
        raise ValueError(f"{name}[{i}, {j}] = {float(arr[i, j])!r} is out of range; valid "
                         "range is "
                         f"{'(' if lo_open else '['}{lower:g}, {upper:g}{')' if hi_open else ']'}")
    return arr


#: The plugin's valid ranges (lower, upper, lower open, upper open), docs/powder.md
_PHYSICAL = {
    "albedo": (0.0, 1.0, False, False),
    "amplitude_volume": (0.0, math.inf, False, True),
    "g": (-1.0, 1.0, True, True),
    "extinction": (0.0, math.inf, True, True),
    "tau_o": (0.0, math.inf, False, True),
    "thickness": (0.0, math.inf, False, False),
    "amplitude_surface": (0.0, math.inf, False, True),
    "correlation_length": (0.0, math.inf, True, True),
    "sigma": (0.0, math.pi / 2, True, False),
    # per-pixel grain sizes: the range of GrainAlbedo's table (the fit's)
    "radius": (FITTABLE["radius"].lower, FITTABLE["radius"].upper, False, False),
    "agglomerate_radius": (FITTABLE["agglomerate_radius"].lower,
                           FITTABLE["agglomerate_radius"].upper, False, False),
}


def _check_images(images: np.ndarray) -> np.ndarray:
    imgs = np.asarray(images)
    if imgs.ndim != 4 or imgs.shape[3] != 3:
        raise ValueError(f"images has shape {imgs.shape}; expected (K, H, W, 3) (RGB, linear)")
    if not np.all(np.isfinite(imgs)):
        idx = tuple(int(x[0]) for x in np.nonzero(~np.isfinite(imgs)))
        raise ValueError(f"images{list(idx)} = {imgs[idx]!r} is not finite")
    return imgs.astype(np.float32, copy=False)


# ---------------------------------------------------------------------------
#  The per-lane evaluator
# ---------------------------------------------------------------------------

class _Evaluator:
    """One plugin instance that evaluates ``f (n . l)`` of P pixels under K lights per launch.

    Args:
        varying: float properties given per pixel.
        settings: plugin properties held for every pixel (numbers or strings), e.g.
            ``{"lobes": "single,multiple", "g": 0.2}``.
        variant: an RGB variant of Mitsuba (``llvm_ad_rgb``, ``cuda_ad_rgb``).
    """

    def __init__(self, varying: Sequence[str], settings: Mapping, variant: str):
        if "rgb" not in variant:
            raise ValueError(f"variant = {variant!r}: RTI maps need an RGB variant (e.g. "
                             "llvm_ad_rgb or cuda_ad_rgb)")
        if settings.get("energy", "paper") != "paper":
            raise ValueError(f"energy = {settings['energy']!r}: per-pixel maps need energy = "
                             "'paper' (the only valid value here: 'conserving' tabulates its "
                             "normalisation for one value of each parameter, not one per "
                             "pixel)")
        self.variant = variant
        self.varying = list(varying)
        props = {k: v for k, v in settings.items()
                 if k not in ("type", "albedo") + GRAIN_SETTINGS}
        for name in self.varying:  # present at load so that mi.traverse exposes them
            props.setdefault(name, SPECS[name].start)
            if name == "thickness":
                props[name] = 1.0
        with use_variant(variant):
            self.bsdf = mi.load_dict({"type": "powder", **props,
                                      "albedo": {"type": "rgb", "value": [0.5, 0.5, 0.5]}})
            self.params = mi.traverse(self.bsdf)
            missing = [n for n in self.varying if n not in self.params]
            if missing:
                raise ValueError(f"properties {missing} are not differentiable with these "
                                 f"settings ({dict(settings)}); see docs/powder.md (e.g. "
                                 "correlation_length needs specular = 'harvey_shack', sigma "
                                 "needs 'gaussian')")

    def __call__(self, slopes: np.ndarray, albedo: np.ndarray, values: Mapping[str, np.ndarray],
                 directions: np.ndarray, derivatives: Sequence[str] = ()
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """``f (n . l)`` (P, K, 3) float64 and its derivatives.

        Args:
            slopes: (P, 2) normal slopes ``(n_x / n_z, n_y / n_z)``.
            albedo: (P, 3) single-scattering albedo per channel.
            values: varying property -> (P,) values.
            directions: (K, 3) unit vectors towards the lights (image frame).
            derivatives: any of ``slope_x``, ``slope_y``, ``albedo`` and the varying
                properties; ``albedo`` gives d(channel c)/d(albedo c) (the channels are
                independent).
        """
        p, k = len(slopes), len(directions)
        grads: dict[str, np.ndarray] = {}
        with use_variant(self.variant):
            pix = dr.arange(mi.UInt32, p * k) // k
            light = dr.arange(mi.UInt32, p * k) % k
            sources: dict[str, object] = {
                "slope_x": mi.Float(slopes[:, 0].astype(np.float32)),
                "slope_y": mi.Float(slopes[:, 1].astype(np.float32)),
                "albedo": mi.Color3f(*[mi.Float(albedo[:, c].astype(np.float32))
                                       for c in range(3)]),
            }
            for name in self.varying:
                sources[name] = mi.Float(np.asarray(values[name], np.float32).reshape(p))
            for name in derivatives:
                dr.enable_grad(sources[name])
            lanes = {name: dr.gather(type(src), src, pix) for name, src in sources.items()}
            table = mi.Vector3f(*[mi.Float(directions[:, c].astype(np.float32))
                                  for c in range(3)])
            lights = dr.gather(mi.Vector3f, table, light)
            dr.eval(lanes)  # one launch for every gather
            for name in self.varying:
                self.params[name] = lanes[name]
            self.params["albedo.value"] = lanes["albedo"]
            self.params.update()
            n = dr.normalize(mi.Vector3f(lanes["slope_x"], lanes["slope_y"], 1.0))
            frame = mi.Frame3f(n)
            si = dr.zeros(mi.SurfaceInteraction3f, p * k)
            si.wi = frame.to_local(mi.Vector3f(0.0, 0.0, 1.0))
            wo = frame.to_local(lights)
            out = self.bsdf.eval(mi.BSDFContext(), si, wo)
            dr.eval(out)
            value = np.array(out, dtype=np.float64).reshape(3, p, k).transpose(1, 2, 0)
            for name in derivatives:
                grads[name] = forward_grad(sources[name], out).reshape(3, p, k
                                                                         ).transpose(1, 2, 0)
                dr.disable_grad(sources[name])
        return value, grads


def _chunks(count: int, lights: int, max_lanes: int) -> list[slice]:
    """Pixel ranges of at most ``max_lanes // lights`` pixels (at least one)."""
    step = max(1, int(max_lanes) // max(lights, 1))
    return [slice(s, min(s + step, count)) for s in range(0, count, step)]


def _split_maps(maps: Mapping, shape: tuple[int, int]
                ) -> tuple[np.ndarray, np.ndarray, dict[str, np.ndarray], dict]:
    """maps -> normals (H, W, 3), albedo (H, W, 3), per-pixel float properties, settings."""
    grain = grain_map_name(maps)
    if "normal" not in maps or ("albedo" not in maps and grain not in maps):
        raise ValueError(f"maps has keys {sorted(maps)}; it needs 'normal' (H, W, 3) and "
                         f"'albedo' (H, W, 3) or (3,), or '{grain}' (H, W) or a number")
    normals = _check_normals(maps["normal"], shape)
    if grain in maps and "albedo" in maps:
        raise ValueError(f"maps has both 'albedo' and '{grain}': the grains set the albedo; "
                         "give one of them")
    if grain in maps:  # the albedo of the grains, per pixel
        size = _property_map(grain, maps[grain], shape)
        rho, _ = GrainAlbedo(grain, {k: v for k, v in maps.items()
                                     if k not in ("normal", "albedo", grain)
                                     and np.ndim(v) == 0})(size.ravel())
        maps = {**maps, "albedo": rho.reshape(shape + (3,))}
    albedo = np.asarray(maps["albedo"], dtype=np.float64)
    if albedo.shape == (3,):
        albedo = np.broadcast_to(albedo, shape + (3,))
    if albedo.shape != shape + (3,):
        raise ValueError(f"albedo has shape {albedo.shape}; expected (3,) or {shape + (3,)}")
    for c in range(3):
        _property_map("albedo", albedo[..., c], shape)
    values, settings = {}, {}
    for key, value in maps.items():
        if key in ("normal", "albedo"):
            continue
        if key in MAP_PROPERTIES:
            values[key] = _property_map(key, value, shape)
        elif key == grain:
            continue  # turned into the albedo above
        elif np.ndim(value) != 0 and key in GRAIN_SETTINGS:
            raise ValueError(f"maps[{key!r}]: only {grain} may vary per pixel among the grain "
                             "properties (give the others as numbers)")
        else:
            settings[key] = value
    return normals, albedo, values, settings


def _slopes(normals: np.ndarray) -> np.ndarray:
    """(..., 3) normals with n_z > 0 -> (..., 2) slopes (n_x / n_z, n_y / n_z)."""
    return normals[..., :2] / normals[..., 2:3]


def _normals(slopes: np.ndarray) -> np.ndarray:
    """(..., 2) slopes -> (..., 3) unit normals."""
    n = np.concatenate([slopes, np.ones(slopes.shape[:-1] + (1,))], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def render_capture(maps: Mapping, directions: np.ndarray, gains: np.ndarray | None = None,
                   variant: str = VARIANT, max_lanes: int = MAX_LANES) -> np.ndarray:
    """Render an RTI capture of a powder surface from per-pixel maps (the forward model).

    Args:
        maps: ``normal`` (H, W, 3) unit normals with n_z > 0 (image frame: x right, y up, z to
            the camera); ``albedo`` (H, W, 3) or (3,) single-scattering albedo per channel in
            [0, 1]; any of :data:`MAP_PROPERTIES` as (H, W) maps or scalars in the plugin's
            units (extinction 1/um, lengths um, ``amplitude_surface`` um^2); other plugin
            settings (``lobes``, ``specular``, ``material``, ``rgb_wavelengths``, ...) as
            values for every pixel.
        directions: (K, 3) vectors towards the lights (normalised here).
        gains: (K,) irradiance of each light, W/m^2 on a plane perpendicular to it (default 1).
        variant: an RGB variant.
        max_lanes: pixels x lights per plugin evaluation at most (memory bound).

    Returns:
        float32 (K, H, W, 3) radiance ``E_k f(l_k, v) max(n . l_k, 0)``, W/(m^2 sr) (the
        module docstring gives the exact definition).
    """
    d = _check_directions(directions)
    if "normal" not in maps:
        raise ValueError(f"maps has keys {sorted(maps)}; it needs 'normal' (H, W, 3)")
    shape = tuple(np.shape(maps["normal"])[:2])
    normals, albedo, values, settings = _split_maps(maps, shape)
    g = _check_gains(gains, len(d))
    max_lanes = _check_count("max_lanes", max_lanes, 1)
    ev = _Evaluator(list(values), settings, variant)
    slopes = _slopes(normals).reshape(-1, 2)
    alb = albedo.reshape(-1, 3)
    flat = {k: v.ravel() for k, v in values.items()}
    out = np.empty((len(d),) + shape + (3,), dtype=np.float32)
    view = out.reshape(len(d), -1, 3)
    for s in _chunks(len(slopes), len(d), max_lanes):
        value, _ = ev(slopes[s], alb[s], {k: v[s] for k, v in flat.items()}, d)
        view[:, s] = (value * g[None, :, None]).transpose(1, 0, 2)
    return out


def _check_gains(gains: np.ndarray | None, k: int) -> np.ndarray:
    if gains is None:
        return np.ones(k)
    g = np.asarray(gains, dtype=np.float64)
    if g.shape != (k,):
        raise ValueError(f"gains has shape {g.shape}; expected ({k},), one per light")
    if not np.all(np.isfinite(g)) or np.any(g <= 0):
        i = int(np.nonzero(~(np.isfinite(g) & (g > 0)))[0][0])
        raise ValueError(f"gains[{i}] = {float(g[i])!r} is out of range; valid range is "
                         "(0, inf)")
    return g


# ---------------------------------------------------------------------------
#  Lambertian start
# ---------------------------------------------------------------------------

def lambertian_start(images: np.ndarray, directions: np.ndarray,
                     weights: np.ndarray | None = None, gains: np.ndarray | None = None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """Lambertian photometric stereo (Woodham 1980), vectorised over pixels.

    Solves ``I_k / E_k = b . l_k`` per pixel by weighted least squares on the channel mean,
    then the per-channel reflectance ``R_c = pi sum_k w I_kc (n . l_k) / sum_k w E_k
    (n . l_k)^2`` (over lights with ``n . l_k > 0``).

    Args:
        images: (K, H, W, 3) linear values.
        directions: (K, 3) unit light directions.
        weights: (K, H, W) in {0, 1} (observations used), default all.
        gains: (K,) light irradiances, default 1.

    Returns:
        normals (H, W, 3) (n_z >= 0.05 enforced by tilting towards z) and the Lambertian
        reflectance (H, W, 3) (the albedo of ``f = R / pi``).
    """
    k, h, w, _ = images.shape
    g = np.ones(k) if gains is None else gains
    wt = np.ones((k, h * w)) if weights is None else weights.reshape(k, h * w).astype(float)
    lum = images.reshape(k, h * w, 3).mean(axis=2) / g[:, None]
    a = np.einsum("kp,ki,kj->pij", wt, directions, directions)
    a += 1e-9 * np.eye(3)[None]
    rhs = np.einsum("kp,kp,ki->pi", wt, lum, directions)
    try:
        b = np.linalg.solve(a, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        b = np.einsum("pij,pj->pi", np.linalg.pinv(a), rhs)
    b[:, 2] = np.maximum(b[:, 2], 1e-12)
    n = b / np.linalg.norm(b, axis=1, keepdims=True)
    # keep the start inside the slope bounds (tilt < ~87 degrees)
    n[:, 2] = np.maximum(n[:, 2], 0.05)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cos = np.maximum(directions @ n.T, 0.0)  # (K, P)
    num = np.einsum("kp,kp,kpc->pc", wt, cos, images.reshape(k, h * w, 3))
    den = np.einsum("kp,k,kp->p", wt, g, cos**2)[:, None]
    refl = np.pi * num / np.maximum(den, 1e-30)
    return n.reshape(h, w, 3), refl.reshape(h, w, 3)


def _albedo_table(ev: _Evaluator, values: Mapping[str, float], directions: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Lambertian-equivalent reflectance (per channel) of the powder for a grid of albedos,
    at n = z under the capture's lights above the horizon: (albedos, (M, 3) reflectances)."""
    grid = np.linspace(SPECS["albedo"].lower, SPECS["albedo"].upper, 96)
    up = directions[directions[:, 2] > 0.05]
    if len(up) == 0:
        up = np.array([[0.0, 0.0, 1.0]])
    m = len(grid)
    value, _ = ev(np.zeros((m, 2)), np.repeat(grid[:, None], 3, axis=1),
                  {k: np.full(m, v) for k, v in values.items()}, up)
    cos = up[:, 2]
    refl = np.pi * np.einsum("mkc,k->mc", value, cos) / np.sum(cos**2)
    return grid, refl


# ---------------------------------------------------------------------------
#  The per-pixel least-squares problem
# ---------------------------------------------------------------------------

class _PixelProblem:
    """:class:`mitsuba_powder.optimise.BatchProblem` of many pixels, one row each.

    The last column of ``y`` is the pixel's index into this problem's data (held by the
    optimiser), so that the rows the optimiser passes (active pixels, padded) find their
    observations.
    """

    def __init__(self, ev: _Evaluator, observed: np.ndarray, weights: np.ndarray,
                 directions: np.ndarray, gains: np.ndarray, layout: list[tuple[str, ParamSpec]],
                 fixed: Mapping[str, np.ndarray], fixed_albedo: np.ndarray | None = None,
                 grain: GrainAlbedo | None = None):
        self.ev = ev
        self.grain = grain                  # the albedo from a free grain size
        self.fixed_albedo = fixed_albedo    # (P, 3) when the albedo is not free
        self.observed = observed            # (P, K, 3) float64
        self.sqrt_w = np.sqrt(weights)      # (P, K)
        self.directions = directions
        self.gains = gains
        self.layout = layout                # variable name and spec, in column order
        self.fixed = fixed                  # non-free varying property -> (P,)
        p = len(observed)
        self.lower = np.array([s.to_y(s.lower) for _, s in layout] + [0.0])
        self.upper = np.array([s.to_y(s.upper) for _, s in layout] + [max(p - 1, 0)])
        self.evaluations = 0

    def unpack(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, dict]:
        """y (B, p + 1) -> pixel index, slopes, albedo, property values, dx/dy per column."""
        idx = np.rint(y[:, -1]).astype(np.int64)
        slopes = y[:, :2]
        albedo = None
        values: dict[str, np.ndarray] = {k: v[idx] for k, v in self.fixed.items()}
        dxdy: dict[str, np.ndarray] = {}
        alb_cols = []
        for j, (name, spec) in enumerate(self.layout):
            if j < 2:
                continue
            x = spec.to_x(y[:, j])
            dxdy[name] = spec.dx_dy(x)
            if name.startswith("albedo"):
                alb_cols.append(x)
            elif name in GRAIN_MAPS:
                albedo, self.drho = self.grain(x)
                values[name] = x  # (not a property of the evaluator: its map is kept)
            else:
                values[name] = x
        if albedo is None:
            albedo = np.stack(alb_cols, axis=1) if alb_cols else self.fixed_albedo[idx]
        return idx, slopes, albedo, values, dxdy

    def _residual(self, idx: np.ndarray, value: np.ndarray) -> np.ndarray:
        model = value * self.gains[None, :, None]
        r = (model - self.observed[idx]) * self.sqrt_w[idx][:, :, None]
        return r.reshape(len(idx), -1)

    def residuals(self, y: np.ndarray) -> np.ndarray:
        idx, slopes, albedo, values, _ = self.unpack(y)
        value, _ = self.ev(slopes, albedo, values, self.directions)
        self.evaluations += 1
        return self._residual(idx, value)

    def jacobian(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx, slopes, albedo, values, dxdy = self.unpack(y)
        names = ["slope_x", "slope_y"]
        if any(n.startswith("albedo") or n in GRAIN_MAPS for n, _ in self.layout):
            names.append("albedo")
        names += [n for n, _ in self.layout[2:]
                  if not n.startswith("albedo") and n not in GRAIN_MAPS]
        value, grads = self.ev(slopes, albedo, values, self.directions, names)
        self.evaluations += 1 + len(names)
        b, k = len(idx), len(self.directions)
        scale = (self.gains[None, :, None] * self.sqrt_w[idx][:, :, None])
        jac = np.zeros((b, k, 3, len(self.layout) + 1))
        for j, (name, _) in enumerate(self.layout):
            if name.startswith("albedo"):
                c = int(name[-1])
                jac[:, :, c, j] = grads["albedo"][:, :, c] * scale[:, :, 0] * dxdy[name][:, None]
            elif name in GRAIN_MAPS:  # chain rule through rho(r) per channel
                jac[:, :, :, j] = (grads["albedo"] * self.drho[:, None, :] * scale *
                                   dxdy[name][:, None, None])
            else:
                jac[:, :, :, j] = grads[name] * scale * (dxdy[name][:, None, None]
                                                         if name in dxdy else 1.0)
        return self._residual(idx, value), jac.reshape(b, k * 3, -1)


# ---------------------------------------------------------------------------
#  Result
# ---------------------------------------------------------------------------

@dataclass
class MapsResult:
    """Per-pixel powder maps fitted to an RTI capture (:func:`fit_maps`).

    Attributes:
        normals: float32 (H, W, 3) unit normals (image frame), NaN outside the mask.
        albedo: float32 (H, W, 3) single-scattering albedo per channel.
        maps: property -> float32 (H, W) map, for every free and every per-pixel fixed float
            property (plugin units).
        settings: plugin properties held for every pixel (scalars and strings).
        residual_rms: float32 (H, W) RMS of the used residuals (linear units); NaN where
            fewer observations were used than the pixel has variables (not determined).
        gains: (K,) fitted (or given) light irradiances, mean 1 when fitted.
        used: bool (K, H, W): observations in the loss (not shadowed, not saturated).
        free: the free properties (besides the normal).
        mask: bool (H, W) fitted pixels.
        variant: the Mitsuba variant.
        fit_settings: the fit's options and diagnostics (iterations, seconds, ...).
    """

    normals: np.ndarray
    albedo: np.ndarray
    maps: dict[str, np.ndarray]
    settings: dict
    residual_rms: np.ndarray
    gains: np.ndarray
    used: np.ndarray
    free: list[str]
    mask: np.ndarray
    variant: str = VARIANT
    fit_settings: dict = field(default_factory=dict)

    @property
    def n_parameters(self) -> int:
        """Fitted numbers per pixel: 2 (normal) + 3 (albedo, if free) + 1 per other property."""
        return 2 + sum(3 if n == "albedo" else 1 for n in self.free)

    def as_maps(self) -> dict:
        """The maps as :func:`render_capture` takes them (pixels outside the mask get n = z
        and the median values)."""
        normals = np.where(self.mask[..., None], self.normals, np.array([0.0, 0.0, 1.0]))
        albedo = np.where(self.mask[..., None], self.albedo,
                          np.nanmedian(self.albedo[self.mask], axis=0))
        out: dict = {"normal": normals}
        if not any(name in self.maps for name in GRAIN_MAPS):  # else the grains set it
            out["albedo"] = np.clip(albedo, 0.0, 1.0)
        for k, v in self.maps.items():
            out[k] = np.where(self.mask, v, np.nanmedian(v[self.mask]))
        out.update(self.settings)
        return out

    def predict(self, directions: np.ndarray, gains: np.ndarray | None = None) -> np.ndarray:
        """Relit images float32 (K', H, W, 3) under ``directions`` (K', 3); see :func:`relight`.
        """
        return relight(self, directions, gains)


def relight(result: MapsResult, directions: np.ndarray, gains: np.ndarray | None = None,
            max_lanes: int = MAX_LANES) -> np.ndarray:
    """The fitted surface under new lights: :func:`render_capture` with the fitted maps.

    Args:
        result: a :func:`fit_maps` result.
        directions: (K', 3) vectors towards the lights.
        gains: (K',) light irradiances (default 1: the fit's mean gain).

    Returns:
        float32 (K', H, W, 3) radiance (the capture's linear units); 0 outside the mask.
    """
    out = render_capture(result.as_maps(), directions, gains, result.variant, max_lanes)
    out[:, ~result.mask] = 0.0
    return out


# ---------------------------------------------------------------------------
#  Fit
# ---------------------------------------------------------------------------

def _flags(images_pk: np.ndarray, predicted: np.ndarray, saturated: np.ndarray,
           shadow_ratio: float, shadow_floor: float) -> np.ndarray:
    """Weights (P, K): 0 where saturated or where the observed channel mean is below the
    predicted one by more than ``max(shadow_ratio x predicted, shadow_floor)``."""
    obs = images_pk.mean(axis=2)
    pred = predicted.mean(axis=2)
    shadow = (pred - obs) > np.maximum(shadow_ratio * pred, shadow_floor)
    return (~saturated & ~shadow).astype(np.float64)


def max_correlation_length(directions: np.ndarray, wavelength: float = 464.3) -> float:
    """Largest Harvey-Shack correlation length (um) whose surface lobe a dome resolves.

    The lobe's 1/e half width in the projected plane is ``lambda / (pi l_c)``; a lobe narrower
    than half the typical spacing ``s`` of the lights (median angle from a light to its
    nearest neighbour, radians) falls between them: its height and width are then traded
    against each other freely and it relights wildly (a needle fitted to one light's noise).
    So ``l_c <= lambda / (pi s / 2)``, at the shortest RGB wavelength (nm; the narrowest lobe).
    40 lights at 10-80 degrees: s = 19.5 degrees, 0.87 um.
    """
    d = np.asarray(directions, dtype=np.float64)
    if len(d) < 2:
        return SPECS["correlation_length"].upper
    cos = np.clip(d @ d.T, -1.0, 1.0)
    np.fill_diagonal(cos, -1.0)
    spacing = float(np.median(np.arccos(np.max(cos, axis=1))))
    return float(wavelength * 1e-3 / (math.pi * max(spacing, 1e-6) / 2))


def _gain_system(res: np.ndarray, jac: np.ndarray, model: np.ndarray, sqrt_w: np.ndarray
                 ) -> tuple[np.ndarray, np.ndarray]:
    """The pixels' part of the Gauss-Newton system of the gains with every pixel's variables
    eliminated (Schur complement): ``S = sum_p (D_p - C_p^T A_p^-1 C_p)``,
    ``b = sum_p (J_g^T r - C_p^T A_p^-1 J_p^T r)``.

    Args:
        res: (B, K * 3) weighted residuals; jac: (B, K * 3, q) their Jacobian in the pixels'
            variables; model: (B, K, 3) model values without gain; sqrt_w: (B, K) weights.
    """
    b, n, q = jac.shape
    kk = model.shape[1]
    jg = (sqrt_w[:, :, None] * model)                                  # (B, K, 3)
    jp = jac.reshape(b, kk, 3, q)
    r = res.reshape(b, kk, 3)
    a = np.matmul(jac.transpose(0, 2, 1), jac)  # (B, q, q); matmul: BLAS, 5x einsum
    a += (1e-9 * np.max(np.einsum("bii->bi", a), axis=1) + 1e-30)[:, None, None] * np.eye(q)
    c = np.einsum("bkci,bkc->bik", jp, jg)                             # (B, q, K)
    a_inv_c = np.linalg.solve(a, c)
    jtr = np.matmul(jac.transpose(0, 2, 1), res[:, :, None])[:, :, 0]  # (B, q)
    a_inv_jtr = np.linalg.solve(a, jtr[:, :, None])[:, :, 0]
    s = np.diag(np.einsum("bkc,bkc->k", jg, jg)) - np.einsum("bik,bil->kl", c, a_inv_c)
    rhs = np.einsum("bkc,bkc->k", jg, r) - np.einsum("bik,bi->k", c, a_inv_jtr)
    return s, rhs


def _gain_step(gains: np.ndarray, s: np.ndarray, rhs: np.ndarray, scale: float) -> np.ndarray:
    """Gauss-Newton step of the gains on their reduced system with their mean held at
    ``scale`` (the constraint ``sum(step) = K scale - sum(gains)`` by a Lagrange multiplier),
    kept positive."""
    k = len(gains)
    diag = np.maximum(np.diag(s), 1e-30)
    kkt = np.zeros((k + 1, k + 1))
    kkt[:k, :k] = s + 1e-9 * np.diag(diag)
    kkt[:k, k] = kkt[k, :k] = 1.0
    step = np.linalg.solve(kkt, np.append(-rhs, k * scale - np.sum(gains)))[:k]
    new = np.maximum(gains + step, 0.5 * gains)
    return new * (scale / np.mean(new))


#: Extinctions (1/um) tried per pixel for the start when ``extinction`` is free with a grain
#: size: it sets the width of the coherent cone, whose cost surface has a basin per width
START_EXTINCTIONS = (0.2, 0.5, 1.0, 2.0, 5.0)


def _grain_start(ev: _Evaluator, obs: np.ndarray, weight: np.ndarray, gain: np.ndarray,
                 d: np.ndarray, slopes: np.ndarray, size_grid: np.ndarray,
                 size_rho: np.ndarray, others: Sequence[str], specs: Mapping[str, ParamSpec],
                 fixed_maps: Mapping[str, np.ndarray], max_lanes: int
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Start of a per-pixel grain size: every pixel tries :data:`START_SIZES` sizes of the log
    grid ``size_grid`` (``rho(r)`` has several branches) with its Lambertian normal ``slopes``
    and keeps the one of least weighted residual; all pixels at once, one model evaluation per
    trial. With ``amplitude_volume`` free each trial takes its best value in closed form (the
    model is ``A_v V + S``, linear in it: S, which depends on neither the size nor the
    extinction, is evaluated once with ``A_v = 0``, and each trial's evaluation with
    ``A_v = 1`` gives V); with ``extinction`` free the trials also run over
    :data:`START_EXTINCTIONS`.

    Returns:
        the start size per pixel (P,) and start values (P,) of the free properties it chose.
    """
    npix, k = len(obs), len(d)
    free_av = "amplitude_volume" in others
    exts = START_EXTINCTIONS if "extinction" in others else (None,)
    base = {n: np.full(npix, specs[n].start) for n in others}
    base.update(fixed_maps)
    best_cost = np.full(npix, np.inf)
    best = {"size": np.zeros(npix), "amplitude_volume": np.ones(npix),
            "extinction": np.ones(npix)}
    av_spec = specs["amplitude_volume"]
    chunks = _chunks(npix, k, max_lanes)
    surface = []  # per chunk: S, the model at A_v = 0 (the surface lobe alone)
    if free_av:
        for sl in chunks:
            part = {n: x[sl] for n, x in base.items()}
            value, _ = ev(slopes[sl], np.broadcast_to(size_rho[0], (len(slopes[sl]), 3)),
                          {**part, "amplitude_volume": np.zeros(len(slopes[sl]))}, d)
            surface.append(value * gain[None, :, None])
    for ext in exts:
        vals = dict(base)
        if ext is not None:
            vals["extinction"] = np.full(npix, ext)
        for i in range(0, len(size_grid), max(len(size_grid) // START_SIZES, 1)):
            rho = np.broadcast_to(size_rho[i], (npix, 3))
            cost, av = np.zeros(npix), np.ones(npix)
            for j, sl in enumerate(chunks):
                part = {n: x[sl] for n, x in vals.items()}
                if free_av:
                    unit = np.ones(len(slopes[sl]))
                    one, _ = ev(slopes[sl], rho[sl], {**part, "amplitude_volume": unit}, d)
                    surf = surface[j]
                    vol = one * gain[None, :, None] - surf
                    wv = weight[sl, :, None] * vol
                    num = np.sum(wv * (obs[sl] - surf), axis=(1, 2))
                    den = np.maximum(np.sum(wv * vol, axis=(1, 2)), 1e-30)
                    av[sl] = np.clip(num / den, av_spec.lower, av_spec.upper)
                    model = av[sl, None, None] * vol + surf
                else:
                    v, _ = ev(slopes[sl], rho[sl], part, d)
                    model = v * gain[None, :, None]
                cost[sl] = np.sum(weight[sl, :, None] * (model - obs[sl]) ** 2, axis=(1, 2))
            better = cost < best_cost
            best_cost[better] = cost[better]
            best["size"][better] = size_grid[i]
            best["amplitude_volume"][better] = av[better]
            if ext is not None:
                best["extinction"][better] = ext
    found = {}
    if free_av:
        found["amplitude_volume"] = best["amplitude_volume"]
    if "extinction" in others:
        found["extinction"] = best["extinction"]
    return best["size"], found


def fit_maps(images: np.ndarray, directions: np.ndarray, free: Sequence[str] | None = None,
             mask: np.ndarray | None = None, fixed: Mapping | None = None,
             gains: str = "fit", initial_gains: np.ndarray | None = None,
             max_iterations: int = 30, rounds: int = 3, saturation: float = 0.99,
             shadow_ratio: float = 0.5, shadow_floor: float = 0.03, variant: str = VARIANT,
             max_lanes: int = MAX_LANES, progress: Callable[[str], None] | None = None
             ) -> MapsResult:
    """Fit a normal and powder properties to every pixel of an RTI capture.

    Args:
        images: (K, H, W, 3) linear pixel values, 1.0 = the encoding's maximum.
        directions: (K, 3) vectors towards the lights (image frame; normalised here).
        free: properties fitted per pixel besides the normal: ``albedo`` (3 channels) and any
            of :data:`MAP_PROPERTIES`; default :data:`DEFAULT_FREE`. At most 10 numbers per
            pixel (normal 2 + albedo 3 + 5 more).
        mask: bool (H, W) pixels to fit (default all).
        fixed: plugin properties held: floats or (H, W) maps of :data:`MAP_PROPERTIES` (not
            free), ``albedo`` as (3,) or (H, W, 3) when not free, and settings (``lobes``,
            ``specular``, ``material``, ``rgb_wavelengths``, ...).
        gains: ``fit`` (per-light gains shared by all pixels, mean 1) or ``fixed``
            (``initial_gains``, default 1).
        initial_gains: (K,) start (``fit``) or value (``fixed``) of the gains.
        max_iterations: Levenberg-Marquardt iterations per round, >= 1.
        rounds: alternations of the per-pixel fit with the gains (and the shadow flags), >= 1;
            a final per-pixel fit follows the last gain update.
        saturation: observations with any channel >= this are left out, in (0, inf).
        shadow_ratio, shadow_floor: an observation is "shadowed" (left out) when its channel
            mean is below the model's prediction by more than ``max(shadow_ratio x predicted,
            shadow_floor)``; ratio in (0, 1], floor (linear units) >= 0.
        variant: an RGB variant (``llvm_ad_rgb``, ``cuda_ad_rgb``).
        max_lanes: pixels x lights per plugin evaluation (and per optimiser batch) at most.
        progress: called with a line of text after each stage.

    Returns:
        A :class:`MapsResult`.
    """
    t0 = time.perf_counter()
    imgs = _check_images(images)
    k, h, w, _ = imgs.shape
    d = _check_directions(directions)
    if len(d) != k:
        raise ValueError(f"directions has {len(d)} rows for {k} images; expected one per image")
    free = list(DEFAULT_FREE if free is None else free)
    for name in free:
        if name not in FREE_PROPERTIES:
            raise ValueError(f"free property {name!r} is not fittable per pixel; choose among "
                             f"{list(FREE_PROPERTIES)}")
    if len(set(free)) != len(free):
        raise ValueError(f"free = {free} names a property twice")
    n_par = 2 + sum(3 if n == "albedo" else 1 for n in free)
    if n_par > 10:
        raise ValueError(f"free = {free} gives {n_par} numbers per pixel; valid range is at "
                         "most 10 (normal 2 + albedo 3 + 5)")
    if gains not in GAIN_MODES:
        raise ValueError(f"gains = {gains!r} is not a gain mode; choose one of {GAIN_MODES}")
    max_iterations = _check_count("max_iterations", max_iterations, 1)
    rounds = _check_count("rounds", rounds, 1)
    saturation = _check_range("saturation", saturation, 0.0, math.inf, open_lower=True)
    shadow_ratio = _check_range("shadow_ratio", shadow_ratio, 0.0, 1.0, open_lower=True)
    shadow_floor = _check_range("shadow_floor", shadow_floor, 0.0, math.inf)
    max_lanes = _check_count("max_lanes", max_lanes, 1)
    g = _check_gains(initial_gains, k)
    scale = float(np.mean(g))  # the overall scale: a calibration, not fitted
    if mask is None:
        mask = np.ones((h, w), dtype=bool)
    mask = np.asarray(mask)
    if mask.shape != (h, w):
        raise ValueError(f"mask has shape {mask.shape}; expected ({h}, {w})")
    mask = mask.astype(bool)
    if not mask.any():
        raise ValueError("mask selects no pixel; it needs at least one True")
    fixed = dict(fixed or {})
    for name in free:
        if name in fixed:
            raise ValueError(f"property {name!r} is both free and fixed")
    fixed_maps = {n: _property_map(n, v, (h, w))[mask] for n, v in fixed.items()
                  if n in MAP_PROPERTIES}
    grain_name = grain_map_name(fixed)
    wrong = [n for n in GRAIN_MAPS if n in free and n != grain_name]
    if wrong:
        raise ValueError(f"{wrong[0]} cannot be free with grains = "
                         f"{fixed.get('grains', 'sphere')!r}; free {grain_name} instead")
    settings = {n: v for n, v in fixed.items()
                if n not in MAP_PROPERTIES and n != "albedo" and n != grain_name}
    grain = None
    if grain_name in free or grain_name in fixed:
        if "albedo" in free or "albedo" in fixed:
            raise ValueError(f"albedo and {grain_name} cannot both be given: the grains set the "
                             "albedo per pixel; free or fix one of them")
        grain = GrainAlbedo(grain_name, settings)
    fixed_albedo = None
    if grain is not None and grain_name in fixed:
        size = _property_map(grain_name, fixed[grain_name], (h, w))[mask]
        fixed_albedo = grain(size)[0]
    elif "albedo" not in free and grain_name not in free:
        if "albedo" not in fixed:
            raise ValueError(f"albedo is neither free nor fixed; give fixed={{'albedo': ...}} "
                             f"or free (or fix) the grain size {grain_name}")
        a = np.asarray(fixed["albedo"], dtype=np.float64)
        a = np.broadcast_to(a, (h, w, 3)) if a.shape == (3,) else a
        if a.shape != (h, w, 3):
            raise ValueError(f"fixed albedo has shape {a.shape}; expected (3,) or ({h}, {w}, 3)")
        for c in range(3):
            _property_map("albedo", a[..., c], (h, w))
        fixed_albedo = a[mask]
    others = [n for n in free if n != "albedo" and n not in GRAIN_MAPS]
    varying = others + list(fixed_maps)
    ev = _Evaluator(varying, settings, variant)
    layout: list[tuple[str, ParamSpec]] = [
        ("slope_x", ParamSpec(-SLOPE_LIMIT, SLOPE_LIMIT, False, 0.0)),
        ("slope_y", ParamSpec(-SLOPE_LIMIT, SLOPE_LIMIT, False, 0.0))]
    if "albedo" in free:
        layout += [(f"albedo{c}", SPECS["albedo"]) for c in range(3)]
    if grain_name in free:
        layout.append((grain_name, SPECS[grain_name]))
    specs = dict(SPECS)
    lc_max = max_correlation_length(d)
    lc = specs["correlation_length"]
    specs["correlation_length"] = ParamSpec(lc.lower, max(min(lc.upper, lc_max), 2 * lc.lower),
                                            lc.log, min(lc.start, 0.8 * lc_max))
    layout += [(n, specs[n]) for n in others]
    stages: list[str] = []

    def report(line: str) -> None:
        stages.append(line)
        if progress:
            progress(line)

    # observations of the masked pixels, (P, K, 3)
    obs = np.ascontiguousarray(imgs[:, mask].transpose(1, 0, 2)).astype(np.float64)
    npix = len(obs)
    saturated = np.any(obs >= saturation, axis=2)
    start_values = {n: SPECS[n].start for n in others}
    table_values = {**start_values, **{n: float(np.median(v)) for n, v in fixed_maps.items()}}
    table = (_albedo_table(ev, table_values, d)
             if "albedo" in free or grain_name in free else None)
    size_grid = (np.exp(np.linspace(math.log(SPECS[grain_name].lower),
                                    math.log(SPECS[grain_name].upper), 400))
                 if grain_name in free else None)
    size_rho = grain(size_grid)[0] if size_grid is not None else None

    def start(gain: np.ndarray, weight: np.ndarray, search: bool = True
              ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Lambertian start of every pixel under the gains ``gain`` (on the used lights);
        ``search``: also the grain-size search (else the default size)."""
        n0, refl = lambertian_start(obs.transpose(1, 0, 2)[:, :, None, :], d,
                                    weight.T[:, :, None], gain)
        n0, refl = n0[:, 0], refl[:, 0]
        y = np.zeros((npix, len(layout) + 1))
        y[:, :2] = np.clip(_slopes(n0), -SLOPE_LIMIT, SLOPE_LIMIT)
        col = 2
        starts: dict[str, np.ndarray] = {}
        if table is not None:
            albedo0 = np.stack([np.interp(refl[:, c], table[1][:, c], table[0])
                                for c in range(3)], axis=1)
            if size_grid is None:
                y[:, col:col + 3] = albedo0
                col += 3
            elif not search:
                y[:, col] = specs[grain_name].to_y(specs[grain_name].start)
                col += 1
            else:
                # rho(r) has several branches: every pixel tries a log grid of sizes with the
                # Lambertian normal (one model evaluation per size, all pixels at once) and
                # starts from the one of least weighted residual
                slopes0 = np.clip(_slopes(n0), -SLOPE_LIMIT, SLOPE_LIMIT)
                size, found = _grain_start(ev, obs, weight, gain, d, slopes0, size_grid,
                                           size_rho, others, specs, fixed_maps, max_lanes)
                y[:, col] = specs[grain_name].to_y(size)
                col += 1
                starts.update(found)
        for name in others:
            y[:, col] = specs[name].to_y(starts.get(name, specs[name].start))
            col += 1
        y[:, -1] = np.arange(npix)
        return y, n0, refl

    # shadows flagged against the Lambertian prediction (twice: the second fit without them)
    wt = (~saturated).astype(np.float64)
    for i in range(2):
        y, n0, refl = start(g, wt, search=i == 1)
        pred = (np.maximum(n0 @ d.T, 0.0)[:, :, None] * refl[:, None, :] / np.pi
                * g[None, :, None])
        wt = _flags(obs, pred, saturated, shadow_ratio, shadow_floor)
    report(f"start: Lambertian photometric stereo on {npix} pixels, "
           f"{int(np.sum(wt == 0))} observations flagged")
    hold = np.zeros(len(layout) + 1, dtype=bool)
    hold[-1] = True
    chunks = _chunks(npix, k, max_lanes)
    iterations, evaluations = 0, 0
    value = np.zeros((npix, k, 3))
    total_rounds = rounds + (1 if gains == "fit" else 0)
    for r in range(total_rounds):
        last = r == total_rounds - 1
        update_gains = gains == "fit" and not last
        reduced = np.zeros((k, k)), np.zeros(k)
        y_start = start(g, wt)[0] if r > 0 else y
        for s in chunks:
            prob = _PixelProblem(ev, obs[s], wt[s], d, g, layout,
                                 {n: v[s] for n, v in fixed_maps.items()},
                                 None if fixed_albedo is None else fixed_albedo[s], grain)
            # every round starts from the Lambertian start under the current gains: a warm
            # start would keep pixels in the surface-lobe basin the previous gains led them to
            y_chunk = y_start[s].copy()
            y_chunk[:, -1] = np.arange(len(y_chunk))
            # hopeless = inf: pixels are not competing starts (inf x a zero cost, of a pixel
            # with no used observation, is NaN and stops nothing: not a warning)
            with np.errstate(invalid="ignore"):
                state = batch_levenberg_marquardt(prob, y_chunk, max_iterations, hold=hold,
                                                  hopeless=math.inf)
            y[s, :-1] = state.y[:, :-1]
            iterations = max(iterations, state.iterations)
            _, slopes, albedo, values, _ = prob.unpack(state.y)
            if update_gains:
                res, jac = prob.jacobian(state.y)
                value[s], _ = ev(slopes, albedo, values, d)
                part = _gain_system(res, jac[:, :, :-1], value[s], prob.sqrt_w)
                reduced = reduced[0] + part[0], reduced[1] + part[1]
            else:
                value[s], _ = ev(slopes, albedo, values, d)
            evaluations += prob.evaluations
        if update_gains:
            g = _gain_step(g, *reduced, scale)
        if not last:
            wt = _flags(obs, value * g[None, :, None], saturated, shadow_ratio, shadow_floor)
        rms = np.sqrt(np.sum(wt[:, :, None] * (value * g[None, :, None] - obs) ** 2)
                      / max(3 * np.sum(wt), 1))
        report(f"round {r + 1}/{total_rounds}: Levenberg-Marquardt ({len(chunks)} chunk(s)), "
               f"RMS residual {rms:.5g}, {int(np.sum(wt == 0))} observations left out")

    # maps
    def to_map(values: np.ndarray, channels: int = 0) -> np.ndarray:
        shape = (h, w, channels) if channels else (h, w)
        out = np.full(shape, np.nan, dtype=np.float32)
        out[mask] = values
        return out

    prob = _PixelProblem(ev, obs, wt, d, g, layout, fixed_maps, fixed_albedo, grain)
    y_all = y.copy()
    y_all[:, -1] = np.arange(npix)
    _, slopes, albedo, values, _ = prob.unpack(y_all)
    resid = (value * g[None, :, None] - obs) * wt[:, :, None]
    used_count = np.maximum(3 * wt.sum(axis=1), 1)
    rms_map = np.sqrt(np.sum(resid**2, axis=(1, 2)) / used_count)
    # a pixel with fewer used observations than variables is not determined: NaN residual
    underdetermined = 3 * wt.sum(axis=1) < len(layout)
    rms_map[underdetermined] = np.nan
    used = np.zeros((k, h, w), dtype=bool)
    used[:, mask] = (wt > 0).T
    return MapsResult(
        normals=to_map(_normals(slopes), 3), albedo=to_map(albedo, 3),
        maps={n: to_map(v) for n, v in values.items()}, settings=settings,
        residual_rms=to_map(rms_map), gains=g, used=used, free=free, mask=mask,
        variant=variant,
        fit_settings={"free": free, "gains": gains, "max_iterations": max_iterations,
                      "rounds": rounds, "saturation": saturation,
                      "shadow_ratio": shadow_ratio, "shadow_floor": shadow_floor,
                      "max_lanes": max_lanes, "chunks": len(chunks),
                      "correlation_length_max_um": specs["correlation_length"].upper,
                      "iterations_last_round": iterations, "evaluations": evaluations,
                      "underdetermined_pixels": int(np.sum(underdetermined)),
                      "seconds": time.perf_counter() - t0, "stages": stages,
                      "fixed": {n: v for n, v in fixed.items()
                                if np.ndim(v) == 0 or isinstance(v, str)}})


# ---------------------------------------------------------------------------
#  Synthetic capture
# ---------------------------------------------------------------------------

#: Properties of the four regions of :func:`synthetic_capture` (top-left, top-right,
#: bottom-left, bottom-right quadrants)
SYNTHETIC_REGIONS: list[dict] = [
    {"albedo": (0.90, 0.62, 0.38), "amplitude_volume": 1.0, "g": 0.3, "extinction": 0.5,
     "amplitude_surface": 3e-5, "correlation_length": 0.4},
    {"albedo": (0.55, 0.70, 0.85), "amplitude_volume": 0.8, "g": -0.2, "extinction": 2.0,
     "amplitude_surface": 1e-4, "correlation_length": 0.25},
    {"albedo": (0.75, 0.75, 0.72), "amplitude_volume": 1.3, "g": 0.0, "extinction": 1.0,
     "amplitude_surface": 1e-5, "correlation_length": 0.6},
    {"albedo": (0.95, 0.85, 0.45), "amplitude_volume": 1.1, "g": 0.5, "extinction": 0.2,
     "amplitude_surface": 5e-5, "correlation_length": 0.3},
]

#: Properties of the four regions of a SYNTHETIC capture of hematite grains
#: (``regions="grains"``): grain radius (um; the albedo per channel follows from it),
#: ``amplitude_volume`` and ``extinction`` (1/um) differ per region, ``g``, and the surface
#: lobe are the same everywhere
SYNTHETIC_GRAIN_REGIONS: list[dict] = [
    {"radius": 0.045, "amplitude_volume": 1.0, "extinction": 0.5, "g": 0.0,
     "amplitude_surface": 1e-5, "correlation_length": 0.4},
    {"radius": 0.06, "amplitude_volume": 0.8, "extinction": 2.0, "g": 0.0,
     "amplitude_surface": 1e-5, "correlation_length": 0.4},
    {"radius": 0.08, "amplitude_volume": 1.3, "extinction": 1.0, "g": 0.0,
     "amplitude_surface": 1e-5, "correlation_length": 0.4},
    {"radius": 0.4, "amplitude_volume": 1.1, "extinction": 3.0, "g": 0.0,
     "amplitude_surface": 1e-5, "correlation_length": 0.4},
]

#: Region sets of :func:`synthetic_maps`
SYNTHETIC_REGION_SETS: dict[str, list[dict]] = {"albedo": SYNTHETIC_REGIONS,
                                                 "grains": SYNTHETIC_GRAIN_REGIONS}


def dome_directions(count: int = 40, min_elevation: float = 10.0, max_elevation: float = 80.0,
                    seed: int = 0) -> np.ndarray:
    """``count`` light directions on a dome: a Fibonacci spiral in elevation between
    ``min_elevation`` and ``max_elevation`` (degrees, uniform in sin(elevation)), (count, 3)."""
    count = _check_count("count", count, 1)
    lo = _check_range("min_elevation", min_elevation, 0.0, 90.0)
    hi = _check_range("max_elevation", max_elevation, lo, 90.0)
    i = np.arange(count) + 0.5
    s = np.sin(np.radians(lo)) + (np.sin(np.radians(hi)) - np.sin(np.radians(lo))) * i / count
    phi = i * math.pi * (3.0 - math.sqrt(5.0)) + 0.3 * seed
    c = np.sqrt(1.0 - s**2)
    return np.stack([c * np.cos(phi), c * np.sin(phi), s], axis=1)


def synthetic_maps(height: int = 64, width: int = 64, relief: float = 0.25,
                   seed: int = 0, regions: str = "albedo") -> tuple[dict, np.ndarray]:
    """SYNTHETIC per-pixel maps: four quadrants with the properties of
    :data:`SYNTHETIC_REGIONS` (``regions="albedo"``: an albedo per channel) or
    :data:`SYNTHETIC_GRAIN_REGIONS` (``"grains"``: a hematite grain radius) and a gentle
    relief: six Gaussian bumps (random centres, widths 0.08-0.2 of the image, heights
    +-(0.5-1) ``relief`` x width), which tilts the normals by up to about 15 degrees (median 5)
    at the default ``relief`` = 0.25.

    Returns:
        maps for :func:`render_capture` and the (H, W) region index (0-3).
    """
    h = _check_count("height", height, 2)
    w = _check_count("width", width, 2)
    relief = _check_range("relief", relief, 0.0, 2.0)
    if regions not in SYNTHETIC_REGION_SETS:
        raise ValueError(f"regions = {regions!r} is not a region set; choose one of "
                         f"{list(SYNTHETIC_REGION_SETS)}")
    table = SYNTHETIC_REGION_SETS[regions]
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    u, v = (xx + 0.5) / w, 1.0 - (yy + 0.5) / h          # image frame: x right, y up
    z = np.zeros((h, w))
    dzdu, dzdv = np.zeros((h, w)), np.zeros((h, w))
    for _ in range(6):
        cu, cv = rng.uniform(0.1, 0.9, 2)
        s = rng.uniform(0.08, 0.2)
        a = rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0) * relief * s
        e = a * np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * s * s))
        z += e
        dzdu += -e * (u - cu) / (s * s)
        dzdv += -e * (v - cv) / (s * s)
    normal = np.stack([-dzdu, -dzdv, np.ones((h, w))], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    region = (yy >= h / 2).astype(int) * 2 + (xx >= w / 2).astype(int)
    maps: dict = {"normal": normal}
    for name in table[0]:
        maps[name] = np.zeros((h, w, 3) if name == "albedo" else (h, w))
    for i, props in enumerate(table):
        sel = region == i
        for name, value in props.items():
            maps[name][sel] = value
    return maps, region


def synthetic_capture(height: int = 64, width: int = 64, lights: int = 40,
                      noise: float = 0.01, gains: np.ndarray | None = None,
                      relief: float = 0.25, seed: int = 0, exposure: float | None = 2.0,
                      variant: str = VARIANT, regions: str = "albedo",
                      near_camera: int = 0) -> dict:
    """A SYNTHETIC RTI capture rendered by :func:`render_capture` from known maps.

    Four quadrants of different properties (:func:`synthetic_maps`: ``regions="albedo"``,
    :data:`SYNTHETIC_REGIONS`, or ``"grains"``, :data:`SYNTHETIC_GRAIN_REGIONS`), a relief of
    Gaussian bumps, ``lights`` lights on a dome (elevations 10-80 degrees,
    :func:`dome_directions`), additive Gaussian noise of standard deviation ``noise`` (linear
    units, 1 = full scale).

    Args:
        exposure: the light irradiance (every gain is multiplied by it) so that the images
            fill the range (the brightest values stay below 1); None: the brightest
            noise-free value is 0.9.
        gains: (lights,) relative per-light gains (default 1).
        near_camera: how many of the ``lights`` sit at elevations 82-88 degrees, 2-8 degrees
            from the camera (the rest on the 10-80 degree dome): they sample the coherent
            back-scattering cone, the only part of the images that depends on the
            ``extinction`` (module doc, "What a dome of lights determines").

    Returns:
        dict: ``images`` float32 (K, H, W, 3) (noisy), ``clean`` (noise-free),
        ``directions`` (K, 3), ``maps`` (the truth), ``region`` (H, W), ``gains`` (the
        irradiances used), ``noise``, and ``label = "SYNTHETIC"``.
    """
    noise = _check_range("noise", noise, 0.0, math.inf)
    if exposure is not None:
        exposure = _check_range("exposure", exposure, 0.0, math.inf, open_lower=True)
    lights = _check_count("lights", lights, 1)
    near = _check_count("near_camera", near_camera, 0, lights)
    d = np.concatenate(([dome_directions(lights - near)] if lights > near else []) +
                       ([dome_directions(near, 82.0, 88.0, seed=1)] if near else []))
    rel = _check_gains(gains, len(d))
    maps, region = synthetic_maps(height, width, relief, seed, regions)
    if exposure is None:
        exposure = 0.9 / float(np.max(render_capture(maps, d, rel, variant)))
    clean = render_capture(maps, d, exposure * rel, variant)
    rng = np.random.default_rng(seed + 1)
    images = (clean + rng.normal(0.0, noise, clean.shape)).astype(np.float32)
    return {"images": images, "clean": clean, "directions": d, "maps": maps,
            "region": region, "gains": exposure * rel, "noise": noise,
            "label": "SYNTHETIC"}
