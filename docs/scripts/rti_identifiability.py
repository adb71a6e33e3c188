"""What an RTI dome determines: Cramer-Rao bounds of per-pixel powder properties.

For each region of ``rti.SYNTHETIC_GRAIN_REGIONS`` (hematite grain radius, A_v and
extinction differ; g and the surface lobe held), the 1-sigma bound of each free variable of one
pixel is ``sqrt(diag((J^T J)^-1))`` with J the Jacobian of the pixel's 3 x K values (central
differences of ``rti.render_capture``, in log radius, log A_v, log extinction and the two
normal slopes) divided by the noise (1 % of full scale, the brightest noise-free value 0.9).
Two light sets of 40: the 10-80 degree dome, and the same with 8 lights at 82-88 degrees
(2-8 degrees from the camera; ``synthetic_capture(near_camera=8)``). Prints a Markdown table.

    python docs/scripts/rti_identifiability.py [--tilt DEG] [--json OUT.json]
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import numpy as np

from mitsuba_powder import rti as rf

FREE = ("radius", "amplitude_volume", "extinction")
HELD = ("g", "amplitude_surface", "correlation_length")


def light_sets() -> dict[str, np.ndarray]:
    """The two light sets compared (40 lights each)."""
    return {"dome 10-80 degrees": rf.dome_directions(40),
            "32 on the dome + 8 at 82-88 degrees": np.concatenate(
                [rf.dome_directions(32), rf.dome_directions(8, 82.0, 88.0, seed=1)])}


def bounds(directions: np.ndarray, tilt_deg: float = 0.0, noise: float = 0.01,
           step: float = 1e-4) -> np.ndarray:
    """(regions, 3) relative 1-sigma bounds (fractions) of radius, A_v and extinction of one
    pixel per region, its normal tilted by ``tilt_deg`` towards +x (also free)."""
    regions = rf.SYNTHETIC_GRAIN_REGIONS
    p = len(regions)
    theta = np.log([[r[n] for n in FREE] for r in regions])          # (P, 3)
    t = math.radians(tilt_deg)
    slopes = np.tile([math.tan(t), 0.0], (p, 1))

    def render(th: np.ndarray, sl: np.ndarray, gain: float = 1.0) -> np.ndarray:
        n = np.concatenate([sl, np.ones((p, 1))], axis=1)
        n /= np.linalg.norm(n, axis=1, keepdims=True)
        maps = {"normal": n[None]}
        maps.update({name: np.exp(th[:, j])[None] for j, name in enumerate(FREE)})
        maps.update({name: np.array([[r[name] for r in regions]]) for name in HELD})
        return rf.render_capture(maps, directions, gains=np.full(len(directions), gain))

    gain = 0.9 / float(np.max(render(theta, slopes)))
    columns = []
    for j in range(2):
        e = np.zeros_like(slopes)
        e[:, j] = step
        columns.append((render(theta, slopes + e, gain) - render(theta, slopes - e, gain))
                       / (2 * step))
    for j in range(len(FREE)):
        e = np.zeros_like(theta)
        e[:, j] = step
        columns.append((render(theta + e, slopes, gain) - render(theta - e, slopes, gain))
                       / (2 * step))
    out = np.zeros((p, len(FREE)))
    for i in range(p):
        jac = np.stack([c[:, 0, i, :].ravel() for c in columns], axis=1) / noise
        cov = np.linalg.inv(jac.T @ jac)
        out[i] = np.sqrt(np.diag(cov))[2:]   # log-parameter sigma ~ relative sigma
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--tilt", type=float, default=0.0, help="normal tilt, degrees")
    parser.add_argument("--json", type=Path, help="also write the bounds here")
    args = parser.parse_args()
    results = {}
    print(f"Per-pixel 1-sigma (%), 1 % noise, normal tilted {args.tilt:g} degrees, "
          f"{', '.join(FREE)} and the normal free\n")
    print("| lights | region | radius um | A_v | extinction 1/um | sigma radius | sigma A_v "
          "| sigma extinction |")
    print("|---|---|---|---|---|---|---|---|")
    for name, d in light_sets().items():
        b = bounds(d, args.tilt)
        results[name] = b.tolist()
        for i, r in enumerate(rf.SYNTHETIC_GRAIN_REGIONS):
            print(f"| {name} | {i} | {r['radius']:g} | {r['amplitude_volume']:g} | "
                  f"{r['extinction']:g} | " + " | ".join(f"{100 * v:.1f}" for v in b[i]) + " |")
    if args.json:
        args.json.write_text(json.dumps({"tilt_deg": args.tilt, "free": FREE,
                                         "bounds": results}, indent=1))


if __name__ == "__main__":
    main()
