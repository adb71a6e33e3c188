"""A SYNTHETIC relief capture with real cast shadows: a height field of steep bumps and a
ridge as a mesh (a vertex per half pixel, analytic normals), the powder BSDF with one set of
properties, path traced by Mitsuba under directional lights (shadows and interreflections)."""

from __future__ import annotations

import math

import numpy as np

from mitsuba_powder.rti.maps import write_relief_ply
from mitsuba_powder.rti.synthetic import SYNTHETIC_REGIONS, dome_directions
from mitsuba_powder.variants import use_variant

#: The powder of the capture (the first synthetic region's), plugin defaults otherwise
PROPERTIES = dict(SYNTHETIC_REGIONS[0])


def relief_height(h: int, w: int, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Heights (pixel units) and unit normals of the relief sampled every ``1 / scale``
    pixel (row, column coordinates of pixel centres: (i + 0.5) / scale)."""
    r, c = np.mgrid[0:h * scale, 0:w * scale].astype(float)
    r, c = (r + 0.5) / scale, (c + 0.5) / scale
    z = np.zeros_like(r)
    zr = np.zeros_like(r)
    zc = np.zeros_like(r)
    u = min(h, w) / 32.0  # bumps in proportion to the image
    for (r0, c0, a, s) in ((0.3, 0.3, 4.0, 3.0), (0.65, 0.7, 5.0, 3.5), (0.3, 0.75, 3.0, 2.5)):
        a, s = a * u, s * u
        g = a * np.exp(-((r - r0 * h) ** 2 + (c - c0 * w) ** 2) / (2 * s * s))
        z += g
        zr += -g * (r - r0 * h) / s**2
        zc += -g * (c - c0 * w) / s**2
    # a ridge along the rows in the lower-left quarter (an elongated bump)
    sc, sr = 2.0 * u, 6.0 * u
    g = 3.0 * u * np.exp(-((c - 0.25 * w) ** 2) / (2 * sc**2) - (r - 0.75 * h) ** 2 / (2 * sr**2))
    z += g
    zc += -g * (c - 0.25 * w) / sc**2
    zr += -g * (r - 0.75 * h) / sr**2
    n = np.stack([-zc, zr, np.ones_like(z)], axis=-1)  # z_y = -z_row
    return z, n / np.linalg.norm(n, axis=-1, keepdims=True)


def lights(count: int = 40, held: int = 6) -> tuple[np.ndarray, np.ndarray]:
    """``count`` lights at 5-80 degrees (a spiral) and the indices of ``held`` of those at
    5-15 degrees, spread in azimuth, held out."""
    d = dome_directions(count, 5.0, 80.0)
    low = np.nonzero(np.degrees(np.arcsin(d[:, 2])) <= 15.0)[0]
    pick = low[np.linspace(0, len(low) - 1, held).round().astype(int)]
    return d, np.unique(pick)


def render(directions: np.ndarray, h: int, w: int, spp: int, folder, seed: int = 0,
           variant: str = "llvm_ad_rgb", max_depth: int = 4) -> np.ndarray:
    """Linear images (K, H, W, 3) of the relief under unit-irradiance directional lights."""
    import mitsuba as mi

    z, n = relief_height(h, w, scale=2)
    ply = folder / "truth.ply"
    write_relief_ply(ply, z * 2, n)  # heights in the fine grid's pixels
    out = np.empty((len(directions), h, w, 3), dtype=np.float32)
    aspect = w / h
    with use_variant(variant):
        bsdf = {"type": "powder", **{k: v for k, v in PROPERTIES.items() if k != "albedo"},
                "albedo": {"type": "rgb", "value": list(PROPERTIES["albedo"])}}
        for k, d in enumerate(directions):
            scene = mi.load_dict({
                "type": "scene",
                "integrator": {"type": "path", "max_depth": max_depth},
                "sensor": {"type": "orthographic",
                           "to_world": mi.ScalarTransform4f().scale([aspect, aspect, 1])
                           @ mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0],
                                                            up=[0, 1, 0]),
                           "sampler": {"type": "independent", "sample_count": spp},
                           "film": {"type": "hdrfilm", "width": w, "height": h,
                                    "rfilter": {"type": "box"}}},
                "emitter": {"type": "directional", "direction": [-float(x) for x in d],
                            "irradiance": {"type": "rgb", "value": 1.0}},
                "shape": {"type": "ply", "filename": str(ply), "face_normals": False,
                          "bsdf": bsdf}})
            out[k] = np.asarray(mi.render(scene, spp=spp, seed=seed + k))[..., :3]
    return out


def relief_capture(h: int, w: int, folder, spp: int = 64, noise: float = 0.005,
                   seed: int = 0, exposure: float = 1.0) -> dict:
    """The capture (module docstring): ``images`` (noisy, lights of irradiance
    ``exposure``: 1 is the fit's calibration), ``clean``, ``again`` (a second render,
    another seed: the renders' Monte Carlo noise), ``directions``, ``held`` (indices),
    ``noise``."""
    d, held = lights()
    a = render(d, h, w, spp, folder, seed=1000 * seed)
    b = render(d, h, w, spp, folder, seed=1000 * seed + 500)
    a, b = a * exposure, b * exposure
    rng = np.random.default_rng(seed)
    images = (a + rng.normal(0.0, noise, a.shape)).astype(np.float32)
    return {"images": images, "clean": a, "again": b, "directions": d, "held": held,
            "noise": noise, "exposure": exposure, "label": "SYNTHETIC"}


def noise_floor(cap: dict, idx: np.ndarray) -> float:
    """The RMS noise of the held-out images: the added noise and the render's Monte Carlo
    noise (half the mean square difference of two renders)."""
    mc = float(np.mean((cap["clean"][idx] - cap["again"][idx]) ** 2) / 2.0)
    return math.sqrt(cap["noise"] ** 2 + mc)
