"""Render the ochre series in a small scene: spheres of hematite at 1-50 % by mass in kaolinite
(host grains 1 um), one row per hematite grain radius (0.05 and 0.25 um), lit from just above
the camera (each sphere is seen near back-scattering at its centre, further from it towards
its rim) and by a dim uniform sky.

    python docs/scripts/ochre_render.py [--spp 32] [--variant llvm_ad_spectral] [--res 720x270]
                                        [--out DIR | --refresh-docs]

Writes ochre_render.png (labelled) and ochre_render.json (time, variant) into a new temporary
folder, the folder given with ``--out``, or, with ``--refresh-docs``, docs/figures. The
powders are those of docs/scripts/ochre_series.py (its mass fractions, radii and BRDF
parameters), built with ``mitsuba_powder.plugin.grains.mixture_properties``.
"""

from __future__ import annotations

import argparse
import io
import json
import platform
import time
from pathlib import Path

import numpy as np
from docs_output import add_output_options, output_dir, render_size, write_output
from ochre_series import BRDF, HEMATITE_RADII, MASS

from mitsuba_powder.plugin.grains import mixture_properties
from mitsuba_powder.variants import check_variant, use_variant

ROOT = Path(__file__).resolve().parents[2]
#: the host and its grain radius (um)
HOST = ("kaolinite", 1.0)
#: camera: origin, target, horizontal field of view (degrees)
EYE, TARGET, FOV = np.array([0.0, -15.0, 8.0]), np.array([0.0, 0.3, 0.9]), 46.0
#: sphere radius and spacing (scene units)
SPHERE, STEP_X, STEP_Y = 0.85, 2.1, 2.8


def centres() -> list[tuple[int, int, np.ndarray]]:
    """(row, column, centre) of every sphere: row 0 (back) the fine hematite."""
    n = len(MASS)
    return [(i, j, np.array([(j - (n - 1) / 2) * STEP_X, (0.5 - i) * STEP_Y, SPHERE]))
            for i in range(len(HEMATITE_RADII)) for j in range(n)]


def project(p: np.ndarray, width: int, height: int) -> tuple[float, float]:
    """Pixel (column, row) of a point, for the scene's pinhole camera."""
    fwd = (TARGET - EYE) / np.linalg.norm(TARGET - EYE)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    d = p - EYE
    t = np.tan(np.radians(FOV) / 2)
    x = d @ right / (d @ fwd) / t
    y = d @ up / (d @ fwd) / t * width / height
    return (x + 1) / 2 * width, (1 - y) / 2 * height


def scene(width: int, height: int, spp: int) -> dict:
    """The scene as a ``mi.load_dict`` dictionary."""
    import mitsuba as mi

    look = mi.ScalarTransform4f().look_at(origin=EYE.tolist(), target=TARGET.tolist(),
                                          up=[0, 0, 1])
    light = mi.ScalarTransform4f().look_at(origin=(EYE + [0.0, -1.5, 2.0]).tolist(),
                                           target=TARGET.tolist(), up=[0, 0, 1])
    lamp = light @ mi.ScalarTransform4f().scale([1.5, 1.5, 1.0])
    ground = mi.ScalarTransform4f().scale([40.0, 40.0, 1.0])
    d = {"type": "scene",
         "integrator": {"type": "path", "max_depth": 4},
         "sensor": {"type": "perspective", "fov": FOV, "fov_axis": "x", "to_world": look,
                    "sampler": {"type": "independent", "sample_count": spp},
                    "film": {"type": "hdrfilm", "width": width, "height": height,
                             "rfilter": {"type": "gaussian"}}},
         "light": {"type": "rectangle", "to_world": lamp,
                   "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 90.0}}},
         "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.08}},
         "ground": {"type": "rectangle", "to_world": ground,
                    "bsdf": {"type": "diffuse",
                             "reflectance": {"type": "rgb", "value": 0.35}}}}
    for i, j, c in centres():
        parts = [("hematite", MASS[j], HEMATITE_RADII[i]), (HOST[0], 1.0 - MASS[j], HOST[1])]
        d[f"sphere_{i}_{j}"] = {"type": "sphere", "center": c.tolist(), "radius": SPHERE,
                                "bsdf": {"type": "powder", **mixture_properties(parts, "mass"),
                                         **BRDF}}
    return d


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--spp", type=int, default=32)
    parser.add_argument("--variant", default="llvm_ad_spectral")
    parser.add_argument("--res", default="720x270", help="WIDTHxHEIGHT")
    add_output_options(parser, ROOT / "docs" / "figures", "ochre_render.png and .json")
    args = parser.parse_args()
    width, height = render_size(parser, args)
    try:
        check_variant(args.variant)
    except ValueError as exc:
        parser.error(f"--variant: {exc}")
    out = output_dir(args, ROOT / "docs" / "figures")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import mitsuba as mi

    t0 = time.perf_counter()
    with use_variant(args.variant):
        image = mi.render(mi.load_dict(scene(width, height, args.spp)))
        bitmap = mi.Bitmap(image).convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32,
                                          srgb_gamma=True)
        img = np.array(bitmap)
    if not np.all(np.isfinite(img)):
        parser.exit(2, f"{parser.prog}: error: the render holds {np.sum(~np.isfinite(img))} "
                       "NaN or infinite pixel values (a plugin bug); nothing was written\n")
    img = np.clip(img, 0.0, 1.0)
    seconds = time.perf_counter() - t0
    fig, ax = plt.subplots(figsize=(width / 100, height / 100 + 0.4), dpi=100)
    ax.imshow(img)
    for i, j, c in centres():
        col, row = project(c - [0.0, 0.0, SPHERE], width, height)
        if i == len(HEMATITE_RADII) - 1:
            ax.text(col, row + 4, f"{100 * MASS[j]:g} %", ha="center", va="top", fontsize=8,
                    color="w")
        if j == 0:  # in the margin, left of the image
            ax.text(-6, project(c, width, height)[1], f"hematite\nr = {HEMATITE_RADII[i]:g} um",
                    ha="right", va="center", fontsize=8, clip_on=False)
    ax.set_axis_off()
    ax.set_title(f"hematite in kaolinite, % by mass; {args.variant}, {args.spp} spp, "
                 f"{width}x{height}, {seconds:.1f} s", fontsize=9)
    png = io.BytesIO()
    fig.savefig(png, format="png", bbox_inches="tight")
    plt.close(fig)
    meta = {"variant": args.variant, "spp": args.spp, "width": width, "height": height,
            "seconds_load_and_render": round(seconds, 2),
            "machine": f"{platform.machine()}, {platform.system()}", "date": time.strftime("%F")}
    # both made before either is written; each written whole
    write_output(out, "ochre_render.png", png.getvalue())
    write_output(out, "ochre_render.json", json.dumps(meta, indent=1), finite=meta)
    print(meta)


if __name__ == "__main__":
    main()
