"""Fits larger than memory: the pixels in blocks within a working-memory budget
(:func:`block_pixels`, :func:`pixel_blocks`), the blocks' maps and diagnostics put together
(:func:`merge_block`, :func:`merge_fit_settings`, which the tiles use too) and what a block
held released (:func:`release`).

Once the gains are held (fitted first on a pixel subsample: :mod:`mitsuba_powder.rti.gains`),
a pixel's fit depends only on its own observations, so a fit in blocks gives the maps of a fit
in one (:mod:`mitsuba_powder.rti.plan`; tested bit for bit).
The memory model is measured (``benchmarks/bench_rti_fit.py``): a block's NumPy arrays take
about :data:`OBSERVATION_BYTES` per pixel and light, a Dr.Jit evaluation of the per-pixel
solver :data:`LANE_BYTES` per lane.
"""

from __future__ import annotations

import ctypes
import gc
import math
import os
import resource
from collections.abc import Mapping, Sequence

import drjit as dr
import numpy as np

from .._checks import check_range
from ..variants import use_variant
from .result import MapsResult

__all__ = ["LANE_BYTES", "LANE_SHARE", "MEMORY_GB_MAX", "MIN_MEMORY_GB", "OBSERVATION_BYTES",
           "SUMMED", "block_pixels", "check_memory", "default_memory_gb", "lanes_within",
           "merge_block", "merge_fit_settings", "peak_memory_mib", "pixel_blocks", "release"]

#: Largest default working memory of a fit, GiB (:func:`default_memory_gb`)
MEMORY_GB_MAX = 1.5

#: Bytes per observation (pixel x light) of a block's NumPy working set: observations and
#: model as float32, weights, flags, the starts' temporaries (measured at 1024 x 1024 x 50
#: lights with benchmarks/bench_rti_fit.py: about 130-160)
OBSERVATION_BYTES = 200

#: Bytes per lane of one Dr.Jit evaluation of the per-pixel solver: its inputs, the 36
#: products of the normal equations and their block sums, the model's temporaries and what
#: Dr.Jit's allocator keeps (measured: 2^21 lanes take about 0.5 GiB more than 2^20)
LANE_BYTES = 512

#: Share of the working memory given to Dr.Jit's evaluations (the rest to a block's NumPy
#: arrays)
LANE_SHARE = 1.0 / 3.0


def default_memory_gb() -> float:
    """The default working memory of a fit, GiB: an eighth of this machine's memory, at most
    :data:`MEMORY_GB_MAX`."""
    try:
        total = os.sysconf("SC_PAGE_SIZE") * os.sysconf("SC_PHYS_PAGES") / 2**30
    except (ValueError, OSError, AttributeError):
        return MEMORY_GB_MAX
    return float(min(MEMORY_GB_MAX, max(total / 8.0, 0.25)))


#: The smallest memory budget of a fit, GiB (16 MiB: about 11,000 lanes a launch and 1,100
#: pixels a block at 50 lights; much less fits a handful of pixels per launch and takes hours)
MIN_MEMORY_GB = 1.0 / 64


def check_memory(memory_gb: float | str | None, name: str = "memory_gb") -> float:
    """``memory_gb`` (GiB) checked (>= :data:`MIN_MEMORY_GB`, finite), or the default
    (None)."""
    if memory_gb is None:
        return default_memory_gb()
    return check_range(name, memory_gb, MIN_MEMORY_GB, math.inf, "[)", note="GiB")


def block_pixels(memory_gb: float, lights: int) -> int:
    """Pixels of a block whose NumPy working set (observations, model, weights, flags and
    temporaries: :data:`OBSERVATION_BYTES` per pixel and light) takes the share of
    ``memory_gb`` (GiB) that Dr.Jit's evaluations do not (:data:`LANE_SHARE`)."""
    share = (1.0 - LANE_SHARE) * memory_gb * 2**30
    return max(1, int(share / (OBSERVATION_BYTES * max(lights, 1))))


def lanes_within(memory_gb: float, max_lanes: int) -> int:
    """``max_lanes`` lowered so that a Dr.Jit evaluation (:data:`LANE_BYTES` a lane) takes at
    most :data:`LANE_SHARE` of ``memory_gb`` (GiB)."""
    return max(1, min(int(max_lanes), int(LANE_SHARE * memory_gb * 2**30 / LANE_BYTES)))


def peak_memory_mib() -> float:
    """This process's peak resident memory so far, MiB (Linux ``ru_maxrss``, KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def pixel_blocks(mask: np.ndarray, lights: int, memory_gb: float, gains_fitted: bool
                  ) -> list[np.ndarray]:
    """The masked pixels in blocks of at most :func:`block_pixels` (bands of the image in
    row-major order), bool (H, W) each; one block when the gains are fitted with the maps
    (they couple every pixel)."""
    flat = np.flatnonzero(mask)
    size = block_pixels(memory_gb, lights)
    if gains_fitted or len(flat) <= size:
        return [mask]
    count = math.ceil(len(flat) / size)
    blocks = []
    for part in np.array_split(flat, count):
        block = np.zeros(mask.size, dtype=bool)
        block[part] = True
        blocks.append(block.reshape(mask.shape))
    return blocks


def release(variant: str) -> None:
    """Free what a block held: its evaluator's plugin instance and arrays (in reference
    cycles until collected) and Dr.Jit's cache of freed memory."""
    gc.collect()
    with use_variant(variant):
        dr.flush_malloc_cache()
    try:  # hand the freed heap back to the system (glibc keeps it otherwise)
        ctypes.CDLL("libc.so.6").malloc_trim(0)
    except (OSError, AttributeError):
        pass


def merge_block(out: MapsResult, part: MapsResult) -> MapsResult:
    """``out`` with the maps of the block fit ``part`` (NaN outside its block) put in."""
    sel = part.mask
    out.normals[sel], out.albedo[sel] = part.normals[sel], part.albedo[sel]
    out.residual_rms[sel] = part.residual_rms[sel]
    for name, value in part.maps.items():
        out.maps[name][sel] = value[sel]
    out.used[:, sel] = part.used[:, sel]
    out.fit_settings = merge_fit_settings([out.fit_settings, part.fit_settings])
    return out


#: Diagnostics of ``fit_settings`` that add up over the blocks (or tiles) of a fit
SUMMED = ("evaluations", "chunks", "underdetermined_pixels", "pixels_at_cap_last_round")


def merge_fit_settings(parts: Sequence[Mapping]) -> dict:
    """The ``fit_settings`` of a fit in parts (blocks, tiles): the first part's, with the
    diagnostics of :data:`SUMMED` summed and ``iterations_last_round`` the longest part's."""
    out = dict(parts[0])
    for key in SUMMED:
        if key in out:
            out[key] = sum(int(p.get(key, 0)) for p in parts)
    out["iterations_last_round"] = max(p["iterations_last_round"] for p in parts)
    if "rounds_at_cap" in out:
        out["rounds_at_cap"] = max(int(p.get("rounds_at_cap", 0)) for p in parts)
    return out
