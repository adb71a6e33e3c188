"""Unmixing against the baselines: the powder model, Hapke's intimate-mixture rule and
two-constant Kubelka-Munk fitted to the same synthetic reflectance spectra.

Writes docs/unmix_baselines_table.md (and prints it). Run from the repository root:
python docs/scripts/unmix_baselines.py [--quick] [--out DIR | --refresh-docs]

Everything is synthetic (no measured mixture spectra are available to the project): the
"measured" mixtures and the endmember swatches a user would have (each pure material's
reflectance, and for Kubelka-Munk a tint of each pigment at 10 % by mass in the white host)
are the powder plugin's predictions, except the mixtures made by a baseline's own rule. The
powder model wins on its own mixtures by construction; the rows made by Hapke's rule and by
Kubelka-Munk test the other direction.
"""

from __future__ import annotations

import time
from pathlib import Path

import numpy as np
from docs_output import docs_parser, output_dir, write_output

from mitsuba_powder.fitting import mixing_rules as rules
from mitsuba_powder.fitting.unmix_baselines import (
    PowderReflectance,
    unmix_hapke,
    unmix_km,
    unmix_powder,
)
from mitsuba_powder.plugin.grains import mixture_albedo, mixture_properties, volume_fractions

ROOT = Path(__file__).resolve().parents[2]
#: 24 wavelengths 360-820 nm (the 0/d quadrature of energy = "conserving" is for 360-830 nm)
WAVELENGTHS = np.arange(360.0, 821.0, 20.0)
#: the plugin's other properties, of every powder spectrum here (tau_o given: the powder
#: model's reflectance inversion needs it fixed; energy = "conserving": the white host would
#: otherwise reflect more than it receives, docs/powder.md, "Energy")
PROPERTIES = {"energy": "conserving", "extinction": 1.0, "tau_o": 2.0}
#: 0/d reflectance noise (absolute standard deviation) and its seed
SIGMA, SEED = 0.005, 1
#: the mixtures: name, (material, mass fraction, radius um) with the white host first
MIXTURES = [
    ("ochre: 10 % hematite (0.05 um) in kaolinite",
     [("kaolinite", 0.90, 1.0), ("hematite", 0.10, 0.05)]),
    ("kaolinite + 20 % hematite (0.1 um) + 15 % magnetite (0.3 um)",
     [("kaolinite", 0.65, 1.0), ("hematite", 0.20, 0.1), ("magnetite", 0.15, 0.3)]),
]
#: the pigment's mass fraction in a tint with the host (not a mixture's own: a Kubelka-Munk
#: fitted on a tint reproduces that tint exactly)
TINT = 0.05


def powder_albedo(parts: list, by: str = "mass") -> np.ndarray:
    """The plugin's single-scattering albedo of ``(material, fraction, radius)`` populations."""
    if len(parts) == 1:
        m, _, r = parts[0]
        return mixture_albedo({"material": m, "radius": r}, WAVELENGTHS)[0]
    return mixture_albedo(mixture_properties(parts, by), WAVELENGTHS)[0]


def swatches(parts: list, engine: PowderReflectance) -> tuple[np.ndarray, list]:
    """The pure materials' reflectance (endmembers) and the tints of each pigment with the
    host (population 1), all by the powder plugin."""
    ends = engine(np.array([powder_albedo([p]) for p in parts]))
    host = parts[0]
    tints = [(engine(powder_albedo([(host[0], 1.0 - TINT, host[2]),
                                    (m, TINT, r)])[None])[0], TINT) for m, _, r in parts[1:]]
    return ends, tints


def generated(rule: str, parts: list, engine, ends, tints) -> np.ndarray:
    """The noise-free mixture reflectance by ``rule`` (powder, hapke or km)."""
    mass = np.array([f for _, f, _ in parts])
    if rule == "powder":
        return engine(powder_albedo(parts)[None])[0]
    if rule == "hapke":
        vol = np.array(volume_fractions([(m, f) for m, f, _ in parts], "mass"))
        w = rules.hapke_albedo(ends)
        return rules.hapke_reflectance(rules.hapke_mixture_albedo(
            w, vol, [r for _, _, r in parts]))
    ratio = rules.km_ratio(ends)
    k, s = ratio.copy(), np.ones_like(ratio)
    for j, (tint, c) in enumerate(tints, start=1):
        k[j], s[j] = rules.km_constants(ends[j], tint, c, ratio[0])
    return rules.km_mixture_reflectance(mass, k, s)


def unmix_all(r, sig, start, ends, tints) -> list:
    """(result, seconds) of the powder model, Hapke's rule, Kubelka-Munk with tints and with
    S = 1, on the same reflectance ``r``."""
    calls = [lambda: unmix_powder(WAVELENGTHS, r, sig, start, "mass", properties=PROPERTIES),
             lambda: unmix_hapke(WAVELENGTHS, r, sig, ends, start, "mass"),
             lambda: unmix_km(WAVELENGTHS, r, sig, ends, start, "mass", tints=tints),
             lambda: unmix_km(WAVELENGTHS, r, sig, ends, start, "mass")]
    out = []
    for call in calls:
        t0 = time.perf_counter()
        out.append((call(), time.perf_counter() - t0))
    return out


def main() -> None:
    parser = docs_parser(__doc__, ROOT / "docs", "unmix_baselines_table.md",
                         quick="the first mixture, made by the powder model and by Hapke's "
                               "rule, at 11 wavelengths")
    args = parser.parse_args()
    global WAVELENGTHS
    if args.quick:
        WAVELENGTHS = np.arange(400.0, 801.0, 40.0)
    out = output_dir(args, ROOT / "docs")
    engine = PowderReflectance(WAVELENGTHS, "0:d", PROPERTIES)
    rng = np.random.default_rng(SEED)
    lines = ["<!-- generated by docs/scripts/unmix_baselines.py --refresh-docs; do not "
             "edit -->",
             "| mixture | made by | unmixed by | mass fractions fitted +- standard uncertainty "
             "| abs. error, largest | RMS reflectance | chi2 / dof | s |",
             "|---|---|---|---|---|---|---|---|"]
    notes: list[str] = []
    numbers: list = []  # every number of the table, checked finite before it is written
    start_all = time.perf_counter()
    for name, parts in MIXTURES[:1] if args.quick else MIXTURES:
        truth = np.array([f for _, f, _ in parts])
        ends, tints = swatches(parts, engine)
        start = [(m, 1.0 / len(parts), r) for m, _, r in parts]  # an even start, by mass
        for rule in ("powder", "hapke") if args.quick else ("powder", "hapke", "km"):
            clean = generated(rule, parts, engine, ends, tints)
            r = clean + SIGMA * rng.standard_normal(len(clean))
            fits = unmix_all(r, np.full(len(r), SIGMA), start, ends, tints)
            for u, seconds in fits:
                shown = ", ".join(f"{m} {f:.3f} +- {e:.3f}" for m, f, e in zip(
                    u.materials, u.mass_fractions, u.mass_fraction_errors))
                err = float(np.max(np.abs(u.mass_fractions - truth)))
                numbers.append([u.mass_fractions.tolist(), u.mass_fraction_errors.tolist(), err,
                              u.rms, u.chi2 / u.dof])
                lines.append(f"| {name} ({', '.join(f'{f:g}' for f in truth)}) | {rule} | "
                             f"{u.method} | {shown} | {err:.3f} | {u.rms:.4f} | "
                             f"{u.chi2 / u.dof:.2f} | {seconds:.1f} |")
                notes += [f"- {name}, made by {rule}, unmixed by {u.method}: {w}"
                          for w in u.warnings]
            print("\n".join(lines[-4:]))
    lines.append("")
    if notes:
        lines += ["Warnings of the fits:", ""] + notes + [""]
    lines.append(f"Computed in {time.perf_counter() - start_all:.0f} s. 0/d reflectance at "
                 f"{len(WAVELENGTHS)} wavelengths {WAVELENGTHS[0]:g}-{WAVELENGTHS[-1]:g} nm "
                 f"with noise of standard deviation {SIGMA:g} (seed {SEED}); plugin properties "
                 f"{PROPERTIES}; start: equal mass fractions. Endmembers and tints "
                 f"({100 * TINT:g} % by mass in the host) by the powder plugin (synthetic).")
    write_output(out, "unmix_baselines_table.md", "\n".join(lines) + "\n", finite=numbers)
    print("\n".join(lines))


if __name__ == "__main__":
    main()
