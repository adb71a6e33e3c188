"""Benchmark of the relief of a fit (issue 36): the height field integrated from a normal
map, its horizon map, and a relight rendered by Mitsuba (the relief's mesh path traced with
the powder BSDF), at one size.

    python benchmarks/bench_relief.py [--quick] [--size 1024] [--spp 4]
        [--variant llvm_ad_rgb] [--out benchmarks/results]

The surface is SYNTHETIC: Gaussian bumps of 2-5 % of the image's width (their analytic
normals), uniform powder maps (the first region of ``rti.SYNTHETIC_REGIONS``). Timed, each
once: :func:`~mitsuba_powder.rti.relief.integrate_normals` (weights from a uniform residual),
:func:`~mitsuba_powder.rti.relief.horizon_map` (32 azimuths), the visibility of one light at
every pixel, and :func:`~mitsuba_powder.rti.rendered.render_result` of one light at 20
degrees (maps, relief.ply and scene.xml written, loaded and path traced at ``--spp``).
Prints a table and writes ``relief.json`` and ``relief.png`` (the times as bars) into
``--out``; ``--quick``: 48 x 48 px.
"""

from __future__ import annotations

import time

import numpy as np

from _common import arg_parser, barh_figure, print_table, save
from mitsuba_powder.rti import MapsResult
from mitsuba_powder.rti.relief import (
    Relief,
    horizon_map,
    integrate_normals,
    residual_weights,
    visibility,
)
from mitsuba_powder.rti.rendered import render_result
from mitsuba_powder.rti.synthetic import SYNTHETIC_REGIONS


def surface(n: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """Heights (pixels) and unit normals of random Gaussian bumps on an n x n image."""
    rng = np.random.default_rng(seed)
    r, c = np.mgrid[0:n, 0:n].astype(np.float64)
    z, zr, zc = (np.zeros((n, n)) for _ in range(3))
    for _ in range(20):
        r0, c0 = rng.uniform(0, n, 2)
        s = rng.uniform(0.02, 0.05) * n
        g = rng.uniform(0.5, 1.0) * s * np.exp(-((r - r0) ** 2 + (c - c0) ** 2) / (2 * s * s))
        z += g
        zr -= g * (r - r0) / s**2
        zc -= g * (c - c0) / s**2
    nrm = np.stack([-zc, zr, np.ones_like(z)], axis=-1)
    return z, (nrm / np.linalg.norm(nrm, axis=-1, keepdims=True)).astype(np.float32)


COLUMNS = [("step", "step", "s"), ("seconds", "time s", ".1f")]


def main() -> None:
    ap = arg_parser(__doc__)
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--spp", type=int, default=4)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args()
    n = 48 if args.quick else args.size
    _, normals = surface(n)
    mask = np.ones((n, n), bool)
    residual = np.full((n, n), 0.01, np.float32)
    times = {}
    t = time.perf_counter()
    height = integrate_normals(normals, residual_weights(residual, mask))
    times["height field"] = time.perf_counter() - t
    t = time.perf_counter()
    horizon = horizon_map(height)
    times["horizon map (32 azimuths)"] = time.perf_counter() - t
    light = np.array([[np.cos(np.radians(20)), 0.0, np.sin(np.radians(20))]])
    t = time.perf_counter()
    vis = visibility(horizon, light)
    times["visibility of one light"] = time.perf_counter() - t
    region = SYNTHETIC_REGIONS[0]
    props = {k: np.full((n, n), v, np.float32) for k, v in region.items()
             if k in ("amplitude_surface", "correlation_length")}
    result = MapsResult(normals=normals, albedo=np.broadcast_to(
        np.asarray(region["albedo"], np.float32), (n, n, 3)).copy(), maps=props,
        settings={k: v for k, v in region.items() if k in ("amplitude_volume", "g",
                                                           "extinction")},
        residual_rms=residual, gains=np.ones(1), used=np.ones((1, n, n), bool),
        free=["albedo", *props], mask=mask, relief=Relief(height, horizon))
    t = time.perf_counter()
    img = render_result(result, light, spp=args.spp, variant=args.variant)
    times[f"rendered relight, 1 light, {args.spp} spp ({args.variant})"] = \
        time.perf_counter() - t
    print(f"relief of a {n} x {n} px SYNTHETIC surface: heights {np.ptp(height):.1f} px, "
          f"{100 * float(np.mean(vis < 0.5)):.1f} % of the pixels in shadow at 20 degrees, "
          f"rendered mean {float(img.mean()):.4g}")
    rows = [{"step": k, "seconds": v} for k, v in times.items()]
    print_table(rows, COLUMNS)
    save(args.out, "relief", rows, args.quick, size=n, spp=args.spp, variant=args.variant)
    barh_figure(args.out / "relief.png", list(times), list(times.values()), "C0", "seconds")


if __name__ == "__main__":
    main()
