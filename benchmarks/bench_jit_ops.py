"""What one operation costs in a Dr.Jit LLVM kernel on this host: the unit costs behind the
powder eval's profile (docs/benchmarks.md, section 1).

Each row times a kernel of 16 independent instances of one operation over N lanes (inputs
read from memory, the 16 results summed and written), minus the same kernel without the
operation, divided by 16: milliseconds per operation over N lanes, and its cost relative to a
fused multiply-add. The lookups index a table of 472 records at 4 random wavelengths per
lane as the spectral eval does (position on the 1 nm grid, floor, gather, linear
interpolation): one float per record gathered with `dr.gather(Float, ...)`, and packets of 2,
4 and 8 floats with `dr.gather(ArrayNf, ...)` (as the plugin's C++ `dr::gather<Packet>`);
their rows are per wavelength, i.e. the cost of one channel of a spectral lane. The row
"4 outputs" writes each wavelength's lookups to an output of its own, as the spectral eval
writes one value per wavelength (its base: the same kernel without the gathers). Timed in
turn within each of 15 repeats after a warm-up call that compiles every kernel; medians of
wall times, or with ``--cpu-time`` of the processor time of one Dr.Jit thread.

    python benchmarks/bench_jit_ops.py [--quick] [--cpu-time]
"""

from __future__ import annotations

import time
from collections.abc import Callable

import drjit as dr
import numpy as np
from drjit.llvm import Array2f, Array4f, ArrayXf, Float, UInt32

from _common import arg_parser, barh_figure, print_table, save

COUNT = 16  #: instances of the operation per kernel
RECORDS = 472  #: records of the lookup table (the 1 nm grid of 360-830 nm, plus one)


def arithmetic(op: Callable[[Float, Float], Float], a: Float, b: Float) -> Float:
    """The sum of COUNT independent results of ``op`` (distinct inputs: no sharing)."""
    total = Float(0)
    for i in range(COUNT):
        total += op(a * (1.0 + 0.01 * i), b)
    return total


def _node(lam: Float, i: int) -> tuple[Float, UInt32, Float]:
    """Round ``i``'s grid position ``t`` of a wavelength, its node and the weight of the next."""
    t = dr.clip(lam + 0.25 * i, 0.0, RECORDS - 2.001)
    i0 = UInt32(dr.floor(t))
    return t, i0, t - Float(i0)


def lookups(size: int, lam: list[Float], table: Float) -> Float:
    """COUNT // 4 rounds of 4 per-wavelength lookups of records of ``size`` floats (pairs of
    nodes, interpolated linearly); size 0: the same index arithmetic without a gather;
    size 1: records of one float, two gathers (node and next node)."""
    total = Float(0)
    for i in range(COUNT // 4):
        for c in range(4):
            t, i0, w = _node(lam[c], i)
            if size == 0:
                total += dr.lerp(t, 2.0 * t, w)
            elif size == 1:
                total += dr.lerp(dr.gather(Float, table, i0), dr.gather(Float, table, i0 + 1), w)
            else:
                v = (dr.gather(ArrayXf, table, i0, shape=(size, dr.width(i0))) if size == 8
                     else dr.gather(Array2f if size == 2 else Array4f, table, i0))
                for k in range(0, size, 2):
                    total += dr.lerp(v[k], v[k + 1], w)
    return total


def lookups_per_channel(size: int, lam: list[Float], table: Float) -> list[Float]:
    """As ``lookups`` (size 0 or 2), each wavelength's sum a separate output, as the spectral
    eval writes one value per wavelength."""
    totals = [Float(0) for _ in range(4)]
    for i in range(COUNT // 4):
        for c in range(4):
            t, i0, w = _node(lam[c], i)
            if size == 0:
                totals[c] += dr.lerp(t, 2.0 * t, w)
            else:
                v = dr.gather(Array2f, table, i0)
                totals[c] += dr.lerp(v[0], v[1], w)
    return totals


def measure(n: int, repeat: int, clock=None) -> list[dict]:
    rng = np.random.default_rng(0)
    a = Float(rng.uniform(0.5, 2.0, n).astype(np.float32))
    b = Float(rng.uniform(0.5, 2.0, n).astype(np.float32))
    lam = [Float(rng.uniform(0.0, RECORDS - 2, n).astype(np.float32)) for _ in range(4)]
    table = Float(rng.uniform(0.5, 2.0, RECORDS * 8).astype(np.float32))
    dr.eval(a, b, lam, table)
    dr.make_opaque(table)
    kernels: dict[str, Callable[[], Float]] = {
        "none (arithmetic)": lambda: arithmetic(lambda x, y: x, a, b),
        "fma": lambda: arithmetic(lambda x, y: dr.fma(x, y, y), a, b),
        "floor": lambda: arithmetic(lambda x, y: dr.floor(x * y), a, b),
        "division": lambda: arithmetic(lambda x, y: x / y, a, b),
        "sqrt": lambda: arithmetic(lambda x, y: dr.sqrt(x + y), a, b),
        "rsqrt": lambda: arithmetic(lambda x, y: dr.rsqrt(x + y), a, b),
        "exp": lambda: arithmetic(lambda x, y: dr.exp(-x * y), a, b),
        "none (lookup)": lambda: lookups(0, lam, table),
        "lookup, 2 gathers of 1 float": lambda: lookups(1, lam, table),
        "lookup, packet of 2": lambda: lookups(2, lam, table),
        "lookup, packet of 4": lambda: lookups(4, lam, table),
        "lookup, packet of 8": lambda: lookups(8, lam, table),
        "none (lookup, 4 outputs)": lambda: lookups_per_channel(0, lam, table),
        "lookup, packet of 2, 4 outputs": lambda: lookups_per_channel(2, lam, table),
    }
    times: dict[str, list[float]] = {k: [] for k in kernels}
    for fn in kernels.values():
        dr.eval(fn())
        dr.sync_thread()
    clock = clock or time.perf_counter
    for _ in range(repeat):
        for name, fn in kernels.items():
            t = clock()
            dr.eval(fn())
            dr.sync_thread()
            times[name].append(clock() - t)
    med = {k: float(np.median(v)) for k, v in times.items()}
    per_op = {}
    for name, t in med.items():
        if name.startswith("none"):
            continue
        base = med["none (arithmetic)" if not name.startswith("lookup") else
                   "none (lookup, 4 outputs)" if name.endswith("4 outputs") else
                   "none (lookup)"]
        per_op[name] = max(t - base, 0.0) / COUNT
    fma = per_op["fma"]
    return [{"operation": k, "ms": 1e3 * v, "cost_vs_fma": v / fma if fma > 0 else None}
            for k, v in per_op.items()]


def main() -> None:
    ap = arg_parser(__doc__)
    ap.add_argument("--cpu-time", action="store_true",
                    help="processor time of one Dr.Jit thread instead of wall time")
    args = ap.parse_args()
    n, repeat = (1 << 12, 2) if args.quick else (1 << 21, 15)
    if args.cpu_time:
        dr.set_thread_count(1)
    rows = measure(n, repeat, time.process_time if args.cpu_time else None)
    print(f"per operation over {n} lanes (lookups: per wavelength of a spectral lane)")
    print_table(rows, [("operation", "operation", "s"), ("ms", "ms per op", ".3f"),
                       ("cost_vs_fma", "cost / fma", ".1f")])
    save(args.out, "jit_ops", rows, args.quick, lanes=n, repeats=repeat, count=COUNT)
    barh_figure(args.out / "jit_ops.png", [r["operation"] for r in rows],
                [r["cost_vs_fma"] or 0.0 for r in rows], "tab:blue",
                f"cost of one operation / fma, Dr.Jit LLVM, {n} lanes")


if __name__ == "__main__":
    main()
