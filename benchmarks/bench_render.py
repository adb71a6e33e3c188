"""Rendering: time and error of the trades a user makes.

1. Sampling: the powder's lobe mixture (``sampling=lobes``, the default) against cosine-only
   sampling (``sampling=cosine``), at equal samples per pixel and at equal time. Cases: the
   gonio patch with a 5-degree source (BSDF sampling only) and a 1-degree one (MIS), at
   back-scattering and off it, the patch under a uniform sky (BSDF sampling), and the
   showcase scene (path tracing, MIS). Error: per-pixel relative RMSE against the analytic
   value (gonio, sky) or a high-sample reference (showcase). Gain = (err^2 t)_cosine /
   (err^2 t)_lobes, the ratio of the times to reach the same error.
2. Variants: llvm_ad_rgb, llvm_ad_mono and llvm_ad_spectral at equal spp on the showcase
   and on the gonio patch over both protocols (time), and the colour RGB loses: CIEDE2000
   of the RGB render against the spectral one (both converged), and per powder of the
   showcase the BRF colour of the gonio patch.
3. Render cost of the powder against diffuse, roughplastic and principled (patch under a
   uniform sky, equal spp) in scalar_rgb and llvm_ad_rgb.
Times are the best of 3 renders after a warm-up render (kernel compilation).
Prints tables, writes benchmarks/results/render.json and render.png.
Run:  python benchmarks/bench_render.py [--quick]
"""

from __future__ import annotations

import tempfile
import time
from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np

from _common import arg_parser, print_table, pyplot, save, save_figure, use_variant

ROOT = Path(__file__).resolve().parents[1]
REPEAT = 3  # timings are the best of REPEAT renders
SHOWCASE = ROOT / "scenes" / "showcase.xml"
SHARP = {"albedo": {"type": "rgb", "value": [0.95, 0.7, 0.4]}, "extinction": 0.1}
BROAD = {"albedo": {"type": "rgb", "value": [0.85, 0.55, 0.3]}, "extinction": 1.0,
         "amplitude_surface": 1e-3}
#: the showcase's seven powders (Table 2 radii, um; fraction2 0.5 as in the scene)
SAMPLES = {"1": {"radius": 0.017}, "2": {"radius": 0.016}, "3": {"radius": 0.016},
           "4": {"radius": 0.015},
           "5": {"radius": 0.083, "radius2": 0.046, "fraction2": 0.5},
           "6": {"radius": 0.687, "radius2": 0.043, "fraction2": 0.5},
           "7": {"radius": 2.222, "radius2": 0.049, "fraction2": 0.5}}


def _render(scene, spp: int, seed: int = 0) -> tuple[np.ndarray, float]:
    t = time.perf_counter()
    img = mi.render(scene, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return np.array(img, dtype=np.float64), time.perf_counter() - t


# ----------------------------------------------------------------------------- sampling

def sampling_case_gonio(name, props, geometry, strategy, radius, res, spp, equal_time=True):
    from mitsuba_powder.rendering.gonio import render_gonio

    rows = []
    out = {}
    for sampling in ("lobes", "cosine"):
        p = {**props, "sampling": sampling}
        render_gonio(p, *[[g] for g in geometry], variant="llvm_ad_rgb", spp=spp,
                     resolution=res, source_radius=radius, strategy=strategy)  # compile
        runs = [render_gonio(p, *[[g] for g in geometry], variant="llvm_ad_rgb", spp=spp,
                             resolution=res, source_radius=radius, strategy=strategy,
                             seed=1 + k) for k in range(REPEAT)]
        r = runs[0]
        r.seconds = min(x.seconds for x in runs)  # timing: best of REPEAT
        pix_std = r.stderr[0] * res
        err = float(np.sqrt(np.mean(pix_std**2 + (r.rendered[0] - r.analytic[0]) ** 2))
                    / np.mean(r.analytic[0]))
        out[sampling] = (err, r.seconds, spp)
    rows.append(_sampling_row(name, out))
    if equal_time:
        spp_cos = max(1, int(round(spp * out["lobes"][1] / out["cosine"][1])))
        r = render_gonio({**props, "sampling": "cosine"}, *[[g] for g in geometry],
                         variant="llvm_ad_rgb", spp=spp_cos, resolution=res,
                         source_radius=radius, strategy=strategy, seed=2)
        err = float(np.sqrt(np.mean((r.stderr[0] * res) ** 2 + (r.rendered[0] - r.analytic[0])
                                    ** 2)) / np.mean(r.analytic[0]))
        rows[-1].update({"equal_time_cosine_spp": spp_cos, "equal_time_cosine_rel_rmse": err,
                         "equal_time_cosine_s": r.seconds})
    return rows


def sampling_case_sky(label, props, theta_o, res, spp):
    from mitsuba_powder.rendering.furnace import white_furnace

    out = {}
    for sampling in ("lobes", "cosine"):
        p = {**props, "sampling": sampling}
        white_furnace(p, (theta_o,), strategy="bsdf", spp=spp, resolution=res)  # compile
        runs = [white_furnace(p, (theta_o,), strategy="bsdf", spp=spp, resolution=res,
                              seed=1 + k) for k in range(REPEAT)]
        f = runs[0]
        f.seconds = min(x.seconds for x in runs)
        pix_std = f.stderr[0] * res
        err = float(np.sqrt(np.mean(pix_std**2 + (f.rendered[0] - f.quadrature[0]) ** 2))
                    / np.mean(f.quadrature[0]))
        out[sampling] = (err, f.seconds, spp)
    row = _sampling_row(f"uniform sky, {label} cone, theta_o {theta_o:g}, bsdf", out)
    spp_cos = max(1, int(round(spp * out["lobes"][1] / out["cosine"][1])))
    f = white_furnace({**props, "sampling": "cosine"}, (theta_o,), strategy="bsdf",
                      spp=spp_cos, resolution=res, seed=7)
    err = float(np.sqrt(np.mean((f.stderr[0] * res) ** 2 + (f.rendered[0] - f.quadrature[0])
                                ** 2)) / np.mean(f.quadrature[0]))
    row.update({"equal_time_cosine_spp": spp_cos, "equal_time_cosine_rel_rmse": err})
    return [row]


def sampling_case_showcase(res, spp, ref_spp):
    use_variant("llvm_ad_rgb")
    w, h = res
    scenes = {"lobes": mi.load_file(str(SHOWCASE), res_x=str(w), res_y=str(h))}
    # sampling is a construction property, not a traversable one: a copy of the scene file
    # with sampling="cosine" on every powder
    with tempfile.TemporaryDirectory() as tmp:
        cos_xml = Path(tmp) / "showcase_cosine.xml"
        cos_xml.write_text(SHOWCASE.read_text().replace(
            '<bsdf type="powder">',
            '<bsdf type="powder">\n            <string name="sampling" value="cosine"/>'))
        scenes["cosine"] = mi.load_file(str(cos_xml), res_x=str(w), res_y=str(h))
    ref, _ = _render(scenes["lobes"], ref_spp, seed=99)
    out = {}
    for s, scene in scenes.items():
        _render(scene, spp)  # compile
        img, sec = _render(scene, spp, seed=1)
        sec = min([sec] + [_render(scene, spp, seed=2 + k)[1] for k in range(REPEAT - 1)])
        err = float(np.sqrt(np.mean((img - ref) ** 2)) / np.mean(ref))
        out[s] = (err, sec, spp)
    row = _sampling_row(f"showcase {w}x{h}, path tracing (MIS)", out)
    row["reference_spp"] = ref_spp
    spp_cos = max(1, int(round(spp * out["lobes"][1] / out["cosine"][1])))
    img, _ = _render(scenes["cosine"], spp_cos, seed=7)
    row.update({"equal_time_cosine_spp": spp_cos,
                "equal_time_cosine_rel_rmse": float(np.sqrt(np.mean((img - ref) ** 2))
                                                    / np.mean(ref))})
    return [row]


def _sampling_row(name, out) -> dict:
    (el, tl, spp), (ec, tc, _) = out["lobes"], out["cosine"]
    return {"case": name, "spp": spp, "lobes_rel_rmse": el, "cosine_rel_rmse": ec,
            "lobes_s": tl, "cosine_s": tc,
            "variance_ratio": ec**2 / max(el**2, 1e-300),
            "gain": (ec**2 * tc) / max(el**2 * tl, 1e-300)}


# ----------------------------------------------------------------------------- variants

def variants_showcase(res, spp, ref_spp) -> tuple[list[dict], dict]:
    from mitsuba_powder.rendering.photo import delta_e_2000

    w, h = res
    rows, images = [], {}
    for variant in ("llvm_ad_rgb", "llvm_ad_mono", "llvm_ad_spectral"):
        use_variant(variant)
        scene = mi.load_file(str(SHOWCASE), res_x=str(w), res_y=str(h))
        _render(scene, spp)
        sec = min(_render(scene, spp, seed=1 + k)[1] for k in range(REPEAT))
        conv, _ = _render(scene, ref_spp, seed=2)
        images[variant] = conv
        rows.append({"variant": variant, "spp": spp, "seconds": sec})
    spec = images["llvm_ad_spectral"]
    lum = lambda x: x[..., :3] @ np.array([0.2126, 0.7152, 0.0722])  # noqa: E731
    white = float(np.percentile(lum(spec), 99))
    de = delta_e_2000(images["llvm_ad_rgb"][..., :3], spec[..., :3], white)
    t_spec = rows[-1]["seconds"]
    for r in rows:
        r["spectral_over_this_time"] = t_spec / r["seconds"]
    rows[0].update({"delta_e_vs_spectral_mean": float(de.mean()),
                    "delta_e_vs_spectral_p95": float(np.percentile(de, 95)),
                    "delta_e_vs_spectral_max": float(de.max())})
    mono = images["llvm_ad_mono"][..., 0]
    rel = np.abs(mono - lum(spec)) / np.maximum(lum(spec), 1e-3 * white)
    rows[1].update({"luminance_rel_error_vs_spectral_median": float(np.median(rel))})
    return rows, {"delta_e": de}


def variants_gonio(spp: int, res: int, quick: bool) -> list[dict]:
    """The gonio patch over both protocols (render-gonio, collimated source, a hematite
    powder with a Mie albedo) in each variant: render time, and the RGB BRF's colour error
    against the spectral one (analytic values, CIEDE2000, white 1)."""
    from mitsuba_powder.fitting.protocols import protocol_geometries
    from mitsuba_powder.rendering.gonio import render_gonio
    from mitsuba_powder.rendering.photo import delta_e_2000

    ti, to, ph = protocol_geometries("backscatter" if quick else "shadows,backscatter")
    props = {**SAMPLES["5"], "extinction": 1.0}
    rows, vals = [], {}
    for variant in ("llvm_ad_rgb", "llvm_ad_mono", "llvm_ad_spectral"):
        render_gonio(props, ti, to, ph, variant=variant, spp=spp, resolution=res)
        runs = [render_gonio(props, ti, to, ph, variant=variant, spp=spp, resolution=res,
                             seed=k) for k in range(REPEAT)]
        vals[variant] = runs[0].analytic
        rows.append({"variant": variant, "geometries": len(ti), "spp": spp,
                     "seconds": min(r.seconds for r in runs)})
    de = delta_e_2000(vals["llvm_ad_rgb"][None], vals["llvm_ad_spectral"][None], 1.0)[0]
    t_spec = rows[-1]["seconds"]
    for r in rows:
        r["spectral_over_this_time"] = t_spec / r["seconds"]
    rows[0].update({"delta_e_vs_spectral_mean": float(de.mean()),
                    "delta_e_vs_spectral_max": float(de.max())})
    return rows


def variants_powder_colour() -> list[dict]:
    """BRF colour of each showcase powder on the gonio patch: RGB variant (3 wavelengths)
    against the spectral film value, CIEDE2000 (linear sRGB reflectance factors, white 1)."""
    from mitsuba_powder.rendering.gonio import render_gonio
    from mitsuba_powder.rendering.photo import delta_e_2000

    rows = []
    for name, props in SAMPLES.items():
        vals = {}
        for variant in ("llvm_ad_rgb", "llvm_ad_spectral"):
            r = render_gonio({**props, "extinction": 1.0}, [30.0, 30.0], [30.0, -30.0],
                             [0.0, 0.0], variant=variant, spp=1, resolution=2)
            vals[variant] = r.analytic
        de = delta_e_2000(vals["llvm_ad_rgb"][None], vals["llvm_ad_spectral"][None], 1.0)[0]
        rows.append({"sample": name, **{k: v for k, v in props.items()},
                     "rgb_backscatter": vals["llvm_ad_rgb"][0].tolist(),
                     "spectral_backscatter": vals["llvm_ad_spectral"][0].tolist(),
                     "delta_e_backscatter": float(de[0]), "delta_e_mirror": float(de[1])})
    return rows


# ----------------------------------------------------------------------------- render cost

def render_cost(res_jit, spp_jit, res_scalar, spp_scalar) -> list[dict]:
    rows = []
    bsdfs = {"powder": {"type": "powder", **BROAD},
             "powder (Mie albedo)": {"type": "powder", "radius": 0.05, "extinction": 1.0},
             "diffuse": {"type": "diffuse"}, "roughplastic": {"type": "roughplastic"},
             "principled": {"type": "principled"}}
    for variant in ("scalar_rgb", "llvm_ad_rgb"):
        use_variant(variant)
        res, spp = (res_scalar, spp_scalar) if variant.startswith("scalar") else (res_jit,
                                                                                 spp_jit)
        times = {}
        for name, bsdf in bsdfs.items():
            scene = mi.load_dict({
                "type": "scene", "integrator": {"type": "direct"},
                "patch": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(100),
                          "bsdf": bsdf},
                "sky": {"type": "constant"},
                "sensor": {"type": "orthographic", "to_world": mi.ScalarTransform4f().look_at(
                    origin=[3, 0, 5], target=[0, 0, 0], up=[0, 0, 1]),
                    "film": {"type": "hdrfilm", "width": res, "height": res},
                    "sampler": {"type": "independent", "sample_count": spp}}})
            _render(scene, spp)
            times[name] = min(_render(scene, spp, seed=k)[1] for k in range(3))
        for name, sec in times.items():
            rows.append({"variant": variant, "bsdf": name, "pixels": res * res, "spp": spp,
                         "seconds": sec, "cost_vs_diffuse": sec / times["diffuse"]})
    return rows


def main() -> None:
    parser = arg_parser(__doc__)
    args = parser.parse_args()
    q = args.quick
    gres, gspp = (4, 4) if q else (64, 64)
    use_variant("llvm_ad_rgb")
    sampling = []
    for cone, props in (("sharp", SHARP), ("broad", BROAD)):
        for where, geom in (("back-scattering", (30.0, 30.0, 0.0)),
                            ("off-peak", (30.0, -50.0, 0.0))):
            for strategy, radius in (("bsdf", 5.0), ("mis", 1.0)):
                sampling += sampling_case_gonio(
                    f"gonio, {cone} cone, {where}, {radius:g}-deg source, {strategy}", props,
                    geom, strategy, radius, gres, gspp)
    sampling += sampling_case_sky("broad", BROAD, 30.0, gres, gspp)
    sampling += sampling_case_sky("sharp", SHARP, 30.0, gres, gspp)
    sres, sspp, sref = ((48, 15), 2, 8) if q else ((240, 75), 16, 1024)
    sampling += sampling_case_showcase(sres, sspp, sref)
    print("\n1. sampling: relative RMSE per pixel, equal spp; gain = time-to-equal-error ratio")
    print_table(sampling, [("case", "case", "s"), ("spp", "spp", "d"),
                           ("lobes_rel_rmse", "lobes err", ".4f"),
                           ("cosine_rel_rmse", "cosine err", ".4f"),
                           ("lobes_s", "lobes s", ".3f"), ("cosine_s", "cosine s", ".3f"),
                           ("equal_time_cosine_rel_rmse", "cos err @ equal t", ".4f"),
                           ("variance_ratio", "var ratio", ".2f"), ("gain", "gain", ".2f")])
    vres, vspp, vref = ((48, 15), 2, 4) if q else ((480, 150), 64, 512)
    variants, maps = variants_showcase(vres, vspp, vref)
    print("\n2. variants on the showcase")
    print_table(variants, [("variant", "variant", "s"), ("spp", "spp", "d"),
                           ("seconds", "s", ".2f"),
                           ("spectral_over_this_time", "spectral time / this", ".2f"),
                           ("delta_e_vs_spectral_mean", "DE00 mean", ".2f"),
                           ("delta_e_vs_spectral_p95", "DE00 p95", ".2f"),
                           ("luminance_rel_error_vs_spectral_median", "mono lum err", ".3f")])
    gonio_variants = variants_gonio(4 if q else 64, 4 if q else 16, q)
    print("\n   the gonio patch (sample 5's powder) over the protocols")
    print_table(gonio_variants, [("variant", "variant", "s"), ("seconds", "s", ".3f"),
                                 ("spectral_over_this_time", "spectral time / this", ".2f"),
                                 ("delta_e_vs_spectral_mean", "DE00 mean", ".2f"),
                                 ("delta_e_vs_spectral_max", "DE00 max", ".2f")])
    colours = variants_powder_colour()
    print("\n   BRF colour per powder, RGB variant vs spectral (CIEDE2000)")
    print_table(colours, [("sample", "sample", "s"), ("delta_e_backscatter", "DE00 retro", ".2f"),
                          ("delta_e_mirror", "DE00 mirror", ".2f")])
    cost = render_cost(*(((16, 4, 8, 2)) if q else (256, 64, 128, 16)))
    print("\n3. render cost (patch under a uniform sky, direct/MIS, equal spp)")
    print_table(cost, [("variant", "variant", "s"), ("bsdf", "bsdf", "s"),
                       ("seconds", "s", ".3f"), ("cost_vs_diffuse", "cost/diffuse", ".2f")])
    save(args.out, "render", [], q, sampling=sampling, variants=variants, colours=colours,
         render_cost=cost, gonio_variants=gonio_variants)
    plt = pyplot()
    fig, axes = plt.subplots(1, 2, figsize=(12, 3.6), gridspec_kw={"width_ratios": [1, 1.4]})
    ax = axes[0]
    ax.barh([r["case"] for r in sampling], [r["gain"] for r in sampling], color="tab:orange")
    ax.axvline(1.0, color="k", lw=0.8)
    ax.set_xscale("log")
    ax.set_xlabel("sampling gain of the lobe mixture over cosine (time to equal error)")
    ax.tick_params(labelsize=6)
    ax.invert_yaxis()
    im = axes[1].imshow(maps["delta_e"], cmap="magma", vmin=0)
    axes[1].set_title("CIEDE2000, llvm_ad_rgb vs llvm_ad_spectral (showcase)", fontsize=8)
    axes[1].axis("off")
    fig.colorbar(im, ax=axes[1], fraction=0.03)
    save_figure(fig, args.out / "render.png")


if __name__ == "__main__":
    main()
