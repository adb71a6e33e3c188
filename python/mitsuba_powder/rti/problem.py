"""The least-squares problems of the per-pixel RTI fit: every pixel's (:class:`PixelProblem`,
for :func:`mitsuba_powder.fitting.optimise.batch_levenberg_marquardt`) and the per-light gains' with
every pixel's variables eliminated (:func:`gain_system`, :func:`gain_step`)."""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from ..fitting.optimise import ParamSpec
from .forward import PixelEvaluator
from .properties import GRAIN_MAPS, GrainAlbedo

__all__ = ["PixelProblem", "gain_step", "gain_system"]


class PixelProblem:
    """:class:`mitsuba_powder.fitting.optimise.BatchProblem` of many pixels, one row each.

    The last column of ``y`` is the pixel's index into this problem's data (held by the
    optimiser), so that the rows the optimiser passes (active pixels, padded) find their
    observations, and, for lights at a finite distance, their per-pixel light directions
    ``directions`` (P, K, 3) and irradiance factors ``irradiance`` (P, K) (the model of pixel
    p under light k is then ``g_k s_pk f(d_pk) (n . d_pk)``).
    """

    def __init__(self, ev: PixelEvaluator, observed: np.ndarray, weights: np.ndarray,
                 directions: np.ndarray, gains: np.ndarray, layout: list[tuple[str, ParamSpec]],
                 fixed: Mapping[str, np.ndarray], fixed_albedo: np.ndarray | None = None,
                 grain: GrainAlbedo | None = None, irradiance: np.ndarray | None = None):
        self.ev = ev
        self.grain = grain                  # the albedo from a free grain size
        self.fixed_albedo = fixed_albedo    # (P, 3) when the albedo is not free
        self.observed = observed            # (P, K, 3) float64
        self.sqrt_w = np.sqrt(weights)      # (P, K)
        self.directions = directions        # (K, 3), or (P, K, 3) per pixel
        self.irradiance = irradiance        # None (distant lights) or (P, K)
        self.gains = gains
        self.layout = layout                # variable name and spec, in column order
        self.fixed = fixed                  # non-free varying property -> (P,)
        p = len(observed)
        self.lower = np.array([s.to_y(s.lower) for _, s in layout] + [0.0])
        self.upper = np.array([s.to_y(s.upper) for _, s in layout] + [max(p - 1, 0)])
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


def gain_system(res: np.ndarray, jac: np.ndarray, model: np.ndarray, sqrt_w: np.ndarray
                ) -> tuple[np.ndarray, np.ndarray]:
    """The pixels' part of the Gauss-Newton system of the gains with every pixel's variables
    eliminated (Schur complement): ``S = sum_p (D_p - C_p^T A_p^-1 C_p)``,
    ``b = sum_p (J_g^T r - C_p^T A_p^-1 J_p^T r)``.

    Args:
        res: (B, K * 3) weighted residuals; jac: (B, K * 3, q) their Jacobian in the pixels'
            variables; model: (B, K, 3) model values without gain; sqrt_w: (B, K) weights.
    """
    b, n, q = jac.shape
    kk = model.shape[1]
    jg = (sqrt_w[:, :, None] * model)                                  # (B, K, 3)
    jp = jac.reshape(b, kk, 3, q)
    r = res.reshape(b, kk, 3)
    a = np.matmul(jac.transpose(0, 2, 1), jac)  # (B, q, q); matmul: BLAS, faster than einsum
    a += (1e-9 * np.max(np.einsum("bii->bi", a), axis=1) + 1e-30)[:, None, None] * np.eye(q)
    c = np.einsum("bkci,bkc->bik", jp, jg)                             # (B, q, K)
    a_inv_c = np.linalg.solve(a, c)
    jtr = np.matmul(jac.transpose(0, 2, 1), res[:, :, None])[:, :, 0]  # (B, q)
    a_inv_jtr = np.linalg.solve(a, jtr[:, :, None])[:, :, 0]
    s = np.diag(np.einsum("bkc,bkc->k", jg, jg)) - np.einsum("bik,bil->kl", c, a_inv_c)
    rhs = np.einsum("bkc,bkc->k", jg, r) - np.einsum("bik,bi->k", c, a_inv_jtr)
    return s, rhs


def gain_step(gains: np.ndarray, s: np.ndarray, rhs: np.ndarray, scale: float) -> np.ndarray:
    """Gauss-Newton step of the gains on their reduced system with their mean held at
    ``scale`` (the constraint ``sum(step) = K scale - sum(gains)`` by a Lagrange multiplier),
    kept positive."""
    k = len(gains)
    diag = np.maximum(np.diag(s), 1e-30)
    kkt = np.zeros((k + 1, k + 1))
    kkt[:k, :k] = s + 1e-9 * np.diag(diag)
    kkt[:k, k] = kkt[k, :k] = 1.0
    step = np.linalg.solve(kkt, np.append(-rhs, k * scale - np.sum(gains)))[:k]
    new = np.maximum(gains + step, 0.5 * gains)
    return new * (scale / np.mean(new))
