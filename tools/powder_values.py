"""Values of the powder plugin at fixed inputs, as JSON: what two builds are compared by.

For each of a few powders (:data:`POWDERS`: volume terms, the surface lobe, Mie albedo from
the hematite files, the energy-conserving table, the Gaussian surface lobe with its Fresnel
factor) it prints ``eval`` and ``pdf`` at a grid of direction pairs (exact back-scattering
included) and ``sample`` at a grid of random numbers (direction, weight, pdf). Run it with
the Python and the plugin of each build, then compare (``tools/check-aarch64`` compares an
aarch64 build under emulation with the x86-64 one; ``tests/package/test_wheel.py`` a wheel
with the source build).

    python tools/powder_values.py --variant scalar_rgb [--plugin-dir DIR] > values.json

Without ``--plugin-dir`` the plugin of the installed ``mitsuba_powder`` is used; with it, only
``DIR/plugins/powder.so`` and the package's data files beside this script (``python/
mitsuba_powder``), without the Python package: it runs where only mitsuba is installed.
It imports nothing but mitsuba, drjit and the standard library.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

#: the powders evaluated: name -> plugin properties
POWDERS: dict[str, dict] = {
    "volume": {"albedo": [0.9, 0.55, 0.35], "extinction": 0.5, "g": 0.2},
    "surface": {"albedo": [0.9, 0.55, 0.35], "extinction": 0.5, "g": 0.2,
                "amplitude_surface": 2e-4, "correlation_length": 0.8},
    "hematite_mie": {"radius": 0.05, "extinction": 0.5, "g": 0.2},
    "conserving": {"albedo": [0.95, 0.95, 0.95], "extinction": 2.0, "g": -0.3,
                   "energy": "conserving", "tau_o": 1.0},
    "gaussian_fresnel": {"radius": 0.2, "extinction": 1.0, "specular": "gaussian",
                         "amplitude_surface": 0.05, "sigma": 0.2, "surface_fresnel": "fresnel"},
}

#: incidence and outgoing zenith angles (degrees) and relative azimuths of the eval grid
THETA_I = (0.0, 30.0, 60.0, 80.0)
THETA_O = (0.0, 25.0, 50.0, 75.0, 85.0)
PHI = (0.0, 90.0, 179.0, 180.0)
#: the incidences (degrees) and the (sample1, sample2) grid of ``sample``
SAMPLE_THETA_I = (0.0, 45.0, 80.0)
SAMPLE_1D = (0.05, 0.5, 0.95)
SAMPLE_2D = tuple((u, v) for u in (0.1, 0.4, 0.7, 0.99) for v in (0.2, 0.6, 0.9))


def _direction(theta_deg: float, phi_deg: float) -> list[float]:
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return [math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)]


def pairs() -> tuple[list[list[float]], list[list[float]]]:
    """(wi, wo) of the eval grid: every THETA_I x THETA_O x PHI, plus wo = wi at each
    incidence (the back-scattering peak)."""
    wi, wo = [], []
    for ti in THETA_I:
        for to in THETA_O:
            for p in PHI:
                wi.append(_direction(ti, 0.0))
                wo.append(_direction(to, p))
        wi.append(_direction(ti, 0.0))
        wo.append(_direction(ti, 0.0))
    return wi, wo


def _rows(x, n: int) -> list[list[float]]:
    """A Mitsuba/Dr.Jit value over ``n`` inputs as one list of floats per input (scalar
    variants: ``n`` = 1; JIT variants: one lane per input)."""
    import drjit as dr

    if not dr.is_array_v(x):
        return [[float(x)]]
    if dr.depth_v(x) == 1:
        lanes = [float(v) for v in x]
        return [[v] for v in lanes] if dr.is_jit_v(x) else [lanes]
    columns = [_rows(x[i], n) for i in range(len(x))]
    return [[v for c in columns for v in c[j]] for j in range(len(columns[0]))]


def _columns(mi, rows: list[list[float]]) -> list:
    """Rows of inputs as one value per component: ``mi.Float`` columns (one lane per row) in
    JIT variants, the floats of the single row in scalar variants."""
    if mi.variant().startswith("scalar"):
        (row,) = rows
        return list(row)
    return [mi.Float([r[k] for r in rows]) for k in range(len(rows[0]))]


def _evaluate(bsdf, mi, wi, wo) -> dict[str, list[float]]:
    """eval and pdf over the pairs, sample over the grid: one call per input in scalar
    variants, one call over all inputs (one lane each) in JIT variants; the same numbers
    in the same order either way."""
    ctx = mi.BSDFContext()
    samples = [(_direction(t, 0.0), s1, s2) for t in SAMPLE_THETA_I for s1 in SAMPLE_1D
               for s2 in SAMPLE_2D]
    calls = [(wi, wo, samples)]
    if mi.variant().startswith("scalar"):
        calls = [([a], [b], []) for a, b in zip(wi, wo)] + [([], [], [s]) for s in samples]
    out: dict[str, list[float]] = {"eval": [], "pdf": [], "sample": []}
    for a, b, smp in calls:
        if a:
            si = mi.SurfaceInteraction3f()
            si.wi = mi.Vector3f(*_columns(mi, a))
            w = mi.Vector3f(*_columns(mi, b))
            out["eval"] += [v for r in _rows(bsdf.eval(ctx, si, w), len(a)) for v in r]
            out["pdf"] += [v for r in _rows(bsdf.pdf(ctx, si, w), len(a)) for v in r]
        if smp:
            si = mi.SurfaceInteraction3f()
            si.wi = mi.Vector3f(*_columns(mi, [x[0] for x in smp]))
            (s1,) = _columns(mi, [[x[1]] for x in smp])
            bs, weight = bsdf.sample(ctx, si, s1, mi.Point2f(*_columns(mi, [x[2] for x in smp])))
            rows = zip(_rows(bs.wo, len(smp)), _rows(bs.pdf, len(smp)),
                       _rows(weight, len(smp)))
            out["sample"] += [v for r in rows for part in r for v in part]
    return out


def values(variant: str, plugin_dir: str | None) -> dict:
    """``{"variant", "mitsuba", "drjit", "powders": {name: {"eval", "pdf", "sample"}}}``."""
    import drjit as dr
    import mitsuba as mi

    mi.set_variant(variant)
    if plugin_dir is None:
        import mitsuba_powder  # noqa: F401  (registers the installed plugin)
    else:
        resolver = mi.file_resolver()
        # the package's data files (optical constants), then the plugin folder
        resolver.prepend(str(Path(__file__).resolve().parents[1] / "python" / "mitsuba_powder"))
        resolver.prepend(str(Path(plugin_dir).resolve()))
    wi, wo = pairs()
    result = {"variant": variant, "mitsuba": mi.__version__, "drjit": dr.__version__,
              "powders": {}}
    for name, props in POWDERS.items():
        props = {k: ({"type": "rgb", "value": v} if isinstance(v, list) else v)
                 for k, v in props.items()}
        bsdf = mi.load_dict({"type": "powder", **props})
        result["powders"][name] = _evaluate(bsdf, mi, wi, wo)
    return result


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--variant", default="scalar_rgb",
                        choices=("scalar_rgb", "llvm_ad_rgb", "cuda_ad_rgb"),
                        help="Mitsuba variant (RGB: the properties give RGB albedos)")
    parser.add_argument("--plugin-dir", default=None,
                        help="folder holding plugins/powder.so (default: the installed package)")
    args = parser.parse_args(argv)
    json.dump(values(args.variant, args.plugin_dir), sys.stdout)
    print()
    return 0


if __name__ == "__main__":
    sys.exit(main())
