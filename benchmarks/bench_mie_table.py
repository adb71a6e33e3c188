"""Accuracy of the spectral albedo table: the plugin's rho on the 1 nm grid (360-830 nm, stored
in single precision, interpolated linearly in wavelength, docs/model.md) against Mie at the
exact wavelength, for grain radii 0.05-10 um of hematite, magnetite and weakly absorbing
constant indices (whose Mie resonances are narrow in wavelength).

The reference is Mie in double precision (mitsuba_powder._optics, the plugin's code, which
agrees with miepython to 1e-7: tests/grains/test_mie.py) on a 0.05 nm grid; the table is the
same code at the 1 nm nodes, rounded to single precision and interpolated linearly. Resonances
narrower than the reference grid are missed by both, so the errors of the resonant rows are
lower bounds. The largest radius is limited by the size parameter's range (x <= 200: 11.4 um
at 360 nm). Prints the largest relative error |rho_table - rho| / rho per material and radius,
and the wavelength where it occurs, and beside it that of a polynomial of degree 32 in
wavelength (a least-squares Chebyshev fit to the reference: what a lookup-free eval would
evaluate); writes benchmarks/results/mie_table.json and .png.

    python benchmarks/bench_mie_table.py [--quick]
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from _common import arg_parser, print_table, pyplot, save, save_figure

RADII = (0.05, 0.1, 0.3, 1.0, 3.0, 10.0)  #: um
#: constant indices n + ik: weakly absorbing, resonant grains
CONSTANT = {"n 1.5, k 1e-3": 1.5 + 1e-3j, "n 1.5, k 1e-5": 1.5 + 1e-5j,
            "n 2.6, k 1e-4": 2.6 + 1e-4j}


def material_index(name: str):
    """The index n + ik of a built-in material as a function of the wavelength (nm), linear
    in the table's rows as the plugin reads it (two files: orientation average)."""
    import mitsuba_powder
    from mitsuba_powder import _optics

    base = Path(mitsuba_powder.__file__).parent
    files = [str(base / f) for f in _optics.material_files()[name]]
    wl, n, k = map(np.array, _optics.hematite_average(*files) if len(files) == 2
                   else _optics.load_optical_constants(files[0]))
    return lambda lam: np.interp(lam * 1e-3, wl, n) + 1j * np.interp(lam * 1e-3, wl, k)


POLY_DEGREE = 32


def table_error(index, radius: float, step: float) -> tuple[float, float, float]:
    """(largest relative error of the interpolated 1 nm table against Mie on a grid of
    ``step`` nm, the wavelength where it occurs, largest relative error of the polynomial of
    degree POLY_DEGREE fitted to Mie on that grid)."""
    from mitsuba_powder import _optics

    nodes = np.arange(360.0, 831.0, 1.0)
    fine = np.arange(360.0, 830.0 + 1e-9, step)

    def rho(lam):
        return np.array(_optics.albedo_table("sphere", list(lam), list(index(lam)), radius)[0])

    exact = rho(fine)
    table = np.interp(fine, nodes, rho(nodes).astype(np.float32).astype(np.float64))
    err = np.abs(table - exact) / exact
    i = int(np.argmax(err))
    u = (fine - 595.0) / 235.0  # [-1, 1]
    poly = np.polynomial.chebyshev.chebval(u, np.polynomial.chebyshev.chebfit(u, exact,
                                                                              POLY_DEGREE))
    return float(err[i]), float(fine[i]), float(np.max(np.abs(poly - exact) / exact))


def main() -> None:
    args = arg_parser(__doc__).parse_args()
    radii, step = ((0.05, 1.0), 0.25) if args.quick else (RADII, 0.05)
    indices = {name: material_index(name) for name in ("hematite", "magnetite")}
    indices.update({name: (lambda lam, m=m: np.full(lam.shape, m))
                    for name, m in CONSTANT.items()})
    rows = []
    for name, index in indices.items():
        for r in radii:
            err, at, poly = table_error(index, r, step)
            rows.append({"material": name, "radius_um": r, "max_rel_error": err,
                         "at_nm": at, "poly_max_rel_error": poly})
    print(f"1 nm table (single precision, linear) against Mie on a {step} nm grid, 360-830 nm")
    print_table(rows, [("material", "material", "s"), ("radius_um", "radius um", "g"),
                       ("max_rel_error", "max rel. error", ".1e"), ("at_nm", "at nm", ".2f"),
                       ("poly_max_rel_error", f"degree-{POLY_DEGREE} polynomial", ".1e")])
    save(args.out, "mie_table", rows, args.quick, reference_step_nm=step)
    plt = pyplot()
    fig, ax = plt.subplots(figsize=(6, 3.8))
    for name in indices:
        sel = [r for r in rows if r["material"] == name]
        ax.loglog([r["radius_um"] for r in sel], [max(r["max_rel_error"], 1e-9) for r in sel],
                  "o-", label=name)
    ax.set_xlabel("grain radius (um)")
    ax.set_ylabel("largest relative error of rho")
    ax.set_title("1 nm albedo table against Mie at the exact wavelength", fontsize=9)
    ax.legend(fontsize=7)
    save_figure(fig, args.out / "mie_table.png")


if __name__ == "__main__":
    main()
