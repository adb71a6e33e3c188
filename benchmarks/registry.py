"""Every benchmark of the project, registered once.

A :class:`Benchmark` names its script, the results it writes (``<results>.json`` and
``<results>.png``), the column headers its printed table always shows, and the tables of
docs/benchmarks.md made from its JSON. ``run_all.py`` runs what is listed here, ``report.py``
writes the tables listed here, and the tests run every entry in quick mode and check that every
script in this folder is listed. Adding a benchmark: write the script (``--quick`` and
``--out`` as ``_common.arg_parser`` gives them), add one entry below, and put a
``<!-- table:NAME -->`` ... ``<!-- /table:NAME -->`` block into docs/benchmarks.md for each
table it fills.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

#: a table column: (key in the JSON row, header, format spec)
Column = tuple[str, str, str]


def _fmt(v, spec: str) -> str:
    if v is None:
        return "-"
    if isinstance(v, str):
        return v
    return format(v, spec)


def md_table(rows: list[dict], columns: list[Column]) -> str:
    """A Markdown table of ``rows`` with ``columns``; a missing value is written ``-``."""
    head = "| " + " | ".join(h for _, h, _ in columns) + " |"
    sep = "|" + "|".join("---" for _ in columns) + "|"
    body = ["| " + " | ".join(_fmt(r.get(k), f) for k, _, f in columns) + " |" for r in rows]
    return "\n".join([head, sep, *body])


def _rows(columns: list[Column], key: str = "rows") -> Callable[[dict], str]:
    """A table of the JSON's ``key`` list with ``columns``."""
    return lambda data: md_table(data[key], columns)


def _meta(key: str, columns: list[Column], optional: bool = False) -> Callable[[dict], str]:
    """A table of the list ``data["meta"][key]``; an ``optional`` one is empty where the
    results lack it (sections that a quick run or an older result file does not have)."""
    return lambda data: md_table(data["meta"].get(key, []) if optional else data["meta"][key],
                                 columns)


def _machine(data: dict) -> str:
    m = data["meta"]
    return (f"{m['cpu']}, {m['cpus']} logical CPUs; Python {m['python']}, mitsuba "
            f"{m['mitsuba']}, drjit {m['drjit']}; measured {m['date']}.")


def _colours(data: dict) -> str:
    cols = []
    for r in data["meta"]["colours"]:
        radii = f"{1e3 * r['radius']:g} nm" + (f" + {1e3 * r['radius2']:g} nm"
                                               if "radius2" in r else "")
        cols.append({**r, "radii": radii,
                     "rgb": ", ".join(f"{v:.4f}" for v in r["rgb_backscatter"]),
                     "spec": ", ".join(f"{v:.4f}" for v in r["spectral_backscatter"])})
    return md_table(cols, [
        ("sample", "sample", "s"), ("radii", "radii", "s"),
        ("rgb", "BRF retro, llvm_ad_rgb (R, G, B)", "s"),
        ("spec", "BRF retro, llvm_ad_spectral (R, G, B)", "s"),
        ("delta_e_backscatter", "CIEDE2000 retro", ".2f"),
        ("delta_e_mirror", "CIEDE2000 mirror", ".2f")])


def _mie_update(data: dict) -> str:
    return md_table([{**r, "u": 1e3 * r["update_s"], "ua": 1e3 * r["update_ad_s"],
                      "eb": 1e3 * r["eval_backward_s"]} for r in data["rows"]], [
        ("variant", "variant", "s"), ("radius_um", "radius (um)", "g"),
        ("directions", "pairs", "d"), ("u", "update (ms)", ".3f"),
        ("ua", "update with AD tangents (ms)", ".3f"), ("eb", "eval + backward (ms)", ".3f"),
        ("update_ad_over_eval_backward", "ratio", ".2f")])


def _construction(data: dict) -> str:
    return md_table([{**r, "g": 1e3 * r["load_tau_given_s"], "f": 1e3 * r["load_tau_fresnel_s"],
                      "d": 1e3 * r["fresnel_s"]} for r in data.get("construction", [])], [
        ("variant", "variant", "s"), ("g", "load, tau_o given (ms)", ".2f"),
        ("f", "load, tau_o from Fresnel (ms)", ".2f"), ("d", "Fresnel table (ms)", ".2f")])


def _fit(data: dict) -> str:
    before = {r["case"]: r for r in data["meta"].get("before", [])}
    rows = [{**r, "before_s": before.get(r["case"], {}).get("seconds"),
             "before_evaluations": before.get(r["case"], {}).get("evaluations")}
            for r in data["rows"]]
    return md_table(rows, [
        ("protocol", "protocol", "s"), ("geometries", "geometries", "d"),
        ("wavelengths", "wavelengths", "d"), ("free", "free", "d"), ("starts", "starts", "d"),
        ("agreeing", "starts at the best", "d"), ("evaluations", "evaluations", "d"),
        ("seconds", "s", ".2f"), ("seconds_first", "s (first fit)", ".2f"),
        ("chi2_per_point", "chi2 / N", ".3f"), ("max_abs_z", "max abs z", ".2f"),
        ("before_s", "before: s", ".2f"), ("before_evaluations", "before: evaluations", "d")])


#: tables that a script prints as they appear on docs/benchmarks.md
EVAL_SIZE_COLUMNS: list[Column] = [
    ("variant", "variant", "s"), ("log2_pairs", "log2 pairs", "d"),
    ("powder_ms", "powder ms", ".3f"), ("principled_ms", "principled ms", ".3f"),
    ("coloured_ms", "coloured principled ms", ".3f"),
    ("floor_ms", "memory floor ms", ".3f"),
    ("cost_vs_principled", "eval cost / principled", ".2f"),
    ("cost_vs_coloured", "eval cost / coloured principled", ".2f")]

AB_COLUMNS: list[Column] = [
    ("variant", "variant", "s"), ("configuration", "configuration", "s"),
    ("baseline_vs_principled", "baseline / principled", ".2f"),
    ("new_vs_principled", "new / principled", ".2f"),
    ("new_vs_baseline", "new / baseline", ".3f"),
    ("new_vs_baseline_fastest", "fastest new / fastest baseline", ".3f"),
    ("max_rel_difference", "max rel. difference", ".1e")]

PYTHON_BSDF_COLUMNS: list[Column] = [
    ("variant", "variant", "s"), ("implementation", "implementation", "s"),
    ("eval", "eval M/s", ".3g"), ("sample", "sample M/s", ".3g"),
    ("eval_pdf", "eval_pdf M/s", ".3g"),
    ("eval_cpp_speedup", "C++ eval speedup", ".1f"),
    ("sample_cpp_speedup", "C++ sample speedup", ".1f"),
    ("render_first_s", "first render s (compiles)", ".3f"),
    ("render_s", "render s", ".3f"),
    ("render_cpp_speedup", "C++ render speedup", ".1f"),
    ("max_rel_difference", "max rel. difference", ".1e")]


@dataclass(frozen=True)
class Benchmark:
    """One benchmark script and what it produces."""

    #: file name in benchmarks/
    script: str
    #: base name of the ``.json`` and ``.png`` it writes into ``--out``
    results: str
    #: column headers its printed table always contains (checked in quick mode)
    prints: tuple[str, ...]
    #: docs/benchmarks.md tables it fills: {table name: builder from its JSON}
    tables: dict[str, Callable[[dict], str]] = field(default_factory=dict)


BENCHMARKS: tuple[Benchmark, ...] = (
    Benchmark("bench_bsdf.py", "bsdf", ("eval M/s", "eval cost/diffuse"), {
        "machine": _machine,
        "bsdf": _rows([
            ("variant", "variant", "s"), ("bsdf", "BSDF", "s"), ("eval", "eval M/s", ".1f"),
            ("sample", "sample M/s", ".1f"), ("eval_pdf", "eval_pdf M/s", ".1f"),
            ("eval_backward", "eval + backward M/s", ".1f"),
            ("eval_cost_vs_diffuse", "eval cost / diffuse", ".2f"),
            ("sample_cost_vs_diffuse", "sample cost / diffuse", ".2f"),
            ("eval_cost_vs_principled", "eval cost / principled", ".2f")])}),
    Benchmark("bench_eval_breakdown.py", "eval_breakdown", ("eval ms", "cost / principled"), {
        "eval_breakdown": _rows([
            ("variant", "variant", "s"), ("configuration", "configuration", "s"),
            ("volume", "volume constants", "s"), ("ms", "eval ms", ".2f"),
            ("cost_vs_principled", "eval cost / principled", ".2f")])}),
    Benchmark("bench_eval_size.py", "eval_size", ("log2 pairs", "cost / coloured principled"), {
        "eval_size": _rows(EVAL_SIZE_COLUMNS)}),
    Benchmark("bench_ab.py", "ab", ("new / baseline", "max rel. difference"), {
        "ab": _rows(AB_COLUMNS)}),
    Benchmark("bench_jit_ops.py", "jit_ops", ("ms per op", "cost / fma"), {
        "jit_ops": _rows([
            ("operation", "operation", "s"), ("ms", "ms per operation", ".3f"),
            ("cost_vs_fma", "cost / fma", ".1f")])}),
    Benchmark("bench_python_bsdf.py", "python_bsdf", ("eval speedup", "render speedup"), {
        "python_bsdf": _rows(PYTHON_BSDF_COLUMNS)}),
    Benchmark("bench_render.py", "render", ("gain", "DE00 mean", "cost/diffuse"), {
        "sampling": _meta("sampling", [
            ("case", "case", "s"), ("spp", "spp", "d"),
            ("lobes_rel_rmse", "error, lobes", ".4f"),
            ("cosine_rel_rmse", "error, cosine", ".4f"), ("lobes_s", "time lobes s", ".3f"),
            ("cosine_s", "time cosine s", ".3f"),
            ("equal_time_cosine_spp", "cosine spp at equal time", "d"),
            ("equal_time_cosine_rel_rmse", "cosine error at equal time", ".4f"),
            ("variance_ratio", "variance ratio cosine / lobes", ".2f"),
            ("gain", "gain", ".2f")]),
        "variants": _meta("variants", [
            ("variant", "variant", "s"), ("spp", "spp", "d"), ("seconds", "render s", ".2f"),
            ("spectral_over_this_time", "spectral time / this", ".2f"),
            ("delta_e_vs_spectral_mean", "CIEDE2000 vs spectral, mean", ".2f"),
            ("delta_e_vs_spectral_p95", "p95", ".2f"),
            ("delta_e_vs_spectral_max", "max", ".1f"),
            ("luminance_rel_error_vs_spectral_median",
             "luminance error vs spectral (median)", ".3f")]),
        "gonio_variants": _meta("gonio_variants", [
            ("variant", "variant", "s"), ("geometries", "geometries", "d"),
            ("spp", "spp", "d"), ("seconds", "render s", ".3f"),
            ("spectral_over_this_time", "spectral time / this", ".2f"),
            ("delta_e_vs_spectral_mean", "CIEDE2000 vs spectral, mean", ".2f"),
            ("delta_e_vs_spectral_max", "max", ".2f")], optional=True),
        "colours": _colours,
        "render_cost": _meta("render_cost", [
            ("variant", "variant", "s"), ("bsdf", "BSDF", "s"), ("pixels", "pixels", "d"),
            ("spp", "spp", "d"), ("seconds", "render s", ".3f"),
            ("cost_vs_diffuse", "cost / diffuse", ".2f")])}),
    Benchmark("bench_mie_update.py", "mie_update", ("update+AD ms", "Fresnel ms"), {
        "mie_update": _mie_update, "construction": _construction}),
    Benchmark("bench_mie_table.py", "mie_table", ("max rel. error", "at nm"), {
        "mie_table": _rows([
            ("material", "material", "s"), ("radius_um", "radius (um)", "g"),
            ("max_rel_error", "largest relative error of rho", ".1e"),
            ("at_nm", "at (nm)", ".2f"),
            ("poly_max_rel_error", "degree-32 polynomial", ".1e")])}),
    Benchmark("bench_fit.py", "fit", ("s (first)", "loss/best", "agreeing"), {
        "fit": _fit,
        "fit_ptfe": _meta("ptfe", [
            ("wavelength", "nm", "g"), ("seed", "seed", "d"), ("loss", "loss", ".6f"),
            ("reference_loss", "reference best", ".6f"), ("ratio", "loss / best", ".5f"),
            ("rmse", "RMSE BRF", ".5f"), ("agreeing", "starts at the best", "d"),
            ("seconds", "s", ".2f")], optional=True)}),
    Benchmark("bench_memory.py", "memory", ("peak RSS MiB",), {
        "memory": _rows([
            ("job", "job", "s"), ("what", "what", "s"),
            ("peak_rss_mib", "peak RSS (MiB)", ".0f"),
            ("over_baseline_mib", "over its baseline (MiB)", ".0f"),
            ("seconds", "wall s", ".1f")])}),
    # their tables are on the pages of their features (docs/powder.md, docs/rti.md, docs/fitting.md)
    Benchmark("bench_textures.py", "textures", ("relative to constant", "max relative error")),
    Benchmark("bench_rti_fit.py", "rti_fit", ("fit s", "peak MiB")),
    Benchmark("bench_rti_tiles.py", "rti_tiles", ("fit s", "peak MiB/worker", "identical")),
    Benchmark("bench_relief.py", "relief", ("step", "time s")),
    Benchmark("bench_unmix_global.py", "unmix_global", ("success (2 %)", "chi2 <= truth",
                                                        "evaluations")),
    Benchmark("ptfe_reference_fit.py", "ptfe_reference", ("RMSE BRF", "within 1 %")),
)
