"""Writing IPAG files (:mod:`mitsuba_powder.io.ipag` describes the layouts): one
multi-geometry file, or a folder of single-geometry files; numbers as the shortest text that
reads back exactly."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from ..outputs import output_file, output_path
from .dataset import Measurements, format_number
from .ipag_angles import from_project
from .ipag_text import (
    _SAMPLE_OK,
    CONVENTIONS,
    LAYOUTS,
    NEWLINES,
    _fields,
    _is_number,
    geometry_tag,
)


def _free_text(line: str) -> str:
    """A comment line that no IPAG reader mistakes for a header, angle or data row."""
    line = line.replace("\t", " ").replace("\r", " ").replace("\n", " ").strip()
    first = _fields(line)[0] if _fields(line) else ""
    if _is_number(first) or first.lower() in ("angles", "incidence", "emergence", "azimuth") \
            or first.lower().startswith("wavelength"):
        line = "Note: " + line
    return line


def _num(value: float) -> str:
    """A number as the shortest text that reads back to the same float."""
    return format_number(value, None)


def _check_arguments(data: Measurements, layout: str, sample: str, convention: str,
                     newline: str) -> None:
    """The checks of :func:`save_ipag`'s arguments (``ValueError`` naming the bad one)."""
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


def _multi_table(data: Measurements, keys: np.ndarray, err: np.ndarray, convention: str
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The multi-geometry table: every geometry at every wavelength.

    Args:
        keys: per row, its (incidence, emergence, azimuth) rounded to 9 decimals.

    Returns:
        (wavelengths, rows that give the geometries' order (those of the first wavelength),
        table[wavelength, geometry] = (reflectance, error)).
    """
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
    return lams, first, table


def _write_multi(path: Path, data: Measurements, angles: tuple[np.ndarray, ...],
                 keys: np.ndarray, err: np.ndarray, sample: str, convention: str,
                 newline: str, comments: list[str]) -> None:
    """One multi-geometry file: comments, header line, angle rows, column names, data."""
    inc, em, az = angles
    lams, first, table = _multi_table(data, keys, err, convention)
    geo = [(inc[i], em[i], az[i]) for i in first]
    out = list(comments)
    out.append("Angles\tphysical" if convention == "physical" else str(len(geo)))
    for label, k in (("Incidence", 0), ("Emergence", 1), ("Azimuth", 2)):
        out.append(label + "\t" + "\t".join(_num(g[k]) for g in geo) + "\t")
    head = [f"Wavelength_{sample}"]
    for g in geo:
        tag = geometry_tag(*g)
        head += [f"Refl_{sample}_{tag}", f"Err_{sample}_{tag}"]
    out.append("\t".join(head))
    for w, lam in enumerate(lams):
        out.append("\t".join([_num(lam)] + [_num(v) for v in table[w].ravel()]))
    output_file(path).write_bytes((newline.join(out) + newline).encode("utf-8"))


def _write_singles(path: Path, data: Measurements, angles: tuple[np.ndarray, ...],
                   keys: np.ndarray, err: np.ndarray, sample: str, newline: str,
                   comments: list[str]) -> None:
    """A folder (new or empty of .txt files) of single-geometry files, one per geometry."""
    inc, em, az = angles
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
        out = [f"Sample data file : {name[:-6]}.txt"] + comments
        out += [f"{_num(data.wavelength[i])}\t{_num(data.brf[i])}\t{_num(err[i])}"
                for i in rows]
        output_path(path, name).write_bytes((newline.join(out) + newline).encode("utf-8"))


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
    _check_arguments(data, layout, sample, convention, newline)
    angles = from_project(data.theta_i, data.theta_o, data.phi, convention)
    lines_comments = [_free_text(c) for c in (data.comments if comments is None else comments)]
    keys = np.round(np.stack(angles, axis=1), 9) + 0.0
    err = data.sigma if data.sigma is not None else np.zeros(len(data))
    if layout == "multi":
        _write_multi(path, data, angles, keys, err, sample, convention, newline,
                     lines_comments)
    else:
        _write_singles(path, data, angles, keys, err, sample, newline, lines_comments)
    return path
