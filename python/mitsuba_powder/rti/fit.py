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
properties at their defaults. Per-light gains ``E_k`` shared by all pixels alternate with the
per-pixel fit: closed-form least squares given the per-pixel models
(:func:`mitsuba_powder.rti.problem.gain_system`), normalised to mean 1 (the overall scale goes
into the albedo and ``amplitude_volume``).

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

**Scale.** The overall scale of the gains is not fitted: it is a calibration (the mean of
``initial_gains``, default 1, e.g. from a white reference); only the gains relative to it are.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass

import numpy as np

from ..fitting.optimise import ParamSpec, batch_levenberg_marquardt
from ..variants import use_variant
from .blocks import (
    GAIN_PIXELS,
    check_memory,
    gain_sample,
    lanes_within,
    merge_block,
    peak_memory_mib,
    pixel_blocks,
    release,
)
from .checks import check_count
from .distance import polish_inverse_distance, scan_inverse_distance, subsample_mask
from .engine import PixelSystem
from .forward import (
    MAX_LANES,
    VARIANT,
    PixelEvaluator,
    check_rgb_variant,
    normals_of_slopes,
    pixel_chunks,
)
from .gains import GainOptions
from .inputs import GAIN_MODES, SOLVERS, FitData, set_up
from .problem import PixelProblem, gain_step, gain_system
from .properties import (
    MAP_PROPERTIES,
    SLOPE_LIMIT,
    SPECS,
    property_map,
)
from .result import MapsResult
from .starts import PixelStarts

__all__ = ["GAIN_MODES", "GAIN_PIXELS", "SOLVERS", "fit_light_distance", "fit_maps",
           "max_correlation_length"]


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


# ---------------------------------------------------------------------------
#  Parameter layout
# ---------------------------------------------------------------------------

def _parameter_layout(data: FitData) -> tuple[list[tuple[str, ParamSpec]], dict]:
    """The variables of a pixel in column order (name, spec): the normal's slopes, the albedo
    per channel or the grain size, the other free properties; and the specs by name, with the
    correlation length bounded by what the lights resolve (:func:`max_correlation_length`).
    """
    layout: list[tuple[str, ParamSpec]] = [
        ("slope_x", ParamSpec(-SLOPE_LIMIT, SLOPE_LIMIT, False, 0.0)),
        ("slope_y", ParamSpec(-SLOPE_LIMIT, SLOPE_LIMIT, False, 0.0))]
    if "albedo" in data.free:
        layout += [(f"albedo{c}", SPECS["albedo"]) for c in range(3)]
    if data.grain_name in data.free:
        layout.append((data.grain_name, SPECS[data.grain_name]))
    specs = dict(SPECS)
    lc_max = max_correlation_length(data.d)
    lc = specs["correlation_length"]
    specs["correlation_length"] = ParamSpec(lc.lower, max(min(lc.upper, lc_max), 2 * lc.lower),
                                            lc.log, min(lc.start, 0.8 * lc_max))
    layout += [(n, specs[n]) for n in data.others]
    return layout, specs


class _Log:
    """The fit's stages: kept for the result and passed to ``progress`` as they come."""

    def __init__(self, progress: Callable[[str], None] | None):
        self.stages: list[str] = []
        self.progress = progress

    def __call__(self, line: str) -> None:
        self.stages.append(line)
        if self.progress:
            self.progress(line)


# ---------------------------------------------------------------------------
#  Starts
# ---------------------------------------------------------------------------

def _initial_start(starts: PixelStarts, data: FitData, log: _Log
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Start rows and observation weights: shadows are flagged against the Lambertian
    prediction twice, the second start without them (and with the grain-size search)."""
    g = data.gains
    wt = (~data.saturated).astype(np.float64)
    for i in range(2):
        y, n0, refl = starts(g, wt, search=i == 1)
        if data.field is None:
            cos = np.maximum(n0 @ data.d.T, 0.0)
        else:
            cos = np.maximum(np.einsum("pki,pi->pk", data.field[0], n0), 0.0)
        pred = cos[:, :, None] * refl[:, None, :] / np.pi * data.light_gains(g)
        wt = data.flags(pred)
    log(f"start: Lambertian photometric stereo on {len(data.obs)} pixels, "
        f"{int(np.sum(wt == 0))} observations flagged")
    return y, wt


# ---------------------------------------------------------------------------
#  Alternation: per-pixel maps and per-light gains
# ---------------------------------------------------------------------------

@dataclass
class _State:
    """The alternation's state: the pixels' rows, the gains and weights, the models."""

    y: np.ndarray           # (P, variables + 1) fitted rows
    gains: np.ndarray       # (K,)
    weights: np.ndarray     # (P, K) observation weights in {0, 1}
    value: np.ndarray       # (P, K, 3) float32, the model without gain at the fitted rows
    chunks: list[slice]
    information: np.ndarray | None = None  # (K,) diagonal of the gains' reduced system
    iterations: int = 0
    evaluations: int = 0


def _fit_chunk(ev: PixelEvaluator, data: FitData, layout: list, state: _State,
               y_start: np.ndarray, s: slice, with_gains: bool
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """Fit the pixels ``s`` from ``y_start`` under the current gains; update ``state``; with
    ``with_gains`` return their part of the gains' reduced system."""
    if data.solver == "drjit":
        return _fit_chunk_drjit(ev, data, layout, state, y_start, s, with_gains)
    prob = PixelProblem(ev, data.obs[s], state.weights[s], data.lights(s), state.gains, layout,
                        {n: v[s] for n, v in data.fixed_maps.items()},
                        None if data.fixed_albedo is None else data.fixed_albedo[s], data.grain,
                        data.irradiance(s))
    y_chunk = y_start[s].copy()
    y_chunk[:, -1] = np.arange(len(y_chunk))
    hold = np.zeros(len(layout) + 1, dtype=bool)
    hold[-1] = True  # the pixel index
    # hopeless = inf: pixels are not competing starts (inf x a zero cost, of a pixel with no
    # used observation, is NaN and stops nothing: not a warning)
    with np.errstate(invalid="ignore"):
        fitted = batch_levenberg_marquardt(prob, y_chunk, data.max_iterations, hold=hold,
                                           hopeless=math.inf)
    state.y[s, :-1] = fitted.y[:, :-1]
    state.iterations = max(state.iterations, fitted.iterations)
    _, slopes, albedo, values, _ = prob.unpack(fitted.y)
    part = None
    if with_gains:
        res, jac = prob.jacobian(fitted.y)
        state.value[s], _ = ev(slopes, albedo, values, data.lights(s))
        # d(residual)/d(g_k) = sqrt(w) s_pk f: the model times the irradiance factors
        model = (state.value[s] if data.field is None
                 else state.value[s] * data.field[1][s][:, :, None])
        part = gain_system(res, jac[:, :, :-1], model, prob.sqrt_w)
    else:
        state.value[s], _ = ev(slopes, albedo, values, data.lights(s))
    state.evaluations += prob.evaluations
    return part


def _fit_chunk_drjit(ev: PixelEvaluator, data: FitData, layout: list, state: _State,
                     y_start: np.ndarray, s: slice, with_gains: bool
                     ) -> tuple[np.ndarray, np.ndarray] | None:
    """:func:`_fit_chunk` by the Dr.Jit engine (:class:`~mitsuba_powder.rti.engine.PixelSystem`).
    """
    system = PixelSystem(ev, data.obs[s], state.weights[s], data.lights(s), state.gains,
                         layout, {n: v[s] for n, v in data.fixed_maps.items()},
                         None if data.fixed_albedo is None else data.fixed_albedo[s],
                         data.grain, data.irradiance(s))
    fitted = system.solve(y_start[s], data.max_iterations)
    state.y[s, :-1] = fitted.y
    state.iterations = max(state.iterations, fitted.iterations)
    state.value[s], part = system.model(fitted.y, with_gains)
    state.evaluations += system.evaluations
    return part


def _alternate(ev: PixelEvaluator, starts: PixelStarts, data: FitData, layout: list,
               y: np.ndarray, wt: np.ndarray, log: _Log) -> _State:
    """Rounds of the per-pixel fit alternated with a Gauss-Newton step of the gains (mode
    ``fit``) and new shadow flags; a final per-pixel fit follows the last gain update."""
    npix, k = data.obs.shape[:2]
    state = _State(y=y, gains=data.gains, weights=wt,
                   value=np.zeros((npix, k, 3), dtype=np.float32),
                   chunks=pixel_chunks(npix, k, data.max_lanes))
    total = data.rounds + (1 if data.gain_mode == "fit" else 0)
    previous = None  # the weights of the last round, when the gains did not move since
    for r in range(total):
        last = r == total - 1
        with_gains = data.gain_mode == "fit" and not last
        if previous is not None and np.array_equal(previous, state.weights):
            # same gains, same flags: this round would repeat the last one exactly
            log(f"round {r + 1}/{total}: observation flags unchanged, round {r} holds")
            continue
        previous = None if with_gains else state.weights.copy()
        reduced = np.zeros((k, k)), np.zeros(k)
        # every round starts from the Lambertian start under the current gains: a warm start
        # would keep pixels in the surface-lobe basin the previous gains led them to
        y_start = starts(state.gains, state.weights)[0] if r > 0 else state.y
        for s in state.chunks:
            part = _fit_chunk(ev, data, layout, state, y_start, s, with_gains)
            if part is not None:
                reduced = reduced[0] + part[0], reduced[1] + part[1]
        if with_gains:
            state.gains = gain_step(state.gains, *reduced, data.scale)
            state.information = np.diag(reduced[0]).copy()
            if data.gain_model.mode == "smooth":
                state.gains = data.gain_model.smooth(data.d, state.gains, state.information,
                                                     data.scale)
        model = state.value * data.light_gains(state.gains)
        if not last:
            state.weights = data.flags(model)
        rms = np.sqrt(np.sum(state.weights[:, :, None] * (model - data.obs) ** 2)
                      / max(3 * np.sum(state.weights), 1))
        log(f"round {r + 1}/{total}: Levenberg-Marquardt ({len(state.chunks)} chunk(s)), "
            f"RMS residual {rms:.5g}, {int(np.sum(state.weights == 0))} observations left out")
    return state


# ---------------------------------------------------------------------------
#  Result
# ---------------------------------------------------------------------------

def _result(ev: PixelEvaluator, data: FitData, layout: list, specs: Mapping[str, ParamSpec],
            state: _State, variant: str, log: _Log, t0: float) -> MapsResult:
    """The maps of the fitted rows (NaN outside the mask), the residual per pixel, the
    observations used, and the fit's options and diagnostics."""
    h, w = data.mask.shape
    npix, k = data.obs.shape[:2]

    def to_map(values: np.ndarray, channels: int = 0) -> np.ndarray:
        out = np.full((h, w, channels) if channels else (h, w), np.nan, dtype=np.float32)
        out[data.mask] = values
        return out

    wt, g = state.weights, state.gains
    prob = PixelProblem(ev, data.obs, wt, data.lights(), g, layout, data.fixed_maps,
                        data.fixed_albedo, data.grain, data.irradiance())
    y_all = state.y.copy()
    y_all[:, -1] = np.arange(npix)
    _, slopes, albedo, values, _ = prob.unpack(y_all)
    resid = (state.value * data.light_gains(g) - data.obs) * wt[:, :, None]
    rms_map = np.sqrt(np.sum(resid**2, axis=(1, 2)) / np.maximum(3 * wt.sum(axis=1), 1))
    # a pixel with fewer used observations than variables is not determined: NaN residual
    underdetermined = 3 * wt.sum(axis=1) < len(layout)
    rms_map[underdetermined] = np.nan
    used = np.zeros((k, h, w), dtype=bool)
    used[:, data.mask] = (wt > 0).T
    fit_settings = {
        "free": data.free, "gains": data.gain_mode, "max_iterations": data.max_iterations,
        "rounds": data.rounds, "saturation": data.saturation,
        "shadow_ratio": data.shadow_ratio, "shadow_floor": data.shadow_floor,
        "max_lanes": data.max_lanes, "chunks": len(state.chunks), "solver": data.solver,
        "correlation_length_max_um": specs["correlation_length"].upper,
        "iterations_last_round": state.iterations, "evaluations": state.evaluations,
        "underdetermined_pixels": int(np.sum(underdetermined)),
        "seconds": time.perf_counter() - t0, "stages": log.stages,
        "fixed": {n: v for n, v in data.fixed.items()
                  if np.ndim(v) == 0 or isinstance(v, str)},
        "light_distance": _json_distance(data.light_distance),
        "gain_model": data.gain_model.settings()}
    return MapsResult(
        normals=to_map(normals_of_slopes(slopes), 3), albedo=to_map(albedo, 3),
        maps={n: to_map(v) for n, v in values.items()}, settings=data.settings,
        residual_rms=to_map(rms_map), gains=g, used=used, free=data.free, mask=data.mask,
        variant=variant, fit_settings=fit_settings, light_distance=data.light_distance,
        gain_model=(None if data.gain_model.mode == "none" else
                    data.gain_model.fit(data.d, g, state.information)))


# ---------------------------------------------------------------------------
#  Fit
# ---------------------------------------------------------------------------

def fit_maps(images: np.ndarray, directions: np.ndarray, free: Sequence[str] | None = None,
             mask: np.ndarray | None = None, fixed: Mapping | None = None,
             gains: str = "fit", initial_gains: np.ndarray | None = None,
             max_iterations: int = 30, rounds: int = 3, saturation: float = 0.99,
             shadow_ratio: float = 0.5, shadow_floor: float = 0.03, variant: str = VARIANT,
             max_lanes: int = MAX_LANES, progress: Callable[[str], None] | None = None,
             light_distance: float | np.ndarray | str = math.inf,
             gain_model: GainOptions | None = None, solver: str = "drjit",
             gain_pixels: int | None = GAIN_PIXELS, seed: int = 0,
             memory_gb: float | None = None) -> MapsResult:
    """Fit a normal and powder properties to every pixel of an RTI capture.

    Args:
        images: (K, H, W, 3) linear pixel values, 1.0 = the encoding's maximum.
        directions: (K, 3) vectors towards the lights (image frame; normalised here).
        free: properties fitted per pixel besides the normal: ``albedo`` (3 channels), a grain
            size of :data:`~mitsuba_powder.rti.properties.GRAIN_MAPS` instead of the albedo,
            and any of :data:`~mitsuba_powder.rti.properties.MAP_PROPERTIES`; default
            :data:`~mitsuba_powder.rti.properties.MAP_DEFAULT_FREE`. At most 10 numbers per
            pixel (normal 2 + albedo 3 + 5 more).
        mask: bool (H, W) pixels to fit (default all).
        fixed: plugin properties held: floats or (H, W) maps of
            :data:`~mitsuba_powder.rti.properties.MAP_PROPERTIES` (not free), ``albedo`` as
            (3,) or (H, W, 3) when not free, and settings (``lobes``, ``specular``,
            ``material``, ``rgb_wavelengths``, ...).
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
        light_distance: the lights' distance from the image's centre in image widths
            (:mod:`mitsuba_powder.rti.lights`): ``inf`` (default, distant lights), a number
            or (K,) beyond the image's half-diagonal, or ``"fit"``: one distance for every
            light fitted with the gains (:mod:`mitsuba_powder.rti.distance`: a Lambertian
            scan, then a polish with this fit on a subsample of pixels).
        gain_model: how the gains generalise to lights not fitted
            (:class:`~mitsuba_powder.rti.gains.GainOptions`; default ``none``: gain 1 for a
            light not fitted; ``free``: the fitted gains unchanged, a smooth trend in the light
            direction for other lights).

    Returns:
        A :class:`~mitsuba_powder.rti.result.MapsResult`.
    """
    t0 = time.perf_counter()
    # one variant for the whole fit: nested blocks then switch nothing (a switch re-registers
    # the plugin and Mitsuba reloads its Python integrators, 0.1-0.5 s each)
    with use_variant(check_rgb_variant(variant)):
        options = {"gains": gains, "max_iterations": max_iterations, "rounds": rounds,
                   "saturation": saturation, "shadow_ratio": shadow_ratio,
                   "shadow_floor": shadow_floor, "max_lanes": max_lanes, "solver": solver}
        gain_model = GainOptions() if gain_model is None else gain_model
        log = _Log(progress)
        plan = set_up(images, directions, free, mask, fixed, initial_gains, options,
                       pixels=False)
        budget = check_memory(memory_gb)
        scan = None
        if isinstance(light_distance, str):
            if light_distance != "fit":
                raise ValueError(f"light_distance = {light_distance!r} is not valid; give a "
                                 "distance in image widths (> the half-diagonal), inf or 'fit'")
            data = set_up(images, directions, free, mask, fixed, initial_gains, options,
                           pixels=subsample_mask(plan.mask))
            refit = {"free": free, "fixed": fixed, "gains": gains, "initial_gains": initial_gains,
                     "variant": variant, "gain_model": gain_model, "memory_gb": budget, **options}
            light_distance, scan = _fit_distance(images, data, refit, log)
        held = _gains_on_subsample(images, plan, gain_pixels, seed, log,
                                   {"free": free, "fixed": fixed, "variant": variant,
                                    "gain_model": gain_model, "light_distance": light_distance,
                                    "memory_gb": budget, **options})
        options.update(gains=plan.gain_mode, max_lanes=lanes_within(budget, max_lanes))
        blocks = pixel_blocks(plan.mask, len(plan.d), budget, plan.gain_mode == "fit")
        result, ev = None, None
        medians = {n: float(np.median(property_map(n, v, plan.mask.shape)[plan.mask]))
                   for n, v in plan.fixed.items() if n in MAP_PROPERTIES}
        for i, block in enumerate(blocks):
            if len(blocks) > 1:
                log(f"block {i + 1}/{len(blocks)}: {int(block.sum())} pixels")
            data = set_up(images, directions, free, mask, fixed, plan.gains, options,
                           light_distance, pixels=block if len(blocks) > 1 else None)
            data.gain_model, data.scale = gain_model, plan.scale
            ev = ev or PixelEvaluator(data.others + list(data.fixed_maps), data.settings, variant)
            part = _fit_pixels(ev, data, variant, log, medians)
            del data
            release(variant)
            result = part if result is None else merge_block(result, part)
        result.mask = plan.mask
        result.fit_settings.update(
            seconds=time.perf_counter() - t0, stages=log.stages, blocks=len(blocks),
            memory_gb=budget, peak_memory_mib=peak_memory_mib(),
            light_distance_source=("fitted" if scan is not None else "distant"
                                   if np.all(np.isinf(light_distance)) else "given"),
            light_distance_scan=scan)
        if held is not None:
            result.fit_settings.update(gains="fit", gain_pixels=held.fit_settings["gain_pixels"],
                                       gain_stages=held.fit_settings["stages"])
            result.gain_model = held.gain_model
        return result


def _fit_pixels(ev: PixelEvaluator, data: FitData, variant: str, log: _Log,
                medians: Mapping[str, float]) -> MapsResult:
    """The maps of the pixels of ``data`` with the evaluator ``ev``: starts (the held
    properties at ``medians`` in the albedo table), rounds, result."""
    layout, specs = _parameter_layout(data)
    starts = PixelStarts(ev, data.obs, data.d, layout, specs, data.free, data.others,
                         data.grain_name, data.fixed_maps, data.grain, data.max_lanes,
                         data.field, medians)
    y, wt = _initial_start(starts, data, log)
    state = _alternate(ev, starts, data, layout, y, wt, log)
    return _result(ev, data, layout, specs, state, variant, log, time.perf_counter())


def _gains_on_subsample(images: np.ndarray, data: FitData, gain_pixels: int | None,
                        seed: int, log: _Log, refit: dict) -> MapsResult | None:
    """With gains fitted and more masked pixels than ``gain_pixels``: fit the maps and gains on
    a random subsample (:func:`gain_sample`), then hold those gains in ``data`` (mode
    ``fixed``). Returns the subsample's fit, or None when the gains are fitted on every
    pixel."""
    if gain_pixels is not None:
        gain_pixels = check_count("gain_pixels", gain_pixels, 1)
    check_count("seed", seed, 0)
    if data.gain_mode != "fit" or gain_pixels is None or data.mask.sum() <= gain_pixels:
        return None
    flat = gain_sample(data.mask, gain_pixels, seed)
    sub = np.zeros(data.mask.size, dtype=bool)
    sub[flat] = True
    part = fit_maps(images, data.d, mask=sub.reshape(data.mask.shape), gains="fit",
                    initial_gains=data.gains, gain_pixels=None,
                    **{k: v for k, v in refit.items() if k != "gains"})
    part.fit_settings["gain_pixels"] = len(flat)
    data.gain_mode, data.gains = "fixed", part.gains
    log(f"gains: fitted on {len(flat)} of {int(data.mask.sum())} pixels (seed {seed}), "
        f"range {np.min(part.gains):.4g}-{np.max(part.gains):.4g}, held for every pixel")
    return part


def fit_light_distance(images: np.ndarray, directions: np.ndarray,
                       mask: np.ndarray | None = None, progress: Callable[[str], None] | None
                       = None, **options) -> tuple[float, dict]:
    """One light distance for the whole dome fitted to a capture, without the maps
    (:mod:`mitsuba_powder.rti.distance`; what ``fit_maps(light_distance="fit")`` does first).

    Args:
        images, directions, mask, progress: as :func:`fit_maps`.
        options: the other keyword arguments of :func:`fit_maps` (``free``, ``fixed``,
            ``gains``, ``initial_gains``, ``rounds``, ...), used by the polish.

    Returns:
        r in image widths (``inf`` when distant lights fit best) and the scan's record
        (``inverse_distance`` u = 1/r, 1/image width, and the Lambertian ``cost`` per grid
        point; the powder fit's cost per polish evaluation).
    """
    names = ("gains", "max_iterations", "rounds", "saturation", "shadow_ratio",
             "shadow_floor", "max_lanes", "solver")
    defaults = {"gains": "fit", "max_iterations": 30, "rounds": 3, "saturation": 0.99,
                "shadow_ratio": 0.5, "shadow_floor": 0.03, "max_lanes": MAX_LANES,
                "solver": "drjit"}
    checked = {n: options.get(n, defaults[n]) for n in names}
    args = (images, directions, options.get("free"), mask, options.get("fixed"),
            options.get("initial_gains"), checked)
    data = set_up(*args, pixels=subsample_mask(set_up(*args, pixels=False).mask))
    return _fit_distance(images, data, {**defaults, **options}, _Log(progress))


def _fit_distance(images: np.ndarray, data: FitData, refit: dict, log: _Log
                  ) -> tuple[float, dict]:
    """One light distance for the whole dome (:mod:`mitsuba_powder.rti.distance`): the
    Lambertian scan on a subsample of the mask, then the powder fit's cost polished over the
    scan's best bracket. Returns r (image widths) and the record for ``fit_settings``."""
    sub = subsample_mask(data.mask)
    keep = sub[data.mask]
    wt = (~data.saturated[keep]).astype(np.float64)
    us, costs = scan_inverse_distance(data.obs[keep], wt, sub, data.d, data.gains)
    log(f"light distance: Lambertian scan of u = 1/r on {int(sub.sum())} pixels, best "
        f"u = {us[int(np.argmin(costs))]:.4g}")

    def cost(u: float) -> float:
        r = math.inf if u <= 0 else 1.0 / u
        part = fit_maps(images, data.d, mask=sub, light_distance=r, **refit)
        rms = part.residual_rms[sub]
        return float(np.nanmean(rms**2))

    u, seen = polish_inverse_distance(cost, us, costs)
    r = math.inf if u <= 0 else 1.0 / u
    log(f"light distance: polished with the powder fit ({len(seen)} fits), r = {r:.5g} "
        "image widths")
    return r, {"inverse_distance": us.tolist(), "cost": costs.tolist(),
               "polish": [{"inverse_distance": a, "cost": b} for a, b in seen]}


def _json_distance(r: float | np.ndarray) -> float | list | None:
    """A light distance for JSON: a number, a list (one per light) or None (inf)."""
    if np.ndim(r) == 0:
        return None if math.isinf(float(r)) else float(r)
    return [None if math.isinf(v) else float(v) for v in np.asarray(r, dtype=np.float64)]
