"""Figure of the plane of incidence in the three angle conventions the loader meets.

Writes docs/figures/ipag_conventions.png. Run from the repo root:

    python docs/scripts/ipag_conventions.py [--out FOLDER]

The angles written on the figure come from the package (``mitsuba_powder.io.ipag.from_project``
and ``to_project``), so the figure shows what the code does, not a separate drawing of it.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
from docs_output import add_output_options, output_dir  # noqa: E402

from mitsuba_powder.io.ipag import from_project, to_project  # noqa: E402
from mitsuba_powder.io.measurements import gonio_directions  # noqa: E402

ROOT = Path(__file__).resolve().parents[2]
THETA_I = 40.0


def _label(convention: str, theta_o: float, phi: float) -> str:
    """How a view (project angles) is written in a convention."""
    if convention == "project":
        return f"theta_o = {theta_o:+g}, phi = {phi:g}"
    _, e, a = (float(v[0]) for v in from_project([THETA_I], [theta_o], [phi], convention))
    back = to_project([THETA_I], [e], [a], convention)       # the loader's reading of it
    wo = gonio_directions([THETA_I], back[1], back[2])[1][0]
    assert np.allclose(wo, gonio_directions([THETA_I], [theta_o], [phi])[1][0])
    return f"e = {e:+g}" if convention == "signed" else f"e = {e:g}, azimuth {a:g}"


def draw(ax, convention: str, title: str, rule: str) -> None:
    ax.set_aspect("equal")
    ax.axis("off")
    ax.set_xlim(-1.55, 1.55)
    ax.set_ylim(-0.35, 1.45)
    ax.add_patch(plt.Rectangle((-1.3, -0.18), 2.6, 0.18, color="#c9b18b"))   # the powder
    t = np.linspace(0, np.pi, 200)
    ax.plot(np.cos(t), np.sin(t), color="0.8", lw=1, ls="--")
    ax.plot([0, 0], [0, 1.1], color="0.5", lw=1)
    ax.text(0, 1.13, "normal", ha="center", fontsize=8, color="0.4")
    ti = np.radians(THETA_I)
    # light: at azimuth 0, on +x (docs/model.md); the arrow points from the source to the sample
    src = np.array([np.sin(ti), np.cos(ti)]) * 1.25
    ax.annotate("", xy=(0.03, 0.03), xytext=src,
                arrowprops=dict(arrowstyle="-|>", color="#e8a200", lw=2.5))
    ax.text(*(src + [0.05, 0.05]), f"light, i = {THETA_I:g}", color="#b07a00", fontsize=9)
    # ticks along the arc, written in this convention
    for to in (-60, -20, 20, 60):
        x, z = np.sin(np.radians(to)), np.cos(np.radians(to))   # +theta_o: light's side, +x
        ax.plot([x * 0.97, x * 1.03], [z * 0.97, z * 1.03], color="0.5", lw=1)
        text = _label(convention, float(to), 0.0).replace("theta_o", "θo").replace("phi", "φ")
        ax.text(x * 1.13, z * 1.1, text, ha="center", va="center", fontsize=7, color="0.35")
    # back-scattering (the light's own direction) and the mirror direction
    for to, colour, name in ((THETA_I, "#c0392b", "back-scattering"),
                             (-THETA_I, "#2471a3", "specular (mirror)")):
        x, z = np.sin(np.radians(to)), np.cos(np.radians(to))
        ax.annotate("", xy=(x * 0.85, z * 0.85), xytext=(0, 0),
                    arrowprops=dict(arrowstyle="-|>", color=colour, lw=1.8))
        label = _label(convention, to, 0.0)
        label = label.replace("theta_o", "θo").replace("phi", "φ")
        ax.text(x * 0.55 + (0.08 if to > 0 else -0.08), z * 0.45 - 0.02,
                f"{name}\n{label}", color=colour, fontsize=8,
                ha="left" if to > 0 else "right", va="center")
    ax.set_title(title, fontsize=10)
    ax.text(0, -0.28, rule, ha="center", fontsize=8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    add_output_options(parser, ROOT / "docs" / "figures", "ipag_conventions.png")
    args = parser.parse_args()
    fig, axes = plt.subplots(1, 3, figsize=(15, 3.9))
    draw(axes[0], "project", "project (CSV, docs/model.md)",
         "light at azimuth 0; θo signed, + on the light's side")
    draw(axes[1], "signed", "older IPAG files (count line)",
         "e signed, + on the forward side; azimuth 0: θo = -e, φ = 0")
    draw(axes[2], "physical", "newer IPAG ('Angles physical'), SSHADE",
         "e >= 0; azimuth 0 at opposition, 180 forward: θo = e, φ = azimuth")
    fig.suptitle(f"Plane of incidence, incidence {THETA_I:g} deg: the same two directions "
                 "written in each convention", fontsize=11)
    fig.tight_layout()
    out = output_dir(args, ROOT / "docs" / "figures")
    out.mkdir(parents=True, exist_ok=True)
    fig.savefig(out / "ipag_conventions.png", dpi=110)
    print(f"wrote {out / 'ipag_conventions.png'}")


if __name__ == "__main__":
    main()
