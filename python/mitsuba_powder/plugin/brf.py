"""BRF of the powder plugin at measurement geometries, vectorised, differentiable.

- :class:`PowderBRF`: the plugin as a user loads it, one ``llvm_ad_mono`` instance per distinct
  wavelength (``wavelength`` property, Mie albedo from the radius), each evaluated over all of
  that wavelength's geometries in one call. Simulation, prediction and reports use it.
- :class:`BatchBRF`: the fit's engine: one ``llvm_ad_spectral`` instance evaluates every row
  of every wavelength for a batch of parameter sets in one launch, with forward-mode
  derivatives; it takes the albedo and tau_o as numbers (from
  :mod:`mitsuba_powder.plugin.grains`) and equals :class:`PowderBRF` to float precision.

Any wavelength the optical constants cover works (e.g. 351 and 1064 nm for PTFE).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from .._checks import check_range
from ..io.measurements import Measurements
from ..variants import use_variant
from .grains import DEFAULT_MATERIAL

VARIANT = "llvm_ad_mono"


class PowderBRF:
    """Evaluate ``BRF = pi f(wi, wo)`` of the powder plugin at measured geometries.

    Args:
        data: the geometries (and wavelengths) to evaluate.
        properties: plugin properties (without ``type`` and ``wavelength``).

    Attributes:
        groups: per wavelength, ``(wavelength, row indices, bsdf, params, si, wo, mu_o)``.
    """

    def __init__(self, data: Measurements, properties: dict):
        self.data = data
        self.properties = dict(properties)
        self.groups = []
        wi, wo = data.directions()
        with use_variant(VARIANT):
            for lam in data.wavelengths():
                idx = np.nonzero(data.wavelength == lam)[0]
                bsdf = mi.load_dict({"type": "powder", **self.properties,
                                     "wavelength": float(lam)})
                si = dr.zeros(mi.SurfaceInteraction3f, len(idx))
                si.wi = mi.Vector3f(*[wi[idx, k].astype(np.float32) for k in range(3)])
                wov = mi.Vector3f(*[wo[idx, k].astype(np.float32) for k in range(3)])
                self.groups.append((float(lam), idx, bsdf, mi.traverse(bsdf), si, wov,
                                    mi.Float(wo[idx, 2].astype(np.float32))))

    def brf_dr(self, group) -> mi.Float:
        """Dr.Jit BRF of one wavelength group (differentiable)."""
        _, _, bsdf, _, si, wo, mu_o = group
        value = bsdf.eval(mi.BSDFContext(), si, wo)
        return dr.pi * value[0] / mu_o

    def brf(self) -> np.ndarray:
        """BRF at every row of ``data`` (float64 copy of the float32 values)."""
        out = np.empty(len(self.data))
        with use_variant(VARIANT):
            for group in self.groups:
                out[group[1]] = np.array(self.brf_dr(group), dtype=np.float64)
        return out



#: Variant of :class:`BatchBRF` with several wavelengths: each lane carries its own
BATCH_VARIANT = "llvm_ad_spectral"


def batch_variant(wavelengths: np.ndarray) -> str:
    """The variant :class:`BatchBRF` uses: ``llvm_ad_mono`` (the ``wavelength`` property) for
    one wavelength, ``llvm_ad_spectral`` (each lane at its own wavelength) for several."""
    return VARIANT if len(np.unique(wavelengths)) == 1 else BATCH_VARIANT

#: Forward passes keep the graph's edges (several passes share one traced evaluation)
_KEEP_EDGES = dr.ADFlag.ClearInterior | dr.ADFlag.ClearInput

#: Plugin properties that describe the grains: :class:`BatchBRF` takes the albedo and tau_o
#: they give as numbers (see :mod:`mitsuba_powder.plugin.grains`)
GRAIN_PROPERTIES = ("radius", "radius2", "fraction2", "grains", "agglomerate_radius",
                    "agglomerate_fill", "mixing", "material", "eta", "k", "radius3",
                    "fraction3", "radius4", "fraction4") + tuple(
    f"{k}{j}" for j in (2, 3, 4) for k in ("material", "eta", "k"))
#: The grain material's index, which the surface term reads with surface_fresnel = "fresnel"
INDEX_PROPERTIES = ("material", "eta", "k")


def engine_properties(properties: dict) -> dict:
    """The fixed properties :class:`BatchBRF` gives the plugin itself: all but the grain
    properties, ``albedo`` and ``tau_o`` (which come per call, as numbers), and but ``type``
    and ``wavelength``; with ``surface_fresnel = "fresnel"`` the grain material's index
    (``material``, ``eta``, ``k``; the default material when none is given) too, since the
    surface term's factor reads it."""
    fresnel = properties.get("surface_fresnel") == "fresnel"
    out = {k: v for k, v in properties.items()
           if (k not in GRAIN_PROPERTIES or (fresnel and k in INDEX_PROPERTIES))
           and k not in ("albedo", "tau_o", "type", "wavelength")}
    if fresnel and not any(k in properties for k in INDEX_PROPERTIES):
        # the engine gives tau_o as a number: name the material the fit's tau_o comes from
        out["material"] = DEFAULT_MATERIAL
    return out


def forward_grad(source, output) -> np.ndarray:
    """Tangent of ``output`` for a unit tangent on every entry of ``source``, by forward-mode AD.

    Used for Jacobian columns: one call per variable (or per group of variables whose
    tangents do not mix, e.g. the three channels of a colour), several calls on one graph.

    Args:
        source: a Dr.Jit variable (or a list of them) with gradients enabled, on which
            ``output`` depends.
        output: the evaluated output of the graph.

    Returns:
        ``output``'s tangent as a float64 array shaped as ``np.array(output)`` gives it
        (e.g. (3, N) for a colour of N lanes). The graph's edges are kept (``KeepEdges``) so
        that later calls can traverse it again; the output's gradient is cleared.
    """
    sources = source if isinstance(source, (list, tuple)) else [source]
    for s in sources:
        dr.set_grad(s, dr.ones(type(s), dr.shape(s)) if dr.is_tensor_v(s) else
                    dr.full(type(s), 1.0, dr.width(s)))
        dr.enqueue(dr.ADMode.Forward, s)
    dr.traverse(dr.ADMode.Forward, flags=_KEEP_EDGES)
    grad = dr.grad(output)
    dr.eval(grad)
    out = np.array(grad, dtype=np.float64)
    dr.clear_grad(output)
    return out


class BatchBRF:
    """The plugin's BRF at every measured row for ``batch`` parameter sets at once.

    One plugin instance evaluates every row of every set in one lane: in ``llvm_ad_spectral``
    each lane at its own wavelength (all four spectral samples of a lane set to the row's
    wavelength), or, with one wavelength, in ``llvm_ad_mono`` at its ``wavelength`` property
    (:func:`batch_variant`). An evaluation is one Dr.Jit launch and each derivative one
    forward-mode pass over the same traced graph. Per-set values of the ``varying`` properties
    are gathered per lane. The albedo is a number per set and wavelength, given to the plugin as a
    one-texel-per-value ``bitmap``; ``tau_o`` is given per lane (from the grain material, or
    per set when it is fitted). Values equal a ``llvm_ad_mono`` instance at the row's
    wavelength (``tests/fitting/test_fit.py``).

    Args:
        data: the geometries and wavelengths.
        properties: plugin properties held fixed; ``albedo``, ``tau_o`` and the grain
            properties are ignored (they come per call).
        batch: number of parameter sets per evaluation.
        varying: float properties set per parameter set (e.g. ``extinction``; ``tau_o`` too).
    """

    def __init__(self, data: Measurements, properties: dict, batch: int, varying: list[str]):
        check_range("batch", batch, 1)
        self.data = data
        self.batch = int(batch)
        self.varying = list(varying)
        self.wavelengths = data.wavelengths()
        n, w = len(data), len(self.wavelengths)
        fixed = engine_properties(properties)
        self.texels = max(self.batch * w, 2)  # a bitmap edited through mi.traverse: >= 2 x 2
        wi, wo = data.directions()
        lane_set = np.repeat(np.arange(self.batch), n)
        lane_row = np.tile(np.arange(n), self.batch)
        row_wl = np.searchsorted(self.wavelengths, data.wavelength)
        texel = lane_set * w + row_wl[lane_row]
        self.variant = batch_variant(self.wavelengths)
        mono = self.variant == VARIANT
        if mono:
            fixed["wavelength"] = float(self.wavelengths[0])
        with use_variant(self.variant):
            texture = {"type": "bitmap", "raw": True, "filter_type": "nearest",
                       "wrap_mode": "clamp",
                       "data": mi.TensorXf(np.full((2, self.texels, 1), 0.5, np.float32))}
            self.bsdf = mi.load_dict({"type": "powder", **fixed, "albedo": texture,
                                      "tau_o": 1.0})
            self.params = mi.traverse(self.bsdf)
            si = dr.zeros(mi.SurfaceInteraction3f, n * self.batch)
            si.wi = mi.Vector3f(*[wi[lane_row, k].astype(np.float32) for k in range(3)])
            si.uv = mi.Point2f(mi.Float(((texel + 0.5) / self.texels).astype(np.float32)),
                               mi.Float(np.full(len(texel), 0.25, np.float32)))
            if not mono:
                lam = mi.Float(data.wavelength[lane_row].astype(np.float32))
                si.wavelengths = mi.Spectrum(lam, lam, lam, lam)
            self.si = si
            self.wo = mi.Vector3f(*[wo[lane_row, k].astype(np.float32) for k in range(3)])
            self.mu_o = mi.Float(wo[lane_row, 2].astype(np.float32))
            self.lane_set = mi.UInt32(lane_set.astype(np.uint32))
            self.lane_wavelength = mi.UInt32(row_wl[lane_row].astype(np.uint32))

    def evaluate(self, values: dict[str, np.ndarray], albedo: np.ndarray,
                 tau_o: np.ndarray | None = None, derivatives: bool = False
                 ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """BRF (batch, N) and, with ``derivatives``, its derivatives (batch, N) with respect
        to each varying property and to ``albedo`` (the albedo of each row's own wavelength).

        Args:
            values: varying property -> (batch,) values.
            albedo: (batch, W) single-scattering albedo per set and wavelength (W: the
                distinct wavelengths, sorted).
            tau_o: (W,) extrapolation ratio per wavelength, unless ``tau_o`` is varying.
        """
        w = len(self.wavelengths)
        albedo = np.asarray(albedo, dtype=np.float64).reshape(self.batch, w)
        n = len(self.data)
        grads: dict[str, np.ndarray] = {}
        with use_variant(self.variant):
            sources, lanes = {}, {}
            for name in self.varying:
                v = np.asarray(values[name], dtype=np.float32).reshape(self.batch)
                sources[name] = mi.Float(v)
                if derivatives:
                    dr.enable_grad(sources[name])
                lanes[name] = dr.gather(mi.Float, sources[name], self.lane_set)
            if "tau_o" not in self.varying:
                if tau_o is None:
                    raise ValueError("tau_o per wavelength is needed unless it is varying")
                table = mi.Float(np.asarray(tau_o, dtype=np.float32).reshape(w))
                lanes["tau_o"] = dr.gather(mi.Float, table, self.lane_wavelength)
            dr.eval(lanes)  # one launch for every gather (the plugin makes them opaque)
            for name, value in lanes.items():
                self.params[name] = value
            texels = np.full(self.texels, albedo[-1, -1], np.float32)
            texels[:self.batch * w] = albedo.ravel()
            tex = mi.TensorXf(np.tile(texels[None, :, None], (2, 1, 1)))
            if derivatives:
                dr.enable_grad(tex)
            self.params["albedo.data"] = tex
            self.params.update()
            value = self.bsdf.eval(mi.BSDFContext(), self.si, self.wo)
            out = dr.pi * value[0] / self.mu_o
            dr.eval(out)
            brf = np.array(out, dtype=np.float64).reshape(self.batch, n)
            if derivatives:
                for name, src in list(sources.items()) + [("albedo", tex)]:
                    grads[name] = forward_grad(src, out).reshape(self.batch, n)
        return brf, grads
