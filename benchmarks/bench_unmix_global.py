"""The global stage of unmixing: Sobol starts against nlopt's MLSL and CRS2 on multimodal mixtures.

Synthetic single-scattering albedo spectra of 3- and 4-material mixtures (the plugin's mixture
rule, ``mitsuba_powder.plugin.grains.mixture_albedo``) at the 26 wavelengths 360-860 nm with
1 % noise (sigma = 1 % of the albedo), unmixed with every radius free as well as the fractions
(the multimodal case: the albedo of a population has several branches in its radius). Per
seed, the truth is drawn at random: volume fractions from a Dirichlet law (the white host the
largest on average), radii log-uniform within a factor 10^0.1 = 1.26 of the nominal ones
(``--radius-spread 0.3``: a factor 2). Every search starts where a user would (``--mix``):
equal fractions at the nominal radii, the radii free within a factor 10 of them.

Searches (``mitsuba_powder.fitting.unmix.unmix``, ``global_stage`` and ``starts``):

- ``local``: from the ``--mix`` start only (``starts=1``: the Levenberg-Marquardt steps and
  the polish; unmixing before the global stage existed);
- ``sobol``: the default 64 Sobol starts, batched Levenberg-Marquardt, the polish;
- ``mlsl``: nlopt's GN_MLSL_LDS (local searches by LD_MMA) then the same
  Levenberg-Marquardt steps and polish from its best distinct points;
- ``crs2``: nlopt's GN_CRS2_LM, then the same.

The nlopt stages get the model evaluations that ``sobol`` spent on the same spectrum, less
what their Levenberg-Marquardt steps and polish take (``--nlopt-share`` of it, default 0.85),
so that the totals are about equal. Per mixture and search: the success rate (every fraction
within 0.02 absolute of the truth), how often the search reached the chi2 of the truth or
lower and the best chi2 any search found for that spectrum (within 1 %: the search's own
success, whatever the data can decide), median chi2/dof, model evaluations (points, with or
without derivatives) and wall time.

Prints a table, writes benchmarks/results/unmix_global.json and unmix_global.png.
Run:  python benchmarks/bench_unmix_global.py [--quick] [--seeds N]
"""

from __future__ import annotations

import time

import numpy as np

from _common import arg_parser, print_table, pyplot, save, save_figure

WAVELENGTHS = np.arange(360.0, 861.0, 20.0)
#: (material, nominal radius um) per population; the first is the host
MIXTURES = {
    "3 materials": [("kaolinite", 1.0), ("hematite", 0.1), ("magnetite", 0.3)],
    "4 materials": [("kaolinite", 1.0), ("calcite", 0.2), ("hematite", 0.1),
                    ("magnetite", 0.3)],
}
#: Dirichlet weights of the true fractions (the host the largest on average)
ALPHA = {3: (4.0, 1.5, 1.0), 4: (4.0, 2.0, 1.5, 1.0)}
SEARCHES = ("local", "sobol", "mlsl", "crs2")
SUCCESS = 0.02

COLUMNS = [("mixture", "mixture", "s"), ("search", "search", "s"),
           ("success", "success (2 %)", ".0%"), ("reached_truth", "chi2 <= truth", ".0%"),
           ("reached_best", "best known", ".0%"),
           ("chi2_dof", "median chi2/dof", ".3g"), ("worst_error", "worst fraction error", ".3f"),
           ("evaluations", "evaluations", ".0f"), ("seconds", "seconds", ".2f")]


def case(materials: list, seed: int, spread: float) -> dict:
    """The truth and the noisy spectrum of one seed."""
    from mitsuba_powder.plugin.grains import mixture_albedo, mixture_properties

    rng = np.random.default_rng(seed)
    n = len(materials)
    fractions = rng.dirichlet(ALPHA[n])
    radii = [r * 10.0 ** rng.uniform(-spread, spread) for _, r in materials]
    truth = [(m, float(f), float(r)) for (m, _), f, r in zip(materials, fractions, radii)]
    rho, _ = mixture_albedo(mixture_properties(truth), WAVELENGTHS)
    albedo = np.clip(rho * (1.0 + 0.01 * rng.standard_normal(len(rho))), 0.0, 1.0)
    sigma = 0.01 * rho
    chi2_truth = float(np.sum(((rho - albedo) / sigma) ** 2))
    start = [(m, 1.0 / n, r) for m, r in materials]
    return {"truth": truth, "albedo": albedo, "sigma": sigma, "chi2_truth": chi2_truth,
            "start": start}


def run(c: dict, search: str, seed: int, budget: int | None, starts: int) -> dict:
    from mitsuba_powder.fitting.unmix import unmix

    kwargs = {"local": {"starts": 1}, "sobol": {"starts": starts}}.get(
        search, {"global_stage": search, "max_evaluations": budget})
    t = time.perf_counter()
    r = unmix(WAVELENGTHS, c["albedo"], c["sigma"], c["start"], free_radii=True, seed=seed,
              **kwargs)
    seconds = time.perf_counter() - t
    error = float(np.max(np.abs(r.fractions - [f for _, f, _ in c["truth"]])))
    return {"error": error, "chi2": r.chi2, "dof": r.dof, "evaluations": r.evaluations,
            "seconds": seconds,
            "reached_truth": bool(r.chi2 <= c["chi2_truth"] * (1.0 + 1e-3) + 1e-9)}


def summary(mixture: str, search: str, runs: list[dict]) -> dict:
    errors = np.array([r["error"] for r in runs])
    return {"mixture": mixture, "search": search, "seeds": len(runs),
            "success": float(np.mean(errors <= SUCCESS)),
            "reached_truth": float(np.mean([r["reached_truth"] for r in runs])),
            "reached_best": float(np.mean([r["reached_best"] for r in runs])),
            "chi2_dof": float(np.median([r["chi2"] / r["dof"] for r in runs])),
            "worst_error": float(np.max(errors)),
            "median_error": float(np.median(errors)),
            "evaluations": float(np.median([r["evaluations"] for r in runs])),
            "seconds": float(np.median([r["seconds"] for r in runs]))}


def figure(path, rows: list[dict]) -> None:
    plt = pyplot()
    fig, axes = plt.subplots(1, 4, figsize=(13, 3.4))
    mixtures = list(dict.fromkeys(r["mixture"] for r in rows))
    width = 0.8 / len(SEARCHES)
    for ax, key, label in zip(axes, ("success", "reached_best", "evaluations", "seconds"),
                              ("fractions within 2 % (share)", "best known chi2 (share)",
                               "model evaluations (median)", "seconds (median)")):
        for k, search in enumerate(SEARCHES):
            values = [next(r[key] for r in rows if r["mixture"] == m and r["search"] == search)
                      for m in mixtures]
            ax.bar(np.arange(len(mixtures)) + (k - 1.5) * width, values, width, label=search)
        ax.set_xticks(np.arange(len(mixtures)), mixtures)
        ax.set_title(label, fontsize=9)
    axes[0].legend(fontsize=7)
    save_figure(fig, path)


def main() -> None:
    ap = arg_parser(__doc__)
    ap.add_argument("--seeds", type=int, default=12, help="random mixtures per size")
    ap.add_argument("--starts", type=int, default=64, help="Sobol starts (the default 64)")
    ap.add_argument("--nlopt-share", type=float, default=0.85,
                    help="the nlopt stage's share of the Sobol run's evaluations")
    ap.add_argument("--radius-spread", type=float, default=0.1,
                    help="true radii within 10^+-this of the nominal ones (default 0.1)")
    args = ap.parse_args()
    seeds = 2 if args.quick else args.seeds
    starts = 8 if args.quick else args.starts
    mixtures = {"3 materials": MIXTURES["3 materials"]} if args.quick else MIXTURES
    rows, raw = [], []
    for mixture, materials in mixtures.items():
        runs: dict[str, list[dict]] = {s: [] for s in SEARCHES}
        for seed in range(seeds):
            c = case(materials, 1000 * len(materials) + seed, args.radius_spread)
            budget = None
            found = {}
            for search in SEARCHES:
                found[search] = run(c, search, seed, budget, starts)
                if search == "sobol":
                    budget = max(1, int(args.nlopt_share * found[search]["evaluations"]))
            best = min(c["chi2_truth"], *(r["chi2"] for r in found.values()))
            for search, r in found.items():
                r["reached_best"] = bool(r["chi2"] <= 1.01 * best)
                runs[search].append(r)
                raw.append({"mixture": mixture, "seed": seed, "search": search,
                            "chi2_truth": c["chi2_truth"], **r})
        rows += [summary(mixture, s, runs[s]) for s in SEARCHES]
    print(f"unmixing with the radii free, {len(WAVELENGTHS)} wavelengths, 1 % noise, "
          f"{seeds} random mixtures per size (true radii within 10^+-{args.radius_spread:g} "
          f"of the nominal ones); Sobol: {starts} starts; nlopt: "
          f"{args.nlopt_share:g} x the Sobol run's evaluations, then LM and the polish")
    print_table(rows, COLUMNS)
    save(args.out, "unmix_global", rows, args.quick, runs=raw, seeds=seeds, starts=starts,
         nlopt_share=args.nlopt_share, success=SUCCESS, radius_spread=args.radius_spread)
    figure(args.out / "unmix_global.png", rows)


if __name__ == "__main__":
    main()
