"""Which properties are free per pixel, chosen per capture by cross-validation over held-out
lights on a subsample of pixels (the plan's ``free choice``).

A property free per pixel that the capture does not need (the surface lobe of a matte clay)
fits the noise and the model's error at a few lights and relights the others worse. The
candidates (:func:`free_candidates`) run from the albedo alone to the default free set
(:data:`~mitsuba_powder.rti.properties.MAP_DEFAULT_FREE`); each is fitted to the subsample
with one fold of the lights held out (the lights ``k % FOLDS == f``), and the held-out lights
are predicted at the fitted maps (under the fit's gains and light distance). The score is the
RMS of the held-out residuals over the folds (observations not saturated); the simplest
candidate whose score is within :data:`TOLERANCE` of the best is chosen (a property earns its
place by relighting better, not by fitting the lights it saw). ``free`` given (``--free``)
skips the choice.

The cast shadows of the fit's relief (``shadows="auto"``, the default) are chosen the same
way (:func:`choose_shadows`): on the same subsample and folds, the held-out squared residuals
of each pixel, fitted without the relief (the ratio test only, the lights relit unshaded) and
under the relief's visibility (the lights below a pixel's horizon left out, the held-out
lights relit shaded by their visibility). Shadows matter at few (pixel, light) pairs, so a
margin on the RMS over every light would hide them; instead the paired per-pixel differences
(without minus with) are compared over the pixels the relief shades under at least one of the
capture's lights (:meth:`~mitsuba_powder.rti.inputs.FitInputs.shaded`; the others see the
same data either way; fewer than :data:`MIN_SHADED` of them is a tie, judged on too few
pixels), and the relief is kept when their mean is above :data:`SHADOW_Z`
standard errors (nearby pixels are not independent: the error is a scale, not a
probability). The relief adds no free parameter (its heights are the fitted normals'), so no
margin against overfitting is asked: it is kept when it relights the held-out lights better
on average (``z > 0``), and refused when they contradict it. A tie (nothing shades) keeps the
fit without it. The relief is integrated once, from the normals of the fit of every light (a
fold's held-out lights have seen the heights they are relit over; the folds refit every pixel
of the subsample without them).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from .forward import PixelEvaluator, slopes_of_normals
from .inputs import FitData, FitInputs
from .options import FitOptions
from .pixelfit import Log, fit_pixels, pinned_lobes, without_lobe
from .properties import LOBE, MAP_DEFAULT_FREE
from .relief import Relief

__all__ = ["FOLDS", "MIN_SHADED", "SHADOW_Z", "TOLERANCE", "Z_CAP", "FreeChoice",
           "ShadowChoice", "choose_free", "choose_shadows", "free_candidates", "held_out_rms",
           "held_out_squares", "paired_z"]

#: Folds of the lights (light k is held out in fold ``k % FOLDS``)
FOLDS = 5
#: A simpler candidate is chosen when its cross-validated RMS is within this fraction of the
#: best one's
TOLERANCE = 0.01
#: The relief's cast shadows are kept when they lower the held-out squared residuals by more
#: than this many standard errors (their per-pixel difference, paired, over the subsample's
#: pixels that the relief shades): 0, any improvement, since the relief adds no parameter
SHADOW_Z = 0.0
#: Fewer of the subsample's pixels shaded by the relief than this is a tie (too few to judge)
MIN_SHADED = 10
#: The largest |z| recorded (every shaded pixel gaining exactly the same has no spread)
Z_CAP = 1000.0


@dataclass
class FreeChoice:
    """The choice: each candidate's free set and cross-validated RMS (linear units), the one
    chosen, the folds and the pixels."""

    candidates: list[tuple[str, ...]]
    rms: list[float]
    chosen: tuple[str, ...]
    folds: int
    pixels: int

    def to_dict(self) -> dict:
        return {"candidates": [{"free": list(c), "cv_rms": r}
                               for c, r in zip(self.candidates, self.rms)],
                "chosen": list(self.chosen), "folds": self.folds, "pixels": self.pixels,
                "tolerance": TOLERANCE}


def free_candidates(options: FitOptions) -> list[tuple[str, ...]]:
    """The free sets the choice compares, simplest first: the default free set without the
    surface lobe, then the default (properties held in ``options.fixed`` left out); one
    candidate (no choice) when the lobe is held."""
    full = tuple(n for n in MAP_DEFAULT_FREE if n not in options.fixed)
    simple = tuple(n for n in full if n not in LOBE)
    return [simple, full] if simple != full else [full]


def choose_free(inputs: FitInputs, sub: np.ndarray, options: FitOptions, gains: np.ndarray,
                light_distance, log: Log, folds: int = FOLDS) -> FreeChoice:
    """Cross-validate :func:`free_candidates` on the pixels ``sub`` (bool (H, W)) under
    ``gains`` and lights at ``light_distance`` (module docstring)."""
    candidates = free_candidates(options)
    folds = max(2, min(int(folds), len(inputs.d)))
    scores = [held_out_rms(inputs, sub, options.replace(free=free), gains, light_distance,
                           folds)[0] for free in candidates]
    best = min(scores)
    chosen = next(c for c, s in zip(candidates, scores) if s <= best * (1 + TOLERANCE))
    log("free set: cross-validated over " + f"{folds} folds of the lights on "
        f"{int(sub.sum())} pixels: " + ", ".join(
            f"normal + {'+'.join(c)} {s:.4g}" for c, s in zip(candidates, scores))
        + f" (held-out RMS); chosen normal + {', '.join(chosen)}")
    return FreeChoice(candidates, scores, chosen, folds, int(sub.sum()))


def held_out_rms(inputs: FitInputs, sub: np.ndarray, options: FitOptions, gains: np.ndarray,
                 light_distance, folds: int = FOLDS, relief: Relief | None = None
                 ) -> tuple[float, int]:
    """The RMS (linear units) of the held-out residuals of the pixels ``sub`` fitted with
    ``options`` under ``gains`` with each fold of the lights held out in turn (light k in fold
    ``k % folds``), and the held-out observations it counts (channels of observations not
    saturated, of pixels whose prediction is finite): :func:`held_out_squares` summed."""
    ssr, n, _ = held_out_squares(inputs, sub, options, gains, light_distance, folds, relief)
    return float(np.sqrt(np.sum(ssr) / max(int(np.sum(n)), 1))), int(np.sum(n))


def held_out_squares(inputs: FitInputs, sub: np.ndarray, options: FitOptions,
                     gains: np.ndarray, light_distance, folds: int = FOLDS,
                     relief: Relief | None = None
                     ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Per pixel of ``sub`` (C order): the sum of squared held-out residuals (:func:`held_out_rms`'s
    folds; a fold whose prediction at the pixel is not finite left out), their count, and
    whether every fold's prediction was finite. With a ``relief``, the pixels are fitted under
    its visibility (:meth:`FitInputs.pixels`) and the held-out lights relit shaded by it, as
    :meth:`~mitsuba_powder.rti.result.MapsResult.predict` does. The predictions are scored
    as the capture's files record them (at most ``options.full_scale``). A pixel whose surface lobe
    ends pinned at its bound in a fold is predicted by that fold's fit without the lobe, as
    the maps would have it (:func:`_pinned_without_lobe`)."""
    k = len(inputs.d)
    medians = {n: float(np.median(m[sub])) for n, m in inputs.maps.items()}
    data = inputs.pixels(sub, gains, light_distance, options)
    fitted, vis = data, None
    if relief is not None:
        fitted = replace(inputs, relief=relief).pixels(sub, gains, light_distance, options)
        vis = relief.visibility(data.d if data.field is None else data.field[0], sub)
    ev = PixelEvaluator(options.others + list(data.fixed_maps), options.settings,
                        options.variant)
    p = len(data.obs)
    ssr, n, finite = np.zeros(p), np.zeros(p, dtype=np.int64), np.ones(p, dtype=bool)
    for f in range(folds):
        held = np.arange(k) % folds == f
        if not held.any() or held.all():
            continue
        part = fit_pixels(ev, _lights(fitted, ~held), Log(), medians)
        pred = _predict(ev, part, data, held)
        pred = _pinned_without_lobe(inputs, sub, part, pred, options, gains, light_distance,
                                    relief, held, medians)
        if vis is not None:
            pred = pred * vis[:, held, None]
        pred = np.minimum(pred, options.full_scale)   # as the capture's files record it
        wt = ~np.any(data.obs[:, held] >= options.saturation, axis=2)     # (P, K_held)
        r = (pred - data.obs[:, held]) * wt[:, :, None]
        good = np.isfinite(r).all(axis=(1, 2))
        finite &= good
        ssr[good] += np.sum(r[good] ** 2, axis=(1, 2))
        n[good] += 3 * np.sum(wt[good], axis=1)
    return ssr, n, finite


@dataclass
class ShadowChoice:
    """The choice of the relief's cast shadows: the cross-validated RMS (linear units)
    without (``ratio``) and with (``relief``) them, the paired difference's ``z`` (in standard
    errors, over the ``shaded`` pixels), the mode chosen, the folds and pixels."""

    ratio: float
    relief: float
    z: float
    chosen: str
    folds: int
    pixels: int
    shaded: int

    def to_dict(self) -> dict:
        return {"option": "auto", "cv_rms": {"ratio": self.ratio, "relief": self.relief},
                "z": self.z, "chosen": self.chosen, "margin_z": SHADOW_Z,
                "folds": self.folds, "pixels": self.pixels, "shaded_pixels": self.shaded}


def choose_shadows(inputs: FitInputs, sub: np.ndarray, options: FitOptions,
                   gains: np.ndarray, light_distance, relief: Relief, log: Log,
                   folds: int = FOLDS) -> ShadowChoice:
    """``relief`` when the fit under ``relief``'s visibility relights the held-out lights of
    the pixels ``sub`` better than the fit without it by more than :data:`SHADOW_Z` standard
    errors of the paired per-pixel difference over the pixels it shades, else ``ratio``
    (module docstring)."""
    folds = max(2, min(int(folds), len(inputs.d)))
    args = (inputs, sub, options.replace(shadows="ratio"), gains, light_distance, folds)
    shaded = inputs.shaded(relief, sub, light_distance)[sub]
    few = int(shaded.sum()) < MIN_SHADED
    a, na, fa = held_out_squares(*args)
    b, nb, fb = (a, na, fa) if few else held_out_squares(*args, relief)
    ok = fa & fb & (na > 0)
    z = 0.0 if few or int((ok & shaded).sum()) < MIN_SHADED else \
        float(np.clip(paired_z(a[ok & shaded] - b[ok & shaded]), -Z_CAP, Z_CAP))
    ratio_rms = float(np.sqrt(a[ok].sum() / max(int(na[ok].sum()), 1)))
    relief_rms = float(np.sqrt(b[ok].sum() / max(int(nb[ok].sum()), 1)))
    chosen = "relief" if z > SHADOW_Z else "ratio"
    log(f"shadows: cross-validated over {folds} folds of the lights on {int(ok.sum())} "
        f"pixels: without the relief {ratio_rms:.4g}, with its cast shadows {relief_rms:.4g} "
        f"(held-out RMS); on the {int((ok & shaded).sum())} pixels it shades, the relief "
        f"better by {z:.3g} standard errors (paired per pixel); chosen {chosen} (the relief "
        f"needs more than {SHADOW_Z:g})")
    return ShadowChoice(ratio_rms, relief_rms, z, chosen, folds, int(ok.sum()),
                        int((ok & shaded).sum()))


def paired_z(diff: np.ndarray) -> float:
    """The mean of ``diff`` in standard errors of the mean (0 for no difference at all,
    +-inf for the same non-zero difference everywhere)."""
    diff = np.asarray(diff, dtype=np.float64)
    if diff.size == 0 or not np.any(diff):
        return 0.0
    se = float(np.std(diff, ddof=1)) / np.sqrt(diff.size) if diff.size > 1 else 0.0
    mean = float(np.mean(diff))
    return mean / se if se > 0 else float(np.sign(mean) * np.inf)


def _pinned_without_lobe(inputs: FitInputs, sub: np.ndarray, part, pred: np.ndarray,
                         options: FitOptions, gains: np.ndarray, light_distance,
                         relief: Relief | None, held: np.ndarray, medians: dict
                         ) -> np.ndarray:
    """``pred`` (a fold's held-out predictions of the pixels ``sub``, fitted in ``part``) with
    the pixels whose surface lobe is pinned at its bound predicted by a fit of the fold
    without the lobe: what the maps do with such pixels (``fit_in_blocks`` fits them again
    without it, under the gains found: fitted gains are held at the fold's), so that a
    cross-validation scores the fit the maps will be."""
    plain = without_lobe(options)
    if plain is None:
        return pred
    pinned = sub & pinned_lobes(part.maps["amplitude_surface"])
    if not pinned.any():
        return pred
    if options.gains.fitted:  # the fold's gains of the lights it saw, held (not refitted
        gains = np.array(gains, dtype=np.float64)  # on the few pinned pixels alone)
        gains[~held] = part.gains
        plain = plain.replace(gains=options.gains.held(gains))
    data = inputs.pixels(pinned, gains, light_distance, plain)
    fitted = data if relief is None else replace(inputs, relief=relief).pixels(
        pinned, gains, light_distance, plain)
    ev = PixelEvaluator(plain.others + list(data.fixed_maps), plain.settings, plain.variant)
    refit = fit_pixels(ev, _lights(fitted, ~held), Log(), medians)
    out = np.array(pred, copy=True)
    out[np.flatnonzero(pinned[sub])] = _predict(ev, refit, data, held)
    return out


def _lights(data: FitData, keep: np.ndarray) -> FitData:
    """``data`` with the lights ``keep`` (bool (K,)) only."""
    field = None if data.field is None else (data.field[0][:, keep], data.field[1][:, keep])
    return FitData(obs=np.ascontiguousarray(data.obs[:, keep]), d=data.d[keep],
                   mask=data.mask, gains=data.gains[keep], fixed_maps=data.fixed_maps,
                   fixed_albedo=data.fixed_albedo, grain=data.grain, options=data.options,
                   field=field, light_distance=data.light_distance,
                   shadowed=None if data.shadowed is None else data.shadowed[:, keep])


def _predict(ev: PixelEvaluator, part, data: FitData, held: np.ndarray) -> np.ndarray:
    """The fitted pixels of ``part`` (a fit of ``data``'s pixels) under the lights ``held``:
    (P, K_held, 3), the gains and irradiance factors applied."""
    sel = data.mask
    slopes = slopes_of_normals(part.normals[sel].astype(np.float64))
    albedo = part.albedo[sel].astype(np.float64)
    values = {n: part.maps[n][sel].astype(np.float64) for n in ev.varying}
    lights = data.d[held] if data.field is None else data.field[0][:, held]
    value, _ = ev(slopes, albedo, values, lights)
    scale = data.gains[held][None, :]
    if data.field is not None:
        scale = scale * data.field[1][:, held]
    return value * np.broadcast_to(scale, value.shape[:2])[:, :, None]
