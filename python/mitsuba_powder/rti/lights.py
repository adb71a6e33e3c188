"""Dome lights at a finite distance: per-pixel light directions and irradiance factors.

**Frame and pixel coordinates** (those of :mod:`mitsuba_powder.rti` and the forward model of
the per-pixel fit): x to the image's right, y to its top, z towards the camera; the sample is
the plane z = 0 and the image's centre is the origin. Images are arrays (H, W) with row 0 at
the TOP of the image and column 0 at its left. Lengths are in IMAGE WIDTHS: pixel (i, j)
(row i, column j) has its centre at

    ``x = (j + 0.5 - W / 2) / W``,    ``y = (H / 2 - i - 0.5) / W``

so x spans [-1/2, 1/2] and y spans [-H / (2 W), H / (2 W)] (:func:`pixel_coordinates`).

**Model.** Light k sits at ``r_k l_k``, with ``l_k`` the unit direction of the ``.lp`` file
(from the image's centre towards the light) and ``r_k`` its distance from the centre in image
widths (one value r for the whole dome in the usual case; ``inf`` is a distant light). At a
point x of the plane, the light's direction and its irradiance relative to the image's centre
(on a plane perpendicular to the light, as the per-light gain ``E_k`` is defined) are

    ``d_k(x) = (r_k l_k - x) / |r_k l_k - x|``,    ``s_k(x) = (r_k / |r_k l_k - x|)^2``

(``s_k(0) = 1``: the gain ``E_k`` stays the irradiance at the image's centre). With the
inverse distance ``u = 1 / r`` these are ``d = w / |w|`` and ``s = 1 / |w|^2`` with
``w = l - u x``: smooth in u through ``u = 0``, where they are the distant light's ``l`` and 1
exactly; a fit of the distance works in u (:func:`light_field_derivatives` gives d/du).

**Valid distances.** A light with ``l_z > 0`` is above the image plane at every pixel for any
r > 0 (its height ``r l_z`` does not depend on the pixel; one with ``l_z <= 0``, which
:func:`mitsuba_powder.rti.read_lp` admits down to -0.1, is at or below it everywhere, as a
distant one). What a finite distance needs besides is a light outside the imaged area, so
that ``|r l - x|`` never vanishes: every ``r_k`` must exceed the image's half-diagonal
``rho = sqrt(1 + (H / W)^2) / 2`` image widths (0.707 for a square image); then
``|r l - x| >= r - rho > 0`` at every point of the image and ``(r / (r + rho))^2 <= s <=
(r / (r - rho))^2``. Real domes put their lights 2-5 image widths away.

**Light files.** Dome software writes either unit vectors or light POSITIONS (norm clearly
not 1) in ``.lp`` files. :func:`rig_from_vectors` (``kind="auto"``) reads a file's vectors as
directions when every norm is within :data:`UNIT_TOLERANCE` of 1, as positions when none is,
and refuses a file that mixes both (naming a line of each kind). Positions are relative to
the image's centre, in a unit given as ``image_width`` (the image's width in that unit, e.g.
pixel size x width in pixels); they give each light its own distance. A position file whose
lights all lie 1 +- 1 % of its unit from the centre cannot be told from directions: give
``kind="positions"``.

**Mitsuba scenes.** A point light of intensity I (W/sr) at distance D gives the irradiance
``I / D^2`` on a plane perpendicular to it; :func:`point_lights` places light k at
``r_k l_k`` times the image's width in scene units and sets ``I_k = E_k (r_k W_scene)^2``, so
that the irradiance at the image's centre is the distant light's ``E_k``.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from .._checks import out_of_range

__all__ = ["LP_KINDS", "UNIT_TOLERANCE", "LightRig", "check_distance", "distance_from_json",
           "distance_to_json", "half_diagonal", "image_light_field", "light_field",
           "light_field_derivatives", "parse_light_distance", "pixel_coordinates",
           "point_lights", "read_lp_rig", "rig_from_vectors", "unit_directions"]

#: How far from 1 the norm of an ``.lp`` vector may be for the vector to count as a unit
#: direction (relative; dome calibrations print 6 decimals)
UNIT_TOLERANCE = 1e-2

#: What the vectors of an ``.lp`` file are: decided from their norms, or said by the caller
LP_KINDS = ("auto", "directions", "positions")


def unit_directions(directions: np.ndarray, name: str = "directions") -> np.ndarray:
    """(K, 3) finite non-zero vectors, K >= 1 -> unit float64 vectors (a copy); the error
    names ``name`` and the first bad row."""
    d = np.array(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] < 1:
        raise ValueError(f"{name} has shape {d.shape}; expected (K, 3) with K >= 1")
    norm = np.linalg.norm(d, axis=1)
    bad = ~np.all(np.isfinite(d), axis=1) | (norm == 0)
    if np.any(bad):
        k = int(np.flatnonzero(bad)[0])
        raise ValueError(f"{name}[{k}] = {d[k].tolist()} is not a finite non-zero vector")
    return d / norm[:, None]


@dataclass(frozen=True, eq=False)
class LightRig:
    """The lights of a dome: unit directions and distances from the image's centre.

    Attributes:
        directions: float64 (K, 3) unit vectors from the image's centre towards the lights
            (normalised on construction; image frame, module docstring). Read-only.
        distance: r in image widths, one number for every light (``math.inf``: distant
            lights, today's model exactly) or float64 (K,) one per light (lights read as
            positions). Each must be > 0 or ``inf``; the image-dependent minimum (the
            half-diagonal) is checked where pixels are given (:func:`check_distance`).
    """

    directions: np.ndarray
    distance: float | np.ndarray = math.inf

    def __post_init__(self) -> None:
        d = unit_directions(self.directions)
        d.setflags(write=False)
        object.__setattr__(self, "directions", d)
        r = np.array(self.distance, dtype=np.float64)
        if r.ndim not in (0, 1) or (r.ndim == 1 and r.shape != (len(d),)):
            raise ValueError(f"distance has shape {r.shape}; expected a number or ({len(d)},), "
                             "one per light")
        bad = np.isnan(r) | (r <= 0)
        if np.any(bad):
            k = int(np.flatnonzero(np.atleast_1d(bad))[0])
            value = float(np.atleast_1d(r)[k])
            where = "distance" if r.ndim == 0 else f"distance[{k}]"
            raise ValueError(out_of_range(f"{where} = {value!r} image widths", "(0, inf]",
                                          "(inf: a distant light)"))
        if r.ndim == 0:
            object.__setattr__(self, "distance", float(r))
        else:
            r.setflags(write=False)
            object.__setattr__(self, "distance", r)

    @property
    def count(self) -> int:
        """K, the number of lights."""
        return int(len(self.directions))

    @property
    def distances(self) -> np.ndarray:
        """float64 (K,) r_k in image widths (``inf`` for distant lights)."""
        return np.broadcast_to(np.asarray(self.distance, dtype=np.float64), (self.count,)).copy()

    @property
    def inverse_distances(self) -> np.ndarray:
        """float64 (K,) ``u_k = 1 / r_k`` in 1/image width (0 for distant lights)."""
        return 1.0 / self.distances

    @property
    def is_distant(self) -> bool:
        """True when every light is at infinity (the distant-light model)."""
        return bool(np.all(np.isinf(self.distances)))

    @property
    def positions(self) -> np.ndarray:
        """float64 (K, 3) ``r_k l_k`` in image widths from the image's centre.

        Raises:
            ValueError: a light is distant (it has no position).
        """
        r = self.distances
        if np.any(np.isinf(r)):
            k = int(np.flatnonzero(np.isinf(r))[0])
            raise ValueError(f"light {k} is distant (distance = inf): it has no position")
        return r[:, None] * self.directions

    def take(self, indices: np.ndarray | Sequence[int]) -> LightRig:
        """The lights ``indices`` (e.g. the kept or held-out lights of a comparison), each
        with its own distance."""
        idx = np.asarray(indices, dtype=np.int64)
        r = self.distance if np.ndim(self.distance) == 0 else self.distances[idx]
        return LightRig(self.directions[idx], r)

    def with_distance(self, distance: float | np.ndarray) -> LightRig:
        """The same directions at another distance (number or (K,), image widths)."""
        return LightRig(self.directions, distance)


def half_diagonal(shape: tuple[int, int]) -> float:
    """Half the diagonal of an image of (H, W) pixels, in image widths:
    ``sqrt(1 + (H / W)^2) / 2``, the radius of the circle around the image's centre through
    its corners (the least valid light distance, module docstring)."""
    h, w = _shape(shape)
    return 0.5 * math.hypot(1.0, h / w)


def _shape(shape: tuple[int, int]) -> tuple[int, int]:
    try:
        h, w = (int(s) for s in shape)
    except (TypeError, ValueError):
        raise ValueError(f"shape = {shape!r}: expected (H, W), two whole numbers") from None
    if h < 1 or w < 1 or (h, w) != tuple(shape):
        raise ValueError(out_of_range(f"shape = {tuple(shape)!r}", "H, W >= 1",
                                      "(whole numbers of pixels)"))
    return h, w


def pixel_coordinates(shape: tuple[int, int]) -> np.ndarray:
    """Centres of the pixels of an (H, W) image in image widths from its centre.

    Returns:
        float64 (H, W, 2): ``[..., 0] = x = (j + 0.5 - W / 2) / W`` (to the right),
        ``[..., 1] = y = (H / 2 - i - 0.5) / W`` (up; row i = 0 is the top of the image).
    """
    h, w = _shape(shape)
    x = (np.arange(w, dtype=np.float64) + 0.5 - 0.5 * w) / w
    y = (0.5 * h - np.arange(h, dtype=np.float64) - 0.5) / w
    xy = np.empty((h, w, 2))
    xy[..., 0] = x[None, :]
    xy[..., 1] = y[:, None]
    return xy


def check_distance(distance: float | np.ndarray, shape: tuple[int, int],
                   name: str = "distance") -> np.ndarray:
    """Light distances valid for an (H, W) image: every r_k > the half-diagonal (or inf).

    Args:
        distance: r in image widths, a number or (K,).
        shape: (H, W) pixels.
        name: the parameter's name in the error message (e.g. ``--light-distance``).

    Returns:
        float64 array of the distances (the input's shape).

    Raises:
        ValueError: naming the parameter, the value, the valid range and why.
    """
    r = np.asarray(distance, dtype=np.float64)
    rho = half_diagonal(shape)
    bad = np.isnan(r) | (r <= rho)
    if np.any(bad):
        k = int(np.flatnonzero(np.atleast_1d(bad))[0])
        where = name if r.ndim == 0 else f"{name}[{k}]"
        h, w = _shape(shape)
        raise ValueError(out_of_range(
            f"{where} = {float(np.atleast_1d(r)[k])!r} image widths",
            f"({rho:.6g}, inf]: a light must be farther from the image's centre than the "
            f"corners of the {w} x {h} px image (its half-diagonal), so that it is never over "
            "the imaged area"))
    return r


def parse_light_distance(value, name: str = "light_distance", fit: bool = True
                         ) -> float | np.ndarray | str:
    """A light distance as given (a number, (K,) numbers, or text: a number, ``inf`` or, with
    ``fit``, ``"fit"``); checked against an image by :func:`check_distance`.

    Raises:
        ValueError: text that is none of these, naming ``name``.
    """
    if not isinstance(value, str):
        return value
    if fit and value.strip() == "fit":
        return "fit"
    try:
        return float(value)
    except ValueError:
        raise ValueError(f"{name} = {value!r} is not valid; give a distance in image widths "
                         "(> the half-diagonal), inf" + (" or 'fit'" if fit else "")) from None


def distance_to_json(r: float | np.ndarray) -> float | list | None:
    """A light distance for JSON: a number, a list (one per light) or None (inf)."""
    if np.ndim(r) == 0:
        return None if math.isinf(float(r)) else float(r)
    return [None if math.isinf(v) else float(v) for v in np.asarray(r, dtype=np.float64)]


def distance_from_json(value) -> float | np.ndarray:
    """The inverse of :func:`distance_to_json`."""
    if value is None:
        return math.inf
    if isinstance(value, list):
        return np.array([math.inf if v is None else float(v) for v in value])
    return float(value)


def _points(xy: np.ndarray) -> np.ndarray:
    p = np.asarray(xy, dtype=np.float64)
    if p.ndim < 1 or p.shape[-1] != 2 or not np.all(np.isfinite(p)):
        raise ValueError(f"xy has shape {p.shape}; expected (..., 2) finite image-plane "
                         "coordinates (image widths)")
    return p


def _w(rig: LightRig, p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(w = l - u x (K, *S, 3), |w| (K, *S), x as 3-vectors (*S, 3)) after the distance check."""
    u = rig.inverse_distances
    reach = float(np.max(np.linalg.norm(p, axis=-1))) if p.size else 0.0
    r = rig.distances
    if np.any(r <= reach):
        k = int(np.flatnonzero(r <= reach)[0])
        raise ValueError(f"distance of light {k} = {float(r[k])!r} image widths is out of "
                         f"range for these points; valid range is ({reach:.6g}, inf] (beyond "
                         "the farthest point from the image's centre)")
    x3 = np.concatenate([p, np.zeros(p.shape[:-1] + (1,))], axis=-1)
    shape = (len(u),) + (1,) * (p.ndim - 1) + (1,)
    w = rig.directions.reshape((len(u),) + (1,) * (p.ndim - 1) + (3,)) - u.reshape(shape) * x3
    # a distant light's w is its unit l: |w| = 1 exactly, so that r = inf is today's model to
    # the last bit
    q = np.where(u.reshape(shape[:-1]) == 0, 1.0, np.linalg.norm(w, axis=-1))
    return w, q, x3


def light_field(rig: LightRig, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per-point light directions and irradiance factors (module docstring).

    Args:
        rig: the lights.
        xy: (*S, 2) points of the image plane in image widths from the image's centre (e.g.
            :func:`pixel_coordinates`, or the masked pixels' (P, 2)). Every light must be
            farther from the centre than every point.

    Returns:
        ``directions`` float64 (K, *S, 3) unit vectors from each point towards light k, and
        ``irradiance`` float64 (K, *S), ``(r_k / |r_k l_k - x|)^2`` (1 at the centre; all 1
        for distant lights). Memory: 32 K x points bytes.
    """
    w, q, _ = _w(rig, _points(xy))
    return w / q[..., None], 1.0 / q**2


def light_field_derivatives(rig: LightRig, xy: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Derivatives of :func:`light_field` with respect to each light's inverse distance
    ``u_k = 1 / r_k`` (1/image width), at the rig's distances.

    With ``w = l - u x``, ``q = |w|``, ``d = w / q``: ``dd/du = (d (d . x) - x) / q`` and
    ``ds/du = 2 (d . x) / q^3``. At a distant light (u = 0): ``d (l . x) - x`` and
    ``2 l . x``. For a derivative in r multiply by ``du/dr = -1 / r^2``.

    Returns:
        float64 (K, *S, 3) and (K, *S), the derivatives of light k's direction and irradiance
        factor with respect to its own ``u_k``.
    """
    w, q, x3 = _w(rig, _points(xy))
    d = w / q[..., None]
    dx = np.sum(d * x3, axis=-1)
    return (d * dx[..., None] - x3) / q[..., None], 2.0 * dx / q**3


def image_light_field(rig: LightRig, shape: tuple[int, int]) -> tuple[np.ndarray, np.ndarray]:
    """:func:`light_field` at the pixel centres of an (H, W) image, after
    :func:`check_distance` (every distance beyond the half-diagonal).

    Returns:
        float64 (K, H, W, 3) directions and (K, H, W) irradiance factors.
    """
    check_distance(rig.distance, shape)
    return light_field(rig, pixel_coordinates(shape))


def point_lights(rig: LightRig, scene_width: float, gains: np.ndarray | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
    """Point lights of a Mitsuba scene that reproduce the rig: positions and intensities.

    The scene has the image plane at z = 0 with the image's centre at the origin and the
    image frame's axes (as :mod:`mitsuba_powder.rti_maps`' ``scene.xml``, whose image is
    ``2 W / H`` scene units wide).

    Args:
        rig: lights at finite distances.
        scene_width: the image's width in scene units, > 0.
        gains: (K,) irradiance of each light at the image's centre on a plane perpendicular to
            it (the fit's gains ``E_k``), > 0; default 1.

    Returns:
        ``positions`` float64 (K, 3) in scene units (``r_k l_k scene_width``) and
        ``intensities`` float64 (K,) ``E_k (r_k scene_width)^2`` (the ``point`` emitter's
        ``intensity``, radiance units x scene units^2): ``I / D^2 = E_k`` at the centre.

    Raises:
        ValueError: a distant light (use a ``directional`` emitter of irradiance ``E_k``), a
            scene width or gain out of range.
    """
    width = float(scene_width)
    if not (math.isfinite(width) and width > 0):
        raise ValueError(out_of_range(f"scene_width = {scene_width!r}", "(0, inf)",
                                      "scene units"))
    g = np.ones(rig.count) if gains is None else np.asarray(gains, dtype=np.float64)
    if g.shape != (rig.count,):
        raise ValueError(f"gains has shape {g.shape}; expected ({rig.count},), one per light")
    if not np.all(np.isfinite(g) & (g > 0)):
        k = int(np.flatnonzero(~(np.isfinite(g) & (g > 0)))[0])
        raise ValueError(out_of_range(f"gains[{k}] = {float(g[k])!r}", "(0, inf)"))
    if np.any(np.isinf(rig.distances)):
        k = int(np.flatnonzero(np.isinf(rig.distances))[0])
        raise ValueError(f"light {k} is distant (distance = inf): a point light cannot "
                         "reproduce it; use a directional emitter of irradiance = its gain")
    positions = rig.positions * width
    return positions, g * (rig.distances * width) ** 2


def rig_from_vectors(vectors: np.ndarray, kind: str = "auto", image_width: float | None = None,
                     distance: float = math.inf, where: Sequence[str] | None = None,
                     tolerance: float = UNIT_TOLERANCE) -> tuple[LightRig, str]:
    """A rig from the vectors of an ``.lp`` file: directions or positions.

    Args:
        vectors: float (K, 3) as written in the file (image frame).
        kind: ``auto`` (directions when every norm is within ``tolerance`` of 1, positions
            when none is, an error when some are), ``directions`` (normalised, whatever their
            norm) or ``positions``.
        image_width: positions only (required then): the image's width in the positions'
            unit (e.g. pixel size x width in pixels), > 0.
        distance: directions only: r in image widths (default ``inf``, distant lights).
        where: K labels of the vectors for messages (e.g. ``"dome.lp, line 7"``); default
            ``"vector k"``.
        tolerance: see ``kind``, in (0, 1).

    Returns:
        (rig, kind read: ``directions`` or ``positions``); positions give ``r_k = |p_k| /
        image_width`` and ``l_k = p_k / |p_k|``.

    Raises:
        ValueError: a mixed file (naming a line of each kind), positions without
            ``image_width``, a distance given with positions, values out of range.
    """
    v = np.asarray(vectors, dtype=np.float64)
    unit_directions(v, "vectors")
    labels = list(where) if where is not None else [f"vector {k}" for k in range(len(v))]
    if len(labels) != len(v):
        raise ValueError(f"where has {len(labels)} labels for {len(v)} vectors")
    if kind not in LP_KINDS:
        raise ValueError(f"kind = {kind!r} is not valid; choose one of {LP_KINDS}")
    if not 0.0 < float(tolerance) < 1.0:
        raise ValueError(out_of_range(f"tolerance = {tolerance!r}", "(0, 1)"))
    norm = np.linalg.norm(v, axis=1)
    unit = np.abs(norm - 1.0) <= tolerance
    if kind == "auto":
        if not unit.all() and unit.any():
            i, j = int(np.flatnonzero(unit)[0]), int(np.flatnonzero(~unit)[0])
            raise ValueError(
                f"{labels[j]}: light vector of length {norm[j]:.6g} is a position (not within "
                f"{tolerance:g} of 1) but {labels[i]} has length {norm[i]:.6g}, a unit "
                f"direction; a file holds either unit directions or positions ({int(unit.sum())}"
                f" of {len(v)} are unit); say which with kind='directions' or 'positions'")
        kind = "directions" if unit.all() else "positions"
    if kind == "directions":
        return LightRig(v, distance), kind
    if not math.isinf(distance):
        raise ValueError(f"distance = {distance!r} was given for light positions: positions set "
                         "each light's distance; give image_width (their unit) only")
    if image_width is None:
        raise ValueError(f"{labels[0]}: the lights are positions (lengths {norm.min():.6g}-"
                         f"{norm.max():.6g}); their unit is needed: give image_width, the "
                         "image's width in that unit (e.g. pixel size x width in pixels)")
    width = float(image_width)
    if not (math.isfinite(width) and width > 0):
        raise ValueError(out_of_range(f"image_width = {image_width!r}", "(0, inf)",
                                      "in the positions' unit"))
    return LightRig(v, norm / width), kind


def read_lp_rig(path: str | Path, kind: str = "auto", image_width: float | None = None,
                distance: float = math.inf, min_lz: float | None = None
                ) -> tuple[list[str], LightRig, str]:
    """The names and the light rig of an ``.lp`` file (directions or positions).

    The file is checked by :func:`mitsuba_powder.rti.read_lp` (format, counts, names, the
    normalised ``lz >= min_lz``); the vectors are then taken as written, not normalised, and
    classified by :func:`rig_from_vectors` (messages name the file and line).

    Args:
        path: the ``.lp`` file.
        kind, image_width, distance: as :func:`rig_from_vectors`.
        min_lz: see :func:`mitsuba_powder.rti.read_lp` (default its default).

    Returns:
        (names, rig, kind read).
    """
    from .capture import MIN_LZ_DEFAULT, read_lp_file

    p = Path(path)
    lp = read_lp_file(p, MIN_LZ_DEFAULT if min_lz is None else min_lz)
    rig, found = rig_from_vectors(lp.vectors, kind, image_width, distance,
                                  [f"{p}, line {n}" for n in lp.lines])
    return lp.names, rig, found
