"""Fit time, evaluations and loss against the number of geometries and wavelengths.

1. Synthetic data (1.5 % noise, hematite grains of radius 0.05 um) at the protocol geometries
   and 1, 5 or 26 wavelengths (the seed's 360-860 nm by 20 nm), fitted with the default strategy
   and free set (one wavelength: A_v, g, kappa, albedo, A_s', l_c; several: the radius instead of
   the albedo). Each fit runs four times in the same process: "s (first)" includes kernel
   compilation and imports, "s" is the best of the three after it.
2. NIST PTFE (measurements/ptfe_germer2017.csv) at 351, 532, 633 and 1064 nm with three seeds:
   the loss reached against the best loss of the independent 60-start reference fit
   (benchmarks/ptfe_reference_fit.py -> results/ptfe_reference.json).
3. With ``--before DIR``: the same synthetic cases fitted by an earlier version of the package
   (``DIR`` holds its ``mitsuba_powder`` folder with a built plugin), in a subprocess, with that
   version's defaults, so that today's and the earlier figures sit side by side
   (``--before-from FILE`` reuses the "before" rows of an earlier results file, with its date
   and command).
4. The ``fit`` command end to end: the 26-wavelength data of case 4 (``--quick``: case 1)
   written to a CSV and fitted by ``python -m mitsuba_powder.cli fit DATA.csv --figures MODE``
   in a fresh process for each of ``--figures summary``, ``all`` and ``none``: the optimiser's
   time (``optimizer.seconds`` of that run's ``fit.json``, i.e. ``FitResult.seconds``) beside
   the command's wall time (process start to exit: imports, loading, fit, report, figures)
   and their ratio, both from the same run. The modes take turns in each of ``--repeat``
   rounds, after one unreported warm-up run (Dr.Jit's kernel cache and the file cache).
   ``--command-only`` runs this section alone and writes results/fit_command.json.

Prints tables, writes benchmarks/results/fit.json and fit.png (with section 4 in its meta as
``command_rows``).
Run:  python benchmarks/bench_fit.py [--quick] [--before DIR] [--command-only] [--repeat N]
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from _common import arg_parser, print_table, save, save_figure

ROOT = Path(__file__).resolve().parents[1]
TRUTH = {"amplitude_volume": 1.1, "g": 0.2, "extinction": 0.5, "radius": 0.05,
         "amplitude_surface": 1e-4, "correlation_length": 2.0}
PTFE_FREE = ["amplitude_volume", "g", "extinction", "albedo", "amplitude_surface",
             "correlation_length"]
PTFE_FIXED = {"eta": 1.35, "k": 0.0}
CASES = {
    "1": ("backscatter", (700.0,)),
    "2": ("shadows,backscatter", (700.0,)),
    "3": ("shadows,backscatter", (400.0, 500.0, 600.0, 700.0, 800.0)),
    "4": ("shadows,backscatter", tuple(float(w) for w in np.arange(360.0, 861.0, 20.0))),
}

#: Run by ``--before``: an earlier package's fit() with its defaults on one case
BEFORE = """
import json, sys, time
import numpy as np
from mitsuba_powder.fitting.fit import fit
from mitsuba_powder.fitting.protocols import simulate
truth, protocol, wavelengths = json.loads(sys.argv[1])
data = simulate(truth, protocol, tuple(wavelengths), noise=0.015, seed=1)
fixed = {"radius": truth["radius"]} if len(wavelengths) == 1 else {}
t = time.perf_counter()
result = fit(data, fixed=fixed)
seconds = time.perf_counter() - t
print(json.dumps({"seconds": seconds, "evaluations": result.evaluations,
                  "free": len(result.free), "chi2_per_point": result.loss / len(data)}))
"""


def synthetic_rows(cases: list[str]) -> list[dict]:
    from mitsuba_powder.fitting.fit import fit
    from mitsuba_powder.fitting.protocols import simulate

    rows = []
    for key in cases:
        protocol, wavelengths = CASES[key]
        data = simulate(TRUTH, protocol, wavelengths, noise=0.015, seed=1)
        times = []
        for _ in range(4):  # the first includes compilation; the best of the others is kept
            t = time.perf_counter()
            result = fit(data)
            times.append(time.perf_counter() - t)
        z = {n: (result.parameters[n] - TRUTH[n]) / result.uncertainties[n]
             for n in result.free if n in TRUTH}
        rows.append({"case": key, "protocol": protocol, "geometries": len(data) //
                     len(wavelengths), "wavelengths": len(wavelengths),
                     "free": len(result.free), "starts": len(result.starts),
                     "agreeing": result.agreeing, "evaluations": result.evaluations,
                     "seconds_first": times[0], "seconds": min(times[1:]),
                     "chi2_per_point": result.chi2_per_point,
                     "max_abs_z": max(abs(v) for v in z.values()),
                     "warnings": result.warnings})
        print(f"{protocol:20s} {rows[-1]['geometries']:4d} geometries x {len(wavelengths):2d} "
              f"wavelengths: {min(times[1:]):6.2f} s (first {times[0]:.2f} s), "
              f"{result.evaluations} evaluations, chi2/N {result.chi2_per_point:.3f}, "
              f"{result.agreeing}/{len(result.starts)} starts agree, max |z| "
              f"{rows[-1]['max_abs_z']:.2f}", flush=True)
    return rows


def before_rows(cases: list[str], package: Path) -> list[dict]:
    rows = []
    env = {**os.environ, "PYTHONPATH": str(package)}
    for key in cases:
        protocol, wavelengths = CASES[key]
        proc = subprocess.run([sys.executable, "-c", BEFORE,
                               json.dumps([TRUTH, protocol, list(wavelengths)])],
                              capture_output=True, text=True, env=env, timeout=3600)
        if proc.returncode != 0:
            raise SystemExit(f"--before {package}: {proc.stderr.strip()[-2000:]}")
        out = json.loads(proc.stdout.strip().splitlines()[-1])
        rows.append({"case": key, "protocol": protocol, "geometries": None,
                     "wavelengths": len(wavelengths), **out})
        print(f"before: {protocol:20s} x {len(wavelengths):2d} wavelengths: "
              f"{out['seconds']:7.2f} s, {out['evaluations']} evaluations, chi2/N "
              f"{out['chi2_per_point']:.3f}", flush=True)
    return rows


def ptfe_rows(wavelengths: list[float], seeds: list[int], starts: int | None) -> list[dict]:
    from mitsuba_powder.fitting.fit import DEFAULT_STARTS, fit
    from mitsuba_powder.io.measurements import load_measurements

    reference = json.loads((ROOT / "benchmarks" / "results" / "ptfe_reference.json")
                           .read_text())
    best = {r["wavelength_nm"]: r["loss"] for r in reference["rows"]}
    data = load_measurements(ROOT / "measurements" / "ptfe_germer2017.csv")
    rows = []
    for lam in wavelengths:
        d = data.subset(data.wavelength == lam)
        for seed in seeds:
            t = time.perf_counter()
            result = fit(d, PTFE_FREE, PTFE_FIXED, starts=starts or DEFAULT_STARTS, seed=seed)
            seconds = time.perf_counter() - t
            rows.append({"wavelength": lam, "seed": seed, "n": len(d), "loss": result.loss,
                         "reference_loss": best[lam], "ratio": result.loss / best[lam],
                         "rmse": result.rmse(), "agreeing": result.agreeing,
                         "starts": len(result.starts), "seconds": seconds,
                         "evaluations": result.evaluations})
            print(f"PTFE {lam:6g} nm seed {seed}: loss {result.loss:.6f} (reference "
                  f"{best[lam]:.6f}, ratio {result.loss / best[lam]:.5f}), "
                  f"{result.agreeing}/{len(result.starts)} agree, {seconds:.2f} s", flush=True)
    return rows


#: The ``fit --figures`` modes of section 4, in the order they take turns
FIGURE_MODES = ("summary", "all", "none")
#: Section 4's command, as the tables quote it
FIT_COMMAND = "python -m mitsuba_powder.cli fit DATA.csv --figures MODE --out DIR"


def command_rows(case: str, repeat: int, workdir: Path) -> list[dict]:
    """Section 4: the ``fit`` command end to end, one fresh process per run (see the module
    docstring)."""
    import mitsuba_powder
    from mitsuba_powder.fitting.protocols import simulate
    from mitsuba_powder.io.measurements import save_measurements

    protocol, wavelengths = CASES[case]
    data = simulate(TRUTH, protocol, wavelengths, noise=0.015, seed=1)
    csv = workdir / f"synthetic_{len(wavelengths)}wl.csv"
    save_measurements(csv, data)
    package = str(Path(mitsuba_powder.__file__).resolve().parents[1])
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(
        [package] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])}

    def run(mode: str, out: Path) -> tuple[float, dict]:
        cmd = [sys.executable, "-m", "mitsuba_powder.cli", "fit", str(csv), "--figures", mode,
               "--out", str(out)]
        t = time.perf_counter()
        proc = subprocess.run(cmd, capture_output=True, text=True, env=env, timeout=3600)
        wall = time.perf_counter() - t
        if proc.returncode != 0:
            raise SystemExit(f"{' '.join(cmd)}: {proc.stderr.strip()[-2000:]}")
        return wall, json.loads((out / "fit.json").read_text())

    run("none", workdir / "warm-up")
    rows = []
    for r in range(repeat):
        for mode in FIGURE_MODES:
            out = workdir / f"{mode}_{r + 1}"
            load = os.getloadavg()[0]  # other work on the machine: the times depend on it
            wall, report = run(mode, out)
            seconds = report["optimizer"]["seconds"]
            rows.append({"case": case, "wavelengths": len(wavelengths),
                         "measurements": len(data), "figures": mode, "run": r + 1,
                         "optimiser_s": seconds, "command_s": wall,
                         "other_s": wall - seconds, "ratio": wall / seconds,
                         "png_files": len(list(out.glob("*.png"))), "load_1min": load})
            print(f"fit --figures {mode:7s} ({len(data)} measurements, {len(wavelengths)} "
                  f"wavelengths), run {r + 1}: optimiser {seconds:.2f} s, command "
                  f"{wall:.2f} s, ratio {wall / seconds:.2f}, "
                  f"{rows[-1]['png_files']} PNG files", flush=True)
    return rows


def command_medians(rows: list[dict]) -> list[dict]:
    """Per ``--figures`` mode: the median over the runs of section 4 (the ratio is the median
    of each run's own ratio, not a ratio of medians)."""
    out = []
    for mode in FIGURE_MODES:
        runs = [r for r in rows if r["figures"] == mode]
        if runs:
            out.append({"figures": mode, "runs": len(runs), **{
                k: float(np.median([r[k] for r in runs]))
                for k in ("optimiser_s", "command_s", "other_s", "ratio")},
                "ratio_max": max(r["ratio"] for r in runs),
                "png_files": runs[0]["png_files"]})
    return out


MEDIAN_COLUMNS = [("figures", "--figures", "s"), ("runs", "runs", "d"),
                  ("optimiser_s", "optimiser s", ".2f"), ("command_s", "command s", ".2f"),
                  ("other_s", "command - optimiser s", ".2f"),
                  ("ratio", "median ratio", ".2f"), ("ratio_max", "max ratio", ".2f"),
                  ("png_files", "PNG files", "d")]
COMMAND_COLUMNS = [("figures", "--figures", "s"), ("run", "run", "d"),
                   ("measurements", "rows", "d"), ("wavelengths", "wl", "d"),
                   ("optimiser_s", "optimiser s", ".2f"), ("command_s", "command s", ".2f"),
                   ("other_s", "command - optimiser s", ".2f"),
                   ("ratio", "command/optimiser", ".2f"), ("png_files", "PNG files", "d"),
                   ("load_1min", "load avg", ".2f")]


def plot(rows: list[dict], before: list[dict], path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6, 3.5))
    ax.plot([r["wavelengths"] for r in rows], [r["seconds"] for r in rows], "o", label="today")
    if before:
        ax.plot([r["wavelengths"] for r in before], [r["seconds"] for r in before], "s",
                color="tab:gray", label="before")
    ax.set(xscale="log", yscale="log", xlabel="wavelengths fitted jointly",
           ylabel="fit time (s)", title="fit time, 2-core machine")
    ax.legend()
    save_figure(fig, path)


def main() -> None:

    parser = arg_parser(__doc__)
    parser.add_argument("--before", type=Path, default=None,
                        help="folder holding an earlier mitsuba_powder package to compare")
    parser.add_argument("--before-from", type=Path, default=None,
                        help="reuse the 'before' rows of an earlier results/fit.json (its "
                             "date and command are kept with them)")
    parser.add_argument("--command-only", action="store_true",
                        help="run section 4 alone (the fit command end to end per --figures "
                             "mode) and write results/fit_command.json")
    parser.add_argument("--repeat", type=int, default=None,
                        help="rounds of section 4 (default 3; --quick: 1)")
    args = parser.parse_args()
    repeat = args.repeat if args.repeat is not None else (1 if args.quick else 3)
    if repeat < 1:
        parser.error(f"--repeat: {repeat} is outside the valid range [1, inf)")
    command_case = "1" if args.quick else "4"
    flags = (" --quick" if args.quick else "") + (f" --repeat {args.repeat}"
                                                   if args.repeat else "")
    if args.command_only:
        with tempfile.TemporaryDirectory() as tmp:
            cli = command_rows(command_case, repeat, Path(tmp))
        print_table(cli, COMMAND_COLUMNS)
        print_table(command_medians(cli), MEDIAN_COLUMNS)
        save(args.out, "fit_command", cli, args.quick,
             command="python benchmarks/bench_fit.py --command-only" + flags,
             fit_command=FIT_COMMAND, medians=command_medians(cli))
        return
    cases = ["1"] if args.quick else list(CASES)
    rows = synthetic_rows(cases)
    before = before_rows(cases, args.before) if args.before else []
    if args.before_from:
        earlier = json.loads(args.before_from.read_text())["meta"]
        before = [{**r, "measured": f"{earlier.get('date')}, {earlier.get('command')}"}
                  for r in earlier["before"]]
    ptfe = (ptfe_rows([532.0], [0], 8) if args.quick else
            ptfe_rows([351.0, 532.0, 633.0, 1064.0], [0, 1, 2], None))
    with tempfile.TemporaryDirectory() as tmp:
        cli = command_rows(command_case, repeat, Path(tmp))
    command = ("python benchmarks/bench_fit.py" + flags
               + (" --before DIR" if args.before else ""))
    print_table(rows, [("protocol", "protocol", "s"), ("wavelengths", "wl", "d"),
                       ("free", "free", "d"), ("starts", "starts", "d"),
                       ("agreeing", "agreeing", "d"), ("evaluations", "evals", "d"),
                       ("seconds", "s", ".2f"), ("seconds_first", "s (first)", ".2f"),
                       ("chi2_per_point", "chi2/N", ".3f"), ("max_abs_z", "max|z|", ".2f")])
    print_table(ptfe, [("wavelength", "nm", "g"), ("seed", "seed", "d"),
                       ("loss", "loss", ".6f"), ("reference_loss", "best known", ".6f"),
                       ("ratio", "loss/best", ".5f"), ("agreeing", "agreeing", "d"),
                       ("seconds", "s", ".2f")])
    print_table(cli, COMMAND_COLUMNS)
    print_table(command_medians(cli), MEDIAN_COLUMNS)
    save(args.out, "fit", rows, args.quick, command=command, before=before, ptfe=ptfe,
         command_rows=cli, command_medians=command_medians(cli), fit_command=FIT_COMMAND)
    plot(rows, before, args.out / "fit.png")


if __name__ == "__main__":
    main()
