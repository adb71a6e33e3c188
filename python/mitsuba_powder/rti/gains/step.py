"""The per-light gains' step in the fit's alternation: the Gauss-Newton system of the gains
with every pixel's variables eliminated (:func:`gain_system`, the reference; each per-pixel
solver gives its pixels' part, :data:`mitsuba_powder.rti.solvers.SOLVERS`) and the step on it
with the gains' mean held (:func:`gain_step`)."""

from __future__ import annotations

import numpy as np

__all__ = ["gain_step", "gain_system"]


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
