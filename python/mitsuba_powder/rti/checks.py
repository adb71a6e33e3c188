"""Checks of the RTI inputs (the per-pixel fit's, the forward model's, the baselines' light
directions): light directions, counts, normals, images and light gains; each error names the
argument, its value and the valid range (a number in a range:
:func:`mitsuba_powder._checks.check_range`)."""

from __future__ import annotations

import math

import numpy as np

from .._checks import check_range, out_of_range

__all__ = ["check_count", "check_directions", "check_gains", "check_images", "check_normals"]


def check_directions(directions: np.ndarray, name: str = "directions") -> np.ndarray:
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


def check_count(name: str, value, lower: int, upper: float = math.inf) -> int:
    """A whole number in [lower, upper] (2.5 is an error, not 2; so are True and False)."""
    v = None if isinstance(value, bool) else check_range(name, value, lower, upper, "[]")
    if v is None or not math.isfinite(v) or v != math.floor(v):
        raise ValueError(f"{name} = {value!r} is not a whole number; valid range is "
                         f"[{lower:g}, {upper:g}]")
    return int(v)


def check_normals(normals: np.ndarray, shape: tuple[int, int], name: str = "normal"
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


def check_images(images: np.ndarray) -> np.ndarray:
    """(K, H, W, 3) finite linear RGB values -> float32."""
    imgs = np.asarray(images)
    if imgs.ndim != 4 or imgs.shape[3] != 3:
        raise ValueError(f"images has shape {imgs.shape}; expected (K, H, W, 3) (RGB, linear)")
    if not np.all(np.isfinite(imgs)):
        idx = tuple(int(x[0]) for x in np.nonzero(~np.isfinite(imgs)))
        raise ValueError(f"images{list(idx)} = {imgs[idx]!r} is not finite")
    return imgs.astype(np.float32, copy=False)


def check_gains(gains: np.ndarray | None, k: int) -> np.ndarray:
    """(K,) positive finite light irradiances -> float64; None -> ones."""
    if gains is None:
        return np.ones(k)
    g = np.asarray(gains, dtype=np.float64)
    if g.shape != (k,):
        raise ValueError(f"gains has shape {g.shape}; expected ({k},), one per light")
    if not np.all(np.isfinite(g)) or np.any(g <= 0):
        i = int(np.nonzero(~(np.isfinite(g) & (g > 0)))[0][0])
        raise ValueError(out_of_range(f"gains[{i}] = {float(g[i])!r}", "(0, inf)"))
    return g
