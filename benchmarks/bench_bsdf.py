"""BSDF throughput: powder (all lobes, each lobe alone, Gaussian specular, Mie albedo) against
Mitsuba's diffuse, roughplastic and principled.

Per variant and BSDF: eval, sample and eval_pdf calls per second, and eval + backward
(gradient of the sum of the values with respect to one parameter). JIT variants: one call over
N random direction pairs (kernel compiled in a warm-up call, then the median of the repeats,
the BSDFs timed in turn within each repeat; the time includes Python tracing of the call);
eval cost against principled: the median of the per-repeat ratios. scalar_rgb: a Python loop
of single calls, so its numbers include the binding overhead of each call (the same for every
BSDF).
Prints a table, writes benchmarks/results/bsdf.json and bsdf.png.
Run:  python benchmarks/bench_bsdf.py [--quick]
"""

from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi
import numpy as np

from _common import (
    arg_parser,
    print_table,
    pyplot,
    save,
    save_figure,
    throughput_sizes,
    use_variant,
)

BASE = {"type": "powder", "albedo": 0.8, "extinction": 1.0, "amplitude_surface": 1e-3}
BSDFS = {
    "powder": BASE,
    "powder single": {**BASE, "lobes": "single"},
    "powder multiple": {**BASE, "lobes": "multiple"},
    "powder coherent": {**BASE, "lobes": "coherent"},
    "powder surface": {**BASE, "lobes": "surface"},
    "powder gaussian": {**BASE, "specular": "gaussian", "amplitude_surface": 0.5,
                        "sigma": 0.1},
    "powder Mie albedo": {"type": "powder", "radius": 0.05, "extinction": 1.0,
                          "amplitude_surface": 1e-3},
    # a pigment mixture of four materials (docs/model.md, "Several materials"), and one
    # population as bright as it (the cost follows the albedo: bright powders take the
    # series form of the coherent term)
    "powder Mie 4 materials": {"type": "powder", "radius": 0.05, "extinction": 1.0,
                               "amplitude_surface": 1e-3, "radius2": 0.2, "fraction2": 0.2,
                               "material2": "calcite", "radius3": 1.0, "fraction3": 0.3,
                               "material3": "kaolinite", "radius4": 0.3, "fraction4": 0.1,
                               "material4": "magnetite"},
    "powder Mie white": {"type": "powder", "radius": 1.0, "material": "kaolinite",
                         "extinction": 1.0, "amplitude_surface": 1e-3},
    "diffuse": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.8}},
    "roughplastic": {"type": "roughplastic"},
    "principled": {"type": "principled"},
}
#: parameter whose gradient the eval + backward benchmark computes
GRAD_KEY = {"diffuse": "reflectance.value", "roughplastic": "diffuse_reflectance.value",
            "principled": "base_color.value"}


def directions(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    mu = rng.uniform(0.05, 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - mu**2)
    return np.stack([s * np.cos(phi), s * np.sin(phi), mu], axis=1).astype(np.float32)


def jit_calls(name: str, props: dict, n: int, backward: bool = True) -> dict:
    """{operation: a function making one call over n random direction pairs}."""
    bsdf = mi.load_dict(props)
    wi, wo = directions(n, 1), directions(n, 2)
    rng = np.random.default_rng(3)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(wi[:, 0], wi[:, 1], wi[:, 2])
    if mi.is_spectral:
        si.wavelengths = mi.UnpolarizedSpectrum(*rng.uniform(360, 830, (4, n)).astype(
            np.float32))
    w = mi.Vector3f(wo[:, 0], wo[:, 1], wo[:, 2])
    s1 = mi.Float(rng.uniform(size=n).astype(np.float32))
    s2 = mi.Point2f(*rng.uniform(size=(2, n)).astype(np.float32))
    dr.eval(si, w, s1, s2)
    ctx = mi.BSDFContext()
    params = mi.traverse(bsdf) if backward else None
    key = GRAD_KEY.get(name.split()[0],
                       "amplitude_surface" if name.endswith("surface") else "amplitude_volume")

    def run_eval():
        dr.eval(bsdf.eval(ctx, si, w))

    def run_sample():
        bs, weight = bsdf.sample(ctx, si, s1, s2)
        dr.eval(bs.wo, bs.pdf, weight)

    def run_eval_pdf():
        dr.eval(*bsdf.eval_pdf(ctx, si, w))

    def run_backward():
        dr.enable_grad(params[key])
        params.update()
        value = mi.unpolarized_spectrum(bsdf.eval(ctx, si, w))
        dr.backward(dr.sum(dr.sum(value)))
        dr.eval(dr.grad(params[key]))
        dr.disable_grad(params[key])

    calls = {"eval": run_eval, "sample": run_sample, "eval_pdf": run_eval_pdf}
    if backward:
        calls["eval_backward"] = run_backward
    return calls


def bench_jit(bsdfs: dict, n: int, repeat: int, backward: bool = True) -> dict:
    """{bsdf: {operation: M calls/s}}, and with a "principled" entry the eval cost against
    it. The BSDFs are timed in turn within each repeat (after a warm-up call each that
    compiles the kernels), so that a change of machine load affects them alike; a cost ratio
    is the median of the per-repeat ratios."""
    calls = {name: jit_calls(name, props, n, backward) for name, props in bsdfs.items()}
    times = {name: {op: [] for op in c} for name, c in calls.items()}
    for c in calls.values():
        for fn in c.values():
            fn()
            dr.sync_thread()
    for _ in range(repeat):
        for op in ("eval", "sample", "eval_pdf", "eval_backward"):
            for name, c in calls.items():
                if op not in c:
                    continue
                t = time.perf_counter()
                c[op]()
                dr.sync_thread()
                times[name][op].append(time.perf_counter() - t)
    out = {}
    for name, t in times.items():
        out[name] = {"eval_backward": None,
                     **{op: n / float(np.median(v)) / 1e6 for op, v in t.items()}}
        if "principled" in times:
            ref = np.array(times["principled"]["eval"])
            out[name]["eval_cost_vs_principled"] = float(np.median(np.array(t["eval"]) / ref))
    return out


def bench_scalar(props: dict, n: int) -> dict:
    bsdf = mi.load_dict(props)
    wi, wo = directions(n, 1), directions(n, 2)
    rng = np.random.default_rng(3)
    sis = []
    for k in range(n):
        si = mi.SurfaceInteraction3f()
        si.wi = mi.Vector3f(*wi[k])
        sis.append(si)
    ws = [mi.Vector3f(*v) for v in wo]
    s1 = rng.uniform(size=n).tolist()
    s2 = [mi.Point2f(*p) for p in rng.uniform(size=(n, 2)).tolist()]
    ctx = mi.BSDFContext()
    ops = {"eval": lambda k: bsdf.eval(ctx, sis[k], ws[k]),
           "sample": lambda k: bsdf.sample(ctx, sis[k], s1[k], s2[k]),
           "eval_pdf": lambda k: bsdf.eval_pdf(ctx, sis[k], ws[k])}
    out = {"eval_backward": None}
    for op, fn in ops.items():
        best = np.inf
        for _ in range(3):
            t = time.perf_counter()
            for k in range(n):
                fn(k)
            best = min(best, time.perf_counter() - t)
        out[op] = n / best / 1e6
    return out


def main() -> None:
    parser = arg_parser(__doc__)
    args = parser.parse_args()
    n_jit, n_scalar, repeat = throughput_sizes(args.quick, 1 << 22, 9)
    variants = ["scalar_rgb", "llvm_ad_rgb", "llvm_ad_mono", "llvm_ad_spectral"]
    rows = []
    for variant in variants:
        use_variant(variant)
        if variant.startswith("scalar"):
            results = {name: bench_scalar(props, n_scalar) for name, props in BSDFS.items()}
            for r in results.values():
                r["eval_cost_vs_principled"] = results["principled"]["eval"] / r["eval"]
        else:
            results = bench_jit(BSDFS, n_jit, repeat)
        rows += [{"variant": variant, "bsdf": name, **r} for name, r in results.items()]
        diffuse = next(r for r in rows if r["variant"] == variant and r["bsdf"] == "diffuse")
        for r in rows:
            if r["variant"] == variant:
                r["eval_cost_vs_diffuse"] = diffuse["eval"] / r["eval"]
                r["sample_cost_vs_diffuse"] = diffuse["sample"] / r["sample"]
    print(f"throughput in millions of calls per second; JIT: {n_jit} pairs per call; "
          f"scalar: {n_scalar} Python-level calls")
    print_table(rows, [("variant", "variant", "s"), ("bsdf", "bsdf", "s"),
                       ("eval", "eval M/s", ".3f"), ("sample", "sample M/s", ".3f"),
                       ("eval_pdf", "eval_pdf M/s", ".3f"),
                       ("eval_backward", "eval+bwd M/s", ".3f"),
                       ("eval_cost_vs_diffuse", "eval cost/diffuse", ".2f"),
                       ("sample_cost_vs_diffuse", "sample cost/diffuse", ".2f"),
                       ("eval_cost_vs_principled", "eval cost/principled", ".2f")])
    save(args.out, "bsdf", rows, args.quick, jit_pairs=n_jit, scalar_calls=n_scalar)
    plt = pyplot()
    fig, axes = plt.subplots(1, len(variants), figsize=(4 * len(variants), 3.8), sharey=False)
    for ax, variant in zip(axes, variants, strict=True):
        sel = [r for r in rows if r["variant"] == variant]
        ax.barh([r["bsdf"] for r in sel], [r["eval"] for r in sel], color=[
            "tab:orange" if r["bsdf"].startswith("powder") else "tab:gray" for r in sel])
        ax.set_title(variant, fontsize=9)
        ax.set_xlabel("eval, M calls/s")
        ax.invert_yaxis()
        ax.tick_params(labelsize=7)
    save_figure(fig, args.out / "bsdf.png")


if __name__ == "__main__":
    main()
