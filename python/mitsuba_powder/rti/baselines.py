"""Per-pixel baseline models of RTI captures: PTM, HSH order 2, Lambertian photometric stereo.

Every baseline is linear in its coefficients: pixel value (per channel) = sum_j c_j B_j(l), with
``l = (lu, lv, lz)`` the unit direction towards the light (x to the image's right, y to its
top, z towards the camera, as :mod:`mitsuba_powder.rti` reads it). A fit is one linear least
squares problem per pixel and channel, all sharing the K x n design matrix ``A[k, j] =
B_j(l_k)``: the coefficients of every pixel are ``pinv(A) @ values`` (one matrix product over
all pixels, no loop over pixels). With a per-pixel light mask (shadows, saturation) each pixel
solves its own weighted normal equations ``(A^T W A) c = A^T W y``, batched.

Bases (per channel; values in the capture's linear units):

* ``ptm``, Polynomial Texture Map (Malzbender, Gelb, Wolters, "Polynomial texture maps",
  SIGGRAPH 2001), 6 functions: ``lu^2, lv^2, lu lv, lu, lv, 1`` with ``lu = lx``, ``lv = ly``.
* ``hsh``, hemispherical harmonics of order 2 (Gautron, Krivanek, Pattanaik, Bouatouch, "A
  novel hemispherical basis for accurate and efficient rendering", EGSR 2004; the RTI HSH
  fitters follow it), 9 functions of ``x = cos(theta) = lz`` and ``phi = atan2(ly, lx)``,
  ``s = sqrt(x - x^2)``::

      H0 = 1 / sqrt(2 pi)
      H1 = sqrt(6 / pi) cos(phi) s          H2 = sqrt(3 / (2 pi)) (2x - 1)
      H3 = sqrt(6 / pi) sin(phi) s          H4 = sqrt(30 / pi) cos(2 phi) (x^2 - x)
      H5 = sqrt(30 / pi) cos(phi) (2x - 1) s
      H6 = sqrt(5 / (2 pi)) (6x^2 - 6x + 1)
      H7 = sqrt(30 / pi) sin(phi) (2x - 1) s
      H8 = sqrt(30 / pi) sin(2 phi) (x^2 - x)

  i.e. the real spherical harmonics with ``cos(theta)`` replaced by ``2 cos(theta) - 1``,
  normalised to be orthonormal on the upper hemisphere (signs are immaterial to a fit). The
  basis is defined for ``lz >= 0``: a light slightly below the horizon (``lz < 0``, which
  :func:`mitsuba_powder.rti.read_lp` accepts down to -0.1) is evaluated at ``x = 0`` (on the
  horizon, same azimuth).
* ``lambertian``, photometric stereo (Woodham, "Photometric method for determining surface
  orientation from multiple images", Opt. Eng. 19, 1980): value = ``b . l``, 3 functions
  ``lx, ly, lz``, with ``b = albedo * normal`` per channel; the prediction is NOT clamped at
  zero (lights behind the local tangent plane give negative values): the plain linear model of
  photometric stereo. The normal map is ``b`` summed over channels, normalised; the albedo of a
  channel is ``|b|``.
* ``lambertian_clamped``: the same fit (unclamped least squares), predicting ``max(0, b . l)``,
  the attached shadow of a Lambertian surface (docs/rti.md scores both on RealRTI captures).

**Near-field lights** (``light_distance`` r finite, image widths; :mod:`mitsuba_powder.rti.lights`):
pixel x sees light k from ``d_k(x)`` with the irradiance factor ``s_k(x)``, so each pixel has
its own design ``A_x[k, j] = s_k(x) B_j(d_k(x))`` (the basis models the value per unit
irradiance) and solves its own normal equations, batched over pixels.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from .checks import check_directions
from .lights import LightRig, check_distance, light_field, pixel_coordinates

__all__ = ["BASELINES", "Baseline", "basis", "fit_baseline"]

#: baseline names and their number of basis functions per channel
BASELINES = {"ptm": 6, "hsh": 9, "lambertian": 3, "lambertian_clamped": 3}
#: pixels per chunk of the batched solves (bounds the float64 working memory)
_CHUNK = 1 << 15


def basis(name: str, directions: np.ndarray) -> np.ndarray:
    """Design matrix (K, n) of baseline ``name`` at K light directions.

    Args:
        name: ``ptm``, ``hsh``, ``lambertian`` or ``lambertian_clamped``.
        directions: (K, 3) vectors towards the lights (normalised here).
    """
    if name not in BASELINES:
        raise ValueError(f"baseline {name!r} is not known; choose one of {list(BASELINES)}")
    d = check_directions(directions)
    lx, ly, lz = d[:, 0], d[:, 1], d[:, 2]
    if name == "ptm":
        return np.stack([lx * lx, ly * ly, lx * ly, lx, ly, np.ones_like(lx)], axis=1)
    if name in ("lambertian", "lambertian_clamped"):
        return d.copy()
    x = np.clip(lz, 0.0, 1.0)
    phi = np.arctan2(ly, lx)
    s = np.sqrt(x - x * x)
    t = 2.0 * x - 1.0
    pi = np.pi
    return np.stack([
        np.full_like(x, 1.0 / np.sqrt(2.0 * pi)),
        np.sqrt(6.0 / pi) * np.cos(phi) * s,
        np.sqrt(3.0 / (2.0 * pi)) * t,
        np.sqrt(6.0 / pi) * np.sin(phi) * s,
        np.sqrt(30.0 / pi) * np.cos(2.0 * phi) * (x * x - x),
        np.sqrt(30.0 / pi) * np.cos(phi) * t * s,
        np.sqrt(5.0 / (2.0 * pi)) * (6.0 * x * x - 6.0 * x + 1.0),
        np.sqrt(30.0 / pi) * np.sin(phi) * t * s,
        np.sqrt(30.0 / pi) * np.sin(2.0 * phi) * (x * x - x),
    ], axis=1)


@dataclass
class Baseline:
    """A fitted per-pixel baseline.

    Attributes:
        name: a key of :data:`BASELINES`.
        coefficients: float32 (n, H, W, C): the coefficient of each basis function per pixel
            and channel, in the capture's linear units.
    """

    name: str
    coefficients: np.ndarray
    light_distance: float = math.inf

    @property
    def n_parameters(self) -> int:
        """Fitted numbers per pixel, all channels together (n x C)."""
        return int(self.coefficients.shape[0] * self.coefficients.shape[3])

    def predict(self, directions: np.ndarray) -> np.ndarray:
        """Predicted linear images float32 (K', H, W, C) under K' light directions (K', 3)
        (at the fit's light distance)."""
        a = basis(self.name, directions)
        n, h, w, c = self.coefficients.shape
        if not math.isinf(self.light_distance):
            return self._predict_near(directions)
        flat = self.coefficients.reshape(n, -1)
        out = np.empty((a.shape[0], flat.shape[1]), dtype=np.float32)
        step = _CHUNK * c
        for s in range(0, flat.shape[1], step):
            out[:, s:s + step] = a @ flat[:, s:s + step].astype(np.float64)
        if self.name == "lambertian_clamped":
            np.maximum(out, 0.0, out=out)
        return out.reshape(a.shape[0], h, w, c)

    def _predict_near(self, directions: np.ndarray) -> np.ndarray:
        """:meth:`predict` with each pixel's own light directions and irradiance factors."""
        n, h, w, c = self.coefficients.shape
        k = len(directions)
        flat = self.coefficients.reshape(n, h * w, c)
        out = np.empty((k, h * w, c), dtype=np.float32)
        for s in range(0, h * w, _CHUNK):
            a = _near_design(self.name, directions, self.light_distance, (h, w), s)
            out[:, s:s + a.shape[1]] = np.einsum("kpn,npc->kpc", a,
                                                 flat[:, s:s + a.shape[1]].astype(np.float64))
        if self.name == "lambertian_clamped":
            np.maximum(out, 0.0, out=out)
        return out.reshape(k, h, w, c)

    @property
    def normals(self) -> np.ndarray:
        """Lambertian only: unit normals float32 (H, W, 3) (x right, y up, z to the camera)."""
        if not self.name.startswith("lambertian"):
            raise ValueError(f"normals: only the lambertian baseline has them, not {self.name!r}")
        b = self.coefficients.astype(np.float64).sum(axis=3)  # (3, H, W)
        norm = np.linalg.norm(b, axis=0)
        with np.errstate(invalid="ignore", divide="ignore"):
            n = np.where(norm > 0, b / norm, np.nan)
        return np.moveaxis(n, 0, -1).astype(np.float32)

    @property
    def albedo(self) -> np.ndarray:
        """Lambertian only: ``|b|`` per channel, float32 (H, W, C) (linear units)."""
        if not self.name.startswith("lambertian"):
            raise ValueError(f"albedo: only the lambertian baseline has it, not {self.name!r}")
        return np.linalg.norm(self.coefficients, axis=0).astype(np.float32)


def _near_design(name: str, directions: np.ndarray, distance: float, shape: tuple[int, int],
                 start: int) -> np.ndarray:
    """(K, P_chunk, n) per-pixel design ``s_k(x) B_j(d_k(x))`` of the pixels from ``start``
    (C order, at most ``_CHUNK``) for lights at ``distance`` image widths."""
    check_distance(distance, shape, "light_distance")
    xy = pixel_coordinates(shape).reshape(-1, 2)[start:start + _CHUNK]
    dirs, s = light_field(LightRig(check_directions(directions), distance), xy)
    k, p = s.shape
    a = basis(name, dirs.reshape(-1, 3)).reshape(k, p, -1)
    return a * s[:, :, None]


def _fit_near(name: str, y: np.ndarray, directions: np.ndarray, m: np.ndarray | None,
              distance: float, shape: tuple[int, int]) -> np.ndarray:
    """Coefficients (n, P, C) of a near-field baseline: per-pixel (weighted) normal
    equations."""
    k, npix, c = y.shape
    n = BASELINES[name]
    coef = np.empty((n, npix, c), dtype=np.float32)
    for s in range(0, npix, _CHUNK):
        a = _near_design(name, directions, distance, shape, s)     # (K, P, n)
        p = a.shape[1]
        wgt = np.ones((k, p)) if m is None else m[:, s:s + p].astype(np.float64)
        gram = np.einsum("kp,kpi,kpj->pij", wgt, a, a)
        rhs = np.einsum("kp,kpi,kpc->pic", wgt, a, y[:, s:s + p].astype(np.float64))
        coef[:, s:s + p] = _solve(gram, rhs, s, shape[1], f"the lights at pixel {{}} do not "
                                  f"determine the {n} functions of baseline {name!r}")
    return coef


def _solve(gram: np.ndarray, rhs: np.ndarray, start: int, width: int, message: str
           ) -> np.ndarray:
    """Per-pixel normal equations (P, n, n) x = (P, n, C) -> (n, P, C); an ill-conditioned
    pixel (from ``start`` in C order of an image ``width`` px wide) raises ``message`` with
    the pixel in place of ``{}``."""
    cond = np.linalg.cond(gram)
    if np.any(~np.isfinite(cond) | (cond > 1e12)):
        q = start + int(np.flatnonzero(~np.isfinite(cond) | (cond > 1e12))[0])
        raise ValueError(message.format(f"(x={q % width}, y={q // width})"))
    return np.moveaxis(np.linalg.solve(gram, rhs), 1, 0)


def fit_baseline(name: str, images: np.ndarray, directions: np.ndarray,
                 light_mask: np.ndarray | None = None,
                 light_distance: float = math.inf) -> Baseline:
    """Fit baseline ``name`` to every pixel and channel of K images by linear least squares.

    Args:
        name: a key of :data:`BASELINES` (``ptm``, ``hsh``, ``lambertian``,
            ``lambertian_clamped``).
        images: linear values (K, H, W, C) (or (K, H, W)).
        directions: (K, 3) vectors towards the lights.
        light_mask: optional bool (K, H, W): True where light k is used at a pixel (False
            leaves out shadowed or saturated observations); every pixel needs at least n
            lights (n = 6, 9, 3) in a configuration that determines the basis.
        light_distance: the lights' distance from the image's centre, image widths (beyond
            the image's half-diagonal); ``inf`` (default): distant lights (module docstring).

    Returns:
        A :class:`Baseline`.

    Raises:
        ValueError: shapes that disagree, too few lights (for the basis or at a pixel), or
            light directions that do not determine the basis (rank-deficient design).
    """
    imgs = np.asarray(images)
    if imgs.ndim == 3:
        imgs = imgs[..., None]
    if imgs.ndim != 4:
        raise ValueError(f"images of shape {np.shape(images)}: expected (K, H, W, C)")
    a = _design(name, directions, imgs.shape[0])
    k, n = a.shape
    _, h, w, c = imgs.shape
    y = imgs.reshape(k, h * w, c)
    m = None
    if light_mask is not None:
        m = np.asarray(light_mask, dtype=bool)
        if m.shape != (k, h, w):
            raise ValueError(f"light_mask of shape {m.shape}: expected ({k}, {h}, {w})")
        m = m.reshape(k, h * w)
    if not math.isinf(light_distance):
        coef = _fit_near(name, y, directions, m, float(light_distance), (h, w))
        return Baseline(name, coef.reshape(n, h, w, c), float(light_distance))
    return Baseline(name, _fit_far(name, a, y, m, w).reshape(n, h, w, c))


def _design(name: str, directions: np.ndarray, k: int) -> np.ndarray:
    """The design matrix (K, n) of baseline ``name`` at the K light directions, which must
    determine its n functions."""
    a = basis(name, directions)
    n = a.shape[1]
    if len(a) != k:
        raise ValueError(f"{k} images for {len(a)} light directions")
    if k < n:
        raise ValueError(f"baseline {name!r} has {n} coefficients per channel; {k} lights are "
                         "too few")
    rank = np.linalg.matrix_rank(a)
    if rank < n:
        raise ValueError(f"the {k} light directions determine only {rank} of the {n} "
                         f"functions of baseline {name!r} (rank-deficient design)")
    return a


def _fit_far(name: str, a: np.ndarray, y: np.ndarray, m: np.ndarray | None, w: int
             ) -> np.ndarray:
    """Coefficients (n, P, C) float32 of distant lights: least squares of the observations
    ``y`` (K, P, C) on the design ``a`` (K, n), every light or those of ``m`` (K, P) per pixel
    (of an image ``w`` px wide)."""
    k, n = a.shape
    coef = np.empty((n,) + y.shape[1:], dtype=np.float32)
    if m is None:
        pinv = np.linalg.pinv(a)  # (n, K)
        for s in range(0, y.shape[1], _CHUNK):
            block = y[:, s:s + _CHUNK].astype(np.float64)
            coef[:, s:s + _CHUNK] = np.einsum("nk,kpc->npc", pinv, block)
        return coef
    counts = m.sum(axis=0)
    if np.any(counts < n):
        p = int(np.flatnonzero(counts < n)[0])
        raise ValueError(f"light_mask leaves {int(counts[p])} lights at pixel (x={p % w}, "
                         f"y={p // w}) ({int(np.sum(counts < n))} pixels have fewer than "
                         f"{n}); baseline {name!r} needs >= {n}")
    for s in range(0, y.shape[1], _CHUNK):
        wgt = m[:, s:s + _CHUNK].astype(np.float64)  # (K, P)
        gram = np.einsum("kp,ki,kj->pij", wgt, a, a)
        rhs = np.einsum("kp,ki,kpc->pic", wgt, a, y[:, s:s + _CHUNK].astype(np.float64))
        coef[:, s:s + _CHUNK] = _solve(gram, rhs, s, w, "light_mask: the lights kept at "
                                       f"pixel {{}} do not determine the {n} functions "
                                       f"of baseline {name!r}")
    return coef
