"""The relief of a fitted RTI capture: a height field integrated from the fitted normals, its
horizon map, and the visibility of each light at each pixel (cast shadows).

Frame: the image frame of the capture (x to the image's right, y to its top, z towards the
camera), **heights in pixel units** (one unit = one pixel's width; the camera is
orthographic). A surface ``z(x, y)`` has the normal ``(-z_x, -z_y, 1) / |.|``, so the fitted
normal gives the slopes ``z_x = -n_x / n_z`` and ``z_y = -n_y / n_z`` (height per pixel);
image rows go down, so ``dz/d(row) = -z_y``.

* :func:`integrate_normals`: the weighted least-squares height field (a Poisson problem):
  minimise ``sum_e w_e (z_b - z_a - g_e)^2`` over the edges ``e = (a, b)`` between
  4-neighbouring pixels, ``g_e`` the mean of the two pixels' slopes along the edge (exact for
  quadratic surfaces), ``w_e`` the smaller of the two pixels' weights. Weights come from the
  fit's residual map (:func:`residual_weights`: 1 at the median residual, falling as
  ``1 / (1 + (r / (3 median))^2)``; a small floor elsewhere, so masked and undetermined pixels
  are bridged by their neighbours' slopes instead of giving their own). Solved by conjugate
  gradients preconditioned by the uniform-weight problem's exact solution (a DCT-II Poisson
  solve, ``scipy.fft``), to a relative residual of 1e-8. The height is fixed up to a constant:
  its mean over the weighted pixels is 0.
* :func:`horizon_map`: per pixel and per azimuth bin (``A`` bins, centred on ``2 pi a / A``
  from +x towards +y), the elevation (radians) of the highest point of the height field seen
  along that azimuth: ``max_t atan((z(p + t u) - z(p)) / t)`` over marching distances
  ``t`` (1-16 px by 1, then growing by 6 % to the image's diagonal: an occluder further
  than 16 px is seen up to 6 % low in ``tan``), the height field
  bilinearly interpolated; beyond the image nothing occludes (a flat horizon: elevation 0 is
  the floor of the map). Computed by Dr.Jit kernels (:func:`horizon_map`).
* :func:`visibility`: a light at elevation ``e`` and azimuth ``phi`` (per pixel for lights at
  a distance) is visible by ``clip((e - h(phi)) / (2 delta) + 1/2, 0, 1)``, ``h(phi)`` the
  horizon interpolated linearly between bins, and ``delta`` the larger of the light's angular
  radius (the soft edge of an extended light) and the horizon's spread over the pixel
  (:func:`horizon_spread`: half its largest change to a neighbouring pixel, so that a pixel
  the shadow's edge crosses is partly lit, as its area is): 0.5 where the horizon cuts the
  light's centre.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .._checks import check_range

__all__ = ["AZIMUTHS", "LIGHT_RADIUS_DEG", "Relief", "horizon_map", "horizon_spread",
           "integrate_normals",
           "make_relief", "residual_weights", "visibility"]

#: Azimuth bins of a horizon map (11.25 degrees each)
AZIMUTHS = 32

#: Default angular radius of a light (degrees): the soft edge of its shadows
LIGHT_RADIUS_DEG = 0.5

#: The least weight of a pixel in the integration (masked, undetermined or badly fitted)
WEIGHT_FLOOR = 1e-3

#: The largest slope integrated (a normal 84 degrees from the camera)
MAX_SLOPE = 10.0


def residual_weights(residual: np.ndarray, mask: np.ndarray | None = None) -> np.ndarray:
    """Integration weights (H, W) in [``WEIGHT_FLOOR``, 1] from a fit's RMS residual map:
    ``1 / (1 + (r / (3 median))^2)`` (a pixel fitted as well as most keeps ~1); the floor
    outside ``mask`` and where the residual is not finite (not determined)."""
    r = np.asarray(residual, dtype=np.float64)
    ok = np.isfinite(r) if mask is None else (np.isfinite(r) & np.asarray(mask, bool))
    w = np.full(r.shape, WEIGHT_FLOOR)
    if ok.any():
        scale = 3.0 * max(float(np.median(r[ok])), 1e-12)
        w[ok] = np.maximum(1.0 / (1.0 + (r[ok] / scale) ** 2), WEIGHT_FLOOR)
    return w


def _slopes(normals: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Height per pixel along +x (columns) and along +row (down) of unit ``normals``."""
    n = np.asarray(normals, dtype=np.float64)
    nz = np.maximum(n[..., 2], 1.0 / math.hypot(1.0, MAX_SLOPE))
    zx = np.clip(-n[..., 0] / nz, -MAX_SLOPE, MAX_SLOPE)
    zrow = np.clip(n[..., 1] / nz, -MAX_SLOPE, MAX_SLOPE)
    bad = ~np.all(np.isfinite(n), axis=-1)
    zx[bad], zrow[bad] = 0.0, 0.0
    return zx, zrow


def _dct_preconditioner(h: int, w: int, weight: float, scale: float):
    """The height field's preconditioner: the uniform-weight (``weight``) Neumann Laplacian
    of an (h, w) grid, its constant mode at ``scale``, solved exactly by a DCT."""
    from scipy.fft import dctn, idctn

    ky = 2.0 - 2.0 * np.cos(np.pi * np.arange(h) / h)
    kx = 2.0 - 2.0 * np.cos(np.pi * np.arange(w) / w)
    eig = (ky[:, None] + kx[None, :]) * weight
    eig[0, 0] = scale  # the constant mode

    def precond(r: np.ndarray) -> np.ndarray:
        c = dctn(r.reshape(h, w), type=2, norm="ortho")
        return idctn(c / eig, type=2, norm="ortho").ravel()

    return precond


def integrate_normals(normals: np.ndarray, weights: np.ndarray | None = None,
                      tol: float = 1e-8, max_iterations: int = 500) -> np.ndarray:
    """The height field (H, W) float64 in pixel units whose normals best fit ``normals``
    (H, W, 3) (module docstring), weighted per pixel by ``weights`` (H, W) > 0 (default 1).

    Raises:
        ValueError: shapes that do not match, non-positive or non-finite weights.
    """
    import scipy.sparse as sp
    from scipy.sparse.linalg import LinearOperator, cg

    n = np.asarray(normals)
    if n.ndim != 3 or n.shape[2] != 3:
        raise ValueError(f"normals of shape {n.shape}: expected (H, W, 3)")
    h, w = n.shape[:2]
    wt = np.ones((h, w)) if weights is None else np.asarray(weights, dtype=np.float64)
    if wt.shape != (h, w):
        raise ValueError(f"weights of shape {wt.shape}: expected {(h, w)}")
    if not np.all(np.isfinite(wt)) or np.any(wt <= 0):
        raise ValueError("weights must be finite and > 0 (use a small floor for pixels to "
                         "bridge)")
    if h * w == 1:
        return np.zeros((1, 1))
    zx, zrow = _slopes(n)
    idx = np.arange(h * w).reshape(h, w)
    # edges along x (a = (i, j), b = (i, j + 1)) and along rows (a = (i, j), b = (i + 1, j))
    a = np.concatenate([idx[:, :-1].ravel(), idx[:-1, :].ravel()])
    b = np.concatenate([idx[:, 1:].ravel(), idx[1:, :].ravel()])
    g = np.concatenate([(0.5 * (zx[:, :-1] + zx[:, 1:])).ravel(),
                        (0.5 * (zrow[:-1, :] + zrow[1:, :])).ravel()])
    we = np.minimum(wt.ravel()[a], wt.ravel()[b])
    m = len(a)
    rows = np.concatenate([np.arange(m), np.arange(m)])
    d = sp.csr_matrix((np.concatenate([-np.ones(m), np.ones(m)]),
                       (rows, np.concatenate([a, b]))), shape=(m, h * w))
    lap = (d.T @ sp.diags(we) @ d).tocsr()
    rhs = d.T @ (we * g)
    # the constant is free: fix it by adding the weighted mean's square (a rank-one term)
    pw = wt.ravel() / wt.sum()
    scale = float(np.max(we))

    def matvec(z):
        return lap @ z + scale * pw * (pw @ z) * (h * w)

    op = LinearOperator((h * w, h * w), matvec=matvec, dtype=np.float64)
    precond = _dct_preconditioner(h, w, float(np.median(we)), scale)
    pre = LinearOperator((h * w, h * w), matvec=precond, dtype=np.float64)
    z0 = precond(rhs)
    z, info = cg(op, rhs, x0=z0, rtol=tol, atol=0.0, maxiter=max_iterations, M=pre)
    if info < 0 or not np.all(np.isfinite(z)):
        raise RuntimeError(f"the height field's solve failed (conjugate gradients: {info})")
    z = z.reshape(h, w)
    return z - float(np.sum(pw.reshape(h, w) * z))


def _distances(h: int, w: int) -> np.ndarray:
    """Marching distances of the horizon map (module docstring), pixels."""
    diag = math.hypot(h, w)
    ts = [float(t) for t in range(1, 17)]
    while ts[-1] < diag:
        ts.append(ts[-1] * 1.06)
    return np.array(ts)


def horizon_map(height: np.ndarray, azimuths: int = AZIMUTHS) -> np.ndarray:
    """Horizon elevations (radians, >= 0) float32 (H, W, ``azimuths``) of a height field in
    pixel units (module docstring). One Dr.Jit kernel per azimuth (``drjit.auto``: CUDA where
    a GPU exists, else LLVM), every pixel a lane, the marching unrolled in it."""
    import drjit as dr
    from drjit.auto import Float, UInt32

    z = np.asarray(height, dtype=np.float64)
    if z.ndim != 2:
        raise ValueError(f"height of shape {z.shape}: expected (H, W)")
    azimuths = int(check_range("azimuths", azimuths, 1, 4096, "[]"))
    h, w = z.shape
    table = Float(z.astype(np.float32).ravel())
    lane = dr.arange(UInt32, h * w)
    rows, cols = Float(lane // w), Float(lane % w)
    z0 = dr.gather(Float, table, lane)
    out = np.zeros((h, w, azimuths), dtype=np.float32)
    ts = _distances(h, w)

    def at(r, c):  # the height at (row r, column c), bilinear, clamped to the image
        r0 = dr.clip(dr.floor(r), 0, h - 1)
        c0 = dr.clip(dr.floor(c), 0, w - 1)
        fr, fc = dr.clip(r - r0, 0, 1), dr.clip(c - c0, 0, 1)
        i0, j0 = UInt32(r0), UInt32(c0)
        i1, j1 = dr.minimum(i0 + 1, h - 1), dr.minimum(j0 + 1, w - 1)
        top = dr.lerp(dr.gather(Float, table, i0 * w + j0),
                      dr.gather(Float, table, i0 * w + j1), fc)
        bottom = dr.lerp(dr.gather(Float, table, i1 * w + j0),
                         dr.gather(Float, table, i1 * w + j1), fc)
        return dr.lerp(top, bottom, fr)

    for k in range(azimuths):
        phi = 2.0 * math.pi * k / azimuths
        # opaque: one kernel compiled for every azimuth
        ux, uy = dr.opaque(Float, math.cos(phi)), dr.opaque(Float, math.sin(phi))
        best = dr.zeros(Float, h * w)  # tan of the elevation; 0: the flat horizon
        for t in ts:
            tt = dr.opaque(Float, float(t))
            r, c = rows - tt * uy, cols + tt * ux  # y up = rows down
            inside = (r >= 0) & (r <= h - 1) & (c >= 0) & (c <= w - 1)
            best = dr.select(inside, dr.maximum(best, (at(r, c) - z0) / tt), best)
        out[..., k] = np.arctan(best.numpy().reshape(h, w))
    return out


def horizon_spread(horizon: np.ndarray) -> np.ndarray:
    """Half the largest change (radians) of each azimuth bin's horizon from a pixel to one of
    its 4 neighbours, float32 (H, W, A): the horizon's spread over the pixel's area."""
    hor = np.asarray(horizon, dtype=np.float32)
    pad = np.pad(hor, ((1, 1), (1, 1), (0, 0)), mode="edge")
    spread = np.zeros_like(hor)
    for dr_, dc in ((0, 1), (2, 1), (1, 0), (1, 2)):
        h, w = hor.shape[:2]
        np.maximum(spread, np.abs(pad[dr_:dr_ + h, dc:dc + w] - hor), out=spread)
    return 0.5 * spread


def visibility(horizon: np.ndarray, directions: np.ndarray,
               light_radius_deg: float = LIGHT_RADIUS_DEG,
               pixels: np.ndarray | None = None, spread: np.ndarray | None = None
               ) -> np.ndarray:
    """Visibility in [0, 1] of lights over a horizon map (module docstring).

    Args:
        horizon: (H, W, A) :func:`horizon_map`.
        directions: (K, 3) unit vectors towards the lights, the same at every pixel, or
            (P, K, 3) per pixel of ``pixels`` (lights at a distance).
        light_radius_deg: the lights' angular radius, degrees (0: a hard edge).
        pixels: bool (H, W): the pixels (C order) of the result; default all.
        spread: (H, W, A) :func:`horizon_spread` of ``horizon`` (computed if not given).

    Returns:
        float32 (P, K), P the pixels selected.
    """
    radius = math.radians(check_range("light_radius_deg", light_radius_deg, 0.0, 45.0, "[]",
                                      unit="degrees"))
    if spread is None:
        spread = horizon_spread(horizon)
    hor = horizon.reshape(-1, horizon.shape[-1]) if pixels is None else horizon[pixels]
    spr = spread.reshape(-1, spread.shape[-1]) if pixels is None else spread[pixels]
    p, a = hor.shape
    d = np.asarray(directions, dtype=np.float64)
    d = d / np.linalg.norm(d, axis=-1, keepdims=True)
    elev = np.arcsin(np.clip(d[..., 2], -1.0, 1.0))
    phi = np.mod(np.arctan2(d[..., 1], d[..., 0]), 2.0 * math.pi) * a / (2.0 * math.pi)
    lo = np.floor(phi).astype(np.int64) % a
    hi = (lo + 1) % a
    f = phi - np.floor(phi)
    if d.ndim == 2:  # (K,) the same bins at every pixel
        hz = hor[:, lo] * (1.0 - f)[None] + hor[:, hi] * f[None]
        half = spr[:, lo] * (1.0 - f)[None] + spr[:, hi] * f[None]
        elev = np.broadcast_to(elev[None], hz.shape)
    else:
        if d.shape[0] != p:
            raise ValueError(f"directions of shape {d.shape}: expected ({p}, K, 3)")
        hz = (np.take_along_axis(hor, lo, axis=1) * (1.0 - f)
              + np.take_along_axis(hor, hi, axis=1) * f)
        half = (np.take_along_axis(spr, lo, axis=1) * (1.0 - f)
                + np.take_along_axis(spr, hi, axis=1) * f)
    half = np.maximum(half, radius)
    edge = np.where(half > 0, (elev - hz) / (2.0 * np.maximum(half, 1e-12)) + 0.5,
                    np.where(elev > hz, 1.0, 0.0))
    return np.clip(edge, 0.0, 1.0).astype(np.float32)


@dataclass(eq=False)
class Relief:
    """A fitted surface's relief: its height field (H, W) in pixel units, the horizon map
    (H, W, A) and the lights' angular radius (degrees)."""

    height: np.ndarray
    horizon: np.ndarray
    light_radius_deg: float = LIGHT_RADIUS_DEG
    spread: np.ndarray | None = None

    def visibility(self, directions: np.ndarray, pixels: np.ndarray | None = None
                   ) -> np.ndarray:
        """:func:`visibility` of lights over this relief: float32 (P, K)."""
        if self.spread is None:
            self.spread = horizon_spread(self.horizon)
        return visibility(self.horizon, directions, self.light_radius_deg, pixels,
                          self.spread)


def make_relief(normals: np.ndarray, residual: np.ndarray, mask: np.ndarray,
                light_radius_deg: float = LIGHT_RADIUS_DEG, azimuths: int = AZIMUTHS
                ) -> Relief:
    """The :class:`Relief` of fitted maps: ``normals`` (H, W, 3) (NaN allowed outside the
    mask) integrated with :func:`residual_weights` of ``residual``, and its horizon map."""
    n = np.where(np.asarray(mask, bool)[..., None] & np.all(np.isfinite(normals), axis=-1,
                                                              keepdims=True),
                 normals, np.array([0.0, 0.0, 1.0]))
    height = integrate_normals(n, residual_weights(residual, mask))
    return Relief(height, horizon_map(height, azimuths), float(light_radius_deg))
