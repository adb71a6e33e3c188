"""The dome's light distance fitted to an RTI capture: a scan of the inverse distance with a
Lambertian model, then a polish with the powder fit itself.

With lights at distance r (image widths) light k reaches pixel x from ``d_k(x)`` with the
irradiance factor ``s_k(x)`` (:mod:`mitsuba_powder.rti.lights`). An irradiance falloff common
to all lights is absorbed by the albedo and a direction turn common to all lights by a
tilt of the normal; what pins r is that the falloff and the turn differ from light to light
(``s_k ~ 1 + 2 u l_k . x`` to first order in ``u = 1 / r``). Both steps work in u, in which
the model is smooth through ``u = 0`` (distant lights), on a subsample of pixels spread over
the whole mask (the signal is the variation across the image):

1. **scan** (:func:`scan_inverse_distance`): u on a uniform grid in ``[0, 0.9 / rho]``
   (rho: the image's half-diagonal, the least valid distance); per u the clamped Lambertian
   model with per-pixel normals and reflectances (photometric stereo) and per-light gains
   (closed form), alternated twice; the cost is its weighted sum of squared residuals.
2. **polish** (:func:`polish_inverse_distance`): a bounded scalar minimisation of the powder
   fit's cost (per-pixel fit and gains) over the bracket of the scan's best grid point.

The gains are refitted at every u: the centre irradiance is the gain and r only sets the
variation across the image, which otherwise trades with the gains' mean.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from .lights import LightRig, half_diagonal, light_field, pixel_coordinates
from .starts import lambertian_start

__all__ = ["SCAN_POINTS", "SUBSAMPLE_PIXELS", "polish_bracket", "polish_inverse_distance",
           "scan_inverse_distance", "subsample_mask"]

#: Grid points of the scan in u = 1 / r
SCAN_POINTS = 13
#: Most pixels of the subsample on which the distance is fitted
SUBSAMPLE_PIXELS = 1024
#: Most powder fits of the polish
POLISH_EVALUATIONS = 6


def subsample_mask(mask: np.ndarray, pixels: int = SUBSAMPLE_PIXELS) -> np.ndarray:
    """At most ``pixels`` of the True pixels of ``mask`` (H, W) on a regular stride over the
    whole mask (bool (H, W))."""
    where = np.flatnonzero(mask)
    step = max(1, math.ceil(len(where) / max(int(pixels), 1)))
    out = np.zeros(mask.size, dtype=bool)
    out[where[::step]] = True
    return out.reshape(mask.shape)


def _lambertian_cost(obs: np.ndarray, wt: np.ndarray, dirs: np.ndarray, s: np.ndarray,
                     gains: np.ndarray) -> tuple[float, np.ndarray]:
    """Weighted squared residual of the clamped Lambertian model with the gains refitted.

    Args:
        obs: (P, K, 3) observations; wt: (P, K) weights; dirs: (K, P, 3) and s: (K, P) the
            light field; gains: (K,) start gains (their mean is kept).

    Returns:
        (cost, gains).
    """
    g = gains.copy()
    images = obs.transpose(1, 0, 2)[:, :, None, :]
    for _ in range(2):
        n, refl = lambertian_start(images, dirs[:, :, None, :], wt.T[:, :, None], g,
                                   s[:, :, None])
        cos = np.maximum(np.einsum("kpi,pi->kp", dirs, n[:, 0]), 0.0)       # (K, P)
        unit = cos[:, :, None] * s[:, :, None] * refl[None, :, 0] / np.pi   # (K, P, 3)
        num = np.einsum("pk,kpc,pkc->k", wt, unit, obs)
        den = np.maximum(np.einsum("pk,kpc->k", wt, unit**2), 1e-30)
        new = np.where(den > 1e-30, num / den, g)
        g = np.maximum(new, 1e-6) * (np.mean(gains) / np.mean(np.maximum(new, 1e-6)))
    pred = g[:, None, None] * unit
    return float(np.sum(wt.T[:, :, None] * (pred - obs.transpose(1, 0, 2)) ** 2)), g


def scan_inverse_distance(obs: np.ndarray, wt: np.ndarray, mask: np.ndarray,
                          directions: np.ndarray, gains: np.ndarray,
                          points: int = SCAN_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """The Lambertian cost on a grid of inverse distances (module docstring, step 1).

    Args:
        obs: (P, K, 3) observations of the pixels of ``mask`` (C order); wt: (P, K) weights.
        mask: bool (H, W) the pixels of ``obs``.
        directions: (K, 3) unit vectors from the image's centre towards the lights.
        gains: (K,) start gains.
        points: grid points, >= 3.

    Returns:
        u (points,) in 1/image width (from 0, distant lights) and the cost at each.
    """
    rho = half_diagonal(mask.shape)
    us = np.linspace(0.0, 0.9 / rho, int(points))
    xy = pixel_coordinates(mask.shape)[mask]
    costs = np.empty(len(us))
    for i, u in enumerate(us):
        rig = LightRig(directions, math.inf if u == 0 else 1.0 / u)
        dirs, s = light_field(rig, xy)
        costs[i] = _lambertian_cost(obs, wt, dirs, s, gains)[0]
    return us, costs


def polish_inverse_distance(cost: Callable[[float], float], us: np.ndarray,
                            scan: np.ndarray, evaluations: int = POLISH_EVALUATIONS
                            ) -> tuple[float, list[tuple[float, float]]]:
    """Minimise ``cost(u)`` (the powder fit's) over the bracket of the scan's best grid point
    (module docstring, step 2) with a bounded Brent search of at most ``evaluations``
    evaluations (:func:`polish_bracket`, u kept >= 0).

    Returns:
        u* (1/image width, >= 0) and the (u, cost) pairs evaluated.
    """
    u, seen = polish_bracket(lambda u: cost(max(u, 0.0)), us, scan, evaluations)
    return max(u, 0.0), seen


def polish_bracket(cost: Callable[[float], float], grid: np.ndarray, scan: np.ndarray,
                   evaluations: int = POLISH_EVALUATIONS, width: int = 1
                   ) -> tuple[float, list[tuple[float, float]]]:
    """Minimise ``cost(x)`` over the bracket of the best point of a scan (``scan`` the costs on
    ``grid``; ``width`` grid points either side) by a bounded Brent search of at most
    ``evaluations`` evaluations: the light
    distance's polish (:func:`polish_inverse_distance`) and the exposure's
    (:mod:`mitsuba_powder.rti.exposure`).

    Returns:
        the best x evaluated and the (x, cost) pairs evaluated.
    """
    from scipy.optimize import minimize_scalar

    best = int(np.argmin(scan))
    lo, hi = grid[max(best - width, 0)], grid[min(best + width, len(grid) - 1)]
    seen: list[tuple[float, float]] = []

    def f(x: float) -> float:
        value = cost(float(x))
        seen.append((float(x), value))
        return value

    minimize_scalar(f, bounds=(lo, hi), method="bounded",
                    options={"maxiter": max(int(evaluations) - 1, 1),
                             "xatol": 1e-3 * (hi - lo)})
    x, _ = min(seen, key=lambda p: p[1])
    return x, seen
