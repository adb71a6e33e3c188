"""Colour of hematite powder against grain size for each grain model, and the paper's samples.

Writes docs/figures/grain_colour.png and docs/grain_colour_table.md.
Run from the repository root:  python docs/scripts/grain_colour.py [--quick]
Everything optical comes from the powder plugin (mitsuba_powder.plugin.appearance.powder_colour, in
llvm_ad_spectral): the 0/d reflectance under D65 with the plugin's default BRDF parameters
(amplitude_volume 1, g 0, extinction 1/um, Fresnel tau_o, no surface term).
"""

from __future__ import annotations

import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from docs_output import docs_parser, output_dir  # noqa: E402

from mitsuba_powder.plugin.appearance import PowderColour, powder_colour  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
SPHERE_RADII = [0.01, 0.017, 0.03, 0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 2.0]
AGGLOMERATE_RADII = [0.05, 0.1, 0.2, 0.3, 0.5, 1.0, 2.0]
FILLS = [0.3, 0.45, 0.6]
SLAB_RADII = [0.25, 0.5, 1.0, 2.0, 3.0]
CRYSTALLITE = 0.017  # um: samples 1-4 (Table 2 effective radii 15-17 nm)



def _agglomerate_1_4(radius: float) -> dict:
    """Samples 1-4 as agglomerates (radius 0.2 um, fill 0.4) of crystallites of ``radius``
    (um)."""
    return {"grains": "agglomerate", "radius": radius, "agglomerate_radius": 0.2,
            "agglomerate_fill": 0.4}


#: The paper's seven samples: the isolated-sphere model (scenes/showcase.xml) and the grain
#: model argued from the paper's description (scenes/showcase_grains.xml, its defaults)
SAMPLES = [
    ("1", {"radius": 0.017},
     _agglomerate_1_4(0.017)),
    ("2", {"radius": 0.016},
     _agglomerate_1_4(0.016)),
    ("3", {"radius": 0.016},
     _agglomerate_1_4(0.016)),
    ("4", {"radius": 0.015},
     _agglomerate_1_4(0.015)),
    ("5", {"radius": 0.083, "radius2": 0.046, "fraction2": 0.5},
     {"radius": 0.083, "radius2": 0.046, "fraction2": 0.5}),
    ("6", {"radius": 0.687, "radius2": 0.043, "fraction2": 0.5},
     {"grains": "agglomerate", "radius": 0.010, "agglomerate_radius": 0.687,
      "agglomerate_fill": 0.4}),
    ("7", {"radius": 2.222, "radius2": 0.049, "fraction2": 0.5},
     {"grains": "agglomerate", "radius": 0.049, "agglomerate_radius": 2.222,
      "agglomerate_fill": 0.4}),
]


def colour(props: dict, samples: int) -> PowderColour:
    """powder_colour of a property dict (radius first)."""
    props = dict(props)
    return powder_colour(props.pop("radius"), samples=samples, **props)


def describe(props: dict) -> str:
    """A short label of a grain configuration."""
    model = props.get("grains", "sphere")
    if model == "agglomerate":
        return (f"agglomerate R_a {props['agglomerate_radius']:g} um, fill "
                f"{props.get('agglomerate_fill', 0.5):g}, crystallites {props['radius']:g} um"
                + (", Maxwell Garnett" if props.get("mixing") == "maxwell_garnett" else ""))
    text = f"{model} r {props['radius']:g} um"
    if "radius2" in props:
        text += f" + {props['radius2']:g} um (fraction2 {props['fraction2']:g})"
    return text


def main() -> None:
    args = docs_parser(__doc__, ROOT / "docs", "grain_colour_table.md and figures/grain_colour.png",
                       quick="few sizes, coarse quadrature").parse_args()
    args.out = output_dir(args, ROOT / "docs")
    samples = 256 if args.quick else 2048
    pick = (lambda v: v[::3]) if args.quick else (lambda v: v)
    start = time.perf_counter()

    curves: dict[str, list[tuple[float, PowderColour]]] = {}
    curves["sphere"] = [(r, colour({"radius": r}, samples)) for r in pick(SPHERE_RADII)]
    for fill in pick(FILLS):
        curves[f"agglomerate, fill {fill:g}"] = [
            (ra, colour({"grains": "agglomerate", "radius": CRYSTALLITE,
                         "agglomerate_radius": ra, "agglomerate_fill": fill}, samples))
            for ra in pick(AGGLOMERATE_RADII)]
    curves["agglomerate, fill 0.45, Maxwell Garnett"] = [
        (ra, colour({"grains": "agglomerate", "radius": CRYSTALLITE, "agglomerate_radius": ra,
                     "agglomerate_fill": 0.45, "mixing": "maxwell_garnett"}, samples))
        for ra in pick(AGGLOMERATE_RADII)]
    curves["slab"] = [(r, colour({"grains": "slab", "radius": r}, samples))
                      for r in pick(SLAB_RADII)]
    paper = [] if args.quick else [
        (name, sphere, model, colour(sphere, samples), colour(model, samples))
        for name, sphere, model in SAMPLES]
    seconds = time.perf_counter() - start

    (args.out / "figures").mkdir(parents=True, exist_ok=True)
    fig = plt.figure(figsize=(12, 9))
    rows = len(curves)
    ax_sw = fig.add_axes([0.2, 0.52, 0.38, 0.40])
    for j, (label, curve) in enumerate(curves.items()):
        y = rows - 1 - j
        for i, (size, c) in enumerate(curve):
            ax_sw.add_patch(plt.Rectangle((i, y), 0.95, 0.9, color=np.clip(c.srgb, 0, 1)))
            ax_sw.text(i + 0.47, y + 0.4, f"{size:g}", ha="center", fontsize=7,
                       color="white" if c.lab[0] < 55 else "black")
        ax_sw.text(-0.1, y + 0.45, label, ha="right", va="center", fontsize=8)
    ax_sw.set_xlim(0, max(len(c) for c in curves.values()))
    ax_sw.set_ylim(0, rows)
    ax_sw.axis("off")
    ax_sw.set_title("hematite, sRGB (D65, 0/d) against size in um:\nradius (sphere, slab), "
                    "agglomerate radius (17 nm crystallites)", fontsize=9)
    ax_l = fig.add_axes([0.62, 0.56, 0.35, 0.38])
    ax_a = fig.add_axes([0.62, 0.08, 0.35, 0.38])
    for label, curve in curves.items():
        size = [s for s, _ in curve]
        ax_l.semilogx(size, [c.lab[0] for _, c in curve], "o-", label=label, ms=3)
        ax_a.plot([c.lab[1] for _, c in curve], [c.lab[2] for _, c in curve], "o-", ms=3,
                  label=label)
    ax_l.set(xlabel="size (um)", ylabel="L*")
    ax_l.legend(fontsize=7)
    ax_a.set(xlabel="a*", ylabel="b*", title="chromaticity (a*, b*)")
    ax_a.axhline(0, color="0.7", lw=0.5)
    ax_a.axvline(0, color="0.7", lw=0.5)
    if paper:
        ax_p = fig.add_axes([0.2, 0.06, 0.38, 0.38])
        for i, (name, _s, _m, cs, cm) in enumerate(paper):
            ax_p.add_patch(plt.Rectangle((i, 1), 0.95, 0.9, color=np.clip(cs.srgb, 0, 1)))
            ax_p.add_patch(plt.Rectangle((i, 0), 0.95, 0.9, color=np.clip(cm.srgb, 0, 1)))
            ax_p.text(i + 0.47, 2.0, f"sample {name}", ha="center", fontsize=8)
        ax_p.text(-0.1, 1.45, "isolated spheres\n(Table 2 radii)", ha="right", va="center",
                  fontsize=8)
        ax_p.text(-0.1, 0.45, "grain model per\nsample (assumed\nsizes, see text)",
                  ha="right", va="center", fontsize=8)
        ax_p.set_xlim(0, len(paper))
        ax_p.set_ylim(0, 2.3)
        ax_p.axis("off")
    fig.savefig(args.out / "figures" / "grain_colour.png", dpi=100)

    lines = ["<!-- generated by docs/scripts/grain_colour.py --refresh-docs; do not edit -->",
             "| grain model | size (um) | sRGB (8 bit) | L* | a* | b* | rho 450 nm | "
             "rho 650 nm |", "|---|---|---|---|---|---|---|---|"]

    def at(c: PowderColour, nm: float) -> float:
        return float(c.albedo[int(np.argmin(abs(c.wavelengths_nm - nm)))])

    for label, curve in curves.items():
        for size, c in curve:
            lines.append(f"| {label} | {size:g} | {c.srgb8} | {c.lab[0]:.1f} | {c.lab[1]:.1f} "
                         f"| {c.lab[2]:.1f} | {at(c, 450):.3f} | {at(c, 650):.3f} |")
    if paper:
        lines += ["", "| sample | model | sRGB (8 bit) | L* | a* | b* |",
                  "|---|---|---|---|---|---|"]
        for name, sphere, model, cs, cm in paper:
            for props, c in ((sphere, cs), (model, cm)):
                lines.append(f"| {name} | {describe(props)} | {c.srgb8} | {c.lab[0]:.1f} | "
                             f"{c.lab[1]:.1f} | {c.lab[2]:.1f} |")
    lines += ["", f"Computed in {seconds:.1f} s ({samples} quadrature nodes per colour)."]
    (args.out / "grain_colour_table.md").write_text("\n".join(lines) + "\n")
    print("\n".join(lines))


if __name__ == "__main__":
    main()
