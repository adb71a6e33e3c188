"""The white-furnace grid of docs/powder.md ("Energy"): the directional-hemispherical
reflectance of a white powder (albedo 1, amplitude_volume 1, lobes single,multiple,coherent,
no surface term) over kappa/k0, g, tau_o and incidence, in both `energy` modes, as Markdown
tables of the maximum over g and incidence; and, with --timing, the cost of conserving mode
(eval and parameter update, against paper mode).

Usage: python docs/scripts/energy_grid.py [--timing]
"""

from __future__ import annotations

import argparse
import time

import drjit as dr
import mitsuba as mi
import numpy as np

from mitsuba_powder.rendering.furnace import hemispherical_reflectance
from mitsuba_powder.variants import set_variant

KAPPA_OVER_K0 = (1e-3, 1e-2, 0.05, 0.25, 1.0, 10.0)
G_VALUES = (-0.9, 0.0, 0.9)
TAU_VALUES = (0.0, 2.0 / 3.0, 3.0, 100.0)
INCIDENCES = (0.0, 30.0, 60.0, 85.0)
K0 = 2.0 * np.pi / 0.7  # 1/um at 700 nm


def white(kappa_over_k0: float, g: float, tau: float, energy: str) -> dict:
    """The white powder of the grid (llvm_ad_mono at 700 nm)."""
    return {"type": "powder", "albedo": {"type": "uniform", "value": 1.0},
            "amplitude_volume": 1.0, "g": g, "extinction": kappa_over_k0 * K0, "tau_o": tau,
            "lobes": "single,multiple,coherent", "energy": energy, "wavelength": 700.0}


def grid(energy: str) -> dict[tuple[float, float], float]:
    """(kappa/k0, tau_o) -> maximum reflectance over g and incidence."""
    out = {}
    for r in KAPPA_OVER_K0:
        for tau in TAU_VALUES:
            best = 0.0
            for g in G_VALUES:
                bsdf = mi.load_dict(white(r, g, tau, energy))
                for ti in INCIDENCES:
                    best = max(best, float(hemispherical_reflectance(bsdf, ti)[0]))
            out[r, tau] = best
    return out


def table(values: dict[tuple[float, float], float]) -> str:
    head = "| kappa / k0 | " + " | ".join(f"tau_o = {t:.3g}" for t in TAU_VALUES) + " |"
    lines = [head, "|" + "---|" * (len(TAU_VALUES) + 1)]
    for r in KAPPA_OVER_K0:
        lines.append(f"| {r:g} | " + " | ".join(f"{values[r, t]:.3f}" for t in TAU_VALUES)
                     + " |")
    return "\n".join(lines)


def timing(variant: str, n: int = 1 << 20, repeats: int = 7) -> tuple[float, ...]:
    """(eval paper, eval conserving, update + eval paper, update + eval conserving), ms,
    for n direction pairs (medians of ``repeats``)."""
    set_variant(variant)
    rng = np.random.default_rng(1)

    def dirs():
        mu = rng.uniform(0.05, 1.0, n)
        phi = rng.uniform(0, 2 * np.pi, n)
        s = np.sqrt(1 - mu * mu)
        return mi.Vector3f(*(np.stack([s * np.cos(phi), s * np.sin(phi), mu])
                             .astype(np.float32)))

    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = dirs()
    if mi.is_spectral:
        si.wavelengths = mi.UnpolarizedSpectrum(
            *[mi.Float(rng.uniform(360, 830, n).astype(np.float32)) for _ in range(4)])
    wo = dirs()
    props = {"type": "powder", "radius": 0.05, "extinction": 0.5, "amplitude_surface": 1e-3}
    evals, updates = [], []
    for energy in ("paper", "conserving"):
        bsdf = mi.load_dict({**props, "energy": energy})
        times = []
        for _ in range(repeats):
            dr.eval(si, wo)
            dr.sync_thread()
            t0 = time.perf_counter()
            v = bsdf.eval(mi.BSDFContext(), si, wo)
            dr.eval(v)
            dr.sync_thread()
            times.append(time.perf_counter() - t0)
        evals.append(1e3 * float(np.median(times)))
        params = mi.traverse(bsdf)
        times = []
        for k in range(repeats):
            params["extinction"] = 0.5 + 0.01 * k
            dr.sync_thread()
            t0 = time.perf_counter()
            params.update()
            dr.eval(bsdf.eval(mi.BSDFContext(), si, wo))  # forces the deferred tables
            dr.sync_thread()
            times.append(time.perf_counter() - t0)
        updates.append(1e3 * float(np.median(times)))
    return evals[0], evals[1], updates[0], updates[1]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--timing", action="store_true", help="also time eval and updates")
    args = ap.parse_args()
    set_variant("llvm_ad_mono")
    for energy in ("paper", "conserving"):
        print(f"\nenergy = {energy}: maximum reflectance over g in {G_VALUES} and incidences "
              f"{INCIDENCES} degrees\n")
        print(table(grid(energy)))
    if args.timing:
        print("\n| variant | eval, paper (ms) | eval, conserving (ms) | ratio | "
              "update + eval, paper (ms) | update + eval, conserving (ms) |\n"
              "|---|---|---|---|---|---|")
        for variant in ("llvm_ad_rgb", "llvm_ad_mono", "llvm_ad_spectral"):
            p, c, up, uc = timing(variant)
            print(f"| {variant} | {p:.1f} | {c:.1f} | {c / p:.2f} | {up:.1f} | {uc:.1f} |")


if __name__ == "__main__":
    main()
