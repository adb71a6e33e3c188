"""The capture's exposure fitted to an RTI capture: a scan of its logarithm with the powder fit
of a pixel subsample, then a polish, as the light distance is (:mod:`.distance`).

The exposure ``e`` is one global scale of the lights' irradiances (the gains are ``e g_k``,
``g_k`` the relative gains: 1 by default). A Lambertian surface cannot tell it from its
reflectance (``e rho`` only), but the powder's angular shape changes with its albedo
(multiple scattering: ``L1 ~ rho``, ``L2 ~ rho^2``, ...), so that a wrong exposure leaves the
albedo of an uncalibrated capture off by the ratio (and the surface lobe with it) while the fit
still looks good. What pins ``e`` is that shape: weakly where the albedo is low (single
scattering dominates: the shape no longer changes), well where it is high.

1. **scan** (:func:`exposure_grid`): ``x = ln e`` on a uniform grid, anchored at the exposure
   that gives the subsample's bright pixels (95th percentile of the Lambertian reflectance's
   largest channel) a Lambertian reflectance of 1 (a powder of albedo 1 reflects less than a
   white Lambertian surface, so the truth lies above the anchor); the cost at each point is the
   median over the pixels of their mean squared residual after the powder fit of the
   subsample (a median: a few pixels whose surface lobe falls into another basin at one
   exposure and not at the next made the mean jump).
2. **polish** (:func:`~mitsuba_powder.rti.distance.polish_bracket`): a bounded scalar
   minimisation of the cost over :data:`POLISH_WIDTH` grid points either
   side of the scan's best point, at most :data:`POLISH_EVALUATIONS` fits.
3. **estimate and uncertainty** (:func:`exposure_uncertainty`): the profile likelihood's
   curvature (every pixel's variables refitted at each ``e``): the vertex of a least-squares
   parabola in ``x`` through the evaluations within the polish's bracket is the exposure;
   with ``chi^2(x) = N cost(x) / cost_min`` (the residual variance as the noise),
   ``sigma_x = sqrt(cost_min / (N a))`` (``a`` the parabola's curvature, ``N`` the
   observations used times :data:`MEDIAN_EFFICIENCY`); ``sigma_e = e sigma_x``.

4. **check** (the plan's ``exposure check``, after the free choice; :func:`contradicted`):
   the maps of the subsample fitted at the exposure found and at exposure 1 relight the
   held-out lights of the free choice's folds (:func:`~mitsuba_powder.rti.selection.held_out_rms`);
   where exposure 1 relights them better by more than :data:`HELD_OUT_MARGIN`, the shape that
   set the exposure is not a powder's (RealRTI item 8, a clay relief: a clear minimum at 6.15
   +- 0.11 whose maps relit the held-out lights at 9.99 levels against 8.83 at exposure 1)
   and the capture does not determine it. The held-out score is a check, not the estimate:
   on the SYNTHETIC capture it is too flat to find the exposure (docs/rti.md).

The capture **does not determine** its exposure (:func:`determined`) when the best point is at
an end of the scan, the parabola does not curve upwards or has its vertex outside the
evaluations, ``sigma_e / e`` exceeds :data:`UNDETERMINED`, or the held-out lights contradict
it (step 4); the fit then says so and keeps the exposure at 1 (the images' own scale,
what the fit assumed before it fitted the exposure; the best of the scan is recorded): a best
at the scan's end is no estimate (on RealRTI's clay reliefs the cost falls on towards albedo 0,
where the powder's shape relit grazing light worse). Give the exposure or a reference target to
calibrate.
"""

from __future__ import annotations

import math

import numpy as np

from .starts import lambertian_start

__all__ = ["HELD_OUT_MARGIN", "MEDIAN_EFFICIENCY", "POLISH_EVALUATIONS", "POLISH_WIDTH",
           "SCAN_LOG2", "UNDETERMINED", "contradicted", "determined",
           "exposure_anchor", "exposure_grid", "exposure_uncertainty"]

#: The scan's grid of ``log2(e / anchor)``: from half the anchor (the bright pixels would be
#: brighter than white) to 6x it (the albedo of a powder that dark changes its shape little)
SCAN_LOG2 = np.linspace(-0.5, 2.5, 10)
#: Grid points either side of the scan's best that the polish brackets (the quick fit of the
#: scan can put its best a grid point off the full fit's)
POLISH_WIDTH = 2
#: Most powder fits of the polish
POLISH_EVALUATIONS = 8
#: The efficiency of a median relative to a mean (2 / pi for Gaussian data): the scan's cost
#: is the median over the pixels of their mean squared residual, worth this fraction of the
#: observations in the uncertainty
MEDIAN_EFFICIENCY = 2 / math.pi
#: Relative 1-sigma of the exposure above which the capture does not determine it
UNDETERMINED = 0.1
#: The fraction by which exposure 1 must relight held-out lights better than the exposure
#: found for the capture not to determine it (:func:`contradicted`)
HELD_OUT_MARGIN = 0.01


def exposure_anchor(obs: np.ndarray, wt: np.ndarray, directions: np.ndarray,
                    gains: np.ndarray, percentile: float = 95.0) -> float:
    """The exposure at which the bright pixels (``percentile`` of the largest channel of the
    Lambertian reflectance, photometric stereo with ``gains``) have reflectance 1.

    Args:
        obs: (P, K, 3) observations; wt: (P, K) weights; directions: (K, 3); gains: (K,).
    """
    images = obs.transpose(1, 0, 2)[:, :, None, :]
    _, refl = lambertian_start(images, directions, wt.T[:, :, None], gains)
    top = float(np.nanpercentile(np.max(refl[:, 0], axis=1), percentile))
    return top if math.isfinite(top) and top > 0 else 1.0


def exposure_grid(anchor: float, grid: np.ndarray = SCAN_LOG2) -> np.ndarray:
    """``x = ln e`` of the scan: ``ln anchor + grid ln 2``."""
    return math.log(anchor) + np.asarray(grid, dtype=np.float64) * math.log(2.0)


def exposure_uncertainty(points: list[tuple[float, float]], observations: int,
                         window: float = math.inf) -> tuple[float, float]:
    """(x*, sigma_x) from the (x = ln e, cost) evaluations (module docstring, step 3): the
    vertex of the least-squares parabola through the evaluations within ``window`` of the
    best (at least 3 distinct x; the vertex is steadier than the best point when the cost is
    a little noisy), and its 1-sigma; sigma_x is inf when the parabola does not curve upwards
    or its vertex lies outside those evaluations (the best x is then returned)."""
    pts = sorted(set(points))
    best_x, best_c = min(pts, key=lambda p: p[1])
    near = [p for p in pts if abs(p[0] - best_x) <= window]
    xs = np.array([p[0] for p in near])
    cs = np.array([p[1] for p in near])
    if len(np.unique(np.round(xs, 9))) < 3 or best_c <= 0:
        return best_x, math.inf
    a, b, c = np.polyfit(xs - best_x, cs, 2)
    if not a > 0:
        return best_x, math.inf
    v = -b / (2 * a)
    if not min(xs) <= best_x + v <= max(xs):  # the vertex outside the points: no minimum seen
        return best_x, math.inf
    c_min = max(c - b * b / (4 * a), 1e-300)
    return float(best_x + v), float(math.sqrt(c_min / (max(observations, 1) * a)))


def determined(x: float, sigma_x: float, grid: np.ndarray, scan: np.ndarray | None = None
               ) -> bool:
    """Whether the capture determines its exposure (module docstring): the scan's best
    (``scan``: its costs on ``grid``) not at an end of the grid, ``x`` inside it, and a
    relative 1-sigma within :data:`UNDETERMINED`."""
    step = float(grid[1] - grid[0]) if len(grid) > 1 else 0.0
    inside = grid[0] + 0.5 * step < x < grid[-1] - 0.5 * step
    if scan is not None and int(np.argmin(scan)) in (0, len(grid) - 1):
        return False
    return bool(inside and math.isfinite(sigma_x) and math.expm1(sigma_x) <= UNDETERMINED)


def contradicted(held_out_fitted: float, held_out_unit: float,
                 margin: float = HELD_OUT_MARGIN) -> bool:
    """Whether the held-out lights contradict the exposure found (module docstring, step 4):
    the cross-validated RMS of the maps fitted at exposure 1 (``held_out_unit``) below that
    of the maps fitted at the exposure found (``held_out_fitted``) by more than ``margin``
    (a fraction)."""
    return bool(held_out_unit < held_out_fitted * (1.0 - margin))
