"""Render the showcase (the paper's seven hematite samples) twice and write the labelled figure:
isolated Mie spheres of the Table 2 radii (scenes/showcase.xml) above, a grain model per sample
argued from the paper's description (scenes/showcase_grains.xml) below.

    python docs/scripts/showcase.py [--spp 256] [--variant llvm_ad_spectral] [-D NAME=VALUE]
                                    [--out DIR | --refresh-docs]

Writes showcase.png (labelled) and showcase.json (time, variant) into a new temporary folder,
the folder given with ``--out``, or, with ``--refresh-docs``, docs/figures (the committed
figure).
``-D`` sets a scene parameter of both scenes (e.g. ``-D fraction2=0.3``, ``-D
agglomerate_fill=0.5``; the assumptions the paper does not fix are such parameters).
"""

from __future__ import annotations

import argparse
import json
import platform
import re
import time
from pathlib import Path

import numpy as np
from docs_output import add_output_options, output_dir, render_size

from mitsuba_powder.rendering.render import render_scene

ROOT = Path(__file__).resolve().parents[2]
#: (title, scene, label per sample)
SCENES = [
    ("isolated Mie spheres, Table 2 radii (scenes/showcase.xml)",
     ROOT / "scenes" / "showcase.xml",
     ["1: 17 nm", "2: 16 nm", "3: 16 nm", "4: 15 nm", "5: 83 + 46 nm", "6: 687 + 43 nm",
      "7: 2222 + 49 nm"]),
    ("grain model per sample (scenes/showcase_grains.xml)",
     ROOT / "scenes" / "showcase_grains.xml",
     ["1: aggl.\nof 17 nm", "2: aggl.\nof 16 nm", "3: aggl.\nof 16 nm", "4: aggl.\nof 15 nm",
      "5: 83 + 46 nm", "6: aggl.\n687 nm", "7: aggl.\n2222 nm"]),
]


def dish_columns(width: int) -> list[float]:
    """Pixel column of each dish centre (pinhole projection of the scene's camera)."""
    eye, target = np.array([0.0, -21.0, 14.0]), np.zeros(3)
    fwd = (target - eye) / np.linalg.norm(target - eye)
    right = np.cross(fwd, [0.0, 0.0, 1.0])
    right /= np.linalg.norm(right)
    up = np.cross(right, fwd)
    tan_half = np.tan(np.radians(40.0) / 2)
    cols = []
    for k in range(7):
        p = np.array([-7.5 + 2.5 * k, 0.0, 0.3]) - eye
        x = p @ right / (p @ fwd) / tan_half
        _ = up
        cols.append((x + 1) / 2 * width)
    return cols


def main() -> None:
    parser = argparse.ArgumentParser()
    parser.add_argument("--spp", type=int, default=256)
    parser.add_argument("--variant", default="llvm_ad_spectral")
    parser.add_argument("--res", default="960x300", help="WIDTHxHEIGHT")
    add_output_options(parser, ROOT / "docs" / "figures", "showcase.png and showcase.json")
    parser.add_argument("-D", dest="defines", action="append", default=[],
                        metavar="NAME=VALUE", help="a scene parameter of both scenes")
    args = parser.parse_args()
    width, height = render_size(parser, args)
    defines = {"res_x": str(width), "res_y": str(height)}
    for item in args.defines:
        name, sep, value = item.partition("=")
        if not sep or not name:
            parser.error(f"-D {item!r}: expected NAME=VALUE")
        defines[name] = value
    declared = set()
    for _title, scene, _labels in SCENES:
        declared |= set(re.findall(r'<default name="(\w+)"', scene.read_text()))
    unknown = sorted(set(defines) - declared)
    if unknown:
        parser.error(f"-D {unknown}: not a parameter of the showcase scenes; they declare "
                     f"{', '.join(sorted(declared))}")
    out = output_dir(args, ROOT / "docs" / "figures")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import mitsuba as mi

    fig, axes = plt.subplots(len(SCENES), 1, figsize=(width / 100, len(SCENES) *
                                                      (height / 100 + 0.45)), dpi=100)
    renders = []
    for ax, (title, scene, labels) in zip(axes, SCENES, strict=True):
        exr = out / "showcase_raw.exr"
        declared = set(re.findall(r'<default name="(\w+)"', scene.read_text()))
        result = render_scene(scene, exr, variant=args.variant, spp=args.spp,
                              defines={k: v for k, v in defines.items() if k in declared})
        img = np.array(mi.Bitmap(str(exr)).convert(mi.Bitmap.PixelFormat.RGB,
                                                   mi.Struct.Type.Float32, srgb_gamma=True))
        exr.unlink()
        ax.imshow(np.clip(img, 0, 1))
        for col, label in zip(dish_columns(width), labels, strict=True):
            ax.text(col, height * 0.98, label, ha="center", va="bottom", fontsize=8,
                    color="w", linespacing=1.1)  # two lines where one would overlap
        ax.set_axis_off()
        ax.set_title(f"{title}; {result.variant}, {args.spp} spp, {width}x{height}, "
                     f"{result.seconds:.1f} s", fontsize=9)
        renders.append({"scene": str(scene.relative_to(ROOT)),
                        "seconds_load_and_render": result.seconds})
    fig.suptitle("Hematite samples 1-7 of Gerardin et al. (2023)", fontsize=10)
    fig.savefig(out / "showcase.png", bbox_inches="tight")
    plt.close(fig)
    meta = {"variant": args.variant, "spp": args.spp, "width": width, "height": height,
            "defines": {k: v for k, v in defines.items() if not k.startswith("res_")},
            "renders": renders, "machine": f"{platform.machine()}, {platform.system()}",
            "date": time.strftime("%F")}
    (out / "showcase.json").write_text(json.dumps(meta, indent=1))
    print(meta)


if __name__ == "__main__":
    main()
