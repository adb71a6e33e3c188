"""Render the showcase (the paper's seven hematite samples) and write the labelled figure.

    python docs/scripts/showcase.py [--spp 256] [--variant llvm_ad_spectral]

Writes docs/figures/showcase.png (labelled) and docs/figures/showcase.json (time, variant).
"""

from __future__ import annotations

import argparse
import json
import platform
import time
from pathlib import Path

import numpy as np

from mitsuba_powder.render import render_scene

ROOT = Path(__file__).resolve().parents[2]
SCENE = ROOT / "scenes" / "showcase.xml"
SAMPLES = ["1: 17 nm", "2: 16 nm", "3: 16 nm", "4: 15 nm", "5: 83 + 46 nm", "6: 687 + 43 nm",
           "7: 2222 + 49 nm"]


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
    parser.add_argument("--out", default=str(ROOT / "docs" / "figures"))
    args = parser.parse_args()
    try:
        width, height = (int(v) for v in args.res.split("x"))
    except ValueError:
        parser.error(f"--res {args.res!r}: expected WIDTHxHEIGHT in pixels, e.g. 960x300")
    if width < 1 or height < 1 or args.spp < 1:
        parser.error(f"--res {args.res} and --spp {args.spp} must be positive")
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    exr = out / "showcase_raw.exr"
    result = render_scene(SCENE, exr, variant=args.variant, spp=args.spp,
                          defines={"res_x": str(width), "res_y": str(height)})
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    import mitsuba as mi

    img = np.array(mi.Bitmap(str(exr)).convert(mi.Bitmap.PixelFormat.RGB,
                                               mi.Struct.Type.Float32, srgb_gamma=True))
    fig, ax = plt.subplots(figsize=(width / 100, height / 100 + 0.6), dpi=100)
    ax.imshow(np.clip(img, 0, 1))
    for col, label in zip(dish_columns(width), SAMPLES, strict=True):
        ax.text(col, height * 0.93, label, ha="center", va="top", fontsize=8, color="w")
    ax.set_axis_off()
    ax.set_title(f"Hematite samples 1-7 (Gerardin et al. 2023, Table 2 radii); {result.variant},"
                 f" {args.spp} spp, {width}x{height}, {result.seconds:.1f} s", fontsize=9)
    fig.savefig(out / "showcase.png", bbox_inches="tight")
    plt.close(fig)
    exr.unlink()
    meta = {"variant": result.variant, "spp": args.spp, "width": width, "height": height,
            "seconds_load_and_render": result.seconds,
            "machine": f"{platform.machine()}, {platform.system()}", "date": time.strftime("%F")}
    (out / "showcase.json").write_text(json.dumps(meta, indent=1))
    print(meta)


if __name__ == "__main__":
    main()
