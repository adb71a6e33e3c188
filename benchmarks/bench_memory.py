"""Peak resident memory of a render and a fit.

Each job runs in a fresh Python process, which reports its peak resident set size
(``ru_maxrss``) at the end; ``baseline`` (import, set the variant, load one powder BSDF) is
what every job pays before its own work.
Prints a table, writes benchmarks/results/memory.json and memory.png.
Run:  python benchmarks/bench_memory.py [--quick]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import time
from pathlib import Path

from _common import arg_parser, barh_figure, print_table, save, use_variant

ROOT = Path(__file__).resolve().parents[1]


def job(name: str, quick: bool) -> dict:
    """Run in the child process: do the work, return what was done."""
    import resource

    import drjit as dr
    import mitsuba as mi

    def prepare(variant: str) -> None:
        use_variant(variant)
        mi.load_dict({"type": "powder"})

    info: dict = {}
    if name.startswith("baseline"):
        prepare(name.split(":")[1])
    elif name.startswith("render_showcase"):
        variant = name.split(":")[1]
        prepare(variant)
        res, spp = ((96, 30), 4) if quick else ((960, 300), 64)
        scene = mi.load_file(str(ROOT / "scenes" / "showcase.xml"), res_x=str(res[0]),
                             res_y=str(res[1]))
        img = mi.render(scene, spp=spp)
        dr.eval(img)
        dr.sync_thread()
        info = {"what": f"showcase {res[0]}x{res[1]}, {spp} spp"}
    elif name == "render_gonio":
        prepare("llvm_ad_rgb")
        from mitsuba_powder.fitting.protocols import protocol_geometries
        from mitsuba_powder.rendering.gonio import render_gonio

        ti, to, ph = protocol_geometries("backscatter" if quick else "shadows,backscatter")
        spp = 4 if quick else 64
        render_gonio({"albedo": 0.8}, ti, to, ph, spp=spp)
        info = {"what": f"render-gonio, {len(ti)} geometries, 16x16 px, {spp} spp"}
    elif name == "fit":
        prepare("llvm_ad_mono")
        from mitsuba_powder.fitting.fit import fit
        from mitsuba_powder.io.measurements import load_measurements

        data = load_measurements(ROOT / "measurements" / "ptfe_germer2017.csv")
        data = data.subset(data.wavelength == 351.0)
        starts = 4 if quick else 64  # 64: fit()'s default
        fit(data, ["amplitude_volume", "g", "extinction", "albedo", "amplitude_surface",
                   "correlation_length"], {"eta": 1.35, "k": 0.0}, starts=starts)
        info = {"what": f"fit of PTFE at 351 nm, {len(data)} measurements, {starts} starts"}
    else:
        raise ValueError(f"job {name!r} is not known")
    info["peak_rss_mib"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0
    return info


def main() -> None:
    parser = arg_parser(__doc__)
    parser.add_argument("--job", default=None, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.job:
        print(json.dumps(job(args.job, args.quick)))
        return
    jobs = [("baseline:llvm_ad_rgb", "baseline:llvm_ad_rgb"),
            ("render_showcase:llvm_ad_rgb", "baseline:llvm_ad_rgb"),
            ("baseline:llvm_ad_spectral", "baseline:llvm_ad_spectral"),
            ("render_showcase:llvm_ad_spectral", "baseline:llvm_ad_spectral"),
            ("render_gonio", "baseline:llvm_ad_rgb"),
            ("baseline:llvm_ad_mono", "baseline:llvm_ad_mono"),
            ("fit", "baseline:llvm_ad_mono")]
    rows, base = [], {}
    for name, baseline in jobs:
        t = time.perf_counter()
        cmd = [sys.executable, __file__, "--job", name] + (["--quick"] if args.quick else [])
        proc = subprocess.run(cmd, capture_output=True, text=True, cwd=str(ROOT))
        if proc.returncode != 0:
            raise RuntimeError(f"job {name} failed:\n{proc.stderr}")
        # the job's JSON line, among Mitsuba's log lines and colour codes (a reset code may
        # follow it at exit)
        line = next((t for t in reversed(proc.stdout.splitlines()) if "{" in t), None)
        if line is None:
            raise RuntimeError(f"job {name} printed no result:\n{proc.stdout[-2000:]}")
        info = json.loads(line[line.index("{"):])
        if name.startswith("baseline"):
            base[name] = info["peak_rss_mib"]
        rows.append({"job": name, "what": info.get("what", "import + one powder BSDF"),
                     "peak_rss_mib": info["peak_rss_mib"],
                     "over_baseline_mib": info["peak_rss_mib"] - base[baseline],
                     "seconds": time.perf_counter() - t})
    print_table(rows, [("job", "job", "s"), ("what", "what", "s"),
                       ("peak_rss_mib", "peak RSS MiB", ".0f"),
                       ("over_baseline_mib", "over baseline MiB", ".0f"),
                       ("seconds", "wall s", ".1f")])
    save(args.out, "memory", rows, args.quick)
    barh_figure(args.out / "memory.png", [r["job"] for r in rows],
                [r["peak_rss_mib"] for r in rows], "tab:gray", "peak resident memory, MiB",
                figsize=(7, 3))

if __name__ == "__main__":
    main()
