"""Reading IPAG files (:mod:`mitsuba_powder.io.ipag` describes the layouts): the multi- and
single-geometry readers collect raw values, then :func:`load_ipag` applies the angle convention
and the zero-error policy and says in ``loader:`` comments what it left out."""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from .._checks import out_of_range
from .dataset import MeasurementError, Measurements, _check_column_range
from .ipag_angles import decide_convention, to_project
from .ipag_text import (
    _COLUMN,
    _SINGLE_NAME,
    ZERO_ERROR,
    _agrees,
    _fields,
    _is_number,
    _number,
    file_kind,
    read_lines,
)

_ANGLE_ROWS = ("incidence", "emergence", "azimuth")


@dataclass
class _Raw:
    """Values read from IPAG files, before the convention is applied."""

    kind: str
    # per geometry: (incidence, emergence, azimuth) and where they were read
    geometries: list[tuple[float, float, float]] = field(default_factory=list)
    geometry_where: list[str] = field(default_factory=list)
    # per value
    geometry: list[int] = field(default_factory=list)
    wavelength: list[float] = field(default_factory=list)
    refl: list[float] = field(default_factory=list)
    err: list[float] = field(default_factory=list)        # NaN: no error column
    err_where: list[str] = field(default_factory=list)
    where: list[str] = field(default_factory=list)
    comments: list[str] = field(default_factory=list)
    header: str | None = None        # "physical", "count" or None
    header_where: str = ""
    sample: str = ""
    skipped_rows: list[str] = field(default_factory=list)       # wavelength 0 / NaN rows
    nan_values: int = 0

    def add(self, g: int, lam: float, refl: float, err: float, where: str,
            err_where: str) -> None:
        self.geometry.append(g)
        self.wavelength.append(lam)
        self.refl.append(refl)
        self.err.append(err)
        self.where.append(where)
        self.err_where.append(err_where)


def _read_value(raw: _Raw, g: int, lam: float, refl_text: str, err_text: str | None,
                where: str, err_where: str) -> None:
    """Parse one reflectance (and error) cell pair into ``raw``; NaN is skipped, counted."""
    refl = _number(refl_text, where, "reflectance factor")
    err = np.nan if err_text is None else _number(err_text, err_where, "error")
    if np.isnan(refl) or (err_text is not None and np.isnan(err)):
        raw.nan_values += 1
        return
    if refl < 0:
        raise MeasurementError(out_of_range(f"{where} (reflectance factor): {refl:g}",
                                            "[0, inf)"))
    if err_text is not None and err < 0:
        raise MeasurementError(out_of_range(f"{err_where} (error): {err:g}", "[0, inf)",
                                            "(0: no error, see zero_error)"))
    raw.add(g, lam, refl, err, where, err_where)


def _wavelength(raw: _Raw, text: str, where: str, lineno: int) -> float | None:
    """The wavelength of a row, or None if the row is skipped (0 or NaN)."""
    lam = _number(text, where, "wavelength, nm")
    if np.isnan(lam) or lam == 0:
        raw.skipped_rows.append(f"{lineno}")
        return None
    if lam < 0:
        raise MeasurementError(out_of_range(f"{where} (wavelength, nm): {lam:g}", "(0, inf)"))
    return lam


# ------------------------------------------------------------------ multi-geometry file


def _read_preamble(path: Path, lines: list[str], raw: _Raw) -> tuple[int, int, int]:
    """Free text, then the count or 'Angles physical' line, up to the first angle row.

    Returns:
        (index of the first angle row, announced geometry count, its line number); the count
        and its line are 0 without a count line.
    """
    k = 0
    count, count_line = 0, 0
    while k < len(lines):
        f = _fields(lines[k])
        if not f:
            k += 1
            continue
        head = f[0].lower()
        if head in _ANGLE_ROWS:
            break
        if head == "angles":
            if len(f) < 2 or f[1].lower() != "physical":
                raise MeasurementError(
                    f"{path}, line {k + 1}, column 2: angles convention "
                    f"'{f[1] if len(f) > 1 else ''}' is not known; valid: physical (or give "
                    "the line of the number of geometries, older signed files)")
            raw.header, raw.header_where = "physical", f"line {k + 1}"
        elif len(f) == 1 and re.fullmatch(r"\d+", f[0]):
            raw.header, raw.header_where = "count", f"line {k + 1}"
            count, count_line = int(f[0]), k + 1
        elif raw.header is not None:
            raise MeasurementError(f"{path}, line {k + 1}: expected the 'Incidence' row after "
                                   f"the {raw.header_where} header, found '{lines[k][:40]}'")
        else:
            raw.comments.append(lines[k].strip().replace("\t", " "))
        k += 1
    return k, count, count_line


def _read_angle_rows(path: Path, lines: list[str], k: int
                     ) -> tuple[int, dict[str, tuple[int, list[float]]]]:
    """The Incidence, Emergence and Azimuth rows from index ``k`` on.

    Returns:
        (index after the rows, {row name: (line number, values in degrees)}).
    """
    angles: dict[str, tuple[int, list[float]]] = {}
    while k < len(lines) and len(angles) < 3:
        f = _fields(lines[k])
        if not f:
            k += 1
            continue
        name = f[0].lower()
        if name not in _ANGLE_ROWS or name in angles:
            raise MeasurementError(
                f"{path}, line {k + 1}, column 1: expected the rows Incidence, Emergence and "
                f"Azimuth (each once), found '{f[0]}'")
        values = [_number(t, f"{path}, line {k + 1}, column {c + 2}", f"{f[0]}, degrees",
                          allow_nan=False) for c, t in enumerate(f[1:])]
        angles[name] = (k + 1, values)
        k += 1
    if len(angles) < 3:
        raise MeasurementError(f"{path}: missing angle row(s) "
                               f"{sorted(set(_ANGLE_ROWS) - set(angles))}")
    return k, angles


def _angle_lines(angles: dict[str, tuple[int, list[float]]]) -> str:
    """'lines A-B': where the angle rows are (for messages)."""
    return f"lines {angles['incidence'][0]}-{max(v[0] for v in angles.values())}"


def _add_geometries(path: Path, raw: _Raw, angles: dict[str, tuple[int, list[float]]],
                    count: int, count_line: int) -> int:
    """Check that the angle rows have one value per geometry (as many as a count line
    announces) and add the geometries to ``raw``; returns their number."""
    n = len(angles["incidence"][1])
    for name, (line, values) in angles.items():
        if len(values) != n or n == 0:
            raise MeasurementError(
                f"{path}, line {line}: {len(values)} {name} values, but the Incidence row "
                f"(line {angles['incidence'][0]}) has {n}; every angle row needs one value "
                "per geometry")
    if raw.header == "count" and count != n:
        raise MeasurementError(f"{path}, line {count_line}, column 1: {count} geometries "
                               f"announced, but the angle rows have {n}")
    inc, em, az = (angles[a][1] for a in _ANGLE_ROWS)
    for g in range(n):
        raw.geometries.append((inc[g], em[g], az[g]))
        raw.geometry_where.append(f"{path}, column {g + 2} of the angle rows "
                                  f"({_angle_lines(angles)})")
    return n


def _read_column_header(path: Path, lines: list[str], k: int, raw: _Raw, n: int
                        ) -> tuple[list[str], int, bool]:
    """The ``Wavelength_<sample>`` header line at or after index ``k``; sets ``raw.sample``.

    Returns:
        (its fields, its line number, whether every geometry has an ``Err`` column).
    """
    while k < len(lines) and not _fields(lines[k]):
        k += 1
    if k >= len(lines):
        raise MeasurementError(f"{path}: no 'Wavelength_<sample>' header line after the angle "
                               "rows")
    header = _fields(lines[k])
    hline = k + 1
    if not header[0].lower().startswith("wavelength"):
        raise MeasurementError(f"{path}, line {hline}, column 1: expected "
                               f"'Wavelength_<sample>', found '{header[0]}'")
    raw.sample = header[0][len("wavelength_"):] if "_" in header[0] else ""
    ncol = len(header) - 1
    if ncol not in (n, 2 * n):
        raise MeasurementError(
            f"{path}, line {hline}: {ncol} columns after the wavelength; expected {2 * n} "
            f"(Refl and Err per geometry) or {n} (Refl only) for the {n} geometries of the "
            "angle rows")
    return header, hline, ncol == 2 * n


def _check_column_names(path: Path, raw: _Raw, header: list[str], hline: int, pairs: bool,
                        angles: dict[str, tuple[int, list[float]]]) -> None:
    """Every ``Refl``/``Err`` column names the file's sample and its geometry's angles."""
    for c, name in enumerate(header[1:], start=2):
        g = (c - 2) // 2 if pairs else c - 2
        kind = "Err" if pairs and (c - 2) % 2 else "Refl"
        where = f"{path}, line {hline}, column {c}"
        m = _COLUMN.match(name)
        if m is None or m["kind"].lower() != kind.lower():
            raise MeasurementError(f"{where}: '{name}' is not a column name "
                                   f"{kind}_<sample>_i<inc>e<em>a<az>")
        if m["sample"] != raw.sample:
            raise MeasurementError(f"{where}: sample '{m['sample']}' of '{name}' differs from "
                                   f"'{raw.sample}' of column 1 ({header[0]}); one file holds "
                                   "one sample")
        ti, te, ta = raw.geometries[g]
        if not (_agrees(m["i"], ti) and _agrees(m["e"], te) and _agrees(m["a"], ta)):
            raise MeasurementError(
                f"{where}: the name '{name}' disagrees with the angle rows, which give "
                f"incidence {ti:g}, emergence {te:g}, azimuth {ta:g} for geometry {g + 1} "
                f"({_angle_lines(angles)}, column {g + 2})")


def _read_data_rows(path: Path, lines: list[str], raw: _Raw, header: list[str], hline: int,
                    n: int, pairs: bool) -> None:
    """The rows after the header: wavelength, then reflectance (and error) per geometry."""
    ncol = len(header) - 1
    for k in range(hline, len(lines)):
        f = _fields(lines[k])
        if not f:
            continue
        lam = _wavelength(raw, f[0], f"{path}, line {k + 1}, column 1", k + 1)
        if lam is None:
            continue
        if len(f) != ncol + 1:
            raise MeasurementError(f"{path}, line {k + 1}: {len(f)} columns, expected "
                                   f"{ncol + 1} like the header (line {hline})")
        for g in range(n):
            c = 2 + (2 * g if pairs else g)
            _read_value(raw, g, lam, f[c - 1], f[c] if pairs else None,
                        f"{path}, line {k + 1}, column {c} ({header[c - 1]})",
                        f"{path}, line {k + 1}, column {c + 1}"
                        + (f" ({header[c]})" if pairs else ""))


def _read_multi(path: Path) -> _Raw:
    """The raw values of a multi-geometry file."""
    lines = read_lines(path)
    raw = _Raw("multi")
    k, count, count_line = _read_preamble(path, lines, raw)
    k, angles = _read_angle_rows(path, lines, k)
    n = _add_geometries(path, raw, angles, count, count_line)
    header, hline, pairs = _read_column_header(path, lines, k, raw, n)
    _check_column_names(path, raw, header, hline, pairs, angles)
    _read_data_rows(path, lines, raw, header, hline, n, pairs)
    return raw


# ------------------------------------------------------------------ single-geometry files


def _single_geometry(path: Path) -> tuple[str, tuple[float, float, float]]:
    m = _SINGLE_NAME.match(path.name)
    if m is None:
        raise MeasurementError(f"{path}: an IPAG single-geometry file must be named "
                               "<sample>_i<inc>e<em>a<az>_c.txt (its geometry is in the name)")
    return m["sample"], (float(m["i"]), float(m["e"]), float(m["a"]))


def _read_single_file(path: Path, raw: _Raw, g: int
                      ) -> tuple[dict[str, tuple[str, int]], int]:
    """The header lines and data rows of one single-geometry file (geometry ``g``).

    Returns:
        (its ``key : value`` header lines, {key (lower case): (value, line number)}; the
        number of its data rows).
    """
    meta: dict[str, tuple[str, int]] = {}
    ncol = None
    first_row = 0
    data_rows = 0
    for k, line in enumerate(read_lines(path)):
        f = _fields(line)
        if not f:
            continue
        if ncol is None and data_rows == 0 and not _is_number(f[0]):   # a header line
            text = line.strip().replace("\t", " ")
            key, sep, value = (s.strip() for s in text.partition(":"))
            if sep:
                meta[key.lower()] = (value, k + 1)
            # one copy of each header line; 'Sample data file' names each file's raw data
            if key.lower() != "sample data file" and text not in raw.comments:
                raw.comments.append(text)
            continue
        data_rows += 1
        lam = _wavelength(raw, f[0], f"{path}, line {k + 1}, column 1", k + 1)
        if lam is None:
            continue
        if ncol is None:
            if len(f) not in (2, 3):
                raise MeasurementError(
                    f"{path}, line {k + 1}: {len(f)} columns, expected 3 (wavelength, "
                    "reflectance factor, error) or 2 (no error)")
            ncol, first_row = len(f), k + 1
        elif len(f) != ncol:
            raise MeasurementError(f"{path}, line {k + 1}: {len(f)} columns, expected "
                                   f"{ncol} like line {first_row}")
        _read_value(raw, g, lam, f[1], f[2] if ncol == 3 else None,
                    f"{path}, line {k + 1}, column 2", f"{path}, line {k + 1}, column 3")
    return meta, data_rows


def _check_replicate_metadata(path: Path, meta: dict[str, tuple[str, int]], other: Path,
                              other_meta: dict[str, tuple[str, int]]) -> None:
    """Files of the same geometry share their calibration metadata (every ``key : value``
    header line but ``Sample data file``)."""
    for name, (value, line) in meta.items():
        if name == "sample data file" or name not in other_meta:
            continue
        if other_meta[name][0] != value:
            raise MeasurementError(
                f"{path}, line {line}: '{name}: {value}' contradicts {other}, line "
                f"{other_meta[name][1]} ('{other_meta[name][0]}'), a file of the same "
                "geometry; replicates must share their calibration metadata")


def _read_singles(paths: list[Path]) -> _Raw:
    """The raw values of single-geometry files of one sample."""
    raw = _Raw("single")
    metadata: dict[tuple[float, float, float], tuple[Path, dict[str, tuple[str, int]]]] = {}
    first_sample: tuple[str, Path] | None = None
    for path in paths:
        sample, geometry = _single_geometry(path)
        if first_sample is None:
            first_sample = (sample, path)
            raw.sample = sample
        elif sample != first_sample[0]:
            raise MeasurementError(
                f"{path}: sample '{sample}' (from the file name) differs from '"
                f"{first_sample[0]}' of {first_sample[1]}; a folder is one data set of one "
                "sample")
        g = len(raw.geometries)
        raw.geometries.append(geometry)
        raw.geometry_where.append(f"{path} (file name)")
        meta, data_rows = _read_single_file(path, raw, g)
        key = tuple(np.round(geometry, 9))
        if key in metadata:
            _check_replicate_metadata(path, meta, *metadata[key])
        else:
            metadata[key] = (path, meta)
        if data_rows == 0:
            raise MeasurementError(f"{path}: no data rows (wavelength, reflectance factor, "
                                   "error)")
    return raw


# ------------------------------------------------------------------ loading


def _read_raw(path: Path) -> tuple[_Raw, str, list[str]]:
    """(raw values, what was read, names of a folder's entries that are not .txt files)."""
    kind = file_kind(path)
    ignored: list[str] = []
    if kind == "ipag-multi":
        raw = _read_multi(path)
        what = f"IPAG multi-geometry file, sample '{raw.sample}', {len(raw.geometries)} " \
               "geometries"
    elif kind in ("ipag-single", "ipag-folder"):
        if kind == "ipag-folder":
            files = sorted(p for p in path.iterdir() if p.is_file()
                           and p.suffix.lower() == ".txt")
            ignored = sorted(p.name for p in path.iterdir() if p not in files)
            if not files:
                raise MeasurementError(f"{path}: a folder of IPAG single-geometry files, but "
                                       "it holds no .txt file")
        else:
            files = [path]
        raw = _read_singles(files)
        what = (f"IPAG single-geometry file{'s' if len(files) > 1 else ''} ({len(files)}), "
                f"sample '{raw.sample}'")
    else:
        raise MeasurementError(f"{path}: a CSV file, not an IPAG file")
    return raw, what, ignored


def _skipped_rows_and_nans(raw: _Raw, notes: list[str], skipped: dict[str, int]) -> None:
    """Count (``skipped``) and say (``notes``) the rows and values the readers left out."""
    if raw.skipped_rows:
        skipped["rows_wavelength_0_or_nan"] = len(raw.skipped_rows)
        lines = ", ".join(raw.skipped_rows[:8]) + (", ..." if len(raw.skipped_rows) > 8
                                                   else "")
        notes.append(f"loader: skipped {len(raw.skipped_rows)} rows whose wavelength is 0 or "
                     f"NaN (line{'s' if len(raw.skipped_rows) > 1 else ''} {lines})")
    if raw.nan_values:
        skipped["nan_values"] = raw.nan_values
        notes.append(f"loader: skipped {raw.nan_values} NaN values (reflectance or error)")


def _check_geometries(raw: _Raw, geo: np.ndarray, g: np.ndarray, conv: str) -> None:
    """Every geometry that holds values is in the project's valid angle ranges."""
    for k in range(len(raw.geometries)):
        sel = np.nonzero(g == k)[0]
        if len(sel):
            t = to_project(*geo[k], conv)
            for name, value in zip(("theta_i", "theta_o", "phi"), t):
                _check_column_range(name, float(value), f"{raw.geometry_where[k]} [{conv} "
                             f"convention: incidence {geo[k, 0]:g}, emergence {geo[k, 1]:g}, "
                             f"azimuth {geo[k, 2]:g}]")


def _apply_zero_error(raw: _Raw, columns: tuple[np.ndarray, ...], zero_error: str,
                      notes: list[str], skipped: dict[str, int]
                      ) -> tuple[tuple[np.ndarray, ...], np.ndarray | None]:
    """The zero-error policy (see :mod:`mitsuba_powder.io.ipag`).

    Args:
        columns: (theta_i, theta_o, phi, wavelength, reflectance, error) per value.

    Returns:
        (the first five columns, kept values only; sigma or None).
    """
    err = columns[5]
    sigma: np.ndarray | None = err
    positive = err > 0            # NaN (missing) compares False
    if not positive.any():
        sigma = None
        notes.append("loader: no positive error in the file(s) (all zero or missing): sigma "
                     "not set, fits are unweighted")
    elif not positive.all():
        bad = np.nonzero(~positive)[0]
        if zero_error == "raise":
            first = "; ".join(f"{raw.err_where[i]}: "
                              f"{'0' if err[i] == 0 else 'missing'}" for i in bad[:3])
            raise MeasurementError(
                f"{len(bad)} of {len(err)} values have a zero or missing error ({first}"
                f"{'; ...' if len(bad) > 3 else ''}) while others have one; pass "
                "zero_error='unweighted' (drop every sigma: unweighted fit) or 'skip' (leave "
                "these values out); on the command line --zero-error unweighted|skip")
        if zero_error == "unweighted":
            sigma = None
            notes.append(f"loader: {len(bad)} values have a zero or missing error: every sigma "
                         "dropped (zero_error='unweighted'), fits are unweighted")
        else:
            kept = tuple(a[positive] for a in columns)
            skipped["zero_or_missing_error"] = len(bad)
            notes.append(f"loader: skipped {len(bad)} values with a zero or missing error "
                         "(zero_error='skip')")
            return kept[:5], kept[5]
    return columns[:5], sigma


def load_ipag(path: str | Path, convention: str | None = None,
              zero_error: str = "raise") -> Measurements:
    """Read an IPAG multi- or single-geometry file, or a folder of single-geometry files.

    Args:
        path: the file or folder.
        convention: ``"signed"``, ``"physical"`` or ``None`` (decide; see the docstring of
            :mod:`mitsuba_powder.io.ipag`).
        zero_error: ``"raise"``, ``"unweighted"`` or ``"skip"``: what to do when some (not
            all) errors are zero or missing.

    Returns:
        Measurements in the project convention; ``convention`` says which IPAG convention
        was applied, ``skipped`` what was left out, and ``comments`` end with ``loader:``
        lines saying both.

    Raises:
        MeasurementError: malformed file or folder (file, line and column named), or a
            convention that cannot be decided.
    """
    path = Path(path)
    if zero_error not in ZERO_ERROR:
        raise ValueError(f"zero_error = {zero_error!r}; valid: {', '.join(ZERO_ERROR)}")
    raw, what, ignored = _read_raw(path)
    conv, reason = decide_convention(raw.geometries, raw.header, convention,
                                     raw.geometry_where)
    notes = [f"loader: {what}; angle convention {conv} ({reason}): "
             + {"signed": "theta_o = -emergence, phi = 0",
                "physical": "theta_o = emergence, phi = azimuth",
                "any": "theta_o = emergence = 0"}[conv]]
    skipped: dict[str, int] = {}
    _skipped_rows_and_nans(raw, notes, skipped)
    if not raw.refl:
        raise MeasurementError(f"{path}: no data left ({', '.join(notes[1:]) or 'no rows'})")
    g = np.asarray(raw.geometry)
    geo = np.asarray(raw.geometries, dtype=np.float64)
    ti, to, ph = to_project(geo[g, 0], geo[g, 1], geo[g, 2], conv)
    _check_geometries(raw, geo, g, conv)
    columns = (ti, to, ph, np.asarray(raw.wavelength), np.asarray(raw.refl),
               np.asarray(raw.err))
    (ti, to, ph, lam, refl), sigma = _apply_zero_error(raw, columns, zero_error, notes,
                                                       skipped)
    if ignored:
        notes.append(f"loader: ignored {len(ignored)} entries of the folder that are not .txt "
                     f"files: {', '.join(ignored[:8])}{', ...' if len(ignored) > 8 else ''}")
    data = Measurements(ti, to, ph, lam, refl, sigma, raw.comments, str(path), conv, skipped)
    summary = data.geometry_summary()
    notes.append(f"loader: {summary['rows']} values, {summary['geometries']} unique geometries "
                 f"(incidence, viewing direction, wavelength), {summary['replicated_rows']} "
                 "replicated")
    data.comments = raw.comments + notes
    return data
