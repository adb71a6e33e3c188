"""Commands about a powder's appearance: ``colour`` (from its grains) and ``albedo`` (the albedo
spectrum that reproduces a reflectance or a colour)."""

from __future__ import annotations

import argparse
import math

from ..plugin import registry
from .common import _fixed_properties


def _cmd_colour(args: argparse.Namespace) -> int:
    import numpy as np

    from ..plugin.appearance import mixture_colour, powder_colour
    from ..plugin.grains import parse_mix, volume_fractions

    if args.mix is not None:
        given = [f"--{n.replace('_', '-')}" for n in ("radius", "radius2", "fraction2",
                                                     "material", "agglomerate_radius")
                 if getattr(args, n) is not None]
        if given or args.grains == "agglomerate":
            raise ValueError(f"--mix describes the grains; {', '.join(given) or '--grains'} "
                             "cannot be given with it")
    if (args.radius2 is None) != (args.fraction2 is None):
        raise ValueError("give both --radius2 and --fraction2, or neither")
    if args.radius is None and args.mix is None:
        args.radius = float(registry.DEFAULTS["radius"])
    if args.material is None:
        args.material = str(registry.DEFAULTS["material"])
    model = {}
    if args.grains != registry.DEFAULTS["grains"]:
        model["grains"] = args.grains
    if args.agglomerate_radius is not None:
        model["agglomerate_radius"] = args.agglomerate_radius
    if args.agglomerate_fill is not None:
        model["agglomerate_fill"] = args.agglomerate_fill
    if args.mixing is not None:
        model["mixing"] = args.mixing
    if args.mix is not None:
        parts = parse_mix(args.mix)
        volumes = volume_fractions([(m, f) for m, f, _ in parts], args.by)
        c = mixture_colour(parts, by=args.by, samples=args.samples, **model)
        print(f"mixture ({args.by} fractions -> volume fractions of the solid): " + ", ".join(
            f"{m} {f:.4g} -> {v:.4g}, radius {r:g} um" for (m, f, r), v in zip(parts, volumes)))
        grains = f"{args.grains} grains"
    else:
        c = powder_colour(args.radius, radius2=args.radius2, fraction2=args.fraction2,
                          material=args.material, samples=args.samples, **model)
        grains = f"{args.material}, {args.grains} grains, radius {args.radius:g} um"
    if args.radius2 is not None:
        grains += f" + radius2 {args.radius2:g} um (volume fraction {args.fraction2:g})"
    if args.grains == "agglomerate":
        grains += (f" (crystallites) in agglomerates of radius {args.agglomerate_radius:g} um, "
                   f"fill {c.properties.get('agglomerate_fill', 0.5):g}, "
                   f"{c.properties.get('mixing', 'bruggeman')}")
    print(f"{grains}; plugin defaults otherwise")
    print(f"{'nm':>5s} {'albedo':>8s} {'Q_ext':>9s} {'Q_sca':>9s} {'tau_o':>7s} {'R(0/d)':>8s}")
    step = max(1, len(c.wavelengths_nm) // 12)
    for i in range(0, len(c.wavelengths_nm), step):
        print(f"{c.wavelengths_nm[i]:5.0f} {c.albedo[i]:8.4f} {c.q_ext[i]:9.4g} "
              f"{c.q_sca[i]:9.4g} {c.tau_o[i]:7.3f} {c.reflectance[i]:8.4f}")
    print(f"CIE XYZ (D65): {np.array2string(c.xyz, precision=4)}")
    print(f"sRGB: {np.array2string(c.srgb, precision=4)} (8 bit: {c.srgb8})")
    print(f"CIELAB: L* {c.lab[0]:.2f}, a* {c.lab[1]:.2f}, b* {c.lab[2]:.2f}")
    return 0


def _read_csv_columns(path: str, missing: str, what: str, columns: list[str],
                      fields: str, ranges: list[tuple] | None = None) -> list[list[float]]:
    """Rows of ``len(columns)`` numbers from a CSV (an optional header line; ``#`` lines are
    comments): ``missing`` is the message of a missing file, ``what`` names the file for
    :func:`read_text`, ``fields`` describes the columns in the error messages; with
    ``ranges`` (per column ``(lower, upper, closed)`` of :func:`check_range`), every value is
    checked and the wavelengths (the first column) must increase (:func:`_check_rows`)."""
    import csv
    from pathlib import Path

    from ..outputs import note_input
    from ..readers import read_text

    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(missing)
    note_input(p)
    n = len(columns)
    count = {2: "two", 3: "three"}[n]
    rows, lines = [], []
    for lineno, row in enumerate(csv.reader(read_text(p, what).splitlines()), start=1):
        if not row or row[0].strip().startswith("#"):
            continue
        if len(row) != n:
            raise ValueError(f"{path}, line {lineno}: {len(row)} fields, expected {n} ({fields})")
        try:
            rows.append([float(v) for v in row])
        except ValueError:
            if not rows:  # a header line
                continue
            raise ValueError(f"{path}, line {lineno}: {row!r} is not {count} numbers") from None
        lines.append(lineno)
    if not rows:
        raise ValueError(f"{path}: no data rows (wavelength nm, {', '.join(columns[1:])})")
    if ranges is not None:
        _check_rows(path, rows, lines, columns, ranges)
    return rows


def _check_rows(path: str, rows: list, lines: list[int], columns: list[str],
                ranges: list[tuple]) -> None:
    """Each value of a spectrum's ``rows`` (read from ``lines`` of ``path``) within its
    column's range, the file, line and column named (:func:`check_range`); the wavelengths
    (the first column) increasing: no row given twice, none out of order."""
    from .._checks import check_range

    for row, lineno in zip(rows, lines):
        for value, column, (lower, upper, closed) in zip(row, columns, ranges):
            check_range(f"{path}, line {lineno} ({column})", value, lower, upper, closed)
    for k in range(1, len(rows)):
        if not rows[k][0] > rows[k - 1][0]:
            raise ValueError(f"{path}, line {lines[k]}: wavelength {rows[k][0]:g} nm after "
                             f"{rows[k - 1][0]:g} nm on line {lines[k - 1]}; the wavelengths "
                             "must increase (sort the rows, give each wavelength once)")


#: The range of a wavelength (nm) and of a standard uncertainty in a spectrum's CSV
_WAVELENGTH = _SIGMA = (0.0, math.inf, "()")


def _read_reflectance_csv(path: str) -> tuple:
    """(wavelengths nm, reflectance) from a CSV of two columns (an optional header line;
    ``#`` lines are comments)."""
    import numpy as np

    a = np.array(_read_csv_columns(path, f"--reflectance {path}: no such file", "--reflectance",
                                   ["wavelength", "reflectance"],
                                   "wavelength in nm, reflectance"))
    return a[:, 0], a[:, 1]


def _cmd_albedo(args: argparse.Namespace) -> int:
    from ..plugin.appearance import albedo_for_reflectance, reflectance_of_srgb, write_spectrum

    if (args.reflectance is None) == (args.srgb is None):
        raise ValueError("give exactly one of --reflectance FILE.csv and --srgb R,G,B")
    if args.srgb is not None:
        try:
            rgb = [float(v) for v in args.srgb.split(",")]
        except ValueError:
            raise ValueError(f"--srgb {args.srgb!r}: expected R,G,B, e.g. 0.7,0.35,0.25") \
                from None
        wl, target = reflectance_of_srgb(rgb)
        source = f"sRGB {args.srgb} (spectral upsampling: Mallett & Yuksel 2019)"
    else:
        wl, target = _read_reflectance_csv(args.reflectance)
        source = args.reflectance
    props = _fixed_properties(args.set)
    albedo = albedo_for_reflectance(wl, target, args.geometry, **props)
    write_spectrum(args.out, wl, albedo)
    print(f"albedo for {source}, geometry {args.geometry}, properties "
          f"{props or 'plugin defaults'}: {len(wl)} wavelengths {wl.min():g}-{wl.max():g} nm, "
          f"albedo {albedo.min():.4f}-{albedo.max():.4f}")
    print(f"wrote {args.out} (use it as <spectrum name=\"albedo\" filename=\"{args.out}\"/>)")
    return 0


def _read_albedo_csv(path: str) -> tuple:
    """(wavelengths nm, albedo, sigma) from a CSV of three columns (an optional header line;
    ``#`` lines are comments)."""
    import numpy as np

    a = np.array(_read_csv_columns(path, f"{path}: no such file", "ALBEDO.csv",
                                   ["wavelength", "albedo", "sigma"],
                                   "wavelength in nm, albedo, its standard uncertainty",
                                   [_WAVELENGTH, (0.0, 1.0, "[]"), _SIGMA]))
    return a[:, 0], a[:, 1], a[:, 2]


def _mix(args: argparse.Namespace) -> list[tuple[str, float, float]]:
    """The populations of ``--mix`` (:func:`~mitsuba_powder.plugin.grains.parse_mix`), checked
    before any work: two to four, known materials, radii > 0, no population twice, start
    fractions in [0, 1] summing to 1 by ``--by``
    (:func:`~mitsuba_powder.plugin.grains.volume_fractions`); the errors quote ``--mix``."""
    from .._checks import check_range
    from ..plugin.grains import GrainOptics, parse_mix, volume_fractions

    try:
        parts = parse_mix(args.mix)
        check_range("the number of populations", len(parts), 2, registry.MAX_POPULATIONS,
                    "[]")
        for j, (material, _, radius) in enumerate(parts):
            GrainOptics({"material": material})  # a known material or a readable YAML file
            check_range(f"the radius of {material}", radius, 0.0, closed="()", unit="um")
            if (material, radius) in [(m, r) for m, _, r in parts[:j]]:
                raise ValueError(f"{material} of radius {radius:g} um is given twice: two "
                                 "identical populations cannot be told apart; give it once")
        volume_fractions([(m, f) for m, f, _ in parts], args.by)
    except ValueError as exc:
        raise ValueError(f"--mix {args.mix!r}: {exc}") from None
    return parts


def _check_tables(path: str, wl, parts: list) -> None:
    """The wavelengths of ``path`` within every material's table of optical constants (an
    error naming the file, the wavelength, the material and its table's range)."""
    from ..plugin.grains import GrainOptics

    for material, _, _ in parts:
        try:
            GrainOptics({"material": material}).index(wl)
        except ValueError as exc:
            raise ValueError(f"{path}: {exc}") from None


def _check_unmix_options(args: argparse.Namespace) -> None:
    """The options of ``unmix`` that do not go together, and those of the search
    (:func:`~mitsuba_powder.fitting.optimise.check_search`, before any work): an option that
    would be ignored is an error naming it."""
    from ..fitting.optimise import DEFAULT_STARTS, check_search

    if args.baseline is None:
        given = [f"--{n}" for n in ("endmembers", "tints", "geometry")
                 if getattr(args, n) is not None] + (["--set"] if args.set else [])
        if given:
            raise ValueError(f"{', '.join(given)} {'needs' if len(given) == 1 else 'need'} "
                             "--baseline (a reflectance spectrum); without it the CSV is an "
                             "albedo spectrum")
    else:
        given = [flag for flag, value in (("--free-radii", args.free_radii),
                                          ("--global", args.global_stage),
                                          ("--starts", args.starts)) if value]
        if given:
            raise ValueError(f"{', '.join(given)} not with --baseline (the baselines fit the "
                             "fractions only, from their own Sobol starts; --seed seeds them)")
        if args.tints is not None and args.baseline == "hapke":
            raise ValueError("--tints are Kubelka-Munk's: with --baseline km or all")
        if args.set and args.baseline != "all":
            raise ValueError("--set gives the powder row's properties: only with --baseline all")
    if args.json is not None and not args.json.strip():
        raise ValueError(f"--json {args.json!r}: give a file name")
    args.global_stage = args.global_stage or "sobol"
    args.starts = DEFAULT_STARTS if args.starts is None else args.starts
    args.seed = 0 if args.seed is None else args.seed
    check_search(args.global_stage, args.starts, args.seed, ("--global", "--starts", "--seed"))


def _cmd_unmix(args: argparse.Namespace) -> int:
    from ..fitting.unmix import unmix
    from ..outputs import output_file

    _check_unmix_options(args)
    parts = _mix(args)
    if args.baseline is not None:
        return _cmd_unmix_reflectance(args, parts)
    wl, albedo, sigma = _read_albedo_csv(args.albedo)
    _check_tables(args.albedo, wl, parts)
    if args.json:
        output_file(args.json, "--json")  # refused before the work if it is an input
    r = unmix(wl, albedo, sigma, parts, free_radii=args.free_radii, by=args.by,
              global_stage=args.global_stage, starts=args.starts, seed=args.seed)
    print(f"unmixing {args.albedo}: {len(wl)} wavelengths, chi2 {r.chi2:.4g} for {r.dof} "
          f"degrees of freedom ({r.global_stage} search: {r.evaluations} model evaluations, "
          f"{r.seconds:.2g} s)")
    print(f"{'material':>12s} {'volume':>8s} {'+/-':>7s} {'mass':>8s} {'radius um':>10s} "
          f"{'+/-':>7s}")
    for j, m in enumerate(r.materials):
        mass = "-" if r.mass_fractions is None else f"{r.mass_fractions[j]:.4f}"
        print(f"{m:>12s} {r.fractions[j]:8.4f} {r.fraction_errors[j]:7.4f} {mass:>8s} "
              f"{r.radii[j]:10.4g} {r.radius_errors[j]:7.2g}")
    for w in r.warnings:
        print(f"warning: {w}")
    doc = {"materials": r.materials, "volume_fractions": r.fractions.tolist(),
           "volume_fraction_errors": r.fraction_errors.tolist(),
           "mass_fractions": None if r.mass_fractions is None else r.mass_fractions.tolist(),
           "radii_um": r.radii.tolist(), "radius_errors_um": r.radius_errors.tolist(),
           "chi2": r.chi2, "dof": r.dof, "global_stage": r.global_stage,
           "evaluations": r.evaluations, "warnings": r.warnings}
    return _unmix_output(args, doc)


def _unmix_output(args: argparse.Namespace, doc) -> int:
    """``unmix``'s result ``doc``: an error (exit 2) when it holds NaN or Infinity (a
    degenerate result: the warnings printed above say why), else written to ``--json`` when
    given (:func:`~mitsuba_powder.outputs.write_json`)."""
    from ..outputs import check_finite_json, write_json

    check_finite_json(doc, f"--json {args.json}" if args.json else "the result")
    if args.json:
        print(f"wrote {write_json(args.json, doc, '--json')}")
    return 0


def _reflectance_range(geometry: str) -> tuple[float, float, str]:
    """The range of a measured reflectance at ``geometry``: [0, 1] for 0:d (a hemispherical
    reflectance), [0, inf) for a reflectance factor (which may exceed 1); a bad geometry is an
    error naming ``--geometry``."""
    from ..fitting.mixing_rules import hapke_geometry

    try:
        hemispherical = hapke_geometry(geometry) is None
    except ValueError as exc:
        raise ValueError(f"--geometry: {exc}") from None
    return (0.0, 1.0, "[]") if hemispherical else (0.0, math.inf, "[)")


def _read_swatches(args, wl, n: int) -> tuple:
    """(endmembers (n, W), tints or None) of ``unmix --baseline``: the CSVs of ``--endmembers``
    (one per population of ``--mix``) and ``--tints`` (one per population 2..n), each on the
    measured wavelengths, their values within :func:`_reflectance_range`."""
    import numpy as np

    ranges = [_WAVELENGTH, _reflectance_range(args.geometry)]

    def spectrum(path: str, flag: str):
        w, r = np.array(_read_csv_columns(
            path, f"{flag} {path}: no such file", flag, ["wavelength", "reflectance"],
            "wavelength in nm, reflectance", ranges)).T
        if w.shape != wl.shape or not np.allclose(w, wl, rtol=0, atol=1e-6):
            raise ValueError(f"{flag} {path}: its wavelengths differ from the mixture's "
                             f"({len(w)} against {len(wl)} values)")
        return r

    if args.endmembers is None:
        raise ValueError("--baseline needs --endmembers A.csv,B.csv,... (each pure material's "
                         "reflectance, in the order of --mix)")
    paths = [p.strip() for p in args.endmembers.split(",")]
    if len(paths) != n:
        raise ValueError(f"--endmembers {args.endmembers!r}: {len(paths)} files for the "
                         f"{n} populations of --mix; give one per population, "
                         "in its order")
    ends = np.array([spectrum(p, "--endmembers") for p in paths])
    if args.tints is None:
        return ends, None
    items = [item.strip() for item in args.tints.split(",")]
    if len(items) != n - 1:
        raise ValueError(f"--tints {args.tints!r}: {len(items)} tints for the "
                         f"{n - 1} pigments of --mix (populations 2..n); give "
                         "one per pigment, in its order")
    return ends, [_tint(item, spectrum) for item in items]


def _tint(item: str, spectrum) -> tuple:
    """(reflectance (W,), mass fraction in (0, 1)) of a ``--tints`` item ``FILE.csv:FRACTION``
    (a number or a percentage)."""
    from .._checks import check_range

    path, sep, fraction = item.rpartition(":")
    if not sep or not path:
        raise ValueError(f"--tints item {item!r} is not FILE.csv:FRACTION (e.g. tint.csv:10%)")
    try:
        c = float(fraction[:-1]) / 100 if fraction.endswith("%") else float(fraction)
    except ValueError:
        raise ValueError(f"--tints item {item!r}: the fraction {fraction!r} is not a number "
                         "or a percentage") from None
    check_range(f"--tints item {item!r}: the pigment's mass fraction", c, 0.0, 1.0, "()")
    return spectrum(path, "--tints"), c


def _print_unmix_rows(results: list) -> None:
    """The table of ``unmix --baseline``: per method and material the mass and volume
    fractions with their 1-sigma, then the method's RMS, chi2 and warnings."""
    print(f"{'method':>21s} {'material':>12s} {'mass':>8s} {'+/-':>7s} {'volume':>8s} "
          f"{'+/-':>7s}")
    show = lambda v, j, f: "-" if v is None else format(v[j], f)  # noqa: E731
    for u in results:
        for j, m in enumerate(u.materials):
            print(f"{u.method:>21s} {m:>12s} {show(u.mass_fractions, j, '8.4f')} "
                  f"{show(u.mass_fraction_errors, j, '7.4f')} "
                  f"{show(u.volume_fractions, j, '8.4f')} "
                  f"{show(u.volume_fraction_errors, j, '7.4f')}")
        print(f"{u.method:>21s} RMS reflectance {u.rms:.5f}, chi2 {u.chi2:.4g} for {u.dof} "
              "degrees of freedom")
        for w in u.warnings:
            print(f"warning ({u.method}): {w}")


def _cmd_unmix_reflectance(args: argparse.Namespace, parts: list) -> int:
    """``unmix --baseline``: a reflectance spectrum unmixed by Hapke's rule, Kubelka-Munk or
    both beside the powder model, a row per method."""
    import numpy as np

    from ..fitting.unmix_baselines import unmix_hapke, unmix_km, unmix_powder
    from ..outputs import output_file

    args.geometry = "0:d" if args.geometry is None else args.geometry
    reflectance = _reflectance_range(args.geometry)
    if args.baseline in ("km", "all") and reflectance[1] != 1.0:  # not 0:d
        raise ValueError(f"--geometry {args.geometry}: Kubelka-Munk's R_inf is a "
                         "hemispherical reflectance; give 0:d")
    props = _fixed_properties(args.set)
    wl, r, sigma = np.array(_read_csv_columns(
        args.albedo, f"{args.albedo}: no such file", "the reflectance CSV",
        ["wavelength", "reflectance", "sigma"],
        "wavelength in nm, reflectance, its standard uncertainty",
        [_WAVELENGTH, reflectance, _SIGMA])).T
    ends, tints = _read_swatches(args, wl, len(parts))
    if args.baseline == "all":  # the powder row's model: the materials' optical constants
        _check_tables(args.albedo, wl, parts)
    if args.json:
        output_file(args.json, "--json")  # every input read: refused before the work
    runs = []
    if args.baseline == "all":
        runs.append(lambda: unmix_powder(wl, r, sigma, parts, args.by, args.geometry, props,
                                         seed=args.seed))
    if args.baseline in ("hapke", "all"):
        runs.append(lambda: unmix_hapke(wl, r, sigma, ends, parts, args.by, args.geometry,
                                        seed=args.seed))
    if args.baseline in ("km", "all"):
        runs.append(lambda: unmix_km(wl, r, sigma, ends, parts, args.by, tints, seed=args.seed))
    results = [run() for run in runs]
    print(f"unmixing the reflectance {args.albedo}: {len(wl)} wavelengths, geometry "
          f"{args.geometry}")
    _print_unmix_rows(results)
    as_list = lambda v: None if v is None else v.tolist()  # noqa: E731
    return _unmix_output(args, [
        {"method": u.method, "materials": u.materials,
         "mass_fractions": as_list(u.mass_fractions),
         "mass_fraction_errors": as_list(u.mass_fraction_errors),
         "volume_fractions": as_list(u.volume_fractions),
         "volume_fraction_errors": as_list(u.volume_fraction_errors),
         "rms_reflectance": u.rms, "chi2": u.chi2, "dof": u.dof,
         "reflectance": u.reflectance.tolist(), "warnings": u.warnings} for u in results])
