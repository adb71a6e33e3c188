"""Benchmark of :func:`mitsuba_powder.rti.fit_maps` on SYNTHETIC RTI captures.

Times the per-pixel powder fit (default free set, per-light gains fitted) and records the
process's peak resident memory, for a 256 x 256 capture of 40 lights and, with ``--full``, a
1024 x 1024 capture of 50 lights, in ``llvm_ad_rgb`` (or ``--variant``). Prints a table and
writes ``benchmarks/results/rti_fit.json``.

    python benchmarks/bench_rti_fit.py [--quick] [--full] [--size 256] [--lights 40]

``--quick`` (CI): a 24 x 24 capture of 16 lights, one round.
"""

from __future__ import annotations

import json
import os
import platform
import resource
import time

import numpy as np

from _common import arg_parser, barh_figure
from mitsuba_powder import rti as rf


def _peak_rss_mb() -> float:
    """Peak resident memory of this process, MiB (Linux ru_maxrss is in KiB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def run_case(size: int, lights: int, variant: str, rounds: int) -> dict:
    """Render a SYNTHETIC capture of ``size`` x ``size`` pixels and ``lights`` lights, fit it,
    and return the timings (s), peak memory (MiB) and accuracy."""
    t0 = time.perf_counter()
    cap = rf.synthetic_capture(size, size, lights, noise=0.01, variant=variant)
    t_render = time.perf_counter() - t0
    fixed = {n: cap["maps"][n] for n in ("amplitude_volume", "g", "extinction")}
    t0 = time.perf_counter()
    res = rf.fit_maps(cap["images"], cap["directions"], fixed=fixed, gains="fit",
                      initial_gains=cap["gains"], rounds=rounds, variant=variant,
                      progress=lambda line: print("   ", line, flush=True))
    t_fit = time.perf_counter() - t0
    err = np.degrees(np.arccos(np.clip(np.sum(res.normals * cap["maps"]["normal"], -1),
                                       -1.0, 1.0)))
    return {"label": "SYNTHETIC", "size": size, "lights": lights, "variant": variant,
            "pixels": size * size, "rounds": rounds, "free": res.free,
            "render_s": t_render, "fit_s": t_fit, "peak_rss_mib": _peak_rss_mb(),
            "chunks": res.fit_settings["chunks"],
            "normal_error_median_deg": float(np.median(err)),
            "residual_rms_over_noise": float(np.sqrt(np.mean(res.residual_rms**2)) / 0.01)}


def main() -> None:
    ap = arg_parser(__doc__)
    ap.add_argument("--full", action="store_true", help="also 1024 x 1024 x 50 lights")
    ap.add_argument("--size", type=int, default=256)
    ap.add_argument("--lights", type=int, default=40)
    ap.add_argument("--rounds", type=int, default=3)
    ap.add_argument("--variant", default="llvm_ad_rgb")
    args = ap.parse_args()
    if args.quick:
        args.size, args.lights, args.rounds = 24, 16, 1
    cases = [(args.size, args.lights)] + ([(1024, 50)] if args.full else [])
    rows = []
    for size, lights in cases:
        print(f"{size} x {size}, {lights} lights ({args.variant}):", flush=True)
        rows.append(run_case(size, lights, args.variant, args.rounds))
    print(f"{'capture':>18} {'fit s':>8} {'peak MiB':>9} {'normal err':>10} {'rms/noise':>9}"
          "  (fit s, peak MiB)")
    for r in rows:
        print(f"{r['size']:>5} x {r['size']:<5} x {r['lights']:<3} {r['fit_s']:8.1f} "
              f"{r['peak_rss_mib']:9.0f} {r['normal_error_median_deg']:9.2f}d "
              f"{r['residual_rms_over_noise']:9.3f}")
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {"quick": args.quick, "cpu": platform.processor() or platform.machine(),
            "cpus": os.cpu_count(), "date": time.strftime("%Y-%m-%d")}
    path = args.out / "rti_fit.json"
    path.write_text(json.dumps({"meta": meta, "rows": rows}, indent=1))
    barh_figure(args.out / "rti_fit.png",
                [f"{r['size']}x{r['size']}x{r['lights']} {r['variant']}" for r in rows],
                [r["fit_s"] for r in rows], ["tab:blue"] * len(rows), "fit time (s)")
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
