"""What eval cost / principled measures: the same ratio as bench_bsdf.py for batches of 2^16 to
2^22 direction pairs, against `principled` with its default grey base colour and with a
coloured one, in llvm_ad_rgb and llvm_ad_spectral.

bench_bsdf.py evaluates 2^22 pairs per call and writes the values to memory. The inputs
(wi, wo and, in spectral variants, four wavelengths per lane: 24-40 bytes) and the outputs
(one float per channel) then pass through main memory, not the caches. The default
`principled` is grey: its channels are one array, one float per lane, while the powder's
are three (RGB) or four (spectral). Where memory is the bottleneck, the ratio measures these
extra stores as much as the arithmetic; in small batches, which stay in the caches, it
measures the arithmetic. Inside a render, eval's values stay in registers. The coloured
`principled` (base colour 0.8, 0.5, 0.3) writes as many channels as the powder.

The "memory floor" is a kernel that reads the same inputs as the powder (wi, wo and the
wavelengths) and writes as many channels with one multiply-add each: what the batch costs
when only its memory traffic is paid. A kernel that overlaps its memory traffic with its
arithmetic costs about the larger of the two; one that cannot (docs/benchmarks.md, section 1)
costs about their sum. ``--threads 1`` shows it most plainly.

Powder configuration: bench_bsdf.py's (``albedo 0.8, extinction 1, amplitude_surface
1e-3``). Each batch size: the three BSDFs and the floor timed in turn within each of 21
repeats (after a warm-up call that compiles the kernels), the kernels' execution times
(Dr.Jit's kernel history); a cost is the median of the per-repeat ratios.

    python benchmarks/bench_eval_size.py [--quick] [--threads N]
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np
from registry import EVAL_SIZE_COLUMNS

from _common import (
    arg_parser,
    eval_calls,
    kernel_seconds,
    print_table,
    pyplot,
    random_pairs,
    save,
    save_figure,
    time_in_turn,
    use_variant,
)

POWDER = {"type": "powder", "albedo": 0.8, "extinction": 1.0, "amplitude_surface": 1e-3}
COLOURED = {"type": "principled", "base_color": {"type": "rgb", "value": [0.8, 0.5, 0.3]}}


def memory_floor(si, wo):
    """A function returning as many channels as the powder's eval, each one multiply-add of
    the same inputs (wi, wo and, in spectral variants, the wavelengths)."""
    a = dr.opaque(mi.Float, 0.5)

    def call():
        d = dr.dot(si.wi, wo)
        if mi.is_spectral:
            return mi.UnpolarizedSpectrum(*[dr.fma(si.wavelengths[c], a, d) for c in range(4)])
        return mi.Color3f(*[dr.fma(si.wi[c], a, d) for c in range(3)])

    return call


def measure(variant: str, sizes: list[int], repeat: int) -> list[dict]:
    """One row per batch size: the three eval times, the memory floor and the cost ratios."""
    use_variant(variant)
    ctx = mi.BSDFContext()
    bsdfs = {"powder": mi.load_dict(POWDER), "principled": mi.load_dict({"type": "principled"}),
             "coloured": mi.load_dict(COLOURED)}
    rows = []
    for n in sizes:
        si, wo = random_pairs(n, variant, seed=0)
        dr.eval(si, wo)
        calls = {**eval_calls(bsdfs, ctx, si, wo), "floor": memory_floor(si, wo)}
        t = time_in_turn(calls, repeat, clock=kernel_seconds)
        rows.append({"variant": variant, "pairs": n, "log2_pairs": int(np.log2(n)),
                     "powder_ms": 1e3 * float(np.median(t["powder"])),
                     "principled_ms": 1e3 * float(np.median(t["principled"])),
                     "coloured_ms": 1e3 * float(np.median(t["coloured"])),
                     "floor_ms": 1e3 * float(np.median(t["floor"])),
                     "cost_vs_principled": float(np.median(t["powder"] / t["principled"])),
                     "cost_vs_coloured": float(np.median(t["powder"] / t["coloured"]))})
    return rows


def main() -> None:
    parser = arg_parser(__doc__)
    parser.add_argument("--threads", type=int, default=None,
                        help="Dr.Jit's worker threads (default: its own, one per CPU)")
    args = parser.parse_args()
    if args.threads is not None:
        if not 1 <= args.threads <= 256:
            parser.error(f"--threads: {args.threads} is outside the valid range [1, 256]")
        dr.set_thread_count(args.threads)
    sizes, repeat = ([1 << 10, 1 << 12], 2) if args.quick else (
        [1 << 16, 1 << 18, 1 << 20, 1 << 22], 21)
    rows = []
    for variant in ("llvm_ad_rgb", "llvm_ad_spectral"):
        rows += measure(variant, sizes, repeat)
    print_table(rows, EVAL_SIZE_COLUMNS)
    save(args.out, "eval_size", rows, args.quick, repeats=repeat,
         threads=dr.thread_count())
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.5))
    for variant, colour in (("llvm_ad_rgb", "tab:blue"), ("llvm_ad_spectral", "tab:orange")):
        sel = [r for r in rows if r["variant"] == variant]
        x = [r["log2_pairs"] for r in sel]
        ax.plot(x, [r["cost_vs_principled"] for r in sel], "o-", color=colour,
                label=f"{variant} / principled")
        ax.plot(x, [r["cost_vs_coloured"] for r in sel], "s--", color=colour,
                label=f"{variant} / coloured principled")
    ax.set_xlabel("log2 direction pairs per call")
    ax.set_ylabel("powder eval cost")
    ax.legend(fontsize=7)
    save_figure(fig, args.out / "eval_size.png")


if __name__ == "__main__":
    main()
