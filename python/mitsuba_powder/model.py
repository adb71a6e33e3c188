"""BRF of the powder plugin at measurement geometries, vectorised, differentiable.

One ``llvm_ad_mono`` plugin instance per distinct wavelength (``wavelength`` property), each
evaluated over all of that wavelength's geometries in one call. Any wavelength the optical
constants cover works (e.g. 351 and 1064 nm for PTFE).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import drjit as dr
import mitsuba as mi
import numpy as np

from .measurements import Measurements

VARIANT = "llvm_ad_mono"


@contextmanager
def variant(name: str = VARIANT) -> Iterator[None]:
    """Use a Mitsuba variant inside a block, restoring the caller's afterwards."""
    previous = mi.variant()
    if previous == name:  # nested use (e.g. each objective evaluation of a fit): free
        yield
        return
    mi.set_variant(name)
    from . import register

    register()
    try:
        yield
    finally:
        if previous is not None:
            mi.set_variant(previous)


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
        with variant():
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
        with variant():
            for group in self.groups:
                out[group[1]] = np.array(self.brf_dr(group), dtype=np.float64)
        return out
