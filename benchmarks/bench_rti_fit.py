"""Benchmark of ``mitsuba-powder fit-maps`` on uncalibrated SYNTHETIC RTI captures: time, peak
memory and accuracy against pixels and lights, the Dr.Jit solver beside the NumPy reference.

The capture is issue 35's: four regions of known albedo (``rti.SYNTHETIC_REGIONS``),
``amplitude_surface`` 2e-4 and ``correlation_length`` 0.5 um everywhere, the plugin's
``amplitude_volume``, ``g`` and ``extinction`` (what the fit holds), the relief, lights at
10-80 degrees, noise 0.005, scaled by an exposure of 1.52, written as linear float EXR images
and a ``dirs.lp`` (by another process, into a temporary folder). Each fit is the command a user
runs, ``fit-maps dirs.lp --out maps --encoding linear`` with its defaults, in a process of its
own: it is told neither the exposure nor the gains (it finds the exposure and the free set
itself). Reported: the command's wall time (reading the images and writing the maps
included), its peak resident memory (``fit.json``'s ``peak_memory_mib``), the exposure it
found, the largest error of the region medians of the albedo (any channel) and
``amplitude_surface``, the normals' median error, the residual RMS over the noise, and the
rounds stopped by the iteration cap. Two configurations:

* ``drjit``: the defaults (the Dr.Jit per-pixel solver, pixels in blocks within the default
  working memory);
* ``numpy``: ``--solver numpy``, the reference solver. Run where it finishes in reasonable time
  (``--numpy-max`` pixels, default 256 x 256).

A second table times the batched damped solve of the per-pixel systems, 10^5 of them (2000
with ``--quick``) with 7 and 10 variables: NumPy's ``linalg.solve`` (the reference solver's
``optimise._solve_damped``) against the Dr.Jit engine's unrolled Cholesky factorisation
(``engine._damped_step``), best of three, and their largest relative difference.

Prints the tables and writes ``benchmarks/results/rti_fit.json`` and ``rti_fit.png``.

    python benchmarks/bench_rti_fit.py [--quick] [--full] [--variant cuda_ad_rgb]

Default: 64^2, 128^2, 256^2 at 40 lights, and 16, 40, 100 lights at 128^2. ``--full`` adds
512^2 x 40 and the issue's 1024^2 x 50 lights. ``--quick`` (CI): 24^2 x 16 lights.
"""

from __future__ import annotations

import json
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import arg_parser, pyplot, save, save_figure

NOISE = 0.005
EXPOSURE = 1.52
SURFACE = 2e-4


def _render(folder: Path, size: int, lights: int, variant: str) -> None:
    """Render issue 35's uncalibrated SYNTHETIC capture (module docstring) into ``folder``:
    ``dirs.lp``, ``light<k>.exr`` and the truth (``truth.npz``, which the fit never reads)."""
    from mitsuba_powder import rti as rf
    from mitsuba_powder.rti.forward import render_capture

    maps, region = rf.synthetic_maps(size, size)
    for name in ("amplitude_volume", "g", "extinction"):
        maps.pop(name)
    maps["amplitude_surface"][:] = SURFACE
    maps["correlation_length"][:] = 0.5
    d = rf.dome_directions(lights)
    clean = render_capture(maps, d, np.full(lights, EXPOSURE), variant)
    images = (clean + np.random.default_rng(1).normal(0.0, NOISE, clean.shape)).astype(
        np.float32)
    del clean
    names = [f"light{k:02d}.exr" for k in range(lights)]
    rf.write_lp(folder / "dirs.lp", names, d)
    like = rf.Capture(images=images, directions=d, names=names, encoding="linear",
                      file_format="exr", bit_depth=32)
    rf.write_images(like, images, names, folder)
    np.savez(folder / "truth.npz", region=region, normal=maps["normal"],
             albedo=maps["albedo"])


def _fit(folder: Path, config: str) -> dict:
    """``fit-maps`` of the capture in ``folder`` with ``config`` (drjit: the defaults; numpy:
    ``--solver numpy``) as a user runs it, in a process of its own (the command's default
    variant); its accuracy against the truth."""
    from mitsuba_powder.rti.maps import read_maps

    out = folder / f"maps_{config}"
    command = [sys.executable, "-m", "mitsuba_powder.cli", "fit-maps", str(folder / "dirs.lp"),
               "--out", str(out), "--encoding", "linear"]
    if config == "numpy":
        command += ["--solver", "numpy"]
    t0 = time.perf_counter()
    subprocess.run(command, check=True, capture_output=True, text=True)
    seconds = time.perf_counter() - t0
    res, info = read_maps(out)
    with np.load(folder / "truth.npz") as f:
        region, normal, albedo = f["region"], f["normal"], f["albedo"]
    err = np.degrees(np.arccos(np.clip(np.sum(res.normals * normal, -1), -1.0, 1.0)))
    alb, surf = [], []
    for r in range(4):
        sel = region == r
        alb.append(np.max(np.abs(np.median(res.albedo[sel], axis=0) / albedo[sel][0] - 1)))
        if "amplitude_surface" in res.maps:
            surf.append(abs(np.median(res.maps["amplitude_surface"][sel]) / SURFACE - 1))
    fit = info["fit"]
    return {"fit_s": seconds, "peak_rss_mib": fit["peak_memory_mib"],
            "fit_variant": info["variant"], "blocks": fit["blocks"], "chunks": fit["chunks"],
            "exposure": res.exposure, "exposure_sigma": fit["exposure"].get("sigma"),
            "free": res.free, "albedo_error_max": float(max(alb)),
            "surface_error_max": float(max(surf)) if surf else None,
            "normal_error_median_deg": float(np.median(err)),
            "residual_rms_over_noise": float(np.sqrt(np.nanmean(res.residual_rms**2)) / NOISE),
            "rounds_at_cap": fit.get("rounds_at_cap"),
            "pixels_at_cap": fit.get("pixels_at_cap_last_round")}


def solve_timings(systems: int) -> list[dict]:
    """Best-of-three times (ms) of ``systems`` damped solves, NumPy against Dr.Jit."""
    import drjit as dr
    import mitsuba as mi

    from mitsuba_powder.fitting.optimise import _solve_damped
    from mitsuba_powder.rti.engine import _damped_step
    from mitsuba_powder.variants import use_variant

    rows = []
    rng = np.random.default_rng(0)
    for n in (7, 10):
        m = rng.normal(size=(systems, 3 * n, n))
        a = np.einsum("pki,pkj->pij", m, m)
        g = rng.normal(size=(systems, n))
        lam = np.full(systems, 1e-3)
        times = {"numpy": [], "drjit": []}
        with use_variant("llvm_ad_rgb"):
            tri = [mi.Float64(np.ascontiguousarray(a[:, i, j])) for i in range(n)
                   for j in range(i + 1)]
            rhs = [mi.Float64(np.ascontiguousarray(g[:, i])) for i in range(n)]
            damping = mi.Float64(lam)
            dr.eval(tri, rhs, damping)
            for _ in range(3):
                t0 = time.perf_counter()
                ref = _solve_damped(a, g, lam, np.ones(n, dtype=bool))
                times["numpy"].append(time.perf_counter() - t0)
                t0 = time.perf_counter()
                step = _damped_step(tri, rhs, damping)
                dr.eval(step)
                dr.sync_thread()  # (launches are asynchronous)
                times["drjit"].append(time.perf_counter() - t0)
            got = np.stack([np.array(v) for v in step], axis=1)
        rows.append({"systems": systems, "variables": n,
                     "numpy_ms": 1e3 * min(times["numpy"]), "drjit_ms": 1e3 * min(times["drjit"]),
                     "max_relative_difference": float(np.max(np.abs(got - ref))
                                                      / np.max(np.abs(ref)))})
    return rows


def _print_solve(rows: list[dict]) -> list[dict]:
    """Print the damped-solve table; return its rows."""
    print(f"\n{'systems':>8} {'variables':>9} {'numpy ms':>9} {'drjit ms':>9} {'max rel diff':>12}")
    for r in rows:
        print(f"{r['systems']:8d} {r['variables']:9d} {r['numpy_ms']:9.1f} {r['drjit_ms']:9.1f} "
              f"{r['max_relative_difference']:12.1e}")
    return rows


def _solve_table(out: Path, quick: bool) -> None:
    """Time the damped solves and put them into ``out/rti_fit.json`` (created if absent)."""
    solve = _print_solve(solve_timings(2000 if quick else 100_000))
    path = out / "rti_fit.json"
    data = json.loads(path.read_text()) if path.exists() else {"meta": {}, "rows": []}
    data["meta"]["solve"] = solve
    out.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(data, indent=1))
    print(f"wrote {path}")


def _child(args: list[str]) -> dict:
    """Run this script with ``args`` in a new process and return the JSON it prints last."""
    out = subprocess.run([sys.executable, __file__, *args], check=True, capture_output=True,
                         text=True)
    return json.loads(out.stdout.strip().splitlines()[-1])


def _cases(quick: bool, full: bool) -> list[tuple[int, int]]:
    """(size, lights) of the run."""
    if quick:
        return [(24, 50)]
    cases = [(64, 50), (128, 50), (256, 50), (128, 16), (128, 100)]
    return cases + ([(512, 50), (1024, 50)] if full else [])


def _figure(path: Path, rows: list[dict]) -> None:
    """Fit time against pixels (at 40-50 lights) and against lights (at 128^2)."""
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(9, 3.5))
    for config, color in (("drjit", "tab:blue"), ("numpy", "tab:orange")):
        mine = [r for r in rows if r["config"] == config]
        by_px = sorted((r["pixels"], r["fit_s"]) for r in mine if r["lights"] == 50)
        by_k = sorted((r["lights"], r["fit_s"]) for r in mine if r["size"] == 128)
        if by_px:
            axes[0].loglog(*zip(*by_px), "o-", color=color, label=config)
        if by_k:
            axes[1].plot(*zip(*by_k), "o-", color=color, label=config)
    axes[0].set_xlabel("pixels (50 lights)")
    axes[1].set_xlabel("lights (128 x 128 pixels)")
    for ax in axes:
        ax.set_ylabel("fit time (s)")
        if ax.lines:  # (a --quick run has no row at 40-50 lights or at 128^2)
            ax.legend(fontsize=7)
    save_figure(fig, path)


def main() -> None:
    if len(sys.argv) > 1 and sys.argv[1] in ("--render-one", "--fit-one"):
        if sys.argv[1] == "--render-one":
            _render(Path(sys.argv[2]), int(sys.argv[3]), int(sys.argv[4]), sys.argv[5])
            print(json.dumps({}))
        else:
            print(json.dumps(_fit(Path(sys.argv[2]), sys.argv[3])))
        return
    ap = arg_parser(__doc__)
    ap.add_argument("--full", action="store_true", help="also 512^2 x 50 and 1024^2 x 50")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--numpy-max", type=int, default=256 * 256,
                    help="pixels up to which the NumPy reference runs too")
    ap.add_argument("--solve-only", action="store_true",
                    help="only time the damped solves, updating rti_fit.json in --out")
    args = ap.parse_args()
    if args.solve_only:
        _solve_table(args.out, args.quick)
        return
    rows = []
    print(f"{'capture':>18} {'config':>6} {'fit s':>8} {'peak MiB':>9} {'exposure':>8} "
          f"{'albedo err':>10} {'A_s err':>8} {'normal err':>10} {'rms/noise':>9} "
          f"{'capped':>6}", flush=True)
    with tempfile.TemporaryDirectory() as tmp:
        for size, lights in _cases(args.quick, args.full):
            folder = Path(tmp) / f"capture_{size}_{lights}"
            folder.mkdir()
            _child(["--render-one", str(folder), str(size), str(lights), args.variant])
            for config in ("drjit", "numpy"):
                if config == "numpy" and size * size > args.numpy_max:
                    continue
                row = {"label": "SYNTHETIC, uncalibrated", "size": size, "lights": lights,
                       "pixels": size * size, "variant": args.variant, "config": config,
                       "true_exposure": EXPOSURE, "noise": NOISE,
                       **_child(["--fit-one", str(folder), config])}
                rows.append(row)
                surf = row["surface_error_max"]
                print(f"{size:>5} x {size:<5} x {lights:<3} {config:>6} {row['fit_s']:8.1f} "
                      f"{row['peak_rss_mib']:9.0f} {row['exposure']:8.4f} "
                      f"{100 * row['albedo_error_max']:9.2f}% "
                      + (f"{100 * surf:7.1f}%" if surf is not None else f"{'-':>8}")
                      + f" {row['normal_error_median_deg']:9.3f}d "
                      f"{row['residual_rms_over_noise']:9.3f} {row['rounds_at_cap']:6d}",
                      flush=True)
            shutil.rmtree(folder)
    solve = _print_solve(solve_timings(2000 if args.quick else 100_000))
    out = save(args.out, "rti_fit", rows, args.quick, solve=solve)
    _figure(args.out / "rti_fit.png", rows)
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
