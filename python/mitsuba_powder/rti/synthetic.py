"""SYNTHETIC RTI captures: per-pixel maps of four regions with a gentle relief, rendered by
the forward model under a dome of lights with noise, so that fits can be checked against a
known truth."""

from __future__ import annotations

import math

import numpy as np

from .._checks import check_range
from .checks import check_count, check_gains
from .forward import VARIANT, render_capture

__all__ = ["SYNTHETIC_GRAIN_REGIONS", "SYNTHETIC_REGIONS", "SYNTHETIC_REGION_SETS",
           "dome_directions", "synthetic_capture", "synthetic_maps"]


#: Properties of the four regions of :func:`synthetic_capture` (top-left, top-right,
#: bottom-left, bottom-right quadrants)
SYNTHETIC_REGIONS: list[dict] = [
    {"albedo": (0.90, 0.62, 0.38), "amplitude_volume": 1.0, "g": 0.3, "extinction": 0.5,
     "amplitude_surface": 3e-5, "correlation_length": 0.4},
    {"albedo": (0.55, 0.70, 0.85), "amplitude_volume": 0.8, "g": -0.2, "extinction": 2.0,
     "amplitude_surface": 1e-4, "correlation_length": 0.25},
    {"albedo": (0.75, 0.75, 0.72), "amplitude_volume": 1.3, "g": 0.0, "extinction": 1.0,
     "amplitude_surface": 1e-5, "correlation_length": 0.6},
    {"albedo": (0.95, 0.85, 0.45), "amplitude_volume": 1.1, "g": 0.5, "extinction": 0.2,
     "amplitude_surface": 5e-5, "correlation_length": 0.3},
]

#: Properties of the four regions of a SYNTHETIC capture of hematite grains
#: (``regions="grains"``): grain radius (um; the albedo per channel follows from it),
#: ``amplitude_volume`` and ``extinction`` (1/um) differ per region, ``g``, and the surface
#: lobe are the same everywhere
SYNTHETIC_GRAIN_REGIONS: list[dict] = [
    {"radius": 0.045, "amplitude_volume": 1.0, "extinction": 0.5, "g": 0.0,
     "amplitude_surface": 1e-5, "correlation_length": 0.4},
    {"radius": 0.06, "amplitude_volume": 0.8, "extinction": 2.0, "g": 0.0,
     "amplitude_surface": 1e-5, "correlation_length": 0.4},
    {"radius": 0.08, "amplitude_volume": 1.3, "extinction": 1.0, "g": 0.0,
     "amplitude_surface": 1e-5, "correlation_length": 0.4},
    {"radius": 0.4, "amplitude_volume": 1.1, "extinction": 3.0, "g": 0.0,
     "amplitude_surface": 1e-5, "correlation_length": 0.4},
]

#: Region sets of :func:`synthetic_maps`
SYNTHETIC_REGION_SETS: dict[str, list[dict]] = {"albedo": SYNTHETIC_REGIONS,
                                                 "grains": SYNTHETIC_GRAIN_REGIONS}


def dome_directions(count: int = 40, min_elevation: float = 10.0, max_elevation: float = 80.0,
                    seed: int = 0) -> np.ndarray:
    """``count`` light directions on a dome: a Fibonacci spiral in elevation between
    ``min_elevation`` and ``max_elevation`` (degrees, uniform in sin(elevation)), (count, 3)."""
    count = check_count("count", count, 1)
    lo = check_range("min_elevation", min_elevation, 0.0, 90.0, "[]")
    hi = check_range("max_elevation", max_elevation, lo, 90.0, "[]")
    i = np.arange(count) + 0.5
    s = np.sin(np.radians(lo)) + (np.sin(np.radians(hi)) - np.sin(np.radians(lo))) * i / count
    phi = i * math.pi * (3.0 - math.sqrt(5.0)) + 0.3 * seed
    c = np.sqrt(1.0 - s**2)
    return np.stack([c * np.cos(phi), c * np.sin(phi), s], axis=1)


def synthetic_maps(height: int = 64, width: int = 64, relief: float = 0.25,
                   seed: int = 0, regions: str = "albedo") -> tuple[dict, np.ndarray]:
    """SYNTHETIC per-pixel maps: four quadrants with the properties of
    :data:`SYNTHETIC_REGIONS` (``regions="albedo"``: an albedo per channel) or
    :data:`SYNTHETIC_GRAIN_REGIONS` (``"grains"``: a hematite grain radius) and a gentle
    relief: six Gaussian bumps (random centres, widths 0.08-0.2 of the image, heights
    +-(0.5-1) ``relief`` x width), which tilts the normals by up to about 15 degrees (median 5)
    at the default ``relief`` = 0.25.

    Returns:
        maps for :func:`render_capture` and the (H, W) region index (0-3).
    """
    h = check_count("height", height, 2)
    w = check_count("width", width, 2)
    relief = check_range("relief", relief, 0.0, 2.0, "[]")
    if regions not in SYNTHETIC_REGION_SETS:
        raise ValueError(f"regions = {regions!r} is not a region set; choose one of "
                         f"{list(SYNTHETIC_REGION_SETS)}")
    table = SYNTHETIC_REGION_SETS[regions]
    rng = np.random.default_rng(seed)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float64)
    u, v = (xx + 0.5) / w, 1.0 - (yy + 0.5) / h          # image frame: x right, y up
    z = np.zeros((h, w))
    dzdu, dzdv = np.zeros((h, w)), np.zeros((h, w))
    for _ in range(6):
        cu, cv = rng.uniform(0.1, 0.9, 2)
        s = rng.uniform(0.08, 0.2)
        a = rng.choice([-1.0, 1.0]) * rng.uniform(0.5, 1.0) * relief * s
        e = a * np.exp(-((u - cu) ** 2 + (v - cv) ** 2) / (2 * s * s))
        z += e
        dzdu += -e * (u - cu) / (s * s)
        dzdv += -e * (v - cv) / (s * s)
    normal = np.stack([-dzdu, -dzdv, np.ones((h, w))], axis=-1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    region = (yy >= h / 2).astype(int) * 2 + (xx >= w / 2).astype(int)
    maps: dict = {"normal": normal}
    for name in table[0]:
        maps[name] = np.zeros((h, w, 3) if name == "albedo" else (h, w))
    for i, props in enumerate(table):
        sel = region == i
        for name, value in props.items():
            maps[name][sel] = value
    return maps, region


def synthetic_capture(height: int = 64, width: int = 64, lights: int = 40,
                      noise: float = 0.01, gains: np.ndarray | None = None,
                      relief: float = 0.25, seed: int = 0, exposure: float | None = 2.0,
                      variant: str = VARIANT, regions: str = "albedo",
                      near_camera: int = 0, light_distance: float = math.inf) -> dict:
    """A SYNTHETIC RTI capture rendered by :func:`render_capture` from known maps.

    Four quadrants of different properties (:func:`synthetic_maps`: ``regions="albedo"``,
    :data:`SYNTHETIC_REGIONS`, or ``"grains"``, :data:`SYNTHETIC_GRAIN_REGIONS`), a relief of
    Gaussian bumps, ``lights`` lights on a dome (elevations 10-80 degrees,
    :func:`dome_directions`), additive Gaussian noise of standard deviation ``noise`` (linear
    units, 1 = full scale).

    Args:
        exposure: the light irradiance (every gain is multiplied by it) so that the images
            fill the range (the brightest values stay below 1); None: the brightest
            noise-free value is 0.9.
        gains: (lights,) relative per-light gains (default 1).
        near_camera: how many of the ``lights`` sit at elevations 82-88 degrees, 2-8 degrees
            from the camera (the rest on the 10-80 degree dome): they sample the coherent
            back-scattering cone, the only part of the images that depends on the
            ``extinction`` (:mod:`mitsuba_powder.rti.fit`, "What a dome of lights determines").
        light_distance: the lights' distance from the image's centre, image widths
            (default ``inf``: distant lights; :func:`render_capture`).

    Returns:
        dict: ``images`` float32 (K, H, W, 3) (noisy), ``clean`` (noise-free),
        ``directions`` (K, 3), ``maps`` (the truth), ``region`` (H, W), ``gains`` (the
        irradiances used), ``noise``, and ``label = "SYNTHETIC"``.
    """
    noise = check_range("noise", noise, 0.0, math.inf, "[]")
    if exposure is not None:
        exposure = check_range("exposure", exposure, 0.0, math.inf, "(]")
    lights = check_count("lights", lights, 1)
    near = check_count("near_camera", near_camera, 0, lights)
    d = np.concatenate(([dome_directions(lights - near)] if lights > near else []) +
                       ([dome_directions(near, 82.0, 88.0, seed=1)] if near else []))
    rel = check_gains(gains, len(d))
    maps, region = synthetic_maps(height, width, relief, seed, regions)
    if exposure is None:
        exposure = 0.9 / float(np.max(render_capture(maps, d, rel, variant,
                                                     light_distance=light_distance)))
    clean = render_capture(maps, d, exposure * rel, variant, light_distance=light_distance)
    rng = np.random.default_rng(seed + 1)
    images = (clean + rng.normal(0.0, noise, clean.shape)).astype(np.float32)
    return {"images": images, "clean": clean, "directions": d, "maps": maps,
            "region": region, "gains": exposure * rel, "noise": noise,
            "label": "SYNTHETIC"}
