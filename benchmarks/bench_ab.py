"""A/B of two builds of the powder plugin in one process: the installed one against a baseline
``powder.so`` (for example one built from an earlier commit), each configuration's eval timed
in turn with both builds and with `principled`, so that a change of machine load hits them
alike.

On a shared virtual machine the ratios of bench_bsdf.py vary by 10-20 % from one run to the
next. Two runs of it, one per build, then cannot resolve a change of 10 %, whereas the ratio
of two kernels timed in turn in the same process repeats to about 3 % (a control run of this
script at 2^22 pairs: medians 0.97-1.02, docs/benchmarks.md).
Times are the kernels' own execution times (Dr.Jit's kernel history), not wall-clock times;
with ``--cpu-time``, the processor time of each call on one Dr.Jit thread (tracing included),
which does not count the time other processes hold shared cores.
Without ``--baseline`` the installed plugin is compared with itself: a control whose ratios
should be 1 within that noise.

    python benchmarks/bench_ab.py --baseline /path/to/old/powder.so [--pairs 22] [--cpu-time]
        [--quick]

Build a baseline from an earlier commit, for the variants measured here, e.g.::

    git worktree add /tmp/base COMMIT && cmake -S /tmp/base -B /tmp/base/build -G Ninja \\
        -DPOWDER_VARIANTS=llvm_ad_rgb,llvm_ad_spectral && ninja -C /tmp/base/build powder
"""

from __future__ import annotations

import shutil
import tempfile
from pathlib import Path

import mitsuba as mi
import numpy as np
from registry import AB_COLUMNS

from _common import (
    arg_parser,
    barh_figure,
    cpu_seconds,
    eval_calls,
    kernel_seconds,
    print_table,
    random_pairs,
    save,
    time_in_turn,
    use_variant,
)

BASE = {"albedo": 0.8, "extinction": 1.0, "amplitude_surface": 1e-3}  # bench_bsdf.py's powder
#: (label, extra properties); None removes the property from BASE
CONFIGS = [
    ("all", {}),
    ("all, Gaussian lobe", {"specular": "gaussian"}),
    ("all, tau_o 1.5", {"tau_o": 1.5}),
    ("all, albedo 0.9", {"albedo": 0.9}),
    ("all, Mie albedo", {"albedo": None, "radius": 0.05}),
    ("single, Mie albedo", {"albedo": None, "radius": 0.05, "lobes": "single"}),
    # bench_bsdf.py's pigment mixture of four materials (issue 38)
    ("all, Mie 4 materials", {"albedo": None, "radius": 0.05, "radius2": 0.2, "fraction2": 0.2,
                              "material2": "calcite", "radius3": 1.0, "fraction3": 0.3,
                              "material3": "kaolinite", "radius4": 0.3, "fraction4": 0.1,
                              "material4": "magnetite"}),
    ("coherent", {"lobes": "coherent"}),
    ("surface", {"lobes": "surface"}),
]
BASELINE_NAME = "powder_baseline"


def props(plugin: str, extra: dict) -> dict:
    out = {"type": plugin, **BASE, **extra}
    return {k: v for k, v in out.items() if v is not None}


def measure(variant: str, folder: Path | None, n: int, repeat: int,
            clock=kernel_seconds) -> list[dict]:
    use_variant(variant)
    baseline = "powder"
    if folder is not None:
        mi.file_resolver().prepend(str(folder))
        baseline = BASELINE_NAME
    si, wo = random_pairs(n, variant, seed=4)
    ctx = mi.BSDFContext()
    bsdfs = {"principled": mi.load_dict({"type": "principled"})}
    for label, extra in CONFIGS:
        bsdfs["new " + label] = mi.load_dict(props("powder", extra))
        bsdfs["baseline " + label] = mi.load_dict(props(baseline, extra))
    t = time_in_turn(eval_calls(bsdfs, ctx, si, wo), repeat, clock=clock)
    rows = []
    for label, _ in CONFIGS:
        new, old = t["new " + label], t["baseline " + label]
        a = np.asarray(bsdfs["new " + label].eval(ctx, si, wo))
        b = np.asarray(bsdfs["baseline " + label].eval(ctx, si, wo))
        floor = 1e-9 * float(np.abs(b).max()) + 1e-30
        rows.append({"variant": variant, "configuration": label,
                     "baseline_vs_principled": float(np.median(old / t["principled"])),
                     "new_vs_principled": float(np.median(new / t["principled"])),
                     "new_vs_baseline": float(np.median(new / old)),
                     "new_vs_baseline_fastest": float(new.min() / old.min()),
                     "max_rel_difference": float(np.max(np.abs(a - b) /
                                                        np.maximum(np.abs(b), floor)))})
    return rows


def main() -> None:
    ap = arg_parser(__doc__)
    ap.add_argument("--baseline", type=Path, default=None,
                    help="powder.so of the build to compare with (default: the installed one)")
    ap.add_argument("--pairs", type=int, default=22,
                    help="log2 of the direction pairs, 10 to 24 (default 22)")
    ap.add_argument("--cpu-time", action="store_true",
                    help="processor time of one Dr.Jit thread instead of the kernels' times")
    args = ap.parse_args()
    if not 10 <= args.pairs <= 24:
        ap.error(f"--pairs: {args.pairs} is outside the valid range [10, 24] (log2 of the "
                 "direction pairs: 2^24 pairs take 1-2 GiB)")
    if args.baseline is not None and not args.baseline.is_file():
        ap.error(f"--baseline: no such file: {args.baseline}")
    n, repeat = (1 << 10, 2) if args.quick else (1 << args.pairs, 15)
    clock = kernel_seconds
    if args.cpu_time:
        import drjit as dr

        dr.set_thread_count(1)
        clock = cpu_seconds
    with tempfile.TemporaryDirectory() as tmp:
        folder = None
        if args.baseline is not None:
            folder = Path(tmp)
            (folder / "plugins").mkdir()
            shutil.copy(args.baseline, folder / "plugins" / f"{BASELINE_NAME}.so")
        rows = []
        for variant in ("llvm_ad_rgb", "llvm_ad_spectral"):
            rows += measure(variant, folder, n, repeat, clock)
    print_table(rows, AB_COLUMNS)
    save(args.out, "ab", rows, args.quick, pairs=n, repeats=repeat,
         baseline=str(args.baseline) if args.baseline else "installed (control)",
         clock="processor time, one thread" if args.cpu_time else "kernel execution time")
    barh_figure(args.out / "ab.png", [f"{r['variant'][8:]}: {r['configuration']}" for r in rows],
                [r["new_vs_baseline"] for r in rows], "tab:green", "eval time, new / baseline")


if __name__ == "__main__":
    main()
