"""Write the tables of docs/benchmarks.md from benchmarks/results/*.json.

    python benchmarks/report.py [--results DIR] [--doc docs/benchmarks.md]

Each table sits between ``<!-- table:NAME -->`` and ``<!-- /table:NAME -->`` in the page and
is replaced; the prose around them is not touched.
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _fmt(v, spec: str) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    return format(v, spec)


def md_table(rows: list[dict], columns: list[tuple[str, str, str]]) -> str:
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    sep = "|" + "|".join("---" for _ in columns) + "|"
    body = ["| " + " | ".join(_fmt(r.get(k), f) for k, _, f in columns) + " |" for r in rows]
    return "\n".join([head, sep, *body])


def tables(results: Path) -> dict[str, str]:
    load = lambda name: json.loads((results / f"{name}.json").read_text())  # noqa: E731
    out = {}
    bsdf = load("bsdf")
    out["machine"] = (f"{bsdf['meta']['cpu']}, {bsdf['meta']['cpus']} logical CPUs; Python "
                      f"{bsdf['meta']['python']}, mitsuba {bsdf['meta']['mitsuba']}, drjit "
                      f"{bsdf['meta']['drjit']}; measured {bsdf['meta']['date']}.")
    out["bsdf"] = md_table(bsdf["rows"], [
        ("variant", "variant", "s"), ("bsdf", "BSDF", "s"), ("eval", "eval M/s", ".1f"),
        ("sample", "sample M/s", ".1f"), ("eval_pdf", "eval_pdf M/s", ".1f"),
        ("eval_backward", "eval + backward M/s", ".1f"),
        ("eval_cost_vs_diffuse", "eval cost / diffuse", ".2f"),
        ("sample_cost_vs_diffuse", "sample cost / diffuse", ".2f"),
        ("eval_cost_vs_principled", "eval cost / principled", ".2f")])
    out["eval_breakdown"] = md_table(load("eval_breakdown")["rows"], [
        ("variant", "variant", "s"), ("configuration", "configuration", "s"),
        ("volume", "volume constants", "s"), ("ms", "eval ms", ".2f"),
        ("cost_vs_principled", "eval cost / principled", ".2f")])
    out["eval_size"] = md_table(load("eval_size")["rows"], [
        ("variant", "variant", "s"), ("log2_pairs", "log2 pairs", "d"),
        ("powder_ms", "powder ms", ".3f"), ("principled_ms", "principled ms", ".3f"),
        ("coloured_ms", "coloured principled ms", ".3f"),
        ("floor_ms", "memory floor ms", ".3f"),
        ("cost_vs_principled", "eval cost / principled", ".2f"),
        ("cost_vs_coloured", "eval cost / coloured principled", ".2f")])
    out["ab"] = md_table(load("ab")["rows"], [
        ("variant", "variant", "s"), ("configuration", "configuration", "s"),
        ("baseline_vs_principled", "baseline / principled", ".2f"),
        ("new_vs_principled", "new / principled", ".2f"),
        ("new_vs_baseline", "new / baseline", ".3f"),
        ("new_vs_baseline_fastest", "fastest new / fastest baseline", ".3f"),
        ("max_rel_difference", "max rel. difference", ".1e")])
    out["jit_ops"] = md_table(load("jit_ops")["rows"], [
        ("operation", "operation", "s"), ("ms", "ms per operation", ".3f"),
        ("cost_vs_fma", "cost / fma", ".1f")])
    py = load("python_bsdf")
    out["python_bsdf"] = md_table(py["rows"], [
        ("variant", "variant", "s"), ("implementation", "implementation", "s"),
        ("eval", "eval M/s", ".3g"), ("sample", "sample M/s", ".3g"),
        ("eval_pdf", "eval_pdf M/s", ".3g"), ("eval_cpp_speedup", "C++ eval speed-up", ".1f"),
        ("sample_cpp_speedup", "C++ sample speed-up", ".1f"),
        ("render_first_s", "first render s (compiles)", ".3f"),
        ("render_s", "render s", ".3f"), ("render_cpp_speedup", "C++ render speed-up", ".1f"),
        ("max_rel_difference", "max rel. difference", ".1e")])
    render = load("render")["meta"]
    out["sampling"] = md_table(render["sampling"], [
        ("case", "case", "s"), ("spp", "spp", "d"), ("lobes_rel_rmse", "error, lobes", ".4f"),
        ("cosine_rel_rmse", "error, cosine", ".4f"), ("lobes_s", "time lobes s", ".3f"),
        ("cosine_s", "time cosine s", ".3f"),
        ("equal_time_cosine_spp", "cosine spp at equal time", "d"),
        ("equal_time_cosine_rel_rmse", "cosine error at equal time", ".4f"),
        ("variance_ratio", "variance ratio cosine / lobes", ".2f"), ("gain", "gain", ".2f")])
    out["variants"] = md_table(render["variants"], [
        ("variant", "variant", "s"), ("spp", "spp", "d"), ("seconds", "render s", ".2f"),
        ("spectral_over_this_time", "spectral time / this", ".2f"),
        ("delta_e_vs_spectral_mean", "CIEDE2000 vs spectral, mean", ".2f"),
        ("delta_e_vs_spectral_p95", "p95", ".2f"), ("delta_e_vs_spectral_max", "max", ".1f"),
        ("luminance_rel_error_vs_spectral_median", "luminance error vs spectral (median)",
         ".3f")])
    out["gonio_variants"] = md_table(render.get("gonio_variants", []), [
        ("variant", "variant", "s"), ("geometries", "geometries", "d"), ("spp", "spp", "d"),
        ("seconds", "render s", ".3f"), ("spectral_over_this_time", "spectral time / this", ".2f"),
        ("delta_e_vs_spectral_mean", "CIEDE2000 vs spectral, mean", ".2f"),
        ("delta_e_vs_spectral_max", "max", ".2f")])
    cols = []
    for r in render["colours"]:
        radii = f"{1e3 * r['radius']:g} nm" + (f" + {1e3 * r['radius2']:g} nm"
                                               if "radius2" in r else "")
        cols.append({**r, "radii": radii,
                     "rgb": ", ".join(f"{v:.4f}" for v in r["rgb_backscatter"]),
                     "spec": ", ".join(f"{v:.4f}" for v in r["spectral_backscatter"])})
    out["colours"] = md_table(cols, [
        ("sample", "sample", "s"), ("radii", "radii", "s"),
        ("rgb", "BRF retro, llvm_ad_rgb (R, G, B)", "s"),
        ("spec", "BRF retro, llvm_ad_spectral (R, G, B)", "s"),
        ("delta_e_backscatter", "CIEDE2000 retro", ".2f"),
        ("delta_e_mirror", "CIEDE2000 mirror", ".2f")])
    out["render_cost"] = md_table(render["render_cost"], [
        ("variant", "variant", "s"), ("bsdf", "BSDF", "s"), ("pixels", "pixels", "d"),
        ("spp", "spp", "d"), ("seconds", "render s", ".3f"),
        ("cost_vs_diffuse", "cost / diffuse", ".2f")])
    mie = load("mie_update")
    out["mie_update"] = md_table([
        {**r, "u": 1e3 * r["update_s"], "ua": 1e3 * r["update_ad_s"],
         "eb": 1e3 * r["eval_backward_s"]} for r in mie["rows"]], [
        ("variant", "variant", "s"), ("radius_um", "radius (um)", "g"),
        ("directions", "pairs", "d"), ("u", "update (ms)", ".3f"),
        ("ua", "update with AD tangents (ms)", ".3f"), ("eb", "eval + backward (ms)", ".3f"),
        ("update_ad_over_eval_backward", "ratio", ".2f")])
    out["construction"] = md_table([
        {**r, "g": 1e3 * r["load_tau_given_s"], "f": 1e3 * r["load_tau_fresnel_s"],
         "d": 1e3 * r["fresnel_s"]} for r in mie.get("construction", [])], [
        ("variant", "variant", "s"), ("g", "load, tau_o given (ms)", ".2f"),
        ("f", "load, tau_o from Fresnel (ms)", ".2f"), ("d", "Fresnel table (ms)", ".2f")])
    fit = load("fit")
    before = {r["case"]: r for r in fit["meta"].get("before", [])}
    out["fit"] = md_table([{**r, "before_s": before.get(r["case"], {}).get("seconds"),
                            "before_evaluations": before.get(r["case"], {}).get("evaluations")}
                           for r in fit["rows"]], [
        ("protocol", "protocol", "s"), ("geometries", "geometries", "d"),
        ("wavelengths", "wavelengths", "d"), ("free", "free", "d"), ("starts", "starts", "d"),
        ("agreeing", "starts at the best", "d"), ("evaluations", "evaluations", "d"),
        ("seconds", "s", ".2f"), ("seconds_first", "s (first fit)", ".2f"),
        ("chi2_per_point", "chi2 / N", ".3f"), ("max_abs_z", "max abs z", ".2f"),
        ("before_s", "before: s", ".2f"), ("before_evaluations", "before: evaluations", "d")])
    out["fit_ptfe"] = md_table(fit["meta"].get("ptfe", []), [
        ("wavelength", "nm", "g"), ("seed", "seed", "d"), ("loss", "loss", ".6f"),
        ("reference_loss", "reference best", ".6f"), ("ratio", "loss / best", ".5f"),
        ("rmse", "RMSE BRF", ".5f"), ("agreeing", "starts at the best", "d"),
        ("seconds", "s", ".2f")])
    mem = load("memory")
    out["memory"] = md_table(mem["rows"], [
        ("job", "job", "s"), ("what", "what", "s"), ("peak_rss_mib", "peak RSS (MiB)", ".0f"),
        ("over_baseline_mib", "over its baseline (MiB)", ".0f"), ("seconds", "wall s", ".1f")])
    return out


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--results", type=Path, default=ROOT / "benchmarks" / "results")
    parser.add_argument("--doc", type=Path, default=ROOT / "docs" / "benchmarks.md")
    args = parser.parse_args()
    text = args.doc.read_text()
    for name, table in tables(args.results).items():
        pattern = re.compile(rf"(<!-- table:{name} -->\n)(?:.*?\n)?(<!-- /table:{name} -->)",
                             re.S)
        if not pattern.search(text):
            raise SystemExit(f"{args.doc}: no <!-- table:{name} --> block")
        text = pattern.sub(lambda m, t=table: m.group(1) + t + "\n" + m.group(2), text)
    args.doc.write_text(text)
    print(f"updated {args.doc}")


if __name__ == "__main__":
    main()
