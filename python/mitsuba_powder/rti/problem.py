"""The NumPy reference solver of the per-pixel RTI fit (:class:`NumpySolver`, ``solver =
"numpy"`` of :data:`mitsuba_powder.rti.solvers.SOLVERS`): every pixel's least-squares problem
(:class:`PixelProblem`) for :func:`mitsuba_powder.fitting.optimise.batch_levenberg_marquardt`,
which assembles every pixel's (lights x channels x variables) Jacobian in NumPy."""

from __future__ import annotations

import math

import numpy as np

from ..fitting.optimise import batch_levenberg_marquardt
from .forward import PixelEvaluator
from .gains import gain_system
from .pixels import PixelData, SolverFit
from .properties import GRAIN_MAPS

__all__ = ["NumpySolver", "PixelProblem"]


class PixelProblem:
    """:class:`mitsuba_powder.fitting.optimise.BatchProblem` of many pixels, one row each.

    The last column of ``y`` is the pixel's index into this problem's data (held by the
    optimiser), so that the rows the optimiser passes (active pixels, padded) find their
    observations, and, for lights at a finite distance, their per-pixel light directions
    ``directions`` (P, K, 3) and irradiance factors ``irradiance`` (P, K) (the model of pixel
    p under light k is then ``g_k s_pk f(d_pk) (n . d_pk)``).
    """

    def __init__(self, ev: PixelEvaluator, data: PixelData):
        self.ev = ev
        self.grain = data.grain                # the albedo from a free grain size
        self.fixed_albedo = data.fixed_albedo  # (P, 3) when the albedo is not free
        self.observed = data.observed          # (P, K, 3)
        self.sqrt_w = np.sqrt(data.weights)    # (P, K)
        self.directions = data.directions      # (K, 3), or (P, K, 3) per pixel
        self.irradiance = data.irradiance      # None (distant lights) or (P, K)
        self.gains = data.gains
        self.layout = list(data.layout)        # variable name and spec, in column order
        self.fixed = data.fixed                # non-free varying property -> (P,)
        p = len(self.observed)
        self.lower = np.array([s.to_y(s.lower) for _, s in self.layout] + [0.0])
        self.upper = np.array([s.to_y(s.upper) for _, s in self.layout] + [max(p - 1, 0)])
        self.evaluations = 0

    def unpack(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict, dict]:
        """y (B, p + 1) -> pixel index, slopes, albedo, property values, dx/dy per column."""
        idx = np.rint(y[:, -1]).astype(np.int64)
        slopes = y[:, :2]
        albedo = None
        values: dict[str, np.ndarray] = {k: v[idx] for k, v in self.fixed.items()}
        dxdy: dict[str, np.ndarray] = {}
        alb_cols = []
        for j, (name, spec) in enumerate(self.layout):
            if j < 2:
                continue
            x = spec.to_x(y[:, j])
            dxdy[name] = spec.dx_dy(x)
            if name.startswith("albedo"):
                alb_cols.append(x)
            elif name in GRAIN_MAPS:
                albedo, self.drho = self.grain(x)
                values[name] = x  # (not a property of the evaluator: its map is kept)
            else:
                values[name] = x
        if albedo is None:
            albedo = np.stack(alb_cols, axis=1) if alb_cols else self.fixed_albedo[idx]
        return idx, slopes, albedo, values, dxdy

    def lights(self, idx: np.ndarray) -> np.ndarray:
        """The light directions of the rows ``idx``: (K, 3) or (B, K, 3)."""
        return self.directions if self.directions.ndim == 2 else self.directions[idx]

    def light_gains(self, idx: np.ndarray) -> np.ndarray:
        """(1, K, 1) or (B, K, 1): the gains times the rows' irradiance factors."""
        if self.irradiance is None:
            return self.gains[None, :, None]
        return (self.gains[None, :] * self.irradiance[idx])[:, :, None]

    def _residual(self, idx: np.ndarray, value: np.ndarray) -> np.ndarray:
        model = value * self.light_gains(idx)
        r = (model - self.observed[idx]) * self.sqrt_w[idx][:, :, None]
        return r.reshape(len(idx), -1)

    def residuals(self, y: np.ndarray) -> np.ndarray:
        idx, slopes, albedo, values, _ = self.unpack(y)
        value, _ = self.ev(slopes, albedo, values, self.lights(idx))
        self.evaluations += 1
        return self._residual(idx, value)

    def jacobian(self, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        idx, slopes, albedo, values, dxdy = self.unpack(y)
        names = ["slope_x", "slope_y"]
        if any(n.startswith("albedo") or n in GRAIN_MAPS for n, _ in self.layout):
            names.append("albedo")
        names += [n for n, _ in self.layout[2:]
                  if not n.startswith("albedo") and n not in GRAIN_MAPS]
        value, grads = self.ev(slopes, albedo, values, self.lights(idx), names)
        self.evaluations += 1 + len(names)
        b, k = len(idx), len(self.gains)
        scale = (self.light_gains(idx) * self.sqrt_w[idx][:, :, None])
        jac = np.zeros((b, k, 3, len(self.layout) + 1))
        for j, (name, _) in enumerate(self.layout):
            if name.startswith("albedo"):
                c = int(name[-1])
                jac[:, :, c, j] = grads["albedo"][:, :, c] * scale[:, :, 0] * dxdy[name][:, None]
            elif name in GRAIN_MAPS:  # chain rule through rho(r) per channel
                jac[:, :, :, j] = (grads["albedo"] * self.drho[:, None, :] * scale *
                                   dxdy[name][:, None, None])
            else:
                jac[:, :, :, j] = grads[name] * scale * (dxdy[name][:, None, None]
                                                         if name in dxdy else 1.0)
        return self._residual(idx, value), jac.reshape(b, k * 3, -1)


class NumpySolver:
    """The per-pixel solver in NumPy (:data:`mitsuba_powder.rti.solvers.SOLVERS` ``numpy``):
    :func:`~mitsuba_powder.fitting.optimise.batch_levenberg_marquardt` on a
    :class:`PixelProblem`, every pixel at once; the test reference of the Dr.Jit solver."""

    def __init__(self, ev: PixelEvaluator, data: PixelData):
        self.problem = PixelProblem(ev, data)

    @property
    def evaluations(self) -> int:
        """Model evaluations so far (one per residual, 1 + one per variable group per
        Jacobian)."""
        return self.problem.evaluations

    def solve(self, y_start: np.ndarray, max_iterations: int, ftol: float = 1e-7
              ) -> SolverFit:
        """Levenberg-Marquardt from ``y_start`` (P, n + 1; the last column, the pixel's index,
        is held) with no hopeless test (pixels are not competing starts); a pixel stops when
        a step lowers its cost by less than ``ftol`` (relative)."""
        y = np.array(y_start, dtype=np.float64)
        y[:, -1] = np.arange(len(y))
        hold = np.zeros(y.shape[1], dtype=bool)
        hold[-1] = True
        # hopeless = inf: inf x a zero cost, of a pixel with no used observation, is NaN and
        # stops nothing: not a warning
        with np.errstate(invalid="ignore"):
            fitted = batch_levenberg_marquardt(self.problem, y, max_iterations, hold=hold,
                                               ftol=ftol, hopeless=math.inf)
        return SolverFit(fitted.y[:, :-1], fitted.cost, fitted.iterations, fitted.unfinished)

    def model(self, rows: np.ndarray, gain_terms: bool = False
              ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """The model without gains (P, K, 3) float32 at ``rows`` (P, n) and, with
        ``gain_terms``, the pixels' part of the gains' reduced system
        (:func:`~mitsuba_powder.rti.gains.gain_system`)."""
        prob = self.problem
        y = np.column_stack([rows, np.arange(len(rows), dtype=np.float64)])
        idx, slopes, albedo, values, _ = prob.unpack(y)
        res, jac = prob.jacobian(y) if gain_terms else (None, None)
        value = np.ascontiguousarray(prob.ev(slopes, albedo, values, prob.lights(idx))[0],
                                     dtype=np.float32)
        if not gain_terms:
            return value, None
        # d(residual)/d(g_k) = sqrt(w) s_pk f: the model times the irradiance factors
        model = value if prob.irradiance is None else value * prob.irradiance[idx][:, :, None]
        return value, gain_system(res, jac[:, :, :-1], model, prob.sqrt_w)
