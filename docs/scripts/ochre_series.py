"""An ochre series: hematite 1-50 % by mass in a clay (kaolinite) and in calcite, at two
hematite grain sizes.

Writes docs/figures/ochre_series.png and docs/ochre_table.md: sRGB swatches, CIELAB, reflectance
spectra and the back-scattering ratio of each mixture. Run from the repository root:
python docs/scripts/ochre_series.py [--quick] [--out DIR | --refresh-docs]
Everything optical comes from the powder plugin (mitsuba_powder.plugin.appearance.mixture_colour
for the colour, the plugin's eval for the back-scattering ratio).
"""

from __future__ import annotations

import math
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import drjit as dr  # noqa: E402
import matplotlib.pyplot as plt  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402
from docs_output import docs_parser, output_dir  # noqa: E402

from mitsuba_powder.plugin.appearance import mixture_colour  # noqa: E402
from mitsuba_powder.plugin.grains import mixture_properties  # noqa: E402
from mitsuba_powder.variants import use_variant  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
#: hematite mass fractions
MASS = [0.01, 0.02, 0.05, 0.1, 0.2, 0.5]
#: the extender (host) and its grain radius, um
HOSTS = [("kaolinite", 1.0), ("calcite", 1.0)]
#: hematite grain radii, um
HEMATITE_RADII = [0.05, 0.25]
#: BRDF parameters of every row (energy = "conserving": white hosts would otherwise reflect
#: more than they receive, docs/powder.md, "Energy")
BRDF = {"energy": "conserving", "extinction": 1.0}
#: the back-scattering ratio: BRF at exact back-scattering over BRF 10 degrees away from it in
#: the plane of incidence, light at 30 degrees, 550 nm
THETA_I, OFFSET, RATIO_NM = 30.0, 10.0, 550.0


def backscattering_ratio(props: dict) -> float:
    """BRF(wo = wi) / BRF(theta_o = theta_i + OFFSET, same azimuth) at RATIO_NM."""
    with use_variant("scalar_spectral"):
        bsdf = mi.load_dict({"type": "powder", **props})
        si = mi.SurfaceInteraction3f()
        si.wavelengths = mi.UnpolarizedSpectrum(RATIO_NM)
        t = math.radians(THETA_I)
        si.wi = mi.Vector3f(math.sin(t), 0.0, math.cos(t))
        values = []
        for theta_o in (THETA_I, THETA_I + OFFSET):
            o = math.radians(theta_o)
            wo = mi.Vector3f(math.sin(o), 0.0, math.cos(o))
            values.append(float(dr.slice(bsdf.eval(mi.BSDFContext(), si, wo)[0])) / wo.z)
    return values[0] / values[1]


def main() -> None:
    parser = docs_parser(__doc__, ROOT / "docs", "ochre_table.md and figures/ochre_series.png",
                         quick="two fractions, one grain size, coarse quadrature")
    args = parser.parse_args()
    args.out = output_dir(args, ROOT / "docs")
    mass = MASS[::3] if args.quick else MASS
    radii = HEMATITE_RADII[:1] if args.quick else HEMATITE_RADII
    samples = 128 if args.quick else 2048
    start = time.perf_counter()
    rows = []
    for host, host_radius in HOSTS:
        for r in radii:
            for w in mass:
                parts = [("hematite", w, r), (host, 1.0 - w, host_radius)]
                c = mixture_colour(parts, by="mass", samples=samples, **BRDF)
                props = {**mixture_properties(parts, by="mass"), **BRDF}
                rows.append((host, r, w, props["fraction2"], c, backscattering_ratio(props)))
    seconds = time.perf_counter() - start

    (args.out / "figures").mkdir(parents=True, exist_ok=True)
    groups = [(h, r) for h, _ in HOSTS for r in radii]
    fig = plt.figure(figsize=(11, 3.0 + 2.2 * len(groups) / 2 + 3.2))
    ax_sw = fig.add_axes([0.16, 0.52, 0.8, 0.42])
    for gi, (host, r) in enumerate(groups):
        sel = [row for row in rows if row[0] == host and row[1] == r]
        for i, (_, _, _, _, c, _) in enumerate(sel):
            ax_sw.add_patch(plt.Rectangle((i, len(groups) - 1 - gi), 0.95, 0.9,
                                          color=np.clip(c.srgb, 0, 1)))
        ax_sw.text(-0.1, len(groups) - 1 - gi + 0.45, f"in {host},\nhematite r = {r:g} um",
                   ha="right", va="center", fontsize=8)
    for i, w in enumerate(mass):
        ax_sw.text(i + 0.47, -0.2, f"{100 * w:g} %", ha="center", fontsize=8)
    ax_sw.set_xlim(-0.05, len(mass))
    ax_sw.set_ylim(-0.4, len(groups))
    ax_sw.axis("off")
    ax_sw.set_title("ochres: sRGB (D65, 0/d) against the hematite mass fraction", fontsize=10)
    ax_ref = fig.add_axes([0.07, 0.08, 0.4, 0.34])
    ax_lab = fig.add_axes([0.57, 0.08, 0.4, 0.34])
    host0, r0 = groups[0]
    cmap = plt.get_cmap("viridis")
    sel = [row for row in rows if row[0] == host0 and row[1] == r0]
    for i, (_, _, w, _, c, _) in enumerate(sel):
        ax_ref.plot(c.wavelengths_nm, c.reflectance, color=cmap(i / max(1, len(sel) - 1)),
                    label=f"{100 * w:g} %")
    ax_ref.set(xlabel="wavelength (nm)", ylabel="reflectance, 0/d",
               title=f"hematite (r = {r0:g} um) in {host0}")
    ax_ref.title.set_fontsize(9)
    ax_ref.legend(fontsize=7)
    for host, r in groups:
        sel = [row for row in rows if row[0] == host and row[1] == r]
        ax_lab.semilogx([100 * row[2] for row in sel], [row[4].lab[1] for row in sel], "o-",
                        label=f"a*, {host}, r = {r:g} um")
    ax_lab.set(xlabel="hematite, % by mass", ylabel="CIELAB a*")
    ax_lab.legend(fontsize=7)
    fig.savefig(args.out / "figures" / "ochre_series.png", dpi=110)

    lines = ["<!-- generated by docs/scripts/ochre_series.py --refresh-docs; do not edit -->",
             "| host | hematite radius (um) | hematite, mass | hematite, volume | sRGB (8 bit) "
             "| L* | a* | b* | reflectance 450 nm | reflectance 650 nm | back-scattering ratio |",
             "|---|---|---|---|---|---|---|---|---|---|---|"]
    for host, r, w, v, c, ratio in rows:
        i450 = int(np.argmin(abs(c.wavelengths_nm - 450)))
        i650 = int(np.argmin(abs(c.wavelengths_nm - 650)))
        lines.append(f"| {host} | {r:g} | {100 * w:g} % | {100 * (1 - v):.2f} % | {c.srgb8} | "
                     f"{c.lab[0]:.1f} | {c.lab[1]:.1f} | {c.lab[2]:.1f} | "
                     f"{c.reflectance[i450]:.3f} | {c.reflectance[i650]:.3f} | {ratio:.3f} |")
    lines.append("")
    lines.append(f"Computed in {seconds:.1f} s. Host grains of radius 1 um; energy = "
                 "\"conserving\", extinction = 1/um, g = 0, A_v = 1, tau_o from the mixture's "
                 "Bruggeman index, no surface term. Back-scattering ratio: BRF at exact "
                 f"back-scattering over BRF {OFFSET:g} degrees from it in the plane of incidence, "
                 f"light at {THETA_I:g} degrees, {RATIO_NM:g} nm.")
    (args.out / "ochre_table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
