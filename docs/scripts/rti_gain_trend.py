"""How much of the per-light gains' trend in elevation a near-field light model explains.

Fits the powder maps of a capture (gains fitted, exposure 1, the default free set: the
defaults before issue 35) twice, with distant
lights and with the lights at ``--light-distance`` image widths, and compares the fitted gains:
their spread (standard deviation of ``ln g``), the slope of ``ln g`` against ``sin(elevation)``
(least squares over the lights), and the mean gain per elevation ring. The near-field share of
the trend is ``1 - slope(near) / slope(far)``. Prints Markdown tables.

    python docs/scripts/rti_gain_trend.py CAPTURE.lp --light-distance 13.69 \
        [--encoding linear] [--rings 4] [--json OUT.json]

The capture's images are read from the paths its ``.lp`` file names (not in this repository
for RealRTI: see docs/rti.md).
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from mitsuba_powder import rti as rf


def trend(directions: np.ndarray, gains: np.ndarray, min_elevation: float) -> dict:
    """Spread of ``ln g`` and its least-squares slope (per unit of sin(elevation)), over all
    lights and over those above ``min_elevation`` degrees (where cast shadows, which the gains
    of the lowest lights absorb, matter less)."""
    lz = directions[:, 2] / np.linalg.norm(directions, axis=1)
    lng = np.log(gains)
    high = lz > np.sin(np.radians(min_elevation))
    return {"spread": float(np.std(lng)), "slope": float(np.polyfit(lz, lng, 1)[0]),
            "spread_high": float(np.std(lng[high])),
            "slope_high": float(np.polyfit(lz[high], lng[high], 1)[0])}


def rings(directions: np.ndarray, gains: dict[str, np.ndarray], count: int) -> list[dict]:
    """Mean gain per elevation ring (quantiles of the lights' elevations) for each fit."""
    elev = np.degrees(np.arcsin(np.clip(directions[:, 2] / np.linalg.norm(directions, axis=1),
                                        -1.0, 1.0)))
    edges = np.quantile(elev, np.linspace(0.0, 1.0, count + 1))
    rows = []
    for i in range(count):
        sel = (elev >= edges[i]) & ((elev <= edges[i + 1]) if i == count - 1
                                    else (elev < edges[i + 1]))
        rows.append({"elevation": [float(elev[sel].min()), float(elev[sel].max())],
                     "lights": int(sel.sum()),
                     **{name: float(np.mean(g[sel])) for name, g in gains.items()}})
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("lp", type=Path)
    ap.add_argument("--light-distance", type=float, required=True,
                    help="r of the near-field fit, image widths")
    ap.add_argument("--encoding", default="linear", choices=("linear", "srgb"))
    ap.add_argument("--rings", type=int, default=4)
    ap.add_argument("--min-elevation", type=float, default=15.0,
                    help="degrees: the second slope is over the lights above it")
    ap.add_argument("--json", type=Path, default=None)
    args = ap.parse_args()
    cap = rf.load_capture(args.lp, encoding=args.encoding)
    gains, seconds = {}, {}
    for name, r in (("far", math.inf), ("near", args.light_distance)):
        # the gains fitted (their mean the exposure, 1) with the default free set: the fit
        # whose gains docs/rti.md measures (gains are held by default since issue 35)
        res = rf.fit_maps(cap.images, cap.directions, mask=cap.mask, light_distance=r,
                          gains="fit", exposure=1.0, free=rf.MAP_DEFAULT_FREE)
        gains[name], seconds[name] = res.gains, res.fit_settings["seconds"]
    stats = {n: trend(cap.directions, g, args.min_elevation) for n, g in gains.items()}
    share = {k: 1.0 - stats["near"][k] / stats["far"][k] for k in ("slope", "slope_high")}
    high = f"above {args.min_elevation:g} deg"
    print(f"{args.lp}: {len(cap.directions)} lights, r = {args.light_distance:g} image widths")
    print(f"\n| lights | spread of ln g | slope of ln g per sin(elevation) | spread, {high} | "
          f"slope, {high} | fit s |")
    print("|---|---:|---:|---:|---:|---:|")
    for n in gains:
        st = stats[n]
        print(f"| {n} | {st['spread']:.4f} | {st['slope']:+.4f} | {st['spread_high']:.4f} | "
              f"{st['slope_high']:+.4f} | {seconds[n]:.0f} |")
    print(f"\nnear-field share of the slope: {share['slope']:.1%} (all lights), "
          f"{share['slope_high']:.1%} ({high})")
    table = rings(cap.directions, gains, args.rings)
    print("\n| elevation (deg) | lights | mean gain, far | mean gain, near |")
    print("|---|---:|---:|---:|")
    for row in table:
        lo, hi = row["elevation"]
        print(f"| {lo:.0f}-{hi:.0f} | {row['lights']} | {row['far']:.3f} | {row['near']:.3f} |")
    if args.json:
        args.json.write_text(json.dumps({
            "lp": str(args.lp), "light_distance": args.light_distance, "trend": stats,
            "near_share_of_slope": share, "rings": table, "seconds": seconds,
            "gains": {n: g.tolist() for n, g in gains.items()}}, indent=1))


if __name__ == "__main__":
    main()
