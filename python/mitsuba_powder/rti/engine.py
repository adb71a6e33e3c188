"""The per-pixel Levenberg-Marquardt solver of the RTI fit inside Dr.Jit kernels
(:class:`PixelSystem`), and the pixels' part of the gains' reduced system.

:mod:`mitsuba_powder.rti.problem` states the problem for
:func:`mitsuba_powder.fitting.optimise.batch_levenberg_marquardt`, which assembles every
pixel's (lights x channels x variables) Jacobian in NumPy. This module solves the same
problem, with the same rules, without that array:

* **One kernel per iteration.** Lane ``a K + k`` is active pixel ``a`` under light ``k``. The
  model ``E_k s_k f (n . l_k)``, the weighted residuals and their forward-mode derivatives
  with respect to every variable of the pixel (one AD pass per variable, or per group of
  variables whose tangents do not mix: the three albedo channels) are traced lazily and
  evaluated together, with the products ``sum_c J_ci J_cj`` and ``sum_c J_ci r_c`` of each
  lane; block sums over the K lanes of a pixel give its normal equations ``J^T J`` (n(n+1)/2
  numbers), ``J^T r`` (n) and its cost. Nothing of size lanes x variables leaves Dr.Jit.
* **All pixels at once.** The damped systems ``(J^T J + lambda diag(J^T J)) dy = -J^T r`` are
  solved per pixel by an unrolled Cholesky factorisation in double precision (n <= 10), the
  step is projected onto the box, the trial's cost and normal equations come from the next
  kernel, and a pixel keeps its step where the cost went down: damping, acceptance and
  stopping per pixel exactly as :func:`~mitsuba_powder.fitting.optimise.batch_levenberg_marquardt`
  (``lambda`` / 3 or x 4, stop on a relative change of the cost under ``ftol``, the step kept
  or not, or ``lambda > 1e7``).
  Only the pixels still active are evaluated (their indices by ``dr.compress``).
* **Gains.** After a pixel's fit, one more kernel gives the model (for the shadow flags and
  the residual map) and, when the gains are fitted, the terms of their reduced system
  ``S = sum_p (D_p - C_p^T A_p^-1 C_p)`` (:func:`mitsuba_powder.rti.gains.gain_system`):
  with ``A_p = L_p L_p^T``, the lanes carry ``U = L_p^-1 C_p`` (n numbers per lane), and
  ``sum_p C_p^T A_p^-1 C_p = U^T U`` is one matrix product in NumPy.

The parameter transforms (``log10`` of positive scale properties) and the albedo of a
per-pixel grain size (the cubic Hermite table of
:class:`~mitsuba_powder.rti.properties.GrainAlbedo`) are evaluated in the kernel, so that the
tangents are with respect to the optimiser's variables directly.

The same code runs in every RGB variant with AD (``llvm_ad_rgb``, ``cuda_ad_rgb``).
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import drjit as dr
import mitsuba as mi
import numpy as np

from ..variants import use_variant
from .forward import PixelEvaluator
from .pixels import PixelData, SolverFit
from .properties import GRAIN_MAPS, GrainAlbedo

__all__ = ["PixelSystem", "cholesky_solve"]

#: Forward passes keep the traced graph's edges: several passes share one evaluation
_KEEP_EDGES = dr.ADFlag.ClearInterior | dr.ADFlag.ClearInput

_LN10 = math.log(10.0)


def _f32(a: np.ndarray):
    """A NumPy array as a flat ``mi.Float`` (C order), in the selected variant."""
    return mi.Float(np.ascontiguousarray(a, dtype=np.float32).ravel())


def _tri(i: int, j: int) -> int:
    """Index of (i, j), i >= j, in a row-major lower triangle."""
    return i * (i + 1) // 2 + j


def cholesky_solve(a: Sequence, b: Sequence, tiny: float = 1e-300) -> tuple[list, list, object]:
    """Solve ``A x = b`` per lane by Cholesky factorisation, unrolled.

    Args:
        a: the lower triangle of the symmetric positive-definite A, row-major
            (``a[_tri(i, j)]``, i >= j), Dr.Jit arrays of one type (lanes = systems).
        b: n right-hand sides of that type.
        tiny: a pivot at or below this marks the system as failed.

    Returns:
        x (n arrays), the factor L (lower triangle, row-major) and a mask of the systems whose
        factorisation succeeded (x is 0 elsewhere).
    """
    n = len(b)
    low: list = [None] * len(a)
    ok = True
    for i in range(n):
        for j in range(i + 1):
            s = a[_tri(i, j)]
            for m in range(j):
                s = s - low[_tri(i, m)] * low[_tri(j, m)]
            if i == j:
                ok = ok & (s > tiny)
                low[_tri(i, i)] = dr.sqrt(dr.maximum(s, tiny))
            else:
                low[_tri(i, j)] = s / low[_tri(j, j)]
    z = forward_substitute(low, b)
    x: list = [None] * n
    for i in reversed(range(n)):
        s = z[i]
        for m in range(i + 1, n):
            s = s - low[_tri(m, i)] * x[m]
        x[i] = s / low[_tri(i, i)]
    return [dr.select(ok, v, 0.0) for v in x], low, ok


def forward_substitute(low: Sequence, b: Sequence) -> list:
    """``L^-1 b`` per lane for a lower-triangular L (row-major triangle)."""
    z: list = []
    for i in range(len(b)):
        s = b[i]
        for m in range(i):
            s = s - low[_tri(i, m)] * z[m]
        z.append(s / low[_tri(i, i)])
    return z


class _GrainTable:
    """:class:`GrainAlbedo`'s Hermite table as Dr.Jit arrays: the albedo per channel of a grain
    size, differentiable in the kernel (in double precision: the table has 3000 nodes, and the
    position within an interval must be resolved to far better than float32's 1e-4 there)."""

    def __init__(self, grain: GrainAlbedo):
        self.u0, self.du, self.nodes = grain.u0, grain.du, grain.NODES
        self.rho = [mi.Float64(np.ascontiguousarray(grain.rho[:, c])) for c in range(3)]
        self.m = [mi.Float64(np.ascontiguousarray(grain.drho_du[:, c] * grain.du))
                  for c in range(3)]

    def __call__(self, u):
        """Albedo (Color3f) at ``u = ln r`` (a Float with gradients)."""
        t = dr.clip((mi.Float64(u) - self.u0) / self.du, 0.0, self.nodes - 1 - 1e-9)
        j = dr.minimum(mi.UInt32(t), self.nodes - 2)
        s = t - mi.Float64(j)
        h00, h10 = (1 + 2 * s) * dr.square(1 - s), s * dr.square(1 - s)
        h01, h11 = s * s * (3 - 2 * s), s * s * (s - 1)
        out = []
        for c in range(3):
            p0 = dr.gather(mi.Float64, self.rho[c], j)
            p1 = dr.gather(mi.Float64, self.rho[c], j + 1)
            m0, m1 = dr.gather(mi.Float64, self.m[c], j), dr.gather(mi.Float64, self.m[c], j + 1)
            out.append(mi.Float(h00 * p0 + h10 * m0 + h01 * p1 + h11 * m1))
        return mi.Color3f(*out)


class PixelSystem:
    """The per-pixel least-squares problem of P pixels under K lights, in Dr.Jit: the solver
    ``drjit`` of :data:`mitsuba_powder.rti.solvers.SOLVERS` (the default).

    Args:
        ev: the fit's evaluator (its plugin instance and variant).
        data: the pixels' observations, weights, lights, gains, variables (``layout``: no
            pixel-index column) and held properties.
    """

    def __init__(self, ev: PixelEvaluator, data: PixelData):
        self.ev = ev
        self.layout = list(data.layout)
        self.npix, self.k = data.observed.shape[:2]
        self.lower = np.array([s.to_y(s.lower) for _, s in self.layout], dtype=np.float64)
        self.upper = np.array([s.to_y(s.upper) for _, s in self.layout], dtype=np.float64)
        self.evaluations = 0
        directions, fixed_albedo = data.directions, data.fixed_albedo
        with use_variant(ev.variant):
            self.obs = [_f32(data.observed[:, :, c]) for c in range(3)]
            self.sqrt_w = _f32(np.sqrt(data.weights))
            self.gains = _f32(data.gains)
            self.irradiance = None if data.irradiance is None else _f32(data.irradiance)
            if directions.ndim == 2:
                self.table = [_f32(directions[:, c]) for c in range(3)]
                self.per_pixel_dirs = None
            else:
                self.table = None
                self.per_pixel_dirs = [_f32(directions[:, :, c]) for c in range(3)]
            self.fixed = {n: _f32(v) for n, v in data.fixed.items()}
            self.fixed_albedo = (None if fixed_albedo is None else
                                 [_f32(fixed_albedo[:, c]) for c in range(3)])
            self.grain = None if data.grain is None else _GrainTable(data.grain)
        self._passes = self._tangent_passes()

    # -- variables -----------------------------------------------------------------------

    def _tangent_passes(self) -> list[list[int]]:
        """Columns whose tangents share one forward pass (the albedo channels), in order."""
        passes: list[list[int]] = []
        albedo = [j for j, (n, _) in enumerate(self.layout) if n.startswith("albedo")]
        for j, (name, _) in enumerate(self.layout):
            if name.startswith("albedo"):
                if j == albedo[0]:
                    passes.append(albedo)
            else:
                passes.append([j])
        return passes

    def _lanes(self, y: Sequence, pix, grad: bool):
        """Lane variables of the active pixels ``pix`` (UInt32) at rows ``y`` (n Float64 per
        active pixel): the leaves (one per column, gradients enabled with ``grad``), the
        slopes, albedo (Color3f) and property values per lane, the lane's data index."""
        k = self.k
        lanes = dr.arange(mi.UInt32, dr.width(pix) * k)
        a = lanes // k
        light = lanes - a * k
        p = dr.gather(mi.UInt32, pix, a)
        data = p * k + light
        leaves = [mi.Float(dr.gather(mi.Float64, col, a)) for col in y]
        if grad:
            for leaf in leaves:
                dr.enable_grad(leaf)
        values: dict[str, object] = {n: dr.gather(mi.Float, v, p) for n, v in self.fixed.items()}
        albedo_cols = []
        albedo = None
        for j, (name, spec) in enumerate(self.layout):
            y_j = leaves[j]
            if j < 2:
                continue
            if name.startswith("albedo"):
                albedo_cols.append(dr.exp(_LN10 * y_j) if spec.log else y_j)
            elif name in GRAIN_MAPS:
                albedo = self.grain(_LN10 * y_j if spec.log else dr.log(y_j))
            else:
                values[name] = dr.exp(_LN10 * y_j) if spec.log else y_j
        if albedo_cols:
            albedo = mi.Color3f(*albedo_cols)
        elif albedo is None:
            albedo = mi.Color3f(*[dr.gather(mi.Float, c, p) for c in self.fixed_albedo])
        return leaves, values, albedo, light, data

    def _model(self, leaves, values, albedo, light, data):
        """``f (n . l)`` per lane (Color3f, lazy), the lane's gain x irradiance factor."""
        ev = self.ev
        for name in ev.varying:
            ev.params[name] = values[name]
        ev.params["albedo.value"] = albedo
        ev.params.update()
        n = dr.normalize(mi.Vector3f(leaves[0], leaves[1], 1.0))
        frame = mi.Frame3f(n)
        if self.table is not None:
            lights = mi.Vector3f(*[dr.gather(mi.Float, c, light) for c in self.table])
        else:
            lights = mi.Vector3f(*[dr.gather(mi.Float, c, data) for c in self.per_pixel_dirs])
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(light))
        si.wi = frame.to_local(mi.Vector3f(0.0, 0.0, 1.0))
        out = ev.bsdf.eval(mi.BSDFContext(), si, frame.to_local(lights))
        scale = dr.gather(mi.Float, self.gains, light)
        if self.irradiance is not None:
            scale = scale * dr.gather(mi.Float, self.irradiance, data)
        return out, scale

    def _tangents(self, leaves, out) -> list[mi.Color3f]:
        """d out / d y per pass (Color3f per lane), by forward-mode AD on the traced graph."""
        tangents = []
        for cols in self._passes:
            for j in cols:
                dr.set_grad(leaves[j], 1.0)
                dr.enqueue(dr.ADMode.Forward, leaves[j])
            dr.traverse(dr.ADMode.Forward, flags=_KEEP_EDGES)
            t = dr.grad(out)
            dr.clear_grad(out)
            tangents.append(mi.Color3f(dr.detach(t)))
        return tangents

    def _columns(self, tangents, factor) -> list[list]:
        """The Jacobian's columns per lane: n lists of 3 channels (None: identically 0)."""
        cols: list[list] = [None] * len(self.layout)
        for cols_of_pass, t in zip(self._passes, tangents):
            for c, j in enumerate(cols_of_pass):
                chans = [t[i] * factor for i in range(3)]
                if len(cols_of_pass) > 1:  # one albedo channel per column
                    chans = [chans[i] if i == c else None for i in range(3)]
                cols[j] = chans
        return cols

    def _residuals(self, out, scale, data) -> list:
        """Weighted residuals per lane and channel, float32."""
        w = dr.gather(mi.Float, self.sqrt_w, data)
        return [w * (dr.detach(out[c]) * scale - dr.gather(mi.Float, self.obs[c], data))
                for c in range(3)], w

    # -- normal equations ----------------------------------------------------------------

    def normal_equations(self, y: Sequence, pix) -> tuple[object, list, list]:
        """Cost (Float64), ``J^T J`` (lower triangle) and ``J^T r`` of the pixels ``pix`` at
        rows ``y``: one kernel for the lanes, block sums over each pixel's K lanes."""
        leaves, values, albedo, light, data = self._lanes(y, pix, True)
        out, scale = self._model(leaves, values, albedo, light, data)
        res, w = self._residuals(out, scale, data)
        cols = self._columns(self._tangents(leaves, out), w * scale)
        n = len(cols)
        per_lane = [sum(mi.Float64(r) * mi.Float64(r) for r in res)]
        for i in range(n):
            for j in range(i + 1):
                per_lane.append(_dot(cols[i], cols[j]))
        for i in range(n):
            per_lane.append(_dot(cols[i], res))
        dr.eval([v for v in per_lane if v is not None])
        self.evaluations += 1
        sums = _block_sums(per_lane, self.k, dr.width(pix))
        ntri = n * (n + 1) // 2
        return sums[0], sums[1:1 + ntri], sums[1 + ntri:]

    # -- Levenberg-Marquardt -------------------------------------------------------------

    def solve(self, y0: np.ndarray, max_iterations: int, ftol: float = 1e-7) -> SolverFit:
        """Levenberg-Marquardt from the rows ``y0`` (P, n) (clipped into the box), every pixel at
        once; the rules of
        :func:`~mitsuba_powder.fitting.optimise.batch_levenberg_marquardt` with no hopeless
        test (pixels are not competing starts)."""
        n = len(self.layout)
        y0 = np.clip(np.asarray(y0, dtype=np.float64)[:, :n], self.lower, self.upper)
        with use_variant(self.ev.variant):
            y = [mi.Float64(np.ascontiguousarray(y0[:, j])) for j in range(n)]
            everyone = dr.arange(mi.UInt32, self.npix)
            cost, jtj, jtr = self.normal_equations(y, everyone)
            damping = dr.full(mi.Float64, 1e-3, self.npix)
            active = dr.full(mi.Bool, True, self.npix)
            iterations = 0
            for iterations in range(1, max_iterations + 1):  # noqa: B007
                pix = dr.compress(active)
                if dr.width(pix) == 0:
                    iterations -= 1
                    break
                y_a, c_a, d_a = _take(y, pix), _take(cost, pix), _take(damping, pix)
                a_a, g_a = _take(jtj, pix), _take(jtr, pix)
                dr.eval(y_a, c_a, d_a, a_a, g_a)
                step = _damped_step(a_a, g_a, d_a)
                trial = [dr.clip(y_a[j] + step[j], float(self.lower[j]), float(self.upper[j]))
                         for j in range(n)]
                dr.eval(trial)
                c_t, a_t, g_t = self.normal_equations(trial, pix)
                better = dr.isfinite(c_t) & (c_t < c_a)
                gain = dr.select(better, (c_a - c_t) / dr.maximum(c_a, 1e-300), 0.0)
                d_new = dr.select(better, dr.maximum(d_a / 3.0, 1e-9), d_a * 4.0)
                # a step that changes the cost by less than ftol (relative), kept or not, ends
                # the pixel: it is at its minimum to within the tolerance
                flat = dr.isfinite(c_t) & (dr.abs(c_a - c_t) < ftol * dr.maximum(c_a, 1e-300))
                done = (better & (gain < ftol)) | flat | (d_new > 1e7)
                new_y = [dr.select(better, t, o) for t, o in zip(trial, y_a)]
                new_ne = [dr.select(better, t, o) for t, o in zip(a_t + g_t, a_a + g_a)]
                new_c = dr.select(better, c_t, c_a)
                dr.eval(new_y, new_ne, new_c, d_new, done)
                for full, new in zip(y + jtj + jtr + [cost, damping],
                                     new_y + new_ne + [new_c, d_new]):
                    dr.scatter(full, new, pix)
                dr.scatter(active, ~done, pix)
                dr.eval(y, jtj, jtr, cost, damping, active)
            rows = np.stack([np.array(v, dtype=np.float64) for v in y], axis=1)
            at_cap = int(np.sum(np.array(active))) if iterations == max_iterations else 0
            return SolverFit(rows, np.array(cost, dtype=np.float64), iterations, at_cap)

    # -- after the fit -------------------------------------------------------------------

    def model(self, y: np.ndarray, gain_terms: bool = False
              ) -> tuple[np.ndarray, tuple[np.ndarray, np.ndarray] | None]:
        """The model without gain and irradiance factor, ``f (n . l_k)`` as (P, K, 3) float32,
        at rows ``y``;
        with ``gain_terms``, also the pixels' part ``(S, b)`` of the gains' reduced system
        (:func:`mitsuba_powder.rti.gains.gain_system`: ``S = sum_p (D_p - C_p^T A_p^-1
        C_p)``, ``b = sum_p (J_g^T r - C_p^T A_p^-1 J_p^T r)``)."""
        n, k = len(self.layout), self.k
        with use_variant(self.ev.variant):
            rows = [mi.Float64(np.ascontiguousarray(y[:, j], dtype=np.float64)) for j in range(n)]
            pix = dr.arange(mi.UInt32, self.npix)
            leaves, values, albedo, light, data = self._lanes(rows, pix, gain_terms)
            out, scale = self._model(leaves, values, albedo, light, data)
            value = [dr.detach(out[c]) for c in range(3)]
            if not gain_terms:
                dr.eval(value)
                return _to_pkc(value, self.npix, k), None
            irr = (1.0 if self.irradiance is None
                   else dr.gather(mi.Float, self.irradiance, data))
            res, w = self._residuals(out, scale, data)
            cols = self._columns(self._tangents(leaves, out), w * scale)
            terms = self._gain_terms(cols, res, [w * irr * v for v in value], pix)
            return _to_pkc(value, self.npix, k), terms

    def _gain_terms(self, cols, res, jg, pix) -> tuple[np.ndarray, np.ndarray]:
        """``(S, b)`` of the pixels from the lanes' Jacobian columns ``cols``, residuals
        ``res`` and gain derivatives ``jg`` (sqrt(w) s f per channel)."""
        n, k = len(cols), self.k
        lane_a = [_dot(cols[i], cols[j]) for i in range(n) for j in range(i + 1)]
        lane_g = [_dot(cols[i], res) for i in range(n)]
        lane_c = [_dot(cols[i], jg) for i in range(n)]       # C_p[i, k] on lane (p, k)
        lane_d = _dot(jg, jg)                                 # D_p[k, k]
        lane_jgr = _dot(jg, res)
        dr.eval([v for v in lane_a + lane_g + lane_c + [lane_d, lane_jgr] if v is not None])
        a = _block_sums(lane_a, k, dr.width(pix))
        g = _block_sums(lane_g, k, dr.width(pix))
        # the regularisation of gain_system: 1e-9 x the largest diagonal + 1e-30
        top = a[0]
        for i in range(1, n):
            top = dr.maximum(top, a[_tri(i, i)])
        for i in range(n):
            a[_tri(i, i)] = a[_tri(i, i)] + (1e-9 * top + 1e-30)
        _, low, _ = cholesky_solve(a, g, tiny=0.0)
        v = forward_substitute(low, g)                        # L^-1 J^T r per pixel
        lanes = dr.arange(mi.UInt32, dr.width(pix) * k)
        a_of = lanes // k
        low_l = [dr.gather(mi.Float64, m, a_of) for m in low]
        zero = dr.zeros(mi.Float64, dr.width(lanes))
        u = forward_substitute(low_l, [zero if c is None else mi.Float64(c)
                                       for c in lane_c])              # L^-1 C per lane
        uv = sum(u[i] * dr.gather(mi.Float64, v[i], a_of) for i in range(n))
        dr.eval(u, uv)
        u_np = np.stack([np.array(x, dtype=np.float64).reshape(-1, k) for x in u], axis=1)
        flat = u_np.reshape(-1, k)                            # (P n, K)
        s = np.diag(np.array(lane_d, dtype=np.float64).reshape(-1, k).sum(axis=0))
        s -= flat.T @ flat
        rhs = (np.array(lane_jgr, dtype=np.float64).reshape(-1, k).sum(axis=0)
               - np.array(uv, dtype=np.float64).reshape(-1, k).sum(axis=0))
        return s, rhs


def _dot(a: Sequence, b: Sequence):
    """``sum_c a_c b_c`` per lane over the channels present in both (None: 0); None when
    no channel is."""
    terms = [x * y for x, y in zip(a, b) if x is not None and y is not None]
    if not terms:
        return None
    return sum(terms[1:], terms[0])


def _block_sums(per_lane: Sequence, k: int, count: int) -> list:
    """Sums over blocks of ``k`` lanes as Float64 (``count`` blocks), an entry None as 0."""
    sums = [dr.zeros(mi.Float64, count) if v is None else mi.Float64(dr.block_sum(v, k))
            for v in per_lane]
    dr.eval(sums)
    return sums


def _take(values, pix):
    """The entries ``pix`` of a Float64 array (or of each of a list of them)."""
    if isinstance(values, list):
        return [dr.gather(mi.Float64, v, pix) for v in values]
    return dr.gather(mi.Float64, values, pix)


def _damped_step(a: Sequence, g: Sequence, damping) -> list:
    """Levenberg-Marquardt steps ``-(A + lambda diag(A) + 1e-12 max diag(A))^-1 g`` per pixel
    (the damping of :func:`mitsuba_powder.fitting.optimise._solve_damped`)."""
    n = len(g)
    diag = [dr.maximum(a[_tri(i, i)], 1e-30) for i in range(n)]
    top = diag[0]
    for d in diag[1:]:
        top = dr.maximum(top, d)
    damped = list(a)
    for i in range(n):
        damped[_tri(i, i)] = a[_tri(i, i)] + damping * diag[i] + 1e-12 * top
    x, _, _ = cholesky_solve(damped, g)
    return [-v for v in x]


def _to_pkc(value: Sequence, npix: int, k: int) -> np.ndarray:
    """Three lane arrays (P K) -> (P, K, 3) float32."""
    return np.stack([np.array(v, dtype=np.float32).reshape(npix, k) for v in value], axis=2)
