"""The per-pixel solvers of the RTI fit behind one interface (:data:`SOLVERS`).

A solver is built from the fit's evaluator (:class:`~mitsuba_powder.rti.forward.PixelEvaluator`)
and one :class:`~mitsuba_powder.rti.pixels.PixelData`, and offers (:class:`Solver`):

* ``solve(y_start, max_iterations)``: Levenberg-Marquardt from the start rows (P, n + 1: the
  layout's n columns and the pixel's index, which a solver ignores), every pixel at once,
  with the same damping, acceptance and stopping rules; a
  :class:`~mitsuba_powder.rti.pixels.SolverFit`;
* ``model(rows, gain_terms)``: the model without gains ``f (n . l_k)`` (P, K, 3) float32 at the
  fitted rows (P, n) and, with ``gain_terms``, the pixels' part ``(S, b)`` of the gains'
  reduced system (:func:`mitsuba_powder.rti.gains.gain_system`);
* ``evaluations``: the model evaluations (kernel launches) so far.

``drjit`` (:class:`~mitsuba_powder.rti.engine.PixelSystem`, the default) assembles each pixel's
normal equations inside Dr.Jit kernels; ``numpy``
(:class:`~mitsuba_powder.rti.problem.NumpySolver`, the test reference) assembles every pixel's
Jacobian in NumPy for :func:`~mitsuba_powder.fitting.optimise.batch_levenberg_marquardt`.
"""

from __future__ import annotations

from typing import Protocol

import numpy as np

from .engine import PixelSystem
from .forward import PixelEvaluator
from .pixels import PixelData, SolverFit
from .problem import NumpySolver

__all__ = ["SOLVERS", "Solver"]


class Solver(Protocol):
    """The interface of a per-pixel solver (module docstring)."""

    evaluations: int

    def __init__(self, ev: PixelEvaluator, data: PixelData) -> None: ...

    def solve(self, y_start: np.ndarray, max_iterations: int, ftol: float = 1e-7
              ) -> SolverFit: ...

    def model(self, rows: np.ndarray, gain_terms: bool = False
              ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]: ...


#: The per-pixel solvers by name (``fit_maps(solver=...)``, ``fit-maps --solver``)
SOLVERS: dict[str, type[Solver]] = {"drjit": PixelSystem, "numpy": NumpySolver}
