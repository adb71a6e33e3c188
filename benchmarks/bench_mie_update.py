"""Cost of a radius update (the Mie table) against one optimisation step's BSDF work.

For each variant: the time of `params.update()` after changing `radius` (Mie efficiencies
over the variant's table: 471 wavelengths in spectral variants, 3 in RGB, 1 in mono; plus the
radius tangents), against the time of eval + backward over N direction pairs.
Prints a table, writes benchmarks/results/mie_update.json and .png.
Run:  python benchmarks/bench_mie_update.py [--quick]
"""

from __future__ import annotations

import json
import platform

import drjit as dr
import mitsuba as mi

from _common import arg_parser, random_pairs, save_figure, timeit, use_variant


def bench(variant: str, radius: float, n_dirs: int, repeat: int) -> dict:
    use_variant(variant)
    bsdf = mi.load_dict({"type": "powder", "radius": radius})
    params = mi.traverse(bsdf)
    si, wo = random_pairs(n_dirs, variant, seed=0)
    toggle = [radius, radius * 1.01]

    def update():
        """radius changed, no gradient tracked: the Mie table only"""
        toggle.reverse()
        params["radius"] = mi.Float(toggle[0])
        params.update()
        dr.eval(params["radius"])

    def update_ad():
        """radius changed with gradients tracked: Mie table and its radius tangents"""
        toggle.reverse()
        params["radius"] = mi.Float(toggle[0])
        dr.enable_grad(params["radius"])
        params.update()
        dr.eval(params["radius"])

    def eval_backward():
        """the step's own BSDF work: eval at every direction pair, then backward"""
        v = bsdf.eval(mi.BSDFContext(), si, wo)
        loss = dr.sum(dr.sum(mi.unpolarized_spectrum(v)))
        dr.backward(loss)
        dr.eval(dr.grad(params["radius"]))

    t_update = timeit(update, repeat)
    t_update_ad = timeit(update_ad, repeat)
    t_step = timeit(eval_backward, repeat)
    dr.disable_grad(params["radius"])
    return {"variant": variant, "radius_um": radius, "directions": n_dirs,
            "update_s": t_update, "update_ad_s": t_update_ad, "eval_backward_s": t_step,
            "update_ad_over_eval_backward": t_update_ad / t_step}


def construction(variant: str, repeat: int) -> dict:
    """Time of mi.load_dict of a powder whose albedo comes from Mie theory, with tau_o given
    and with tau_o from Fresnel (computed once per wavelength of the table at construction:
    eta is not a differentiable parameter, so no update recomputes it)."""
    use_variant(variant)
    out = {"variant": variant}
    for label, extra in (("tau_given", {"tau_o": 0.6667}), ("tau_fresnel", {})):
        out[f"load_{label}_s"] = timeit(
            lambda extra=extra: mi.load_dict({"type": "powder", "radius": 0.3, **extra}),
            repeat)
    out["fresnel_s"] = out["load_tau_fresnel_s"] - out["load_tau_given_s"]
    return out


def main() -> None:
    parser = arg_parser(__doc__)
    args = parser.parse_args()
    variants = ["llvm_ad_mono", "llvm_ad_rgb", "llvm_ad_spectral"]
    radii = [0.017, 3.0] if args.quick else [0.017, 0.3, 3.0]
    dirs = [213] if args.quick else [213, 10_000, 1_000_000]
    repeat = 2 if args.quick else 15
    rows = [bench(v, r, n, repeat) for v in variants for r in radii for n in dirs]
    loads = [construction(v, repeat) for v in variants]
    header = (f"{'variant':18s} {'radius um':>9s} {'dirs':>8s} {'update ms':>10s} "
              f"{'update+AD ms':>12s} {'eval+bwd ms':>11s} {'ratio':>6s}")
    print(header)
    for r in rows:
        print(f"{r['variant']:18s} {r['radius_um']:9g} {r['directions']:8d} "
              f"{1e3 * r['update_s']:10.3f} {1e3 * r['update_ad_s']:12.3f} "
              f"{1e3 * r['eval_backward_s']:11.3f} {r['update_ad_over_eval_backward']:6.2f}")
    print("ratio = (update with radius tangents) / (eval + backward over the pairs)")
    print(f"{'variant':18s} {'load, tau_o given ms':>21s} {'load, Fresnel ms':>17s} "
          f"{'Fresnel ms':>11s}")
    for r in loads:
        print(f"{r['variant']:18s} {1e3 * r['load_tau_given_s']:21.3f} "
              f"{1e3 * r['load_tau_fresnel_s']:17.3f} {1e3 * r['fresnel_s']:11.3f}")
    args.out.mkdir(parents=True, exist_ok=True)
    meta = {"machine": platform.processor() or platform.machine(), "cpus": __import__(
        "os").cpu_count(), "python": platform.python_version(), "quick": args.quick}
    (args.out / "mie_update.json").write_text(json.dumps({"meta": meta, "rows": rows,
                                                             "construction": loads}, indent=1))
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(7, 4))
    for v in variants:
        for r in radii:
            sel = [x for x in rows if x["variant"] == v and x["radius_um"] == r]
            ax.loglog([x["directions"] for x in sel], [1e3 * x["update_ad_s"] for x in sel],
                      "o--", label=f"update+AD {v} r={r:g}")
        sel = [x for x in rows if x["variant"] == v and x["radius_um"] == radii[0]]
        ax.loglog([x["directions"] for x in sel], [1e3 * x["eval_backward_s"] for x in sel],
                  "s-", label=f"eval+backward {v}")
    ax.set(xlabel="direction pairs per step", ylabel="ms",
           title="radius update (with tangents) vs eval+backward")
    ax.legend(fontsize=6)
    save_figure(fig, args.out / "mie_update.png", dpi=110)


if __name__ == "__main__":
    main()
