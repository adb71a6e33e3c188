"""Starts of the per-pixel RTI fit: normal and albedo from Lambertian photometric stereo, the
Lambertian reflectance mapped to the powder's albedo through a table of the model, and a
search over grain sizes (and extinctions) for a per-pixel grain size."""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence

import numpy as np

from ..fitting.optimise import ParamSpec
from .forward import PixelEvaluator, pixel_chunks, slopes_of_normals
from .properties import SLOPE_LIMIT, SPECS, GrainAlbedo

__all__ = ["START_EXTINCTIONS", "START_SIZES", "PixelStarts", "lambertian_start"]

#: Grain sizes tried per pixel for the start of a per-pixel grain size (log grid)
START_SIZES = 40

#: Extinctions (1/um) tried per pixel for the start when ``extinction`` is free with a grain
#: size: it sets the width of the coherent cone, whose cost surface has a basin per width
START_EXTINCTIONS = (0.2, 0.5, 1.0, 2.0, 5.0)


def lambertian_start(images: np.ndarray, directions: np.ndarray,
                     weights: np.ndarray | None = None, gains: np.ndarray | None = None,
                     irradiance: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Lambertian photometric stereo (Woodham 1980), vectorised over pixels.

    Solves ``I_k / E_k = b . l_k`` per pixel by weighted least squares on the channel mean,
    then the per-channel reflectance ``R_c = pi sum_k w I_kc (n . l_k) / sum_k w E_k
    (n . l_k)^2`` (over lights with ``n . l_k > 0``).

    Args:
        images: (K, H, W, 3) linear values.
        directions: (K, 3) unit light directions, or (K, H, W, 3) per pixel (lights at a
            finite distance).
        weights: (K, H, W) in {0, 1} (observations used), default all.
        gains: (K,) light irradiances, default 1.
        irradiance: (K, H, W) per-pixel irradiance factors multiplying the gains (lights at a
            finite distance), default 1.

    Returns:
        normals (H, W, 3) (n_z >= 0.05 enforced by tilting towards z) and the Lambertian
        reflectance (H, W, 3) (the albedo of ``f = R / pi``).
    """
    k, h, w, _ = images.shape
    g = np.ones(k) if gains is None else gains
    wt = np.ones((k, h * w)) if weights is None else weights.reshape(k, h * w).astype(float)
    if np.ndim(directions) == 4 or irradiance is not None:
        return _near_lambertian(images, directions, wt, g, irradiance)
    lum = images.reshape(k, h * w, 3).mean(axis=2) / g[:, None]
    a = np.einsum("kp,ki,kj->pij", wt, directions, directions)
    a += 1e-9 * np.eye(3)[None]
    rhs = np.einsum("kp,kp,ki->pi", wt, lum, directions)
    try:
        b = np.linalg.solve(a, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        b = np.einsum("pij,pj->pi", np.linalg.pinv(a), rhs)
    b[:, 2] = np.maximum(b[:, 2], 1e-12)
    n = b / np.linalg.norm(b, axis=1, keepdims=True)
    # keep the start inside the slope bounds (tilt < ~87 degrees)
    n[:, 2] = np.maximum(n[:, 2], 0.05)
    n /= np.linalg.norm(n, axis=1, keepdims=True)
    cos = np.maximum(directions @ n.T, 0.0)  # (K, P)
    num = np.einsum("kp,kp,kpc->pc", wt, cos, images.reshape(k, h * w, 3))
    den = np.einsum("kp,k,kp->p", wt, g, cos**2)[:, None]
    refl = np.pi * num / np.maximum(den, 1e-30)
    return n.reshape(h, w, 3), refl.reshape(h, w, 3)


def _normals_of_b(b: np.ndarray) -> np.ndarray:
    """Photometric-stereo vectors b (P, 3) -> unit normals with n_z >= 0.05."""
    b[:, 2] = np.maximum(b[:, 2], 1e-12)
    n = b / np.linalg.norm(b, axis=1, keepdims=True)
    n[:, 2] = np.maximum(n[:, 2], 0.05)
    return n / np.linalg.norm(n, axis=1, keepdims=True)


def _near_lambertian(images: np.ndarray, directions: np.ndarray, wt: np.ndarray,
                     g: np.ndarray, irradiance: np.ndarray | None
                     ) -> tuple[np.ndarray, np.ndarray]:
    """:func:`lambertian_start` with per-pixel light directions (K, H, W, 3) (or (K, 3)) and
    irradiance factors (K, H, W) (or None): ``I_kp / (E_k s_kp) = b_p . d_kp``."""
    k, h, w, _ = images.shape
    dirs = np.broadcast_to(np.asarray(directions, dtype=np.float64).reshape(k, -1, 3),
                           (k, h * w, 3))
    gs = g[:, None] * (np.ones((k, h * w)) if irradiance is None
                       else np.asarray(irradiance, dtype=np.float64).reshape(k, h * w))
    lum = images.reshape(k, h * w, 3).mean(axis=2) / gs
    a = np.einsum("kp,kpi,kpj->pij", wt, dirs, dirs) + 1e-9 * np.eye(3)[None]
    rhs = np.einsum("kp,kp,kpi->pi", wt, lum, dirs)
    try:
        b = np.linalg.solve(a, rhs[..., None])[..., 0]
    except np.linalg.LinAlgError:
        b = np.einsum("pij,pj->pi", np.linalg.pinv(a), rhs)
    n = _normals_of_b(b)
    cos = np.maximum(np.einsum("kpi,pi->kp", dirs, n), 0.0)
    num = np.einsum("kp,kp,kpc->pc", wt, cos, images.reshape(k, h * w, 3))
    den = np.einsum("kp,kp,kp->p", wt, gs, cos**2)[:, None]
    refl = np.pi * num / np.maximum(den, 1e-30)
    return n.reshape(h, w, 3), refl.reshape(h, w, 3)


def _albedo_table(ev: PixelEvaluator, values: Mapping[str, float], directions: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
    """Lambertian-equivalent reflectance (per channel) of the powder for a grid of albedos,
    at n = z under the capture's lights above the horizon: (albedos, (M, 3) reflectances)."""
    grid = np.linspace(SPECS["albedo"].lower, SPECS["albedo"].upper, 96)
    up = directions[directions[:, 2] > 0.05]
    if len(up) == 0:
        up = np.array([[0.0, 0.0, 1.0]])
    m = len(grid)
    value, _ = ev(np.zeros((m, 2)), np.repeat(grid[:, None], 3, axis=1),
                  {k: np.full(m, v) for k, v in values.items()}, up)
    cos = up[:, 2]
    refl = np.pi * np.einsum("mkc,k->mc", value, cos) / np.sum(cos**2)
    return grid, refl


class PixelStarts:
    """Start rows ``y`` of every pixel for :class:`mitsuba_powder.rti.problem.PixelProblem`.

    The normal (slopes) and the Lambertian reflectance come from :func:`lambertian_start`; a
    free albedo starts at the powder albedo of that reflectance (a table of the model at
    n = z, the free properties at their starts and the fixed ones at their medians); a free
    grain size starts from :meth:`grain_search` (or its default without the search); the
    other free properties at their starts (or the values the search chose).

    Args:
        ev: the fit's evaluator.
        obs: (P, K, 3) observations; directions: (K, 3) unit vectors towards the lights.
        layout: the fit's variables (name, spec) in column order; specs: their specs by name.
        free: the free properties; others: those of them that are neither the albedo nor a
            grain size; grain_name: the per-pixel grain size of the settings.
        fixed_maps: held per-pixel property -> (P,); grain: the albedo of the grain size (or
            None); max_lanes: pixels x lights per evaluation at most.
        field: lights at a finite distance: per-pixel directions (P, K, 3) and irradiance
            factors (P, K) (:func:`mitsuba_powder.rti.forward.near_field`); None: distant.
        medians: the values of the held per-pixel properties in the albedo table (default
            their medians over these pixels; a fit in blocks gives those of all its pixels,
            so that every block starts alike).
    """

    def __init__(self, ev: PixelEvaluator, obs: np.ndarray, directions: np.ndarray,
                 layout: Sequence[tuple[str, ParamSpec]], specs: Mapping[str, ParamSpec],
                 free: Sequence[str], others: Sequence[str], grain_name: str,
                 fixed_maps: Mapping[str, np.ndarray], grain: GrainAlbedo | None,
                 max_lanes: int, field: tuple[np.ndarray, np.ndarray] | None = None,
                 medians: Mapping[str, float] | None = None):
        self.ev, self.obs, self.d, self.field = ev, obs, directions, field
        self.layout, self.specs, self.others = layout, specs, list(others)
        self.grain_name, self.fixed_maps, self.max_lanes = grain_name, fixed_maps, max_lanes
        if medians is None:
            medians = {n: float(np.median(v)) for n, v in fixed_maps.items()}
        table_values = {**{n: SPECS[n].start for n in others}, **medians}
        self.table = (_albedo_table(ev, table_values, directions)
                      if "albedo" in free or grain_name in free else None)
        self.size_grid = (np.exp(np.linspace(math.log(SPECS[grain_name].lower),
                                             math.log(SPECS[grain_name].upper), 400))
                          if grain_name in free else None)
        self.size_rho = grain(self.size_grid)[0] if self.size_grid is not None else None

    def __call__(self, gain: np.ndarray, weight: np.ndarray, search: bool = True
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Start rows (P, variables + 1; the last column the pixel index) under the gains
        ``gain`` and observation weights ``weight`` (P, K), the Lambertian normals (P, 3) and
        reflectances (P, 3). ``search``: also the grain-size search (else the default size).
        """
        npix = len(self.obs)
        if self.field is None:
            n0, refl = lambertian_start(self.obs.transpose(1, 0, 2)[:, :, None, :], self.d,
                                        weight.T[:, :, None], gain)
        else:
            n0, refl = lambertian_start(self.obs.transpose(1, 0, 2)[:, :, None, :],
                                        self.field[0].transpose(1, 0, 2)[:, :, None, :],
                                        weight.T[:, :, None], gain, self.field[1].T[:, :, None])
        n0, refl = n0[:, 0], refl[:, 0]
        y = np.zeros((npix, len(self.layout) + 1))
        slopes0 = np.clip(slopes_of_normals(n0), -SLOPE_LIMIT, SLOPE_LIMIT)
        y[:, :2] = slopes0
        col = 2
        starts: dict[str, np.ndarray] = {}
        if self.table is not None and self.size_grid is None:  # a free albedo
            y[:, col:col + 3] = np.stack([np.interp(refl[:, c], self.table[1][:, c],
                                                    self.table[0]) for c in range(3)], axis=1)
            col += 3
        elif self.size_grid is not None:  # a free grain size
            spec = self.specs[self.grain_name]
            if search:
                size, starts = self.grain_search(weight, gain, slopes0)
            else:
                size = spec.start
            y[:, col] = spec.to_y(size)
            col += 1
        for name in self.others:
            y[:, col] = self.specs[name].to_y(starts.get(name, self.specs[name].start))
            col += 1
        y[:, -1] = np.arange(npix)
        return y, n0, refl

    def lights(self, sl: slice) -> np.ndarray:
        """The light directions of the pixels ``sl``: (K, 3) or (P_sl, K, 3)."""
        return self.d if self.field is None else self.field[0][sl]

    def light_gains(self, gain: np.ndarray, sl: slice) -> np.ndarray:
        """(1, K, 1) or (P_sl, K, 1): the gains times the pixels' irradiance factors."""
        if self.field is None:
            return gain[None, :, None]
        return (gain[None, :] * self.field[1][sl])[:, :, None]

    def grain_search(self, weight: np.ndarray, gain: np.ndarray, slopes: np.ndarray
                     ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
        """Start of a per-pixel grain size: every pixel tries :data:`START_SIZES` sizes of a log
        grid (``rho(r)`` has several branches) with its Lambertian normal ``slopes`` and keeps
        the one of least weighted residual; all pixels at once, one model evaluation per
        trial. With ``amplitude_volume`` free each trial takes its best value in closed form
        (:meth:`_trial_cost`); with ``extinction`` free the trials also run over
        :data:`START_EXTINCTIONS`.

        Returns:
            the start size per pixel (P,) and start values (P,) of the free properties it
            chose.
        """
        npix = len(self.obs)
        free_av = "amplitude_volume" in self.others
        exts = START_EXTINCTIONS if "extinction" in self.others else (None,)
        base = {n: np.full(npix, self.specs[n].start) for n in self.others}
        base.update(self.fixed_maps)
        best_cost = np.full(npix, np.inf)
        best = {"size": np.zeros(npix), "amplitude_volume": np.ones(npix),
                "extinction": np.ones(npix)}
        chunks = pixel_chunks(npix, len(self.d), self.max_lanes)
        surface = (self._surface(base, slopes, gain, chunks) if free_av else None)
        for ext in exts:
            vals = dict(base)
            if ext is not None:
                vals["extinction"] = np.full(npix, ext)
            for i in range(0, len(self.size_grid), max(len(self.size_grid) // START_SIZES, 1)):
                rho = np.broadcast_to(self.size_rho[i], (npix, 3))
                cost, av = self._trial_cost(vals, slopes, rho, weight, gain, chunks, surface)
                better = cost < best_cost
                best_cost[better] = cost[better]
                best["size"][better] = self.size_grid[i]
                best["amplitude_volume"][better] = av[better]
                if ext is not None:
                    best["extinction"][better] = ext
        found = {}
        if free_av:
            found["amplitude_volume"] = best["amplitude_volume"]
        if "extinction" in self.others:
            found["extinction"] = best["extinction"]
        return best["size"], found

    def _surface(self, base: Mapping[str, np.ndarray], slopes: np.ndarray, gain: np.ndarray,
                 chunks: Sequence[slice]) -> list[np.ndarray]:
        """Per chunk: S, the model at ``amplitude_volume = 0`` (the surface lobe alone, which
        depends on neither the grain size nor the extinction)."""
        surface = []
        for sl in chunks:
            part = {n: x[sl] for n, x in base.items()}
            value, _ = self.ev(slopes[sl], np.broadcast_to(self.size_rho[0],
                                                           (len(slopes[sl]), 3)),
                               {**part, "amplitude_volume": np.zeros(len(slopes[sl]))},
                               self.lights(sl))
            surface.append(value * self.light_gains(gain, sl))
        return surface

    def _trial_cost(self, vals: Mapping[str, np.ndarray], slopes: np.ndarray, rho: np.ndarray,
                    weight: np.ndarray, gain: np.ndarray, chunks: Sequence[slice],
                    surface: list[np.ndarray] | None) -> tuple[np.ndarray, np.ndarray]:
        """Weighted cost (P,) of one trial and its ``amplitude_volume`` (P,). With the surface
        terms ``surface`` given (``amplitude_volume`` free), the model is ``A_v V + S``, linear
        in A_v: the evaluation at ``A_v = 1`` gives V and A_v is its least-squares value,
        clipped to the bounds."""
        npix = len(self.obs)
        av_spec = self.specs["amplitude_volume"]
        cost, av = np.zeros(npix), np.ones(npix)
        for j, sl in enumerate(chunks):
            part = {n: x[sl] for n, x in vals.items()}
            obs = self.obs[sl]
            if surface is not None:
                unit = np.ones(len(slopes[sl]))
                one, _ = self.ev(slopes[sl], rho[sl], {**part, "amplitude_volume": unit},
                                 self.lights(sl))
                surf = surface[j]
                vol = one * self.light_gains(gain, sl) - surf
                wv = weight[sl, :, None] * vol
                num = np.sum(wv * (obs - surf), axis=(1, 2))
                den = np.maximum(np.sum(wv * vol, axis=(1, 2)), 1e-30)
                av[sl] = np.clip(num / den, av_spec.lower, av_spec.upper)
                model = av[sl, None, None] * vol + surf
            else:
                v, _ = self.ev(slopes[sl], rho[sl], part, self.lights(sl))
                model = v * self.light_gains(gain, sl)
            cost[sl] = np.sum(weight[sl, :, None] * (model - obs) ** 2, axis=(1, 2))
        return cost, av
