"""The powder model's rows of a held-out-light comparison (``compare-maps``,
:func:`mitsuba_powder.rti.comparison.compare`):

* ``powder``: the per-pixel fit of ``fit-maps`` with the options given (by default
  ``shadows="auto"``: the relief's cast shadows where cross-validation keeps them), relit by
  the per-pixel model as ``relight`` does by default (shaded by the held-out lights'
  visibility over the relief where the fit chose it);
* ``powder_shadows``: the fit with its relief always (``shadows="relief"``, ``fit-maps
  --shadows relief``), relit by the per-pixel model shaded by each held-out light's
  visibility over the relief;
* ``powder_rendered``: the same fit, relit by Mitsuba path tracing the relief's mesh with the
  powder BSDF (:mod:`mitsuba_powder.rti.rendered`: cast shadows and interreflections), at
  the given samples per pixel and variant.

``powder_shadows`` and ``powder_rendered`` share one fit per protocol (and ``powder``'s, where
it chose the relief). Each row notes the shadows its fit used (:attr:`_Predictor.note`). With a
reference card's
calibration (``compare-maps --reference``, :mod:`mitsuba_powder.rti.reference`) every row's fit
holds its lights' relative gains from the card and relights the held-out lights at their
irradiance.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from .options import FitOptions
from .plan import run_fit

__all__ = ["POWDER_ROWS", "light_indices", "powder_fitters", "shadows_note"]

#: The powder model's rows
POWDER_ROWS = ("powder", "powder_shadows", "powder_rendered")


def light_indices(all_directions: np.ndarray, directions: np.ndarray) -> np.ndarray:
    """The rows of ``all_directions`` (K, 3) that ``directions`` (K', 3) are."""
    diff = np.abs(directions[:, None, :] - all_directions[None, :, :]).max(axis=2)
    return np.argmin(diff, axis=1)


def shadows_note(fit_settings: dict) -> str:
    """The shadows a fit used, for a comparison's row: ``shadows relief`` or ``shadows ratio``
    (``auto``: with the cross-validated RMS of both, linear units)."""
    note = f"shadows {fit_settings.get('shadows', 'ratio')}"
    choice = fit_settings.get("shadows_choice")
    if choice:
        cv = choice["cv_rms"]
        note += (f" (auto: cross-validated RMS {cv['ratio']:.4g} without the relief, "
                 f"{cv['relief']:.4g} with it, z = {choice['z']:.3g})")
    return note


class _Predictor:
    """A fit relit by its per-pixel model or rendered
    (:func:`mitsuba_powder.rti.rendered.render_result`; ``render`` not None), at each light's
    irradiance from a reference card (``calibration``) or the fit's own gains."""

    def __init__(self, result, render: dict | None = None, calibration: dict | None = None):
        self.result, self.render, self.calibration = result, render, calibration
        self.n_parameters = result.n_parameters
        self.note = shadows_note(result.fit_settings)

    def predict(self, directions: np.ndarray) -> np.ndarray:
        cal = self.calibration
        gains = None if cal is None else \
            cal["irradiance"][light_indices(cal["directions"], directions)]
        if self.render is None:
            return self.result.predict(directions, gains=gains)
        from .rendered import render_result

        return render_result(self.result, directions, gains=gains, **self.render)


def powder_fitters(names: Sequence[str], options: FitOptions, render: dict | None = None,
                   calibration: dict | None = None) -> dict:
    """The comparison's fitters (``fit(images, directions, mask) -> predictor``) of the powder
    rows ``names`` (module docstring), fitted with ``options`` (their ``shadows`` set per
    row); ``render``: :func:`~mitsuba_powder.rti.rendered.render_maps`' ``spp`` and
    ``variant``; ``calibration``: a reference card's ``directions`` (K, 3) of the whole
    capture, their relative ``gains`` (K,) and ``irradiance`` (K,), or None."""
    from dataclasses import replace

    cache: dict = {}

    def fit(images, directions, mask, shadows: str):
        key = (shadows, np.asarray(directions).tobytes(), images.shape)
        if key not in cache:
            opts = options.replace(shadows=shadows)
            if calibration is not None:
                idx = light_indices(calibration["directions"], directions)
                opts = opts.replace(gains=replace(opts.gains,
                                                  initial=calibration["gains"][idx]))
            if len(cache) > 2:
                cache.clear()
            cache[key] = result = run_fit(images, directions, opts, mask)
            if result.fit_settings.get("shadows") == "relief":  # also the relief row's fit
                cache[("relief",) + key[1:]] = result
        return cache[key]

    def with_relief(images, directions, mask=None):
        return fit(images, directions, mask, "relief")

    fitters = {
        "powder": lambda images, directions, mask=None: _Predictor(
            fit(images, directions, mask, options.shadows), None, calibration),
        "powder_shadows": lambda images, directions, mask=None: _Predictor(
            with_relief(images, directions, mask), None, calibration),
        "powder_rendered": lambda images, directions, mask=None: _Predictor(
            with_relief(images, directions, mask), dict(render or {}), calibration),
    }
    unknown = [n for n in names if n not in fitters]
    if unknown:
        raise ValueError(f"powder rows {unknown} are not known; choose among {POWDER_ROWS}")
    return {n: fitters[n] for n in names}
