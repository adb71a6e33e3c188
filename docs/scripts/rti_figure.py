"""Figure of a powder-map fit of an RTI capture against the baselines, grazing protocol.

Fits the powder model (fit-maps' defaults) and the baselines on the capture's lights except the
lowest-elevation sixth (the grazing protocol of compare-maps), and draws: the fitted maps
(normal, albedo, surface lobe, residual), the lowest held-out light as photographed and as
each model predicts it, and each model's per-pixel error over the held-out lights (8-bit
levels on the capture's encoded scale).

    python docs/scripts/rti_figure.py --refresh-docs       # SYNTHETIC capture -> docs/figures
    python docs/scripts/rti_figure.py --capture /path/item7/dirs.lp --encoding linear \\
        --out /tmp/item7_figure                             # a real capture (not committed)

Real captures without a licence (RealRTI) must not be committed: give --out outside the
repository for them.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from docs_output import add_output_options, output_dir  # noqa: E402

from mitsuba_powder.rti import (  # noqa: E402
    Capture,
    encode,
    fit_maps,
    load_capture,
    synthetic_capture,
)
from mitsuba_powder.rti.baselines import fit_baseline  # noqa: E402
from mitsuba_powder.rti.comparison import held_out  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
BASELINES = ("ptm", "hsh", "lambertian_clamped")


def synthetic(size: int) -> Capture:
    cap = synthetic_capture(size, size, lights=40, noise=0.01, seed=4)
    return Capture(images=cap["images"], directions=cap["directions"],
                   names=[f"SYNTHETIC_{k:02d}" for k in range(40)], encoding="linear")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--capture", default=None, help=".lp file (default: SYNTHETIC)")
    parser.add_argument("--encoding", choices=("srgb", "linear"), default="linear")
    parser.add_argument("--size", type=int, default=96, help="SYNTHETIC capture size (px)")
    add_output_options(parser, ROOT / "docs" / "figures", "rti figure and its JSON")
    args = parser.parse_args()
    args.out = output_dir(args, ROOT / "docs" / "figures")
    cap = synthetic(args.size) if args.capture is None else \
        load_capture(args.capture, encoding=args.encoding)
    label = "SYNTHETIC" if args.capture is None else Path(args.capture).parent.name
    d = cap.directions
    idx = held_out("grazing", d)
    keep = np.setdiff1d(np.arange(len(d)), idx)
    t0 = time.perf_counter()
    powder = fit_maps(cap.images[keep], d[keep], mask=cap.mask)
    seconds = time.perf_counter() - t0
    predictions = {"powder": powder.predict(d[idx])}
    for name in BASELINES:
        predictions[name] = fit_baseline(name, cap.images[keep], d[keep]).predict(d[idx])
    truth = encode(cap.images[idx], cap.encoding)
    errors = {name: 255.0 * np.sqrt(np.mean((encode(p, cap.encoding) - truth) ** 2,
                                            axis=(0, 3)))
              for name, p in predictions.items()}
    lowest = int(np.argmin(d[idx, 2]))

    fig, axes = plt.subplots(3, 4, figsize=(13, 10))
    shown = [("normal (x, y, z) / 2 + 0.5", 0.5 * (powder.normals + 1.0)),
             ("albedo (single scattering)", np.clip(powder.albedo, 0, 1)),
             ("amplitude_surface (um^2, log10)",
              np.log10(powder.maps["amplitude_surface"])),
             ("residual RMS (linear)", powder.residual_rms)]
    for ax, (title, img) in zip(axes[0], shown):
        im = ax.imshow(img)
        if img.ndim == 2:
            fig.colorbar(im, ax=ax, fraction=0.046)
        ax.set_title(title, fontsize=9)
    enc = {"photo": truth[lowest], **{n: encode(p[lowest], cap.encoding)
                                      for n, p in predictions.items()}}
    for ax, (title, img) in zip(axes[1], list(enc.items())[:4]):
        ax.imshow(np.clip(img / max(float(np.percentile(truth[lowest], 99.5)), 1e-6), 0, 1))
        ax.set_title(f"{title}, held-out light {int(idx[lowest])} "
                     f"(elevation {np.degrees(np.arcsin(d[idx[lowest], 2])):.0f} deg)",
                     fontsize=8)
    vmax = float(np.nanpercentile(np.stack(list(errors.values())), 99))
    for ax, (name, emap) in zip(axes[2], errors.items()):
        im = ax.imshow(emap, vmin=0, vmax=vmax, cmap="magma")
        ax.set_title(f"{name}: RMSE {float(np.sqrt(np.nanmean(emap ** 2))):.2f} (8-bit)",
                     fontsize=9)
        fig.colorbar(im, ax=ax, fraction=0.046)
    for ax in axes.ravel():
        ax.set_xticks([])
        ax.set_yticks([])
    fig.suptitle(f"{label}: powder maps (fit-maps defaults, {powder.n_parameters} numbers per "
                 f"pixel, {seconds:.0f} s) and the grazing protocol ({len(idx)} lowest lights "
                 "held out)", fontsize=10)
    args.out.mkdir(parents=True, exist_ok=True)
    name = f"rti_{label.lower()}"
    fig.savefig(args.out / f"{name}.png", dpi=80)
    summary = {"capture": label, "held_out": idx.tolist(), "fit_seconds": seconds,
               "rmse_8bit": {n: float(np.sqrt(np.nanmean(e ** 2))) for n, e in errors.items()}}
    (args.out / f"{name}.json").write_text(json.dumps(summary, indent=1))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
