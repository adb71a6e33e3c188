"""The fit of one set of pixels of an RTI capture, which every stage of a fit runs
(:mod:`mitsuba_powder.rti.plan`): the Lambertian start, rounds of the per-pixel solver
(:data:`~mitsuba_powder.rti.solvers.SOLVERS`) alternated with a step of the per-light gains
and new shadow flags, and the maps (:func:`fit_pixels`); the pixels in blocks within the
memory budget (:func:`fit_in_blocks`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass

import numpy as np

from ..fitting.optimise import ParamSpec
from .blocks import merge_block, pixel_blocks, release
from .forward import PixelEvaluator, normals_of_slopes, pixel_chunks
from .gains import gain_step, uninformed_lights
from .inputs import FitData, FitInputs
from .lights import distance_to_json
from .options import FitOptions
from .problem import PixelProblem
from .properties import LOBE, NO_LOBE, SLOPE_LIMIT, SPECS
from .result import MapsResult
from .solvers import SOLVERS
from .starts import PixelStarts

__all__ = ["CHI2_STEP", "PINNED", "Log", "fit_in_blocks", "fit_pixels", "max_correlation_length",
           "pinned_lobes", "stop_tolerance", "without_lobe"]

#: The stopping rule of the per-pixel Levenberg-Marquardt: a pixel stops when a step changes
#: its chi-square (its cost over the residual variance, estimated by the cost over its
#: observations) by less than this: a relative decrease under ``CHI2_STEP / (3 K)``
CHI2_STEP = 0.01


def stop_tolerance(lights: int) -> float:
    """The relative decrease of a pixel's cost under which its fit stops (:data:`CHI2_STEP`):
    ``CHI2_STEP / (3 K)`` for K lights (3 channels each)."""
    return CHI2_STEP / (3 * max(int(lights), 1))


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


class Log:
    """A fit's stages as lines of text: kept (for ``fit_settings``) and passed to ``progress``
    as they come."""

    def __init__(self, progress: Callable[[str], None] | None = None):
        self.stages: list[str] = []
        self.progress = progress

    def __call__(self, line: str) -> None:
        self.stages.append(line)
        if self.progress:
            self.progress(line)


# ---------------------------------------------------------------------------
#  Pixels in blocks
# ---------------------------------------------------------------------------

def fit_in_blocks(inputs: FitInputs, pixels: np.ndarray, options: FitOptions,
                  gains: np.ndarray, light_distance: float | np.ndarray, log: Log,
                  start_pixels: np.ndarray | None = None) -> MapsResult:
    """The maps of the pixels ``pixels`` (bool (H, W)) under ``gains`` and lights at
    ``light_distance``, fitted with ``options``: in blocks within the memory budget (one
    while the gains are fitted: they couple every pixel), each from the same start (the held
    properties at their medians over ``start_pixels``, default ``pixels``, in the albedo
    table), put together."""
    blocks = pixel_blocks(pixels, len(inputs.d), options.memory_gb, options.gains.fitted)
    at = pixels if start_pixels is None else start_pixels
    medians = {n: float(np.median(m[at])) for n, m in inputs.maps.items()}
    result, ev = None, None
    for i, block in enumerate(blocks):
        if len(blocks) > 1:
            log(f"block {i + 1}/{len(blocks)}: {int(block.sum())} pixels")
        data = inputs.pixels(block, gains, light_distance, options)
        ev = ev or PixelEvaluator(options.others + list(data.fixed_maps), options.settings,
                                  options.variant)
        part = fit_pixels(ev, data, log, medians)
        del data
        release(options.variant)
        result = part if result is None else merge_block(result, part)
    result.mask = pixels
    result.fit_settings["blocks"] = len(blocks)
    return _drop_pinned_lobes(inputs, result, options, light_distance, log, at)


#: A pixel's surface lobe is pinned when its amplitude ends within this fraction of the
#: amplitude's upper bound
PINNED = 1e-3


def pinned_lobes(amplitude: np.ndarray) -> np.ndarray:
    """Where a fitted ``amplitude_surface`` map ends at its upper bound (within
    :data:`PINNED`): bool, the shape of ``amplitude`` (False where it is not finite)."""
    amp = np.asarray(amplitude)
    upper = SPECS["amplitude_surface"].upper
    return np.isfinite(amp) & (amp >= upper * (1.0 - PINNED))


def without_lobe(options: FitOptions) -> FitOptions | None:
    """``options`` with the surface lobe held off (:data:`~mitsuba_powder.rti.properties.LOBE`
    not free: ``amplitude_surface`` at the plugin's default 0); None when it is not free."""
    if "amplitude_surface" not in options.free:
        return None
    return options.replace(free=tuple(f for f in options.free if f not in LOBE))


def _drop_pinned_lobes(inputs: FitInputs, result: MapsResult, options: FitOptions,
                       light_distance: float | np.ndarray, log: Log,
                       start_pixels: np.ndarray) -> MapsResult:
    """``result`` with the pixels whose surface lobe ends at the largest amplitude fitted
    again without the lobe (``amplitude_surface`` 0), under the gains found: such a lobe is
    not determined by the lights (a needle between them or on the pixels' brightest,
    saturated and left out, observations), and it relights far beyond anything observed.
    ``fit_settings["lobe_dropped_pixels"]`` counts them."""
    plain = without_lobe(options)
    if plain is None:
        return result
    pinned = result.mask & pinned_lobes(result.maps["amplitude_surface"])
    upper = SPECS["amplitude_surface"].upper
    n = int(pinned.sum())
    result.fit_settings["lobe_dropped_pixels"] = n
    if not n:
        return result
    log(f"surface lobe: {n} of {int(result.mask.sum())} pixels end at the largest amplitude "
        f"({upper:g} um^2), which the lights do not determine: fitted again without the lobe")
    plain = plain.replace(gains=options.gains.held(result.gains))
    part = fit_in_blocks(inputs, pinned, plain, np.asarray(result.gains), light_distance, log,
                         start_pixels=start_pixels)
    settings = dict(result.fit_settings)
    mask = result.mask
    result = merge_block(result, part)
    for name in LOBE:
        result.maps[name][pinned] = NO_LOBE[name]
    result.mask = mask
    settings["evaluations"] = int(settings.get("evaluations", 0)) + int(
        part.fit_settings.get("evaluations", 0))
    settings["underdetermined_pixels"] = int(np.count_nonzero(
        ~np.isfinite(result.residual_rms[mask])))
    result.fit_settings = settings
    return result


def fit_pixels(ev: PixelEvaluator, data: FitData, log: Log,
               medians: Mapping[str, float] | None = None) -> MapsResult:
    """The maps of the pixels of ``data`` with the evaluator ``ev``: starts (the held
    properties at ``medians`` in the albedo table), rounds, result."""
    t0 = time.perf_counter()
    layout, specs = _parameter_layout(data)
    o = data.options
    starts = PixelStarts(ev, data.obs, data.d, layout, specs, o.free, o.others, o.grain_name,
                         data.fixed_maps, data.grain, o.lanes, data.field, medians)
    y, wt = _initial_start(starts, data, log)
    state = _alternate(ev, starts, data, layout, y, wt, log)
    return _result(ev, data, layout, specs, state, log, t0)


def _parameter_layout(data: FitData) -> tuple[list[tuple[str, ParamSpec]], dict]:
    """The variables of a pixel in column order (name, spec): the normal's slopes, the albedo
    per channel or the grain size, the other free properties; and the specs by name, with the
    correlation length bounded by what the lights resolve (:func:`max_correlation_length`).
    """
    o = data.options
    layout: list[tuple[str, ParamSpec]] = [
        ("slope_x", ParamSpec(-SLOPE_LIMIT, SLOPE_LIMIT, False, 0.0)),
        ("slope_y", ParamSpec(-SLOPE_LIMIT, SLOPE_LIMIT, False, 0.0))]
    if "albedo" in o.free:
        layout += [(f"albedo{c}", SPECS["albedo"]) for c in range(3)]
    if o.grain_name in o.free:
        layout.append((o.grain_name, SPECS[o.grain_name]))
    specs = dict(SPECS)
    lc_max = max_correlation_length(data.d)
    lc = specs["correlation_length"]
    specs["correlation_length"] = ParamSpec(lc.lower, max(min(lc.upper, lc_max), 2 * lc.lower),
                                            lc.log, min(lc.start, 0.8 * lc_max))
    layout += [(n, specs[n]) for n in o.others]
    return layout, specs


# ---------------------------------------------------------------------------
#  Start and alternation: per-pixel maps and per-light gains
# ---------------------------------------------------------------------------

def _initial_start(starts: PixelStarts, data: FitData, log: Log
                   ) -> tuple[np.ndarray, np.ndarray]:
    """Start rows and observation weights: shadows are flagged against the Lambertian
    prediction twice, the second start without them (and with the grain-size search)."""
    g = data.gains
    wt = data.usable.astype(np.float64)
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


@dataclass
class _State:
    """The alternation's state: the pixels' rows, the gains and weights, the models."""

    y: np.ndarray           # (P, variables + 1) fitted rows
    gains: np.ndarray       # (K,)
    weights: np.ndarray     # (P, K) observation weights in {0, 1}
    value: np.ndarray       # (P, K, 3) float32, the model without gain at the fitted rows
    chunks: list[slice]
    information: np.ndarray | None = None  # (K,) diagonal of the gains' reduced system
    held: np.ndarray | None = None         # lights whose gains were held in the last step
    iterations: int = 0
    evaluations: int = 0
    at_cap: int = 0         # pixels the iteration cap stopped in the last round
    capped_rounds: int = 0  # rounds in which the cap stopped some pixels


def _fit_chunk(ev: PixelEvaluator, data: FitData, layout: list, state: _State,
               y_start: np.ndarray, s: slice | np.ndarray, with_gains: bool
               ) -> tuple[np.ndarray, np.ndarray] | None:
    """Fit the pixels ``s`` from ``y_start`` under the current gains with the options'
    solver; update ``state``; with ``with_gains`` return their part of the gains' reduced
    system."""
    solver = SOLVERS[data.options.solver](ev, data.pixel_data(s, state.weights, state.gains,
                                                              layout))
    fitted = solver.solve(y_start[s], data.options.max_iterations,
                          stop_tolerance(data.obs.shape[1]))
    state.y[s, :-1] = fitted.y
    state.iterations = max(state.iterations, fitted.iterations)
    state.at_cap += fitted.at_cap
    state.value[s], part = solver.model(fitted.y, with_gains)
    state.evaluations += solver.evaluations
    return part


def _alternate(ev: PixelEvaluator, starts: PixelStarts, data: FitData, layout: list,
               y: np.ndarray, wt: np.ndarray, log: Log) -> _State:
    """Rounds of the per-pixel fit alternated with a Gauss-Newton step of the gains (when
    they are fitted) and new shadow flags; a final per-pixel fit follows the last gain
    update."""
    npix, k = data.obs.shape[:2]
    fitted = data.options.gains.fitted
    state = _State(y=y, gains=data.gains, weights=wt,
                   value=np.zeros((npix, k, 3), dtype=np.float32),
                   chunks=pixel_chunks(npix, k, data.options.lanes))
    rounds = data.options.rounds
    total = rounds + (1 if fitted else 0)  # fitted gains: a last per-pixel fit under them
    previous = None  # the weights of the last round, when the gains did not move since
    for r in range(total):
        last = r == total - 1
        with_gains = fitted and not last
        name = (f"round {r + 1}/{rounds}" if r < rounds else
                "final fit under the fitted gains")
        if previous is not None and np.array_equal(previous, state.weights):
            # same gains, same flags: this round would repeat the last one exactly
            log(f"{name}: observation flags unchanged, the last round's fit holds")
            continue
        changed = _changed_pixels(previous, state)
        previous = None if with_gains else state.weights.copy()
        # every round starts from the Lambertian start under the current gains: a warm start
        # would keep pixels in the surface-lobe basin the previous gains led them to
        y_start = starts(state.gains, state.weights)[0] if r > 0 else state.y
        state.iterations, state.at_cap = 0, 0
        chunks = _round(ev, data, layout, state, y_start, with_gains, log, changed)
        model = state.value * data.light_gains(state.gains)
        if not last:
            state.weights = data.flags(model)
        rms = np.sqrt(np.sum(state.weights[:, :, None] * (model - data.obs) ** 2)
                      / max(3 * np.sum(state.weights), 1))
        cap = data.options.max_iterations
        again = "" if changed is None else (f" of the {len(changed)} pixels whose observation "
                                            "flags changed (the others' fit holds)")
        log(f"{name}: Levenberg-Marquardt{again} ({chunks} chunk(s)), "
            f"{state.iterations} iterations" + (f" (the cap: {state.at_cap} pixels stopped by it)"
                             if state.at_cap else "")
            + f", RMS residual {rms:.5g}, {int(np.sum(state.weights == 0))} observations left "
            "out")
        state.capped_rounds += int(state.at_cap > 0 and state.iterations >= cap)
    return state


def _changed_pixels(previous: np.ndarray | None, state: _State) -> np.ndarray | None:
    """The pixels a round must fit again when the gains have not moved since the last round
    (``previous``: its weights, else None): those whose observation flags changed. Every
    pixel's fit is its own (the Lambertian start and the solver's steps, per pixel), so the
    others would repeat the last round's exactly. None (fit every pixel) when the gains moved
    or the last round stopped pixels at the iteration cap (not tracked per pixel)."""
    if previous is None or state.at_cap:
        return None
    return np.flatnonzero(np.any(previous != state.weights, axis=1))


def _round(ev: PixelEvaluator, data: FitData, layout: list, state: _State,
           y_start: np.ndarray, with_gains: bool, log: Log,
           pixels: np.ndarray | None = None) -> int:
    """One round: every chunk of pixels (of ``pixels`` only, if given: indices) fitted from
    ``y_start``; with ``with_gains`` a Gauss-Newton step of the gains on the reduced system
    the chunks add up to (their mean held), smoothed by the gains' trend in mode
    ``smooth``. Returns the chunks fitted."""
    k = len(state.gains)
    reduced = np.zeros((k, k)), np.zeros(k)
    chunks = state.chunks if pixels is None else [
        pixels[c] for c in pixel_chunks(len(pixels), 1, state.chunks[0].stop)]
    for s in chunks:
        part = _fit_chunk(ev, data, layout, state, y_start, s, with_gains)
        if part is not None:
            reduced = reduced[0] + part[0], reduced[1] + part[1]
    if with_gains:
        trend = data.options.gains.trend
        held = np.nonzero(uninformed_lights(reduced[0]))[0]
        if len(held) and (state.held is None or not np.array_equal(held, state.held)):
            log(f"gains: {len(held)} light(s) see too little to fit their gain (images "
                f"{_numbers(held)}: below the object's horizon, shadowed or saturated "
                "everywhere): held")
        state.held = held
        state.gains = gain_step(state.gains, *reduced, data.scale)
        state.information = np.diag(reduced[0]).copy()
        if trend.mode == "smooth":
            state.gains = trend.smooth(data.d, state.gains, state.information, data.scale)
    return len(chunks)


def _numbers(indices: np.ndarray, most: int = 12) -> str:
    """Image indices as text, the first ``most`` of them."""
    text = ", ".join(str(int(i)) for i in indices[:most])
    return text + (f" and {len(indices) - most} more" if len(indices) > most else "")


# ---------------------------------------------------------------------------
#  Result
# ---------------------------------------------------------------------------

def _result(ev: PixelEvaluator, data: FitData, layout: list, specs: Mapping[str, ParamSpec],
            state: _State, log: Log, t0: float) -> MapsResult:
    """The maps of the fitted rows (NaN outside the mask), the residual per pixel, the
    observations used, and the fit's options and diagnostics."""
    h, w = data.mask.shape
    npix, k = data.obs.shape[:2]

    def to_map(values: np.ndarray, channels: int = 0) -> np.ndarray:
        out = np.full((h, w, channels) if channels else (h, w), np.nan, dtype=np.float32)
        out[data.mask] = values
        return out

    wt, g, o = state.weights, state.gains, data.options
    prob = PixelProblem(ev, data.pixel_data(slice(None), wt, g, layout))
    y_all = state.y.copy()
    y_all[:, -1] = np.arange(npix)
    _, slopes, albedo, values, _ = prob.unpack(y_all)
    resid = (state.value * data.light_gains(g) - data.obs) * wt[:, :, None]
    rms_map = np.sqrt(np.sum(resid**2, axis=(1, 2)) / np.maximum(3 * wt.sum(axis=1), 1))
    # a pixel with fewer used observations than variables is not determined: NaN residual
    underdetermined = 3 * wt.sum(axis=1) < len(layout)
    rms_map[underdetermined] = np.nan
    if np.any(underdetermined):
        log(f"{int(underdetermined.sum())} of {npix} pixels have fewer used observations "
            f"than variables ({len(layout)}): their maps are the start's, their residual "
            "NaN (saturated, black or shadowed under most lights)")
    used = np.zeros((k, h, w), dtype=bool)
    used[:, data.mask] = (wt > 0).T
    return MapsResult(
        normals=to_map(normals_of_slopes(slopes), 3), albedo=to_map(albedo, 3),
        maps={n: to_map(v) for n, v in values.items()}, settings=o.settings,
        residual_rms=to_map(rms_map), gains=g, used=used, free=list(o.free), mask=data.mask,
        variant=o.variant, light_distance=data.light_distance,
        fit_settings=_fit_settings(data, state, specs, log, t0,
                                   int(np.sum(underdetermined))),
        gain_model=(None if o.gains.trend.mode == "none" else
                    o.gains.trend.fit(data.d, g, state.information)))


def _fit_settings(data: FitData, state: _State, specs: Mapping[str, ParamSpec], log: Log,
                  t0: float, underdetermined: int) -> dict:
    """The options and diagnostics of a fit of the pixels of ``data`` (``fit.json``)."""
    o = data.options
    return {
        "free": list(o.free), "gains": o.gains.mode, "max_iterations": o.max_iterations,
        "rounds": o.rounds, "saturation": o.saturation, "shadow_ratio": o.shadow_ratio,
        "shadow_floor": o.shadow_floor,
        "full_scale": None if math.isinf(o.full_scale) else o.full_scale,
        "max_lanes": o.lanes, "chunks": len(state.chunks),
        "solver": o.solver, "correlation_length_max_um": specs["correlation_length"].upper,
        "iterations_last_round": state.iterations, "evaluations": state.evaluations,
        "pixels_at_cap_last_round": state.at_cap, "rounds_at_cap": state.capped_rounds,
        "stop_tolerance": stop_tolerance(data.obs.shape[1]),
        "underdetermined_pixels": underdetermined, "seconds": time.perf_counter() - t0,
        "stages": log.stages,
        "fixed": {n: v for n, v in o.fixed.items() if np.ndim(v) == 0 or isinstance(v, str)},
        "light_distance": distance_to_json(data.light_distance),
        "gain_model": o.gains.trend.settings()}
