"""Per-pixel powder maps fitted to an RTI capture (:func:`fit_maps`).

The forward model and its frame are :mod:`mitsuba_powder.rti.forward`'s. The fit runs over
every pixel at once, with no Python loop over pixels.

**Fit.** Variables per pixel: the normal as the slopes ``(a, b) = (n_x/n_z, n_y/n_z)``
(``n = (a, b, 1)/|(a, b, 1)|``: smooth everywhere, no singularity at ``n = z``), the albedo per
channel, and the free powder properties (log10 for positive scale properties, as in
:data:`mitsuba_powder.fitting.fit.FITTABLE`). The loss of a pixel is
``sum_{k, c} w_{k} (E_k f_c max(n . l_k, 0) - I_{k, c})^2`` with ``w_k`` in {0, 1}: observations
flagged as saturated (any channel >= ``saturation``) or shadowed (observed far below the
model's prediction) get ``w = 0``. It is minimised by
:func:`mitsuba_powder.fitting.optimise.batch_levenberg_marquardt` with B = pixels (all pixels of a
chunk in each Dr.Jit launch; Jacobian columns by forward-mode AD, one pass per variable and one
pass for the three albedo channels together). Starts (:mod:`mitsuba_powder.rti.starts`):
normal and albedo from Lambertian photometric stereo (weighted least squares per pixel,
vectorised), the Lambertian albedo mapped to the powder's single-scattering albedo through a
table of the model; a free grain size from a search over 40 sizes (x 5 extinctions when
``extinction`` is free, with ``amplitude_volume`` in closed form when it is free); other
properties at their defaults. Per-light gains ``E_k`` are held at the exposure by default
(``gains="fixed"``: fitted gains absorb cast shadows and the model's error at grazing light);
with ``gains="fit"`` they alternate with the per-pixel fit (Gauss-Newton on their reduced
system, :func:`mitsuba_powder.rti.gains.gain_system`), their mean held at the exposure.

**What a dome of lights determines.** Cramer-Rao bounds (1-sigma, from the Jacobian at the
truth) per pixel with 1 % noise, 40 lights at elevations 10-80 degrees, a camera at the zenith,
the four regions of :data:`mitsuba_powder.rti.synthetic.SYNTHETIC_REGIONS`, flat and tilted
normals, all ten parameters free -> the default seven:

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
degrees (median). Hence :data:`~mitsuba_powder.rti.properties.MAP_DEFAULT_FREE`: normal (2),
albedo (3), ``amplitude_surface``, ``correlation_length``: 7 numbers per pixel; the others are
held (at the plugin's defaults or as given in ``fixed``), and the albedo is then relative to
them.

Two changes make ``amplitude_volume`` and ``extinction`` identifiable: a grain size free
instead of the albedo (``free=["radius", ...]``: the grains set all three channels, so A_v
no longer trades against the albedo's scale) and lights near the camera, which sample the
coherent cone (:func:`mitsuba_powder.rti.synthetic_capture` ``near_camera``). Bounds per pixel
with normal, radius, A_v and extinction free (``docs/scripts/rti_identifiability.py``, images
exposed to 0.9): radius 0.2-10 %, A_v 0.4-16 %, extinction 3.7-14 % with 8 of 40 lights at
82-88 degrees, against 6.9-44 % for the extinction on the 10-80 degree dome, where a fit can
also land on a second solution at the noise level; with the near-camera lights, region medians
of the synthetic capture are within 4 % (``tests/rti/test_rti_fit.py``, docs/rti.md).

**Scale.** The overall scale of the gains, the exposure, is fitted when not given (the plan's
``exposure scan``, :mod:`mitsuba_powder.rti.exposure`: the powder's angular shape depends on
its albedo, so a bright powder determines it), or given (``exposure``, or ``initial_gains``,
the irradiances themselves, e.g. from a reference card: :mod:`mitsuba_powder.rti.reference`).
Which properties are free per pixel is chosen by cross-validation over held-out lights when
``free`` is not given (:mod:`mitsuba_powder.rti.selection`).

**Where it runs.** :func:`fit_maps` checks its options once
(:func:`~mitsuba_powder.rti.options.fit_options`), makes the fit's plan and runs it
(:mod:`mitsuba_powder.rti.plan`: distance scan, exposure scan, free choice, gain subsample,
blocks); each stage fits its
pixels with :func:`mitsuba_powder.rti.pixelfit.fit_pixels` and a per-pixel solver of
:data:`~mitsuba_powder.rti.solvers.SOLVERS`.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence

import numpy as np

from .gains import GAIN_MODES, GAIN_PIXELS
from .options import fit_options
from .pixelfit import max_correlation_length
from .plan import fit_distance, run_fit
from .result import MapsResult
from .solvers import SOLVERS

__all__ = ["GAIN_MODES", "GAIN_PIXELS", "SOLVERS", "fit_light_distance", "fit_maps",
           "max_correlation_length"]


def fit_maps(images: np.ndarray, directions: np.ndarray, free: Sequence[str] | None = None,
             mask: np.ndarray | None = None, fixed: dict | None = None, *,
             progress: Callable[[str], None] | None = None, **options) -> MapsResult:
    """Fit a normal and powder properties to every pixel of an RTI capture.

    Args:
        images: (K, H, W, 3) linear pixel values, 1.0 = the encoding's maximum.
        directions: (K, 3) vectors towards the lights (image frame; normalised here).
        free: properties fitted per pixel besides the normal (default
            :data:`~mitsuba_powder.rti.properties.MAP_DEFAULT_FREE`).
        mask: bool (H, W) pixels to fit (default all).
        fixed: plugin properties held: numbers, (H, W) maps, ``albedo`` (3,) or (H, W, 3),
            settings.
        progress: called with a line of text after each stage.
        options: the other options of the fit, checked by
            :func:`~mitsuba_powder.rti.options.fit_options` (meanings, ranges and defaults:
            :class:`~mitsuba_powder.rti.options.FitOptions`): ``gains`` (``fixed``, default:
            the initial gains held, times the exposure; ``fit``: per-light gains shared by
            all pixels, their mean held at the exposure), ``exposure`` (a number, ``"fit"``,
            or None: fitted unless ``initial_gains`` are given), ``initial_gains`` ((K,),
            default 1), ``gain_trend`` (how fitted gains extend to lights not fitted, a
            :class:`~mitsuba_powder.rti.gains.GainTrend`; default none: gain 1),
            ``gain_subsample`` (pixels the gains are fitted on first, then held; default
            :data:`~mitsuba_powder.rti.gains.GAIN_PIXELS`; None: every pixel), ``seed``,
            ``light_distance`` (image widths: ``inf``, a number or (K,) beyond the image's
            half-diagonal, or ``"fit"``: :mod:`mitsuba_powder.rti.distance`),
            ``max_iterations``, ``rounds``, ``saturation``, ``shadow_ratio``,
            ``shadow_floor``, ``solver``, ``variant``, ``max_lanes``, ``memory_gb``,
            ``shadows`` (``auto``, default: the relief's cast shadows where
            cross-validation over held-out lights keeps them; ``relief``; ``ratio``),
            ``light_size``, ``full_scale`` (the largest value the capture's files record,
            which the cross-validations clip held-out predictions at: default ``inf``, as
            EXR; give ``capture.full_scale``, 1, for a PNG or JPEG capture).

    Returns:
        A :class:`~mitsuba_powder.rti.result.MapsResult`.
    """
    return run_fit(images, directions, fit_options(free=free, fixed=fixed, **options), mask,
                   progress)


def fit_light_distance(images: np.ndarray, directions: np.ndarray,
                       mask: np.ndarray | None = None, progress: Callable[[str], None] | None
                       = None, **options) -> tuple[float, dict]:
    """One light distance for the whole dome fitted to a capture, without the maps
    (:mod:`mitsuba_powder.rti.distance`; the ``distance scan`` of
    ``fit_maps(light_distance="fit")``).

    Args:
        images, directions, mask, progress: as :func:`fit_maps`.
        options: the other options of :func:`fit_maps` (``free``, ``fixed``, ``gains``,
            ``initial_gains``, ``rounds``, ...), used by the polish.

    Returns:
        r in image widths (``inf`` when distant lights fit best) and the scan's record
        (``inverse_distance`` u = 1/r, 1/image width, and the Lambertian ``cost`` per grid
        point; the powder fit's cost per polish evaluation).
    """
    return fit_distance(images, directions, fit_options(**options), mask, progress)
