"""How a fit finds the per-light gains (:class:`GainPolicy`, checked by :func:`gain_policy`)
and the pixel subsample they are fitted on before the maps (:func:`gain_sample`).

Gains are shared by every pixel, so a fit of the gains couples every pixel; on a large
capture they are therefore fitted with the maps of a random subsample of the masked pixels
(:data:`GAIN_PIXELS` by default), then held while every pixel is fitted: once the gains are
held a pixel's fit depends on its own observations only, so the pixels can be fitted in
blocks or tiles and give the maps of one fit. The untiled fit
(:mod:`mitsuba_powder.rti.plan`, stage ``gain subsample``) and the tiled one
(:mod:`mitsuba_powder.rti.tiles`) both draw the subsample with :meth:`GainPolicy.draw`, fit it
with :meth:`GainPolicy.on_subsample` and hold its gains with :meth:`GainPolicy.held`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from ..checks import check_count
from .trend import GainTrend

__all__ = ["GAIN_MODES", "GAIN_PIXELS", "GainPolicy", "gain_policy", "gain_sample"]

#: How the gains are found: ``fit`` (fitted with the maps, their mean held at the initial
#: gains' mean) or ``fixed`` (the initial gains held: the default, docs/rti.md "Gains held
#: at 1": fitted gains absorb cast shadows and the model's error at grazing light)
GAIN_MODES = ("fit", "fixed")

#: Pixels of the subsample the per-light gains are fitted on (then held for every pixel)
GAIN_PIXELS = 16384


@dataclass(frozen=True, eq=False)
class GainPolicy:
    """How the per-light gains of a fit are found (build it with :func:`gain_policy`).

    Attributes:
        mode: ``fit`` or ``fixed`` (:data:`GAIN_MODES`).
        initial: (K,) the start (``fit``) or the values (``fixed``) of the gains, > 0; None:
            all 1. Checked against the capture's K lights by
            :func:`mitsuba_powder.rti.inputs.check_inputs`.
        trend: how the fitted gains extend to lights not fitted (:class:`GainTrend`).
        subsample: pixels the gains are fitted on before the maps, then held (:func:`draw`);
            None: fitted with every pixel.
        seed: seed of the subsample's draw, >= 0.
    """

    mode: str = "fixed"
    initial: np.ndarray | None = None
    trend: GainTrend = field(default_factory=GainTrend)
    subsample: int | None = GAIN_PIXELS
    seed: int = 0

    @property
    def fitted(self) -> bool:
        """Whether the gains are fitted (mode ``fit``)."""
        return self.mode == "fit"

    def subsampled(self, pixels: int) -> bool:
        """Whether the gains of a fit of ``pixels`` pixels are fitted on a subsample first
        (fitted, and more pixels than :attr:`subsample`)."""
        return self.fitted and self.subsample is not None and pixels > self.subsample

    def draw(self, mask: np.ndarray) -> np.ndarray:
        """The flat indices (sorted) of the subsample of the True pixels of ``mask``
        (:func:`gain_sample`; all of them when there are not more than :attr:`subsample`)."""
        return gain_sample(mask, self.subsample, self.seed)

    def on_subsample(self) -> GainPolicy:
        """The policy of the subsample's own fit: gains fitted with every one of its pixels."""
        return replace(self, mode="fit", subsample=None)

    def held(self, gains: np.ndarray) -> GainPolicy:
        """The policy once ``gains`` (K,) are found: held (mode ``fixed``)."""
        return replace(self, mode="fixed", initial=np.asarray(gains))


def gain_policy(mode: str = "fixed", initial: np.ndarray | None = None,
                trend: GainTrend | None = None, subsample: int | None = GAIN_PIXELS,
                seed: int = 0, name: Callable[[str], str] = str) -> GainPolicy:
    """A checked :class:`GainPolicy` (the initial gains are checked against the capture).

    Args:
        mode, initial, trend, subsample, seed: see :class:`GainPolicy` (trend None: the
            default :class:`GainTrend`).
        name: how messages name an option (``gains``, ``gain_subsample``, ``seed``), e.g. by
            the command line's flag.
    """
    if mode not in GAIN_MODES:
        raise ValueError(f"{name('gains')} = {mode!r} is not a gain mode; choose one of "
                         f"{GAIN_MODES}")
    trend = GainTrend() if trend is None else trend
    if not isinstance(trend, GainTrend):
        raise ValueError(f"{name('gain_trend')} = {trend!r} is not a GainTrend")
    if subsample is not None:
        subsample = check_count(name("gain_subsample"), subsample, 1)
    return GainPolicy(mode, initial, trend, subsample, check_count(name("seed"), seed, 0))


def gain_sample(mask: np.ndarray, pixels: int | None, seed: int = 0) -> np.ndarray:
    """The flat indices (sorted) of at most ``pixels`` True pixels of ``mask`` drawn at random
    without replacement (``seed``); all of them when there are not more (or ``pixels`` is
    None)."""
    flat = np.flatnonzero(mask)
    if pixels is not None and len(flat) > pixels:
        flat = np.sort(np.random.default_rng(seed).choice(flat, pixels, replace=False))
    return flat
