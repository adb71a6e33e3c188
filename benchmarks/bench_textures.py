"""Texture-valued parameters: eval cost against constant parameters, and the albedo table of
spatially varying grains (build time, node count, accuracy against direct Mie theory).

- eval: 2^20 direction pairs at random uv on a 256 x 256 bitmap, all lobes, for the constant
  powder and with one property at a time a texture (llvm_ad_rgb and llvm_ad_spectral).
- grain table: a radius texture spanning a range of radii; time of mi.load_dict (the table is
  built there), its node count, and the largest relative difference of the plugin's albedo
  (eval_attribute at 400 radii across the range) from direct theory (GrainOptics, double).
Prints tables, writes benchmarks/results/textures.json.
Run:  python benchmarks/bench_textures.py [--quick]
"""

from __future__ import annotations

import json
import platform
import re
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from _common import arg_parser, barh_figure, random_pairs, timeit, use_variant

TEXTURED = {"amplitude_volume": (0.5, 1.5), "g": (-0.3, 0.6), "extinction": (0.3, 3.0),
            "tau_o": (0.5, 5.0), "amplitude_surface": (1e-4, 1e-2),
            "correlation_length": (0.5, 4.0), "radius": (0.02, 0.1)}
RANGES = [(0.01, 0.1), (0.05, 0.5), (0.2, 2.0)]


def bitmap(lo: float, hi: float, size: int, seed: int = 0) -> dict:
    rng = np.random.default_rng(seed)
    data = np.exp(rng.uniform(np.log(lo), np.log(hi), (size, size, 1))) if lo > 0 else \
        rng.uniform(lo, hi, (size, size, 1))
    return {"type": "bitmap", "raw": True, "filter_type": "bilinear",
            "data": mi.TensorXf(data.astype(np.float32))}


def lanes(n: int, variant: str):
    """Random direction pairs (_common.random_pairs) at random uv."""
    si, wo = random_pairs(n, variant, seed=1)
    rng = np.random.default_rng(2)
    si.uv = mi.Point2f(rng.uniform(0, 1, n), rng.uniform(0, 1, n))
    return si, wo


def bench_eval(variant: str, n: int, size: int, repeat: int) -> list[dict]:
    use_variant(variant)
    si, wo = lanes(n, variant)
    base = {"type": "powder", "radius": 0.05, "amplitude_surface": 1e-3}
    rows = []
    for name in [None] + list(TEXTURED):
        props = dict(base)
        if name is not None:
            props[name] = bitmap(*TEXTURED[name], size)
        bsdf = mi.load_dict(props)

        def run(bsdf=bsdf):
            dr.eval(bsdf.eval(mi.BSDFContext(), si, wo))

        rows.append({"variant": variant, "texture": name or "none (constant)",
                     "seconds": timeit(run, repeat)})
    t0 = rows[0]["seconds"]
    for r in rows:
        r["relative"] = r["seconds"] / t0
    return rows


def bench_table(variant: str, lo: float, hi: float) -> dict:
    from mitsuba_powder.plugin.grains import GrainOptics

    use_variant(variant)
    warnings: list[str] = []

    class Capture(mi.Appender):
        def append(self, level, text):
            warnings.append(text)

        def log_progress(self, *args):
            pass

    logger = mi.logger()
    capture = Capture()
    logger.add_appender(capture)
    try:
        t = time.perf_counter()
        bsdf = mi.load_dict({"type": "powder", "radius": {
            "type": "bitmap", "raw": True, "filter_type": "nearest",
            "data": mi.TensorXf(np.array([lo, hi, lo, hi], np.float32).reshape(2, 2, 1))}})
        build = time.perf_counter() - t
    finally:
        logger.remove_appender(capture)
    wavelengths = (450.0, 550.0, 650.0, 750.0) if "spectral" in variant else \
        (611.3, 549.1, 464.3)
    radii = np.exp(np.linspace(np.log(lo), np.log(hi), 400)).astype(np.float32)
    params = mi.traverse(bsdf)
    worst = 0.0
    direct = GrainOptics({}).albedo(list(wavelengths), radii.astype(np.float64))[0]
    for chunk in range(0, len(radii), 100):
        r = radii[chunk:chunk + 100]
        params["radius.data"] = mi.TensorXf(np.tile(r, 2).reshape(2, len(r), 1))
        params.update()
        si = dr.zeros(mi.SurfaceInteraction3f, len(r))
        si.uv = mi.Point2f((np.arange(len(r)) + 0.5) / len(r), np.full(len(r), 0.25))
        if "spectral" in variant:
            si.wavelengths = mi.Spectrum(*wavelengths)
        got = np.array(bsdf.eval_attribute("albedo", si), dtype=np.float64).T
        worst = max(worst, float(np.max(np.abs(got / direct[chunk:chunk + 100] - 1))))
    text = " ".join(warnings)
    nodes = re.search(r"its (\d+) nodes", text)
    return {"variant": variant, "radii_um": [lo, hi], "build_seconds": build,
            "max_relative_error": worst, "table_warning": text or None,
            "nodes_if_capped": int(nodes.group(1)) if nodes else None}


def main() -> None:
    args = arg_parser(__doc__).parse_args()
    n, size, repeat = (1 << 14, 16, 2) if args.quick else (1 << 20, 256, 5)
    evals = [r for v in ("llvm_ad_rgb", "llvm_ad_spectral") for r in bench_eval(v, n, size,
                                                                                  repeat)]
    print(f"eval of {n} pairs, one property a {size}x{size} bitmap at a time")
    print("| variant | texture | time (ms) | relative to constant |\n|---|---|---|---|")
    for r in evals:
        print(f"| {r['variant']} | {r['texture']} | {1e3 * r['seconds']:.1f} | "
              f"{r['relative']:.2f} |")
    ranges = RANGES[:1] if args.quick else RANGES
    tables = [bench_table(v, lo, hi) for v in ("llvm_ad_rgb", "llvm_ad_spectral")
              for lo, hi in ranges]
    print("\nalbedo table of a radius texture")
    print("| variant | radii (um) | build (s) | max relative error vs direct theory |"
          "\n|---|---|---|---|")
    for t in tables:
        print(f"| {t['variant']} | {t['radii_um'][0]:g}-{t['radii_um'][1]:g} | "
              f"{t['build_seconds']:.2f} | {t['max_relative_error']:.1e}"
              f"{' (capped table)' if t['table_warning'] else ''} |")
    out = {"meta": {"quick": args.quick, "machine": f"{platform.machine()}, "
                    f"{platform.system()}", "pairs": n, "bitmap": size,
                    "date": time.strftime("%F")},
           "eval": evals, "grain_table": tables}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "textures.json").write_text(json.dumps(out, indent=1))
    barh_figure(args.out / "textures.png", [f"{r['variant']}: {r['texture']}" for r in evals],
                [r["relative"] for r in evals],
                ["tab:blue" if "rgb" in r["variant"] else "tab:orange" for r in evals],
                "eval time relative to constant parameters", figsize=(7, 5))


if __name__ == "__main__":
    main()
