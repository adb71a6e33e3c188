"""The case for the C++ plugin: the same model as a Python ``mi.BSDF`` subclass.

``python_powder.PythonPowder`` (benchmark-only) against ``powder`` with ``sampling=cosine``
(same values to float32 rounding, same sample distribution): BSDF calls per second, and the
time to render a patch under a uniform environment (MIS, ``direct`` integrator), in scalar_rgb,
llvm_ad_rgb and llvm_ad_spectral. Prints a table, writes benchmarks/results/python_bsdf.json
and python_bsdf.png.
Run:  python benchmarks/bench_python_bsdf.py [--quick]
"""

from __future__ import annotations

import time

import drjit as dr
import mitsuba as mi
import numpy as np
from registry import PYTHON_BSDF_COLUMNS

import python_powder
from _common import arg_parser, barh_figure, print_table, save, throughput_sizes, use_variant
from bench_bsdf import bench_jit, bench_scalar, directions

PROPS = {"albedo": 0.8, "extinction": 1.0, "amplitude_surface": 1e-3, "tau_o": 2.0 / 3.0,
         "g": 0.3}


def furnace_scene(bsdf_type: str, res: int, spp: int):
    extra = {"sampling": "cosine"} if bsdf_type == "powder" else {}
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "direct"},
        "patch": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(100),
                  "bsdf": {"type": bsdf_type, **PROPS, **extra}},
        "sky": {"type": "constant"},
        "sensor": {"type": "orthographic",
                   "to_world": mi.ScalarTransform4f().look_at(origin=[3, 0, 5],
                                                              target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": res, "height": res,
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": spp}}})


def render_seconds(scene, repeat: int) -> tuple[float, float]:
    """(first render incl. kernel compilation, median of later renders), seconds."""
    times = []
    for _ in range(repeat + 1):
        t = time.perf_counter()
        img = mi.render(scene, seed=len(times))
        dr.eval(img)
        dr.sync_thread()
        times.append(time.perf_counter() - t)
    return times[0], float(np.median(times[1:]))


def max_relative_difference(n: int) -> float:
    """max |python - plugin| / max |plugin| of eval over n random pairs (current variant)."""
    a = mi.load_dict({"type": "powder", **PROPS, "sampling": "cosine"})
    b = mi.load_dict({"type": "python_powder", **PROPS})
    wi, wo = directions(n, 5), directions(n, 6)
    if mi.variant().startswith("scalar"):
        va, vb = [], []
        for k in range(min(n, 200)):
            si = mi.SurfaceInteraction3f()
            si.wi = mi.Vector3f(*wi[k])
            va.append(np.array(a.eval(mi.BSDFContext(), si, mi.Vector3f(*wo[k]))))
            vb.append(np.array(b.eval(mi.BSDFContext(), si, mi.Vector3f(*wo[k]))))
        va, vb = np.array(va), np.array(vb)
    else:
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi = mi.Vector3f(*wi.T)
        if mi.is_spectral:
            si.wavelengths = mi.UnpolarizedSpectrum(*np.random.default_rng(7).uniform(
                360, 830, (4, n)).astype(np.float32))
        w = mi.Vector3f(*wo.T)
        va = np.array(a.eval(mi.BSDFContext(), si, w))
        vb = np.array(b.eval(mi.BSDFContext(), si, w))
    return float(np.abs(va - vb).max() / np.abs(va).max())


def main() -> None:
    parser = arg_parser(__doc__)
    args = parser.parse_args()
    n_jit, n_scalar, repeat = throughput_sizes(args.quick, 1 << 21, 7)
    rows = []
    for variant in ["scalar_rgb", "llvm_ad_rgb", "llvm_ad_spectral"]:
        use_variant(variant)
        python_powder.register()
        scalar = variant.startswith("scalar")
        res, spp = (16, 2) if args.quick else ((64, 4) if scalar else (256, 64))
        diff = max_relative_difference(4096)
        for impl, props in [("C++ plugin", {"type": "powder", **PROPS, "sampling": "cosine"}),
                            ("Python mi.BSDF", {"type": "python_powder", **PROPS})]:
            if scalar:
                r = bench_scalar(props, n_scalar)
            else:
                name = "python" if impl.startswith("Python") else "powder"
                r = bench_jit({name: props}, n_jit, repeat, backward=False)[name]
            r.pop("eval_backward", None)
            first, later = render_seconds(furnace_scene(props["type"], res, spp), repeat)
            rows.append({"variant": variant, "implementation": impl, **r,
                         "render_first_s": first, "render_s": later,
                         "render_samples": res * res * spp, "max_rel_difference": diff})
        cpp, py = rows[-2], rows[-1]
        for key in ("eval", "sample", "eval_pdf"):
            py[f"{key}_cpp_speedup"] = cpp[key] / py[key]
        py["render_cpp_speedup"] = py["render_s"] / cpp["render_s"]
        py["render_first_cpp_speedup"] = py["render_first_s"] / cpp["render_first_s"]
    print(f"M calls/s (JIT: {n_jit} pairs per call; scalar: Python-level calls); render: patch "
          "under a uniform sky, direct/MIS; speedup = C++ over Python")
    print_table(rows, PYTHON_BSDF_COLUMNS)
    save(args.out, "python_bsdf", rows, args.quick)
    barh_figure(args.out / "python_bsdf.png",
                [f"{r['variant']}\n{r['implementation']}" for r in rows],
                [r["render_s"] for r in rows],
                ["tab:orange" if r["implementation"].startswith("C++") else "tab:blue"
                 for r in rows], "render time, s (log)", log=True)

if __name__ == "__main__":
    main()
