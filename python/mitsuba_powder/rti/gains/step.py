"""The per-light gains' step in the fit's alternation: the Gauss-Newton system of the gains
with every pixel's variables eliminated (:func:`gain_system`, the reference; each per-pixel
solver gives its pixels' part, :data:`mitsuba_powder.rti.solvers.SOLVERS`) and the step on it
with the gains' mean held (:func:`gain_step`)."""

from __future__ import annotations

import numpy as np

__all__ = ["MAX_STEP_FACTOR", "MIN_INFORMATION", "gain_step", "gain_system",
           "uninformed_lights"]


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


#: A light whose gain has less Gauss-Newton information than this fraction of the median
#: light's (every pixel's variables eliminated) sees too little to fit its gain: a light below
#: the object's horizon, whose image is black, or one whose pixels are all shadowed or
#: saturated. Its gain is held where it is (its step would divide by almost nothing).
MIN_INFORMATION = 1e-4

#: A gain changes by at most this factor (up or down) in one step, before the mean is
#: restored: the step is a linearisation, trusted near the current gains only.
MAX_STEP_FACTOR = 2.0


def uninformed_lights(s: np.ndarray) -> np.ndarray:
    """bool (K,): the lights whose gain the reduced system ``s`` (K, K) cannot determine
    (information below :data:`MIN_INFORMATION` x the median light's, or not finite)."""
    info = np.diag(s)
    ok = np.isfinite(info)
    ref = float(np.median(info[ok])) if np.any(ok) else 0.0
    return ~ok | ~(info > MIN_INFORMATION * max(ref, 0.0)) | (ref <= 0)


def gain_step(gains: np.ndarray, s: np.ndarray, rhs: np.ndarray, scale: float) -> np.ndarray:
    """Gauss-Newton step of the gains on their reduced system with their mean held at
    ``scale`` (the constraint ``sum(step) = K scale - sum(gains)`` by a Lagrange multiplier),
    each gain changed by a factor within [1/:data:`MAX_STEP_FACTOR`, :data:`MAX_STEP_FACTOR`].

    The gains of :func:`uninformed_lights` are held (no step); if no light is informed, or
    the system gives no finite step, the gains are returned unchanged.
    """
    k = len(gains)
    free = ~uninformed_lights(s) & np.isfinite(rhs)
    if not np.any(free) or not np.all(np.isfinite(s[np.ix_(free, free)])):
        return gains.copy()
    idx = np.nonzero(free)[0]
    m = len(idx)
    sub = s[np.ix_(idx, idx)]
    kkt = np.zeros((m + 1, m + 1))
    kkt[:m, :m] = sub + 1e-9 * np.diag(np.maximum(np.diag(sub), 1e-30))
    kkt[:m, m] = kkt[m, :m] = 1.0
    try:
        solved = np.linalg.solve(kkt, np.append(-rhs[idx], k * scale - np.sum(gains)))[:m]
    except np.linalg.LinAlgError:
        return gains.copy()
    if not np.all(np.isfinite(solved)):
        return gains.copy()
    new = gains.astype(np.float64, copy=True)
    new[idx] = np.clip(gains[idx] + solved, gains[idx] / MAX_STEP_FACTOR,
                       gains[idx] * MAX_STEP_FACTOR)
    return new * (scale / np.mean(new))
