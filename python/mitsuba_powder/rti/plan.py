"""The plan of a per-pixel RTI fit: what is fitted, in which stages, run by small named steps.

A fit is one :class:`~mitsuba_powder.rti.options.FitOptions` (checked once by
:func:`~mitsuba_powder.rti.options.fit_options`) and one capture (checked once against them by
:func:`~mitsuba_powder.rti.inputs.check_inputs`). :func:`make_plan` lists the stages they call
for, in order; :func:`run_plan` runs them, each handing the next what it found
(:class:`FitState`):

1. ``distance scan`` (``light_distance="fit"``): one light distance for the whole dome, a
   Lambertian scan of its inverse on a subsample of pixels spread over the mask, then a polish
   with the powder fit of that subsample (:mod:`mitsuba_powder.rti.distance`);
2. ``exposure scan`` (the exposure not given, :attr:`FitOptions.fits_exposure
   <mitsuba_powder.rti.options.FitOptions.fits_exposure>`): one global scale of the gains, a
   scan of its logarithm with the powder fit of a subsample of pixels spread over the
   mask, then a polish (:mod:`mitsuba_powder.rti.exposure`);
3. ``gain subsample`` (gains fitted, more masked pixels than the gain policy's subsample):
   the maps and gains of a random subsample of the masked pixels, whose gains are then held
   for every pixel (:mod:`mitsuba_powder.rti.gains`);
4. ``free choice`` (``free`` not given): which properties are free per pixel, the albedo
   alone or with the surface lobe, by cross-validation over held-out lights on a subsample of
   pixels, under the gains found so far (:mod:`mitsuba_powder.rti.selection`);
5. ``blocks``: every masked pixel, in blocks within the memory budget (one block while the
   gains are still fitted: they couple every pixel) (:mod:`mitsuba_powder.rti.blocks`);
6. ``shadows choice`` (``shadows="auto"``, the default): the height field of the blocks'
   normals and its horizon map (:mod:`mitsuba_powder.rti.relief`), and whether its cast
   shadows relight held-out lights better, cross-validated over folds of the lights on a
   subsample of pixels (:func:`~mitsuba_powder.rti.selection.choose_shadows`);
7. ``relief`` (``shadows="relief"``, or ``auto`` where the choice kept the relief): the
   masked pixels that relief shades under some light (every masked pixel while the gains
   are fitted) fitted again with each light's visibility over it (the lights below a pixel's
   horizon left out, the soft edge in the model), and the relief of these
   normals kept with the maps; where ``auto`` chose ``ratio``, the blocks' maps are kept
   with their relief, unused.

Every stage fits its pixels the same way (:func:`~mitsuba_powder.rti.pixelfit.fit_in_blocks`:
the Lambertian start, rounds of the per-pixel solver alternated with the gains, the maps). A
new stage (e.g. a scan of the exposure) is a step function ``(inputs, stage, state, log) ->
state`` and a line in :func:`make_plan`. A tiled fit (:mod:`mitsuba_powder.rti.tiles`) fits the
gains' subsample on its cluster and each tile with :func:`run_fit`, with the same options.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, replace
from functools import partial

import numpy as np

from ..variants import use_variant
from .blocks import merge_block, peak_memory_mib
from .distance import (
    polish_bracket,
    polish_inverse_distance,
    scan_inverse_distance,
    subsample_mask,
)
from .exposure import (
    HELD_OUT_MARGIN,
    MEDIAN_EFFICIENCY,
    POLISH_EVALUATIONS,
    POLISH_WIDTH,
    SCAN_LOG2,
    contradicted,
    determined,
    exposure_anchor,
    exposure_grid,
    exposure_uncertainty,
)
from .inputs import FitInputs, check_inputs
from .options import FitOptions
from .pixelfit import Log, fit_in_blocks
from .relief import Relief, make_relief
from .result import MapsResult
from .selection import choose_free, choose_shadows, free_candidates, held_out_rms

__all__ = ["FitPlan", "FitState", "Stage", "check_finite", "fit_distance", "make_plan",
           "run_fit", "run_plan"]


@dataclass
class FitState:
    """What the stages of a fit hand on: the light distance (found by the ``distance scan``
    and its record ``scan``), the options the next stage fits with (the gains held after the
    ``gain subsample``) and the gains, the subsample's fit (``held``), the maps
    (``result``), and the relief of the blocks' normals with the ``shadows choice``'s
    record."""

    light_distance: float | np.ndarray | str
    options: FitOptions
    gains: np.ndarray
    scan: dict | None = None
    exposure: dict | None = None
    free_choice: dict | None = None
    held: MapsResult | None = None
    result: MapsResult | None = None
    relief: Relief | None = None
    shadows_choice: dict | None = None


#: A step of a plan: (the checked inputs, its stage, the state so far, the log) -> the state
Step = Callable[[FitInputs, "Stage", FitState, Log], FitState]


@dataclass(frozen=True, eq=False)
class Stage:
    """A stage of a plan: its name, the pixels it fits (bool (H, W)) and its step."""

    name: str
    pixels: np.ndarray
    step: Step


@dataclass(frozen=True, eq=False)
class FitPlan:
    """A fit's checked inputs and its stages, in order."""

    inputs: FitInputs
    stages: tuple[Stage, ...]

    def describe(self) -> list[str]:
        """One line per stage: its name and how many pixels it fits."""
        return [f"{s.name}: {int(s.pixels.sum())} pixels" for s in self.stages]


def make_plan(images: np.ndarray, directions: np.ndarray, options: FitOptions,
              mask: np.ndarray | None = None) -> FitPlan:
    """The stages of a fit of a capture (module docstring), its inputs (the arguments of
    :func:`~mitsuba_powder.rti.inputs.check_inputs`) checked once."""
    inputs = check_inputs(images, directions, options, mask)
    stages = []
    if isinstance(options.light_distance, str):  # "fit"
        stages.append(Stage("distance scan", subsample_mask(inputs.mask), scan_distance))
    if options.fits_exposure:
        stages.append(Stage("exposure scan", subsample_mask(inputs.mask), scan_exposure))
    policy = options.gains
    if policy.subsampled(int(inputs.mask.sum())):
        sub = np.zeros(inputs.mask.size, dtype=bool)
        sub[policy.draw(inputs.mask)] = True
        stages.append(Stage("gain subsample", sub.reshape(inputs.shape), fit_gain_subsample))
    if options.chooses_free and len(free_candidates(options)) > 1:
        # (after the gains' subsample: the choice relights held-out lights at those gains)
        stages.append(Stage("free choice", subsample_mask(inputs.mask), choose_free_set))
    if options.fits_exposure:
        stages.append(Stage("exposure check", subsample_mask(inputs.mask), check_exposure))
    stages.append(Stage("blocks", inputs.mask, fit_blocks))
    if options.shadows == "auto":
        stages.append(Stage("shadows choice", subsample_mask(inputs.mask), choose_shadows_mode))
    if options.shadows != "ratio":
        stages.append(Stage("relief", inputs.mask, fit_with_relief))
    return FitPlan(inputs, tuple(stages))


def run_plan(plan: FitPlan, progress: Callable[[str], None] | None = None) -> MapsResult:
    """Run the stages of ``plan``; the maps of its last, with the fit's diagnostics.

    Args:
        plan: :func:`make_plan`'s.
        progress: called with a line of text after each stage.
    """
    t0 = time.perf_counter()
    log = Log(progress)
    state = run_stages(plan, log)
    return check_finite(_finish(state, log, t0))


def run_stages(plan: FitPlan, log: Log, names: tuple[str, ...] | None = None) -> FitState:
    """The state after the stages of ``plan`` (those of ``names`` only, if given), in the
    options' variant."""
    inputs = plan.inputs
    o = inputs.options
    exposure = 1.0 if o.fits_exposure or o.exposure is None else float(o.exposure)
    source = "initial gains" if o.exposure is None and not o.fits_exposure else "given"
    state = FitState(o.light_distance, o, exposure * inputs.gains,
                     exposure={"value": exposure, "sigma": 0.0, "source": source,
                               "determined": True})
    with use_variant(inputs.options.variant):
        for stage in plan.stages:
            if names is None or stage.name in names:
                state = stage.step(inputs, stage, state, log)
    return state


def run_fit(images: np.ndarray, directions: np.ndarray, options: FitOptions,
            mask: np.ndarray | None = None, progress: Callable[[str], None] | None = None
            ) -> MapsResult:
    """:func:`make_plan` and :func:`run_plan`: the maps of a capture fitted with ``options``."""
    return run_plan(make_plan(images, directions, options, mask), progress)


def fit_distance(images: np.ndarray, directions: np.ndarray, options: FitOptions,
                 mask: np.ndarray | None = None, progress: Callable[[str], None] | None = None
                 ) -> tuple[float, dict]:
    """The ``distance scan`` of a fit with ``options`` alone: r in image widths (``inf``
    when distant lights fit best) and the scan's record."""
    plan = make_plan(images, directions, options.replace(light_distance="fit"), mask)
    state = run_stages(plan, Log(progress), ("distance scan",))
    return state.light_distance, state.scan


# ---------------------------------------------------------------------------
#  Steps
# ---------------------------------------------------------------------------

def scan_distance(inputs: FitInputs, stage: Stage, state: FitState, log: Log) -> FitState:
    """Stage ``distance scan``: the Lambertian scan of u = 1/r on the stage's pixels, then
    the powder fit's cost of those pixels polished over the scan's best bracket."""
    sub = stage.pixels
    data = inputs.pixels(sub, state.gains, math.inf, state.options)
    wt = (~data.saturated).astype(np.float64)
    us, costs = scan_inverse_distance(data.obs, wt, sub, data.d, data.gains)
    log(f"light distance: Lambertian scan of u = 1/r on {int(sub.sum())} pixels, best "
        f"u = {us[int(np.argmin(costs))]:.4g}")
    del data

    def cost(u: float) -> float:
        r = math.inf if u <= 0 else 1.0 / u
        part = fit_in_blocks(inputs, sub, state.options, state.gains, r, Log())
        return float(np.nanmean(part.residual_rms[sub] ** 2))

    u, seen = polish_inverse_distance(cost, us, costs)
    r = math.inf if u <= 0 else 1.0 / u
    log(f"light distance: polished with the powder fit ({len(seen)} fits), r = {r:.5g} "
        "image widths")
    scan = {"inverse_distance": us.tolist(), "cost": costs.tolist(),
            "polish": [{"inverse_distance": a, "cost": b} for a, b in seen]}
    return replace(state, light_distance=r, scan=scan)


def scan_exposure(inputs: FitInputs, stage: Stage, state: FitState, log: Log) -> FitState:
    """Stage ``exposure scan``: x = ln(exposure) scanned with the powder fit of the stage's
    pixels, polished, its uncertainty from the cost's
    curvature (:mod:`mitsuba_powder.rti.exposure`); the gains are then ``exposure x`` the
    initial ones."""
    sub, base, r = stage.pixels, state.gains, state.light_distance
    held = state.options.replace(gains=state.options.gains.held(base))
    data = inputs.pixels(sub, base, r, held)
    anchor = exposure_anchor(data.obs, (~data.saturated).astype(np.float64), data.d, base)
    del data
    counts: dict[float, int] = {}

    def cost(x: float, options) -> float:
        # the median over the pixels of their mean squared residual: a few pixels whose lobe
        # lands in another basin at one exposure and not at the next do not move it
        part = fit_in_blocks(inputs, sub, options, base * math.exp(x), r, Log())
        used = part.used[:, sub]                                   # (K, P)
        counts[x] = int(MEDIAN_EFFICIENCY * 3 * used.sum())
        return float(np.nanmedian(part.residual_rms[sub] ** 2))

    grid = exposure_grid(anchor, SCAN_LOG2)
    costs = np.array([cost(x, held) for x in grid])
    log(f"exposure: scan of {len(grid)} values {math.exp(grid[0]):.4g}-{math.exp(grid[-1]):.4g}"
        f" on {int(sub.sum())} pixels, best {math.exp(grid[int(np.argmin(costs))]):.4g}")
    x, seen = polish_bracket(lambda x: cost(x, held), grid, costs, POLISH_EVALUATIONS,
                             POLISH_WIDTH)
    step = float(grid[1] - grid[0])
    points = seen + list(zip(grid.tolist(), costs.tolist()))
    x, sigma_x = exposure_uncertainty(points, counts[min(seen, key=lambda p: p[1])[0]],
                                      POLISH_WIDTH * step + 1e-9)
    ok = determined(x, sigma_x, grid, costs)
    best = math.exp(x)
    sigma = best * sigma_x if math.isfinite(sigma_x) else math.inf
    e = best if ok else 1.0
    log(f"exposure: polished with the powder fit ({len(seen)} fits), {best:.4g} +- "
        f"{sigma:.2g}" + ("" if ok else "; the capture does NOT determine the exposure "
                          "(its cost has no minimum in the scan, or a flat one): exposure 1 "
                          "is kept (the images' scale), and the albedo and the lobe's "
                          "amplitude are relative to it; give --exposure or --reference to "
                          "calibrate"))
    record = {"value": e, "sigma": sigma if math.isfinite(sigma) and ok else None,
              "source": "fitted", "determined": ok, "best": best, "anchor": anchor,
              "scan": {"exposure": np.exp(grid).tolist(), "cost": costs.tolist(),
                       "polish": [{"exposure": math.exp(a), "cost": b} for a, b in seen]}}
    return replace(state, gains=base * e, exposure=record)


def check_exposure(inputs: FitInputs, stage: Stage, state: FitState, log: Log) -> FitState:
    """Stage ``exposure check``: an exposure the scan determined is kept only if the maps
    fitted with it relight held-out lights (the free choice's folds, on the stage's pixels)
    no worse than at exposure 1, within
    :data:`~mitsuba_powder.rti.exposure.HELD_OUT_MARGIN`
    (:func:`~mitsuba_powder.rti.exposure.contradicted`); else the capture does not determine
    it (the shape that set it is not a powder's) and exposure 1 is kept."""
    record, e = state.exposure, float(state.exposure["value"])
    if not record.get("determined") or e == 1.0:
        return state
    sub, r = stage.pixels, state.light_distance
    choice = state.free_choice
    if choice is not None and choice["pixels"] == int(sub.sum()):
        fitted = next(c["cv_rms"] for c in choice["candidates"]
                      if tuple(c["free"]) == tuple(choice["chosen"]))
    else:
        fitted = held_out_rms(inputs, sub, state.options, state.gains, r)[0]
    unit = held_out_rms(inputs, sub, state.options, state.gains / e, r)[0]
    check = {"cv_rms_fitted": fitted, "cv_rms_exposure_1": unit, "margin": HELD_OUT_MARGIN}
    if not contradicted(fitted, unit):
        log(f"exposure: {e:.4g} relights held-out lights at {fitted:.4g} (exposure 1: "
            f"{unit:.4g}); kept")
        return replace(state, exposure={**record, "held_out": check})
    log(f"exposure: the capture does NOT determine the exposure: the maps fitted at {e:.4g} "
        f"relight held-out lights worse ({fitted:.4g}) than at exposure 1 ({unit:.4g}): the "
        "angular shape that set it is not a powder's; exposure 1 is kept (the images' scale), "
        "and the albedo and the lobe's amplitude are relative to it; give --exposure or "
        "--reference to calibrate")
    record = {**record, "value": 1.0, "sigma": None, "determined": False, "held_out": check}
    return replace(state, gains=state.gains / e, exposure=record)


def choose_free_set(inputs: FitInputs, stage: Stage, state: FitState, log: Log) -> FitState:
    """Stage ``free choice``: the free set cross-validated over held-out lights on the stage's
    pixels (:func:`~mitsuba_powder.rti.selection.choose_free`) is the next stages'."""
    choice = choose_free(inputs, stage.pixels, state.options, state.gains,
                         state.light_distance, log)
    return replace(state, options=state.options.replace(free=choice.chosen),
                   free_choice=choice.to_dict())


def fit_gain_subsample(inputs: FitInputs, stage: Stage, state: FitState, log: Log
                       ) -> FitState:
    """Stage ``gain subsample``: the maps and gains of the stage's pixels, gains fitted with
    every one of them; the gains are then held (mode ``fixed``) for the next stages."""
    policy = state.options.gains
    part = fit_in_blocks(inputs, stage.pixels, state.options.replace(
        gains=policy.on_subsample()), state.gains, state.light_distance, Log())
    count = int(stage.pixels.sum())
    part.fit_settings["gain_pixels"] = count
    log(f"gains: fitted on {count} of {int(inputs.mask.sum())} pixels (seed {policy.seed}), "
        f"range {np.min(part.gains):.4g}-{np.max(part.gains):.4g}, held for every pixel")
    return replace(state, options=state.options.replace(gains=policy.held(part.gains)),
                   gains=part.gains, held=part)


def fit_blocks(inputs: FitInputs, stage: Stage, state: FitState, log: Log) -> FitState:
    """Stage ``blocks``: every pixel of the stage, in blocks within the memory budget."""
    return replace(state, result=fit_in_blocks(inputs, stage.pixels, state.options,
                                               state.gains, state.light_distance, log))


def choose_shadows_mode(inputs: FitInputs, stage: Stage, state: FitState, log: Log
                        ) -> FitState:
    """Stage ``shadows choice``: the relief of the blocks' normals, and whether its cast
    shadows relight held-out lights of the stage's pixels better
    (:func:`~mitsuba_powder.rti.selection.choose_shadows`)."""
    t0 = time.perf_counter()
    relief = _relief_of(state.result, inputs, log)
    seconds = time.perf_counter() - t0
    choice = choose_shadows(inputs, stage.pixels, state.options, state.gains,
                            state.light_distance, relief, log)
    record = {**choice.to_dict(), "relief_seconds": seconds}
    return replace(state, relief=relief, shadows_choice=record)


def _relief_of(first: MapsResult, inputs: FitInputs, log: Log) -> Relief:
    """The relief of the maps ``first`` (:func:`~mitsuba_powder.rti.relief.make_relief`)."""
    t0 = time.perf_counter()
    relief = make_relief(first.normals, first.residual_rms, first.mask,
                         inputs.options.light_size)
    log(f"relief: heights {np.ptp(relief.height[first.mask]):.4g} px from lowest to highest, "
        f"height field and horizon map in {time.perf_counter() - t0:.1f} s")
    return relief


def fit_with_relief(inputs: FitInputs, stage: Stage, state: FitState, log: Log
                    ) -> FitState:
    """Stage ``relief``: the relief of the maps so far (the ``shadows choice``'s, if made),
    the pixels it shades fitted again under its visibility (:func:`_refit_shaded`; every
    pixel of the stage while the gains are fitted), and the relief of the new
    normals kept with them; where the choice was ``ratio``, the maps so far with their
    relief."""
    first = state.result
    if state.shadows_choice is not None and state.shadows_choice["chosen"] == "ratio":
        first.relief = state.relief
        first.fit_settings.update(relief_seconds=state.shadows_choice["relief_seconds"],
                                  shadows="ratio", light_size=inputs.options.light_size)
        log("shadows: the relief is kept with the maps, unused by the fit")
        return state
    t0 = time.perf_counter()
    relief = state.relief if state.relief is not None else _relief_of(first, inputs, log)
    seconds = time.perf_counter() - t0 + (state.shadows_choice or {}).get("relief_seconds", 0)
    below = _below_horizon(relief, inputs.d, first.mask) if np.all(
        np.isinf(state.light_distance)) else None
    result = _refit_shaded(replace(inputs, relief=relief), stage, state, log,
                           "" if below is None else f"{below} observations below the horizon; ")
    t1 = time.perf_counter()
    result.relief = make_relief(result.normals, result.residual_rms, result.mask,
                                inputs.options.light_size)
    result.fit_settings.update(relief_seconds=seconds + time.perf_counter() - t1,
                               shadows="relief", light_size=inputs.options.light_size)
    return replace(state, result=result)


def _below_horizon(relief: Relief, directions: np.ndarray, mask: np.ndarray,
                   rows: int = 64) -> int:
    """How many (pixel, light) pairs of the pixels ``mask`` have the distant lights
    ``directions`` less than half visible over ``relief``, ``rows`` image rows at a time."""
    count = 0
    for r0 in range(0, mask.shape[0], rows):
        part = np.zeros_like(mask)
        part[r0:r0 + rows] = mask[r0:r0 + rows]
        if part.any():
            count += int(np.count_nonzero(relief.visibility(directions, part) < 0.5))
    return count


def _refit_shaded(inputs: FitInputs, stage: Stage, state: FitState, log: Log, said: str
                  ) -> MapsResult:
    """The stage's pixels fitted under the visibility of ``inputs.relief``. With the gains
    held, only the pixels it shades under some light (visibility < 1) are fitted again: the
    others see the same data as in the maps so far (visibility 1 scales nothing, no light is
    left out), and every pixel's fit is its own from the same start, so they keep their maps.
    With the gains fitted (they couple every pixel) every pixel is fitted again, the gains
    with them. The diagnostics in ``fit_settings`` count both fits where the maps merge both
    (``underdetermined_pixels``: those of the merged maps); ``relief_refit`` has the second
    fit's own."""
    fit = partial(fit_in_blocks, inputs, options=state.options, gains=state.gains,
                  light_distance=state.light_distance, log=log, start_pixels=stage.pixels)
    total = int(stage.pixels.sum())
    if state.options.gains.fitted:
        log(f"relief: {said}every pixel fitted again under its lights' visibility (the "
            "gains are fitted)")
        result = fit(stage.pixels)
        result.fit_settings["relief_refit"] = _refit_record(result, total)
        return result
    pixels = inputs.shaded(inputs.relief, stage.pixels, state.light_distance)
    n = int(pixels.sum())
    log(f"relief: {said}{n} of {total} pixels shaded under some light, fitted again under "
        "their lights' visibility (the others keep their maps)")
    first = state.result
    settings = dict(first.fit_settings)
    refit = {"pixels": 0, "evaluations": 0, "pixels_at_cap_last_round": 0,
             "underdetermined_pixels": 0}
    if n:
        part = fit(pixels)
        refit = _refit_record(part, n)
        first = merge_block(first, part)
        settings["evaluations"] = int(settings.get("evaluations", 0)) + refit["evaluations"]
        for key in ("iterations_last_round", "rounds_at_cap"):
            settings[key] = max(int(settings.get(key, 0)), int(part.fit_settings.get(key, 0)))
        # pixels at the cap are counted per fit, not per pixel: the refit's are added
        settings["pixels_at_cap_last_round"] = (int(settings.get("pixels_at_cap_last_round", 0))
                                                + refit["pixels_at_cap_last_round"])
    first.mask = stage.pixels
    settings["underdetermined_pixels"] = int(np.count_nonzero(
        ~np.isfinite(first.residual_rms[stage.pixels])))
    settings["relief_refit"] = refit
    first.fit_settings = settings
    return first


def _refit_record(part: MapsResult, pixels: int) -> dict:
    """The relief stage's own diagnostics (``fit_settings["relief_refit"]``)."""
    return {"pixels": int(pixels), **{key: int(part.fit_settings.get(key, 0)) for key in (
        "evaluations", "pixels_at_cap_last_round", "underdetermined_pixels")}}


def check_finite(result: MapsResult) -> MapsResult:
    """``result``, if its gains and its maps inside the mask are finite; else a
    ``RuntimeError`` naming what is not (which maps, how many pixels, the first of them, which
    lights), never maps with NaN or infinity where pixels were fitted."""
    gains = np.asarray(result.gains, dtype=np.float64)
    if not np.all(np.isfinite(gains)):
        bad = np.nonzero(~np.isfinite(gains))[0]
        raise RuntimeError(f"the fit diverged: the gains of lights {bad.tolist()[:12]} are not "
                           "finite; no maps written (a light that sees nothing with gains "
                           "fitted: hold them, gains fixed)")
    mask = result.mask
    named = {"normal": result.normals, "albedo": result.albedo, **result.maps}
    for name, m in named.items():
        values = np.asarray(m)[mask]
        bad = ~np.isfinite(values) if values.ndim == 1 else ~np.all(np.isfinite(values), axis=1)
        if np.any(bad):
            ys, xs = np.nonzero(mask)
            i = int(np.nonzero(bad)[0][0])
            raise RuntimeError(f"the fit diverged: the {name} map is not finite at "
                               f"{int(bad.sum())} of {int(mask.sum())} fitted pixels (first "
                               f"at x = {int(xs[i])}, y = {int(ys[i])}); no maps written")
    return result


def _finish(state: FitState, log: Log, t0: float) -> MapsResult:
    """The last stage's maps with the fit's stages, memory and light distance recorded (and
    the gains, their trend and their stages from the ``gain subsample``, if run)."""
    result, held = state.result, state.held
    r = state.light_distance
    result.fit_settings.update(
        seconds=time.perf_counter() - t0, stages=log.stages,
        memory_gb=state.options.memory_gb, peak_memory_mib=peak_memory_mib(),
        light_distance_source=("fitted" if state.scan is not None else "distant"
                               if np.all(np.isinf(r)) else "given"),
        light_distance_scan=state.scan, exposure=state.exposure,
        free_choice=state.free_choice, shadows_choice=state.shadows_choice)
    result.fit_settings.setdefault("shadows", "ratio")
    result.exposure = float(state.exposure["value"])
    if held is not None:
        result.fit_settings.update(gains="fit", gain_pixels=held.fit_settings["gain_pixels"],
                                   gain_stages=held.fit_settings["stages"])
        result.gain_model = held.gain_model
    return result
