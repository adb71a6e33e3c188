"""Where the time of powder's eval goes: each lobe alone and all together, for the ways eval
obtains its volume constants (rho, c0, s(c0), tau_o), with a Mie albedo and with energy =
"conserving", against `principled`, in llvm_ad_rgb and llvm_ad_spectral.

The targets (docs/benchmarks.md): an all-lobes eval <= 1.6x `principled` (RGB) and <= 2.2x
(spectral). In spectral variants the volume constants depend on the wavelength unless the albedo and
``tau_o`` are one number each, or the layer is optically thick (2 c0 tau_o >= 18 ln 2 at every
wavelength, where s(c) = 1 / (2 c) within 3.8e-6: bench_bsdf.py's powder, albedo 0.8 with
hematite's Fresnel tau_o); otherwise they are read from a 1 nm table, one packet gather per
channel (albedo 0.9: 2 c0 tau_o >= 9.2). The "volume constants" column is what
``print(bsdf)`` says of each row.

Powder configuration: ``albedo 0.8, extinction 1, amplitude_surface 1e-3`` (bench_bsdf.py's;
``energy`` "paper", the default, unless a row says "conserving"; the Mie row has ``radius 0.05``
instead of the albedo, the constant-index row ``eta 1.35, k 0`` (PTFE-like: a Fresnel tau_o that
is one number), the surface Fresnel factor (`surface_fresnel`) with that constant index and
with hematite's tabulated one (beside the same rows without it), and in RGB a row gives the Mie
albedo's values as a constant albedo), 2^21
random direction pairs (random wavelengths in spectral variants), every configuration timed in
turn within each of 9 repeats; a cost is the median of the per-repeat ratios to `principled`.
Times are wall times, or with ``--cpu-time`` the processor time of one Dr.Jit thread
(``cpu_seconds``: on cores shared with other processes, the time they hold the cores is not
counted). With ``--sorted-wavelengths`` each channel's wavelengths are sorted across the lanes:
the same values and the same instructions, but neighbouring lanes read neighbouring records of
the 1 nm tables, which separates what random table reads cost the memory system from what the
kernel computes (docs/benchmarks.md, "The spectral eval with a Mie albedo").

    python benchmarks/bench_eval_breakdown.py [--quick] [--cpu-time] [--sorted-wavelengths]
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from _common import (
    arg_parser,
    barh_figure,
    cpu_seconds,
    eval_calls,
    print_table,
    random_pairs,
    save,
    time_in_turn,
    use_variant,
    wall_seconds,
)

BASE = {"type": "powder", "albedo": 0.8, "extinction": 1.0, "amplitude_surface": 1e-3}
LOBES = {"all": "all", "single": "single", "multiple": "multiple", "coherent": "coherent",
         "surface": "surface"}
#: (label, lobes, extra properties); None as a value removes the property from BASE
CONFIGS = [
    *[(name, lobes, {}) for name, lobes in LOBES.items()],
    ("all, conserving", "all", {"energy": "conserving"}),
    *[(f"{name}, albedo 0.9", lobes, {"albedo": 0.9}) for name, lobes in LOBES.items()
      if name in ("all", "multiple", "coherent")],
    # the Mie albedo's lobes (issue 38): what its table lookups cost in each
    *[(f"{name}, Mie albedo", lobes, {"albedo": None, "radius": 0.05})
      for name, lobes in LOBES.items() if name != "surface"],
    ("multiple, constant index", "multiple", {"eta": 1.35, "k": 0.0}),
    # the surface term's Fresnel factor (surface_fresnel): its cost against the same index off
    ("all, constant index", "all", {"eta": 1.35, "k": 0.0}),
    ("all, constant index, surface Fresnel", "all",
     {"eta": 1.35, "k": 0.0, "surface_fresnel": "fresnel"}),
    ("surface, constant index, surface Fresnel", "surface",
     {"eta": 1.35, "k": 0.0, "surface_fresnel": "fresnel"}),
    ("all, surface Fresnel", "all", {"surface_fresnel": "fresnel"}),  # hematite's table
    *[(f"{name}, tau_o 1.5", lobes, {"tau_o": 1.5}) for name, lobes in LOBES.items()],
]


def props(lobes: str, extra: dict) -> dict:
    """BASE with ``lobes`` and the extra properties (None: left out)."""
    out = {**BASE, "lobes": lobes, **extra}
    return {k: v for k, v in out.items() if v is not None}


def volume_path(bsdf) -> str:
    """How eval obtains the volume constants, as ``print(bsdf)`` says ("" for others)."""
    return next((line.split("=", 1)[1].strip().rstrip(",") for line in str(bsdf).splitlines()
                 if "volume constants" in line), "")


def measure(variant: str, n: int, repeat: int, clock=wall_seconds,
            sorted_wavelengths: bool = False) -> list[dict]:
    """Eval time of every configuration and of principled over the same lanes."""
    use_variant(variant)
    si, wo = random_pairs(n, variant, seed=4, sorted_wavelengths=sorted_wavelengths)
    ctx = mi.BSDFContext()
    bsdfs = {label: mi.load_dict(props(lobes, extra)) for label, lobes, extra in CONFIGS}
    if variant.endswith("rgb"):
        # the Mie albedo's three values as a constant albedo: what the lookup itself costs
        mie = bsdfs["all, Mie albedo"]
        rho = np.array(mie.eval_attribute("albedo", dr.zeros(mi.SurfaceInteraction3f, 1)))
        bsdfs["all, the Mie albedo's values as a constant"] = mi.load_dict(props("all", {
            "albedo": {"type": "rgb", "value": [float(v) for v in rho.ravel()]}}))
    bsdfs["principled"] = mi.load_dict({"type": "principled"})
    times = time_in_turn(eval_calls(bsdfs, ctx, si, wo), repeat, clock=clock)
    ref = times["principled"]
    return [{"variant": variant, "configuration": label, "volume": volume_path(bsdfs[label]),
             "ms": 1e3 * float(np.median(t)),
             "cost_vs_principled": float(np.median(np.array(t) / ref))}
            for label, t in times.items()]


def main() -> None:
    ap = arg_parser(__doc__)
    ap.add_argument("--cpu-time", action="store_true",
                    help="processor time of one Dr.Jit thread instead of wall time")
    ap.add_argument("--sorted-wavelengths", action="store_true",
                    help="each channel's wavelengths sorted across the lanes (spectral)")
    args = ap.parse_args()
    n, repeat = (1 << 12, 2) if args.quick else (1 << 21, 9)
    if args.cpu_time:
        dr.set_thread_count(1)
    rows = []
    for variant in ("llvm_ad_rgb", "llvm_ad_spectral"):
        rows += measure(variant, n, repeat, cpu_seconds if args.cpu_time else wall_seconds,
                        args.sorted_wavelengths)
    print_table(rows, [("variant", "variant", "s"), ("configuration", "configuration", "s"),
                       ("volume", "volume constants", "s"), ("ms", "eval ms", ".2f"),
                       ("cost_vs_principled", "cost / principled", ".2f")])
    save(args.out, "eval_breakdown", rows, args.quick, pairs=n, repeats=repeat,
         clock="processor time, one thread" if args.cpu_time else "wall",
         wavelengths="sorted across the lanes" if args.sorted_wavelengths else "random")
    spectral = [r for r in rows if r["variant"] == "llvm_ad_spectral"]
    barh_figure(args.out / "eval_breakdown.png", [r["configuration"] for r in spectral],
                [r["cost_vs_principled"] for r in spectral], "tab:orange",
                "llvm_ad_spectral eval cost / principled")


if __name__ == "__main__":
    main()
