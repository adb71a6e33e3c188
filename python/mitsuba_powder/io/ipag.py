"""Read and write the text files of IPAG's spectro-goniometers (SHINE, SHADOWS) and SSHADE.

:func:`mitsuba_powder.io.measurements.load_measurements` dispatches here; use it rather than the
readers below. Every file may end its lines with CRLF, LF or CR alone (old Macintosh files);
text is UTF-8, or Latin-1 when it is not valid UTF-8.

Multi-geometry file (``*_geo*.txt``), tab-separated, a trailing tab allowed on any row::

    Detectors noises: ...                      optional free-text lines (kept as comments)
    3                                          the number of geometries (older files), or
    Angles<TAB>physical                        (newer files and SSHADE)
    Incidence<TAB>0<TAB>20<TAB>20              one value per geometry, degrees
    Emergence<TAB>30<TAB>0<TAB>-30
    Azimuth<TAB>0<TAB>0<TAB>0
    Wavelength_S<TAB>Refl_S_i0e30a0<TAB>Err_S_i0e30a0<TAB>Refl_S_i20e0a0<TAB>...
    400<TAB>0.512<TAB>0.004<TAB>...            wavelength (nm), then reflectance factor and
                                               its 1-sigma error per geometry

``S`` is the sample name; the ``Err`` columns may be absent altogether (errors missing). The
k-th ``Refl``/``Err`` pair belongs to the k-th angle column, and its name must agree with the
angles to the digits the name shows.

Single-geometry file ``<sample>_i<inc>e<em>a<az>_c.txt`` (the geometry only in the name):
optional header lines (``Sample data file : ...``, ``Corrected by: ...``; any line before the
first row whose first field is not a number), then rows ``wavelength, reflectance factor,
error`` (tab- or space-separated; two columns: errors missing). A folder of them is one data
set of one sample; files of other extensions in it are ignored (and listed in the comments).

Angle conventions (the project's: light at azimuth 0, ``theta_o`` signed, positive on the
light's side; see :mod:`mitsuba_powder.io.measurements`):

- ``signed`` (older IPAG files: a geometry-count line, every azimuth 0): the emergence is
  signed, positive on the forward (specular) side, so ``theta_o = -emergence, phi = 0``.
- ``physical`` (``Angles physical`` files and SSHADE): the emergence is >= 0 and the azimuth
  has its origin at opposition (``i = e``, azimuth 0 is back-scattering, 180 the forward
  side), so ``theta_o = emergence, phi = azimuth``.

A multi-geometry file's header line decides (an ``Angles physical`` line: physical; a count
line: signed, which requires every azimuth 0). Without either, and for single-geometry files,
the angles decide: a negative emergence means signed; every emergence >= 0 with some azimuth
not 0 means physical; every emergence 0 means both agree (``"any"``); otherwise (emergences
>= 0, every azimuth 0) the convention cannot be decided and loading fails, asking for
``convention="signed"`` or ``"physical"`` (``--convention`` on the command line).

Values: ``NaN`` (any case) in a reflectance or error cell leaves that value out; a row whose
wavelength is 0 or NaN is left out whole. Both are counted in ``Measurements.skipped`` and in a
``loader:`` comment line, never dropped silently. Any other text that is not a number, an
infinite value, a negative reflectance, error or wavelength, a wrong number of columns or a
column name that disagrees with the angle rows raises :class:`MeasurementError` naming the
file, line and column.

Errors become ``sigma``. A negative error is malformed. Zero and missing errors: if no value
has a positive error (all zero, or no error column), ``sigma`` is ``None`` and a fit is
unweighted (stated in the comments). If only some are zero or missing, ``zero_error`` decides:
``"raise"`` (default; the message names the first lines), ``"unweighted"`` (drop every sigma),
or ``"skip"`` (leave those values out, counted).

Contradictions: one sample per data set. In a multi-geometry file every ``Refl``/``Err``
column names the sample of ``Wavelength_<sample>``; in a folder, every file name has the same
sample prefix, and files of the same geometry (replicates) must agree on every ``key : value``
header line except ``Sample data file`` (which names each file's raw data). Anything else at
the same geometry and wavelength is a replicate: a separate observation.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from ..outputs import note_input, output_file, output_path
from .dataset import (
    MeasurementError,
    Measurements,
    _check_range,
    format_number,
)

CONVENTIONS = ("signed", "physical")
ZERO_ERROR = ("raise", "unweighted", "skip")
LAYOUTS = ("multi", "single")
NEWLINES = ("\r\n", "\n", "\r")

_NUM = r"[-+]?(?:\d+(?:\.\d*)?|\.\d+)"
_GEOMETRY = rf"_i(?P<i>{_NUM})e(?P<e>{_NUM})a(?P<a>{_NUM})"
_SINGLE_NAME = re.compile(rf"^(?P<sample>.*){_GEOMETRY}(?P<suffix>(?:_[A-Za-z0-9]+)*)\.txt$",
                          re.IGNORECASE)
_COLUMN = re.compile(rf"^(?P<kind>Refl|Err)_(?P<sample>.*){_GEOMETRY}$", re.IGNORECASE)
_SAMPLE_OK = re.compile(r"^[A-Za-z0-9][A-Za-z0-9.+-]*(?:_[A-Za-z0-9.+-]+)*$")


# ------------------------------------------------------------------ text helpers


def read_lines(path: Path) -> list[str]:
    """The lines of a text file, split on CRLF, LF or CR (UTF-8, else Latin-1)."""
    note_input(path)
    raw = path.read_bytes()
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        text = raw.decode("latin-1")
    lines = re.split(r"\r\n|\r|\n", text)
    if lines and lines[-1] == "":
        lines.pop()
    return lines


def _fields(line: str) -> list[str]:
    """Tab-separated fields (whitespace-separated if the line has no tab), trailing empty
    fields (a trailing tab) removed."""
    parts = line.split("\t") if "\t" in line else line.split()
    parts = [p.strip() for p in parts]
    while parts and parts[-1] == "":
        parts.pop()
    return parts


def _is_number(text: str) -> bool:
    try:
        float(text)
    except ValueError:
        return False
    return True


def _number(text: str, where: str, what: str, allow_nan: bool = True) -> float:
    """``text`` as a float; NaN allowed (returned) if ``allow_nan``; else a clear error."""
    try:
        value = float(text)
    except ValueError:
        raise MeasurementError(f"{where} ({what}): '{text}' is not a number") from None
    if np.isnan(value) and allow_nan:
        return value
    if not np.isfinite(value):
        raise MeasurementError(f"{where} ({what}): '{text}' is not a finite number")
    return value


def _agrees(name_text: str, value: float) -> bool:
    """Whether an angle written in a name (e.g. '17.5' or '18') agrees with ``value`` to the
    digits the name shows."""
    decimals = len(name_text.split(".")[1]) if "." in name_text else 0
    return abs(float(name_text) - value) <= 0.5 * 10.0 ** (-decimals) + 1e-9


def _tag_number(value: float) -> str:
    """An angle for a column or file name: fixed point, at most 6 decimals, no exponent."""
    text = f"{float(value):.6f}".rstrip("0").rstrip(".")
    return "0" if text in ("-0", "") else text


def geometry_tag(incidence: float, emergence: float, azimuth: float) -> str:
    """``i<inc>e<em>a<az>`` as IPAG writes it in column and file names."""
    return f"i{_tag_number(incidence)}e{_tag_number(emergence)}a{_tag_number(azimuth)}"


# ------------------------------------------------------------------ file kind


def file_kind(path: Path) -> str:
    """``"csv"``, ``"ipag-multi"``, ``"ipag-single"`` or ``"ipag-folder"``.

    Raises:
        MeasurementError: a file that is none of these.
    """
    path = Path(path)
    if path.is_dir():
        return "ipag-folder"
    if path.suffix.lower() == ".csv":
        return "csv"
    lines = [ln for ln in read_lines(path) if ln.strip()]
    for line in lines[:20]:
        f = _fields(line)
        if f and f[0].lower() == "incidence":
            return "ipag-multi"
    first = next((ln for ln in lines if not ln.lstrip().startswith("#")), "")
    if "theta_i" in first and "," in first:
        return "csv"
    if _SINGLE_NAME.match(path.name):
        return "ipag-single"
    raise MeasurementError(
        f"{path}: not a measurement file this package reads: expected a CSV file (header "
        "theta_i,theta_o,phi,wavelength,brf[,sigma]), an IPAG multi-geometry file (an "
        "'Incidence' row among its first lines) or an IPAG single-geometry file named "
        "<sample>_i<inc>e<em>a<az>_c.txt")


# ------------------------------------------------------------------ reading


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
        raise MeasurementError(f"{where} (reflectance factor): {refl:g} is out of range; "
                               "valid range is [0, inf)")
    if err_text is not None and err < 0:
        raise MeasurementError(f"{err_where} (error): {err:g} is out of range; valid range "
                               "is [0, inf) (0: no error, see zero_error)")
    raw.add(g, lam, refl, err, where, err_where)


def _wavelength(raw: _Raw, text: str, where: str, lineno: int) -> float | None:
    """The wavelength of a row, or None if the row is skipped (0 or NaN)."""
    lam = _number(text, where, "wavelength, nm")
    if np.isnan(lam) or lam == 0:
        raw.skipped_rows.append(f"{lineno}")
        return None
    if lam < 0:
        raise MeasurementError(f"{where} (wavelength, nm): {lam:g} is out of range; valid "
                               "range is (0, inf)")
    return lam


def _read_multi(path: Path) -> _Raw:
    lines = read_lines(path)
    raw = _Raw("multi")
    k = 0
    count, count_line = 0, 0
    # free text, then the count or 'Angles physical' line, then the angle rows
    while k < len(lines):
        f = _fields(lines[k])
        if not f:
            k += 1
            continue
        head = f[0].lower()
        if head in ("incidence", "emergence", "azimuth"):
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
    angles: dict[str, tuple[int, list[float]]] = {}
    while k < len(lines) and len(angles) < 3:
        f = _fields(lines[k])
        if not f:
            k += 1
            continue
        name = f[0].lower()
        if name not in ("incidence", "emergence", "azimuth") or name in angles:
            raise MeasurementError(
                f"{path}, line {k + 1}, column 1: expected the rows Incidence, Emergence and "
                f"Azimuth (each once), found '{f[0]}'")
        values = [_number(t, f"{path}, line {k + 1}, column {c + 2}", f"{f[0]}, degrees",
                          allow_nan=False) for c, t in enumerate(f[1:])]
        angles[name] = (k + 1, values)
        k += 1
    if len(angles) < 3:
        raise MeasurementError(f"{path}: missing angle row(s) "
                               f"{sorted({'incidence', 'emergence', 'azimuth'} - set(angles))}")
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
    inc, em, az = (angles[a][1] for a in ("incidence", "emergence", "azimuth"))
    for g in range(n):
        raw.geometries.append((inc[g], em[g], az[g]))
        raw.geometry_where.append(
            f"{path}, column {g + 2} of the angle rows (lines {angles['incidence'][0]}-"
            f"{max(v[0] for v in angles.values())})")
    # column header
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
    pairs = ncol == 2 * n
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
                f"(lines {angles['incidence'][0]}-{max(v[0] for v in angles.values())}, "
                f"column {g + 2})")
    # data rows
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
    return raw


def _single_geometry(path: Path) -> tuple[str, tuple[float, float, float]]:
    m = _SINGLE_NAME.match(path.name)
    if m is None:
        raise MeasurementError(f"{path}: an IPAG single-geometry file must be named "
                               "<sample>_i<inc>e<em>a<az>_c.txt (its geometry is in the name)")
    return m["sample"], (float(m["i"]), float(m["e"]), float(m["a"]))


def _read_singles(paths: list[Path]) -> _Raw:
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
        key = tuple(np.round(geometry, 9))
        if key in metadata:
            other, other_meta = metadata[key]
            for name, (value, line) in meta.items():
                if name == "sample data file" or name not in other_meta:
                    continue
                if other_meta[name][0] != value:
                    raise MeasurementError(
                        f"{path}, line {line}: '{name}: {value}' contradicts {other}, line "
                        f"{other_meta[name][1]} ('{other_meta[name][0]}'), a file of the same "
                        "geometry; replicates must share their calibration metadata")
        else:
            metadata[key] = (path, meta)
        if data_rows == 0:
            raise MeasurementError(f"{path}: no data rows (wavelength, reflectance factor, "
                                   "error)")
    return raw


# ------------------------------------------------------------------ conventions


def decide_convention(raw_geometries: list[tuple[float, float, float]], header: str | None,
                      override: str | None, where: list[str]) -> tuple[str, str]:
    """(convention, reason) for a set of IPAG geometries (incidence, emergence, azimuth).

    Args:
        raw_geometries: the geometries as the file writes them, degrees.
        header: ``"physical"`` (an ``Angles physical`` line), ``"count"`` (a geometry-count
            line) or ``None`` (single-geometry files, or neither line).
        override: ``"signed"``, ``"physical"`` or ``None`` (decide).
        where: per geometry, where it was read (for messages).

    Raises:
        MeasurementError: the convention cannot be decided, or the angles contradict it.
    """
    em = np.array([g[1] for g in raw_geometries])
    az = np.array([g[2] for g in raw_geometries])
    az0 = np.isclose(np.mod(az + 180.0, 360.0) - 180.0, 0.0, atol=1e-9)
    how = ("pass convention='signed' (older files: emergence signed, positive on the forward "
           "side) or convention='physical' (newer files and SSHADE: emergence >= 0, azimuth 0 "
           "at opposition); on the command line --convention signed|physical")
    if override is not None:
        if override not in CONVENTIONS:
            raise MeasurementError(f"convention = {override!r} is not known; valid: "
                                   f"{', '.join(CONVENTIONS)} or None (decide from the file)")
        said = {"physical": "physical", "count": "signed"}.get(header or "")
        convention = override
        reason = "chosen by the caller" + (f"; the file's header says {said}"
                                           if said and said != override else "")
    elif header == "physical":
        convention, reason = "physical", "the file's 'Angles physical' line"
    elif header == "count":
        if not az0.all():
            g = int(np.argmax(~az0))
            raise MeasurementError(
                f"{where[g]}: cannot decide the angle convention: a geometry-count line marks "
                f"an older file with a signed emergence and every azimuth 0, but azimuth "
                f"{az[g]:g} is not 0; {how}")
        convention, reason = "signed", "a geometry-count line (older IPAG file)"
    elif np.all(em == 0):
        return "any", "every emergence is 0, where both conventions agree"
    elif np.any(em < 0):
        if not az0.all():
            g, h = int(np.argmax(em < 0)), int(np.argmax(~az0))
            raise MeasurementError(
                f"cannot decide the angle convention: a negative emergence ({em[g]:g}, "
                f"{where[g]}) means signed, but signed files have every azimuth 0 and "
                f"{where[h]} has azimuth {az[h]:g}; {how}")
        convention, reason = "signed", "a negative emergence (signed, older IPAG file)"
    elif not az0.all():
        convention, reason = "physical", "every emergence >= 0 and some azimuth not 0"
    else:
        raise MeasurementError(
            f"{where[0]}: cannot decide the angle convention: every emergence is >= 0 and "
            "every azimuth is 0, which in the signed convention are views on the forward "
            "(specular) side (theta_o = -emergence) and in the physical convention views on "
            f"the light's side (theta_o = +emergence); {how}")
    if convention == "signed" and not az0.all():
        g = int(np.argmax(~az0))
        raise MeasurementError(f"{where[g]}: azimuth {az[g]:g}: the signed convention (older "
                               "IPAG files) has every azimuth 0; use convention='physical'")
    if convention == "physical" and np.any(em < 0):
        g = int(np.argmax(em < 0))
        raise MeasurementError(f"{where[g]}: emergence {em[g]:g} < 0: the physical convention "
                               "has emergences >= 0; use convention='signed'")
    return convention, reason


def to_project(incidence, emergence, azimuth, convention: str
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IPAG angles (degrees) -> the project's (theta_i, theta_o, phi), degrees."""
    ti = np.asarray(incidence, dtype=np.float64)
    e = np.asarray(emergence, dtype=np.float64)
    a = np.asarray(azimuth, dtype=np.float64)
    if convention == "signed":
        return ti, -e, np.zeros_like(e)
    if convention in ("physical", "any"):
        return ti, e.copy(), a.copy()
    raise ValueError(f"convention = {convention!r}; valid: {', '.join(CONVENTIONS)}")


def from_project(theta_i, theta_o, phi, convention: str
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The project's angles (degrees) -> IPAG (incidence, emergence, azimuth) in a convention.

    ``physical``: emergence ``|theta_o|``, azimuth in [0, 360) (``phi + 180`` where
    ``theta_o < 0``). ``signed``: only the plane of incidence (``phi`` 0 or 180, or
    ``theta_o = 0``): emergence ``-theta_o`` at ``phi = 0``, ``+theta_o`` at 180.

    Raises:
        ValueError: ``signed`` and a direction outside the plane of incidence.
    """
    ti = np.asarray(theta_i, dtype=np.float64)
    to = np.asarray(theta_o, dtype=np.float64)
    ph = np.asarray(phi, dtype=np.float64)
    if convention == "physical":
        a = np.mod(np.where(to < 0, ph + 180.0, ph), 360.0)
        return ti, np.abs(to), a + 0.0
    if convention == "signed":
        wrapped = np.mod(ph + 90.0, 360.0) - 90.0          # in [-90, 270)
        on0 = np.isclose(wrapped, 0.0, atol=1e-9)
        on180 = np.isclose(wrapped, 180.0, atol=1e-9)
        bad = ~(on0 | on180 | (to == 0))
        if bad.any():
            k = int(np.argmax(bad))
            raise ValueError(f"row {k}: phi = {ph[k]:g} with theta_o = {to[k]:g} is outside "
                             "the plane of incidence, which is all the signed convention "
                             "(older IPAG files, every azimuth 0) holds; use "
                             "convention='physical'")
        return ti, np.where(on180, to, -to) + 0.0, np.zeros_like(to)
    raise ValueError(f"convention = {convention!r}; valid: {', '.join(CONVENTIONS)}")


# ------------------------------------------------------------------ loading


def load_ipag(path: str | Path, convention: str | None = None,
              zero_error: str = "raise") -> Measurements:
    """Read an IPAG multi- or single-geometry file, or a folder of single-geometry files.

    Args:
        path: the file or folder.
        convention: ``"signed"``, ``"physical"`` or ``None`` (decide; see the module
            docstring).
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
    conv, reason = decide_convention(raw.geometries, raw.header, convention,
                                     raw.geometry_where)
    notes = [f"loader: {what}; angle convention {conv} ({reason}): "
             + {"signed": "theta_o = -emergence, phi = 0",
                "physical": "theta_o = emergence, phi = azimuth",
                "any": "theta_o = emergence = 0"}[conv]]
    skipped: dict[str, int] = {}
    if raw.skipped_rows:
        skipped["rows_wavelength_0_or_nan"] = len(raw.skipped_rows)
        lines = ", ".join(raw.skipped_rows[:8]) + (", ..." if len(raw.skipped_rows) > 8
                                                   else "")
        notes.append(f"loader: skipped {len(raw.skipped_rows)} rows whose wavelength is 0 or "
                     f"NaN (line{'s' if len(raw.skipped_rows) > 1 else ''} {lines})")
    if raw.nan_values:
        skipped["nan_values"] = raw.nan_values
        notes.append(f"loader: skipped {raw.nan_values} NaN values (reflectance or error)")
    if not raw.refl:
        raise MeasurementError(f"{path}: no data left ({', '.join(notes[1:]) or 'no rows'})")
    g = np.asarray(raw.geometry)
    geo = np.asarray(raw.geometries, dtype=np.float64)
    ti, to, ph = to_project(geo[g, 0], geo[g, 1], geo[g, 2], conv)
    lam = np.asarray(raw.wavelength)
    refl = np.asarray(raw.refl)
    err = np.asarray(raw.err)
    for k in range(len(raw.geometries)):
        sel = np.nonzero(g == k)[0]
        if len(sel):
            t = to_project(*geo[k], conv)
            for name, value in zip(("theta_i", "theta_o", "phi"), t):
                _check_range(name, float(value), f"{raw.geometry_where[k]} [{conv} "
                             f"convention: incidence {geo[k, 0]:g}, emergence {geo[k, 1]:g}, "
                             f"azimuth {geo[k, 2]:g}]")
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
            keep = positive
            ti, to, ph, lam, refl, sigma = (a[keep] for a in (ti, to, ph, lam, refl, err))
            skipped["zero_or_missing_error"] = len(bad)
            notes.append(f"loader: skipped {len(bad)} values with a zero or missing error "
                         "(zero_error='skip')")
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


# ------------------------------------------------------------------ writing


def _free_text(line: str) -> str:
    """A comment line that no IPAG reader mistakes for a header, angle or data row."""
    line = line.replace("\t", " ").replace("\r", " ").replace("\n", " ").strip()
    first = _fields(line)[0] if _fields(line) else ""
    if _is_number(first) or first.lower() in ("angles", "incidence", "emergence", "azimuth") \
            or first.lower().startswith("wavelength"):
        line = "Note: " + line
    return line


def save_ipag(path: str | Path, data: Measurements, layout: str = "multi",
              sample: str = "sample", convention: str = "physical", newline: str = "\r\n",
              comments: list[str] | None = None) -> Path:
    """Write ``data`` as IPAG text: a multi-geometry file or a folder of single-geometry files.

    Numbers are written so that they read back exactly (shortest round-trip text).

    Args:
        path: the file (``layout="multi"``, e.g. ``sample_geo.txt``) or folder (``"single"``;
            created; it must not hold .txt files already).
        data: the measurements (project convention). ``"multi"`` needs every geometry at
            every wavelength (one row per wavelength).
        layout: ``"multi"`` or ``"single"``.
        sample: sample name (letters, digits, ``.+-``, single underscores).
        convention: ``"physical"`` (an ``Angles physical`` line; emergence >= 0, azimuth 0 at
            opposition) or ``"signed"`` (a count line; plane of incidence only).
        newline: ``"\\r\\n"`` (default, as the instruments write), ``"\\n"`` or ``"\\r"``.
        comments: free-text lines first (multi) or header lines (single); default
            ``data.comments``.

    Returns:
        The file or folder written.

    Raises:
        ValueError: an unknown layout, convention or newline, a bad sample name, directions
            the convention cannot hold, or (multi) a geometry missing at some wavelength.
    """
    path = Path(path)
    if layout not in LAYOUTS:
        raise ValueError(f"layout = {layout!r}; valid: {', '.join(LAYOUTS)}")
    if convention not in CONVENTIONS:
        raise ValueError(f"convention = {convention!r}; valid: {', '.join(CONVENTIONS)}")
    if newline not in NEWLINES:
        raise ValueError(f"newline = {newline!r}; valid: '\\r\\n', '\\n', '\\r'")
    if not _SAMPLE_OK.match(sample):
        raise ValueError(f"sample = {sample!r}: use letters, digits, '.', '+', '-' and single "
                         "underscores (it becomes part of column and file names)")
    if len(data) == 0:
        raise ValueError("no measurements to write")
    inc, em, az = from_project(data.theta_i, data.theta_o, data.phi, convention)
    lines_comments = [_free_text(c) for c in (data.comments if comments is None else comments)]
    keys = np.round(np.stack([inc, em, az], axis=1), 9) + 0.0
    err = data.sigma if data.sigma is not None else np.zeros(len(data))
    num = lambda v: format_number(v, None)  # noqa: E731
    if layout == "multi":
        lams = np.unique(data.wavelength)
        rows_of = {lam: np.nonzero(data.wavelength == lam)[0] for lam in lams}
        first = rows_of[lams[0]]
        columns = [tuple(keys[i]) for i in first]
        table = np.empty((len(lams), len(columns), 2))
        for w, lam in enumerate(lams):
            pool: dict[tuple, list[int]] = {}
            for i in rows_of[lam]:
                pool.setdefault(tuple(keys[i]), []).append(int(i))
            for c, key in enumerate(columns):
                if not pool.get(key):
                    raise ValueError(
                        f"layout 'multi' needs every geometry at every wavelength: "
                        f"{lam:g} nm lacks incidence {key[0]:g}, emergence {key[1]:g}, "
                        f"azimuth {key[2]:g} ({convention}); use layout='single'")
                i = pool[key].pop(0)
                table[w, c] = data.brf[i], err[i]
            extra = [k for k, v in pool.items() if v]
            if extra:
                raise ValueError(f"layout 'multi' needs the same geometries at every "
                                 f"wavelength: {lam:g} nm has {extra[0]} which "
                                 f"{lams[0]:g} nm lacks; use layout='single'")
        geo = [(inc[i], em[i], az[i]) for i in first]
        out = list(lines_comments)
        out.append("Angles\tphysical" if convention == "physical" else str(len(geo)))
        for label, k in (("Incidence", 0), ("Emergence", 1), ("Azimuth", 2)):
            out.append(label + "\t" + "\t".join(num(g[k]) for g in geo) + "\t")
        head = [f"Wavelength_{sample}"]
        for g in geo:
            tag = geometry_tag(*g)
            head += [f"Refl_{sample}_{tag}", f"Err_{sample}_{tag}"]
        out.append("\t".join(head))
        for w, lam in enumerate(lams):
            out.append("\t".join([num(lam)] + [num(v) for v in table[w].ravel()]))
        output_file(path).write_bytes((newline.join(out) + newline).encode("utf-8"))
        return path
    # single-geometry files
    if path.exists() and (not path.is_dir() or any(p.suffix.lower() == ".txt"
                                                   for p in path.iterdir())):
        raise ValueError(f"{path}: layout 'single' writes a folder of .txt files; give a new "
                         "or empty folder")
    path.mkdir(parents=True, exist_ok=True)
    groups: dict[tuple, list[int]] = {}
    for i in range(len(data)):
        groups.setdefault(tuple(keys[i]), []).append(i)
    names: dict[str, tuple] = {}
    for key, rows in groups.items():
        i0 = rows[0]
        name = f"{sample}_{geometry_tag(inc[i0], em[i0], az[i0])}_c.txt"
        if name in names:
            raise ValueError(f"geometries {names[name]} and {key} both round to file name "
                             f"{name}")
        names[name] = key
        out = [f"Sample data file : {name[:-6]}.txt"] + lines_comments
        out += [f"{num(data.wavelength[i])}\t{num(data.brf[i])}\t{num(err[i])}" for i in rows]
        output_path(path, name).write_bytes((newline.join(out) + newline).encode("utf-8"))
    return path
