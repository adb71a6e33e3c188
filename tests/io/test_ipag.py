"""IPAG goniometer files (SHINE / SHADOWS) and SSHADE conventions.

Every file here is generated in tmp_path, from the model or by hand: no one's data is shipped.
"""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

from mitsuba_powder.cli import main
from mitsuba_powder.fitting.protocols import simulate
from mitsuba_powder.io.ipag import from_project, save_ipag
from mitsuba_powder.io.measurements import (
    MeasurementError,
    Measurements,
    gonio_directions,
    load_measurements,
    save_measurements,
)
from mitsuba_powder.plugin.brf import PowderBRF

NEWLINES = {"crlf": "\r\n", "lf": "\n", "cr": "\r"}

# strong surface lobe (mirror direction) and a narrow coherent back-scattering peak
PEAKY = {"amplitude_surface": 1e-3, "correlation_length": 2.0, "extinction": 0.05,
         "albedo": 0.9}


@pytest.fixture(scope="module")
def simulated() -> Measurements:
    """The model at the SHADOWS + back-scattering protocol, two wavelengths, 2 % noise."""
    return simulate({"amplitude_surface": 2e-4, "g": 0.2}, "shadows,backscatter",
                    (500.0, 700.0), noise=0.02, seed=3)


def canonical(d: Measurements):
    """Rows sorted by (wavelength, theta_i, |theta_o|, azimuth of the unsigned view, brf); the
    unsigned form makes (theta_o, phi) and (-theta_o, phi + 180) equal."""
    to = np.abs(d.theta_o)
    ph = np.mod(np.where(d.theta_o < 0, d.phi + 180.0, d.phi), 360.0)
    ph = np.where(to == 0, 0.0, ph)
    order = np.lexsort((d.brf, ph, to, d.theta_i, d.wavelength))
    angles = np.stack([d.wavelength, d.theta_i, to, ph], axis=1)[order]
    sigma = None if d.sigma is None else d.sigma[order]
    return angles, d.brf[order], sigma


def assert_same(a: Measurements, b: Measurements) -> None:
    ka, va, sa = canonical(a)
    kb, vb, sb = canonical(b)
    assert len(a) == len(b)
    np.testing.assert_allclose(ka, kb, rtol=0, atol=1e-9)       # angles to 1e-9
    np.testing.assert_array_equal(va, vb)                       # values exactly
    assert (sa is None) == (sb is None)
    if sa is not None:
        np.testing.assert_array_equal(sa, sb)
    wa = np.concatenate(a.directions(), axis=1)
    wb = np.concatenate(b.directions(), axis=1)
    np.testing.assert_allclose(np.sort(wa, axis=0), np.sort(wb, axis=0), atol=1e-9)


def only_line_ending(path: Path, newline: str) -> None:
    raw = path.read_bytes()
    others = {"\r\n": [b"\n\n"], "\n": [b"\r"], "\r": [b"\n"]}[newline]
    assert raw.endswith(newline.encode())
    if newline == "\r\n":
        assert raw.count(b"\n") == raw.count(b"\r\n") == raw.count(b"\r")
    for o in others:
        assert o not in raw


# ------------------------------------------------------------------ round trip


def assert_load_error(path: Path, fragments: list[str]) -> None:
    """Loading ``path`` fails with a message naming it and holding every fragment."""
    with pytest.raises(MeasurementError) as info:
        load_measurements(path)
    msg = str(info.value)
    assert str(path) in msg, msg
    for fragment in fragments:
        assert fragment in msg, msg


@pytest.mark.parametrize("newline", NEWLINES)
def test_round_trip_every_layout(simulated, tmp_path, newline):
    nl = NEWLINES[newline]
    plane = simulated.subset(np.mod(simulated.phi, 180.0) == 0)  # signed: plane of incidence
    assert np.any(plane.theta_o < 0) and np.any(plane.theta_o > 0)
    cases = [
        ("multi", "physical", simulated), ("single", "physical", simulated),
        ("multi", "signed", plane), ("single", "signed", plane),
    ]
    for layout, convention, data in cases:
        out = tmp_path / f"{layout}_{convention}" / ("S_geo.txt" if layout == "multi" else "S")
        save_ipag(out, data, layout=layout, sample="S", convention=convention, newline=nl)
        first = out if layout == "multi" else sorted(out.iterdir())[0]
        only_line_ending(first, nl)
        back = load_measurements(out)
        assert back.convention == convention, (layout, back.comments)
        assert_same(back, data)
        assert any(f"angle convention {convention}" in c for c in back.comments)
        # and through the CSV again, with the same line ending
        csv = save_measurements(tmp_path / f"{layout}_{convention}.csv", back, digits=None,
                                newline=nl)
        only_line_ending(csv, nl)
        assert_same(load_measurements(csv), data)


def test_multi_file_is_one_row_per_wavelength(simulated, tmp_path):
    path = save_ipag(tmp_path / "S_geo.txt", simulated, sample="S")
    lines = path.read_bytes().decode().split("\r\n")[:-1]
    n = len(np.unique(simulated.geometry_keys(False)))
    angle_rows = [ln for ln in lines if ln.split("\t")[0] in ("Incidence", "Emergence",
                                                               "Azimuth")]
    assert [len(r.rstrip("\t").split("\t")) for r in angle_rows] == [n + 1] * 3
    assert "Angles\tphysical" in lines
    header = next(ln for ln in lines if ln.startswith("Wavelength_S"))
    cols = header.split("\t")
    assert len(cols) == 1 + 2 * n
    assert cols[1].startswith("Refl_S_i") and cols[2].startswith("Err_S_i")
    assert len(lines) - lines.index(header) - 1 == 2       # two wavelengths


# ------------------------------------------------------------------ physical check


def _vectors(convention: str, inc, em, az) -> np.ndarray:
    """Viewing unit vectors from IPAG angles, written from the conventions' definitions
    (light at azimuth 0, on +x): physical, azimuth 0 at opposition (the light's side);
    signed, positive emergence on the forward side, away from the light."""
    e, a = np.radians(em), np.radians(az)
    if convention == "physical":
        return np.stack([np.sin(e) * np.cos(a), np.sin(e) * np.sin(a), np.cos(e)], axis=1)
    return np.stack([-np.sin(e), np.zeros_like(e), np.cos(e)], axis=1)


def _model_at(vectors: np.ndarray, theta_i: np.ndarray, props: dict) -> np.ndarray:
    """The model's BRF at viewing vectors (angles taken from the vectors, not from IPAG)."""
    theta_o = np.degrees(np.arccos(np.clip(vectors[:, 2], -1, 1)))
    phi = np.degrees(np.arctan2(vectors[:, 1], vectors[:, 0]))
    data = Measurements(theta_i, theta_o, phi, np.full(len(theta_i), 700.0),
                        np.zeros(len(theta_i)))
    return PowderBRF(data, props).brf()


def _write_by_hand(path: Path, convention: str, inc, em, az, values, newline: str) -> None:
    """A multi-geometry file as the instrument writes it (independent of ipag.save_ipag)."""
    tags = [f"i{i:g}e{e:g}a{a:g}" for i, e, a in zip(inc, em, az)]
    lines = ["Detectors noises: synthetic test file"]
    lines.append("Angles\tphysical" if convention == "physical" else f"{len(inc)}")
    for name, v in (("Incidence", inc), ("Emergence", em), ("Azimuth", az)):
        lines.append(name + "\t" + "\t".join(f"{x:g}" for x in v) + "\t")
    lines.append("Wavelength_P\t" + "\t".join(f"Refl_P_{t}\tErr_P_{t}" for t in tags))
    lines.append("700\t" + "\t".join(f"{float(v)!r}\t{0.01 * float(v)!r}" for v in values))
    path.write_bytes((newline.join(lines) + newline).encode())


@pytest.mark.parametrize("convention", ["physical", "signed"])
@pytest.mark.parametrize("newline", NEWLINES)
def test_physical_check_lobe_and_backscatter(tmp_path, convention, newline):
    """A file generated from the model in each convention: after loading, the surface lobe's
    maximum is the mirror direction (theta_o = -theta_i, phi = 0) and the back-scattering peak
    sits at theta_o = theta_i; the model at the loaded geometries gives the file's values."""
    em_signed = np.arange(-70.0, 70.5, 2.0)
    geo = []
    for ti in (20.0, 40.0):
        if convention == "signed":
            geo += [(ti, e, 0.0) for e in em_signed]
        else:
            geo += [(ti, abs(e), 0.0 if e > 0 else 180.0) for e in em_signed if e != 0]
            geo += [(ti, 0.0, 0.0)] + [(ti, e, 90.0) for e in (20.0, 40.0, 60.0)]
    inc, em, az = (np.array(v) for v in zip(*geo))
    vec = _vectors(convention, inc, em, az)
    values = _model_at(vec, inc, PEAKY)
    path = tmp_path / f"P_{convention}_geo.txt"
    _write_by_hand(path, convention, inc, em, az, values, NEWLINES[newline])

    data = load_measurements(path)
    assert data.convention == convention
    # the loaded geometry is the one the file means, and the model agrees with the file there
    np.testing.assert_allclose(data.directions()[1], vec, atol=1e-12)
    np.testing.assert_array_equal(data.brf, values)
    np.testing.assert_allclose(PowderBRF(data, PEAKY).brf(), data.brf, rtol=1e-6)
    on0 = np.isclose(np.mod(data.phi, 360.0), 0.0)
    on180 = np.isclose(data.phi, 180.0)
    signed = np.where(on180, -data.theta_o, data.theta_o)      # project's signed theta_o
    for ti in (20.0, 40.0):
        sel = np.nonzero(data.theta_i == ti)[0]
        top = sel[np.argmax(data.brf[sel])]
        assert on0[top] or on180[top]
        assert signed[top] == -ti, (ti, data.theta_o[top], data.phi[top])   # mirror side
        light = sel[(on0 | on180)[sel] & (np.abs(signed[sel] - ti) <= 10)]
        peak = light[np.argmax(data.brf[light])]
        assert signed[peak] == ti                                         # back-scattering
        near = light[np.abs(signed[light] - ti) == 2]
        assert data.brf[peak] > 1.3 * data.brf[near].max()


def test_wrong_convention_moves_the_lobe(tmp_path):
    """The check above can fail: forward-side emergences (>= 0, azimuth 0) read with the
    physical convention put the surface lobe on the light's side."""
    em = np.arange(0.0, 70.5, 2.0)
    inc = np.full(len(em), 40.0)
    az = np.zeros(len(em))
    values = _model_at(_vectors("signed", inc, em, az), inc, PEAKY)
    path = tmp_path / "F_geo.txt"
    _write_by_hand(path, "signed", inc, em, az, values, "\n")
    right = load_measurements(path)                                # count line: signed
    wrong = load_measurements(path, convention="physical")
    assert right.theta_o[np.argmax(right.brf)] == -40.0
    assert wrong.theta_o[np.argmax(wrong.brf)] == 40.0
    assert "chosen by the caller; the file's header says signed" in " ".join(wrong.comments)
    assert np.abs(np.log(PowderBRF(wrong, PEAKY).brf() / wrong.brf)).max() > 2


def test_writer_conventions_match_the_definitions(tmp_path):
    """save_ipag's angles mean the same directions as the conventions' definitions."""
    ti = np.array([30.0, 30.0, 30.0, 30.0])
    to = np.array([30.0, -30.0, 20.0, 0.0])
    ph = np.array([0.0, 0.0, 90.0, 45.0])
    inc, em, az = from_project(ti, to, ph, "physical")
    np.testing.assert_allclose(_vectors("physical", inc, em, az),
                               gonio_directions(ti, to, ph)[1], atol=1e-12)
    np.testing.assert_array_equal(az[:2], [0.0, 180.0])       # back-scattering at azimuth 0
    inc, em, az = from_project(ti[:2], to[:2], ph[:2], "signed")
    np.testing.assert_array_equal(em, [-30.0, 30.0])          # mirror positive
    np.testing.assert_allclose(_vectors("signed", inc, em, az),
                               gonio_directions(ti[:2], to[:2], ph[:2])[1], atol=1e-12)


# ------------------------------------------------------------------ file contents


def multi_text(*, header="Angles\tphysical", inc="20\t20\t", em="30\t30\t", az="0\t180\t",
               columns="Wavelength_S\tRefl_S_i20e30a0\tErr_S_i20e30a0\tRefl_S_i20e30a180\t"
                       "Err_S_i20e30a180",
               rows=("500\t0.5\t0.01\t0.6\t0.02", "600\t0.55\t0.01\t0.65\t0.02"),
               first="Detectors noises: 1e-3"):
    lines = ([first] if first else []) + ([header] if header else [])
    lines += [f"Incidence\t{inc}", f"Emergence\t{em}", f"Azimuth\t{az}", columns, *rows]
    return "\r\n".join(lines) + "\r\n"


def write(tmp_path: Path, text: str, name: str = "S_geo.txt") -> Path:
    path = tmp_path / name
    path.write_bytes(text.encode())
    return path


def test_multi_file_read(tmp_path):
    data = load_measurements(write(tmp_path, multi_text()))
    assert data.convention == "physical"
    np.testing.assert_array_equal(data.wavelength, [500, 500, 600, 600])
    np.testing.assert_array_equal(data.theta_o, [30, 30, 30, 30])
    np.testing.assert_array_equal(data.phi, [0, 180, 0, 180])
    np.testing.assert_array_equal(data.brf, [0.5, 0.6, 0.55, 0.65])
    np.testing.assert_array_equal(data.sigma, [0.01, 0.02, 0.01, 0.02])
    assert data.comments[0] == "Detectors noises: 1e-3"


def test_older_signed_file(tmp_path):
    text = multi_text(header="2", em="-30\t30\t", az="0\t0\t",
                      columns="Wavelength_S\tRefl_S_i20e-30a0\tErr_S_i20e-30a0\t"
                              "Refl_S_i20e30a0\tErr_S_i20e30a0", first="")
    data = load_measurements(write(tmp_path, text))
    assert data.convention == "signed"
    np.testing.assert_array_equal(data.theta_o[:2], [30.0, -30.0])
    np.testing.assert_array_equal(data.phi, 0.0)
    assert any("geometry-count line" in c for c in data.comments)


def test_nan_and_zero_wavelength_are_counted(tmp_path):
    rows = ("0\t0\t0\t0\t0", "500\tNaN\t0.01\t0.6\t0.02", "600\t0.55\tnan\t0.65\t0.02",
            "NaN\tNaN\tNaN\tNaN\tNaN", "700\t0.5\t0.01\t0.6\t0.02")
    data = load_measurements(write(tmp_path, multi_text(rows=rows)))
    assert len(data) == 4
    assert data.skipped == {"rows_wavelength_0_or_nan": 2, "nan_values": 2}
    text = " ".join(data.comments)
    assert "skipped 2 rows whose wavelength is 0 or NaN (lines 7, 10)" in text
    assert "skipped 2 NaN values" in text


def test_replicated_geometries_in_multi_file(tmp_path):
    text = multi_text(az="0\t0\t", columns="Wavelength_S\tRefl_S_i20e30a0\tErr_S_i20e30a0\t"
                                            "Refl_S_i20e30a0\tErr_S_i20e30a0")
    data = load_measurements(write(tmp_path, text))
    assert data.geometry_summary() == {"rows": 4, "geometries": 2, "directions": 1,
                                       "replicated_rows": 2, "replicated_geometries": 2}


def test_errors_zero_or_missing(tmp_path):
    no_err = multi_text(columns="Wavelength_S\tRefl_S_i20e30a0\tRefl_S_i20e30a180",
                        rows=("500\t0.5\t0.6",))
    data = load_measurements(write(tmp_path, no_err, "a_geo.txt"))
    assert data.sigma is None and "fits are unweighted" in " ".join(data.comments)
    all_zero = multi_text(rows=("500\t0.5\t0\t0.6\t0",))
    assert load_measurements(write(tmp_path, all_zero, "b_geo.txt")).sigma is None
    some = write(tmp_path, multi_text(rows=("500\t0.5\t0\t0.6\t0.02",)), "c_geo.txt")
    with pytest.raises(MeasurementError) as info:
        load_measurements(some)
    msg = str(info.value)
    for fragment in (str(some), "line 7, column 3 (Err_S_i20e30a0): 0", "zero_error=",
                     "1 of 2 values"):
        assert fragment in msg, msg
    assert load_measurements(some, zero_error="unweighted").sigma is None
    skipped = load_measurements(some, zero_error="skip")
    assert len(skipped) == 1 and skipped.skipped == {"zero_or_missing_error": 1}
    np.testing.assert_array_equal(skipped.sigma, [0.02])
    with pytest.raises(ValueError, match="zero_error = 'x'"):
        load_measurements(some, zero_error="x")


@pytest.mark.parametrize("kwargs,fragments", [
    ({"rows": ("500\t0.5\t0.01\t0.6",)}, ["line 7", "4 columns, expected 5", "header (line 6)"]),
    ({"rows": ("500\t0.5\t0.01\t0.6\t0.02\t7",)}, ["line 7", "6 columns, expected 5"]),
    ({"rows": ("500\t0.5\tabc\t0.6\t0.02",)},
     ["line 7, column 3 (Err_S_i20e30a0)", "'abc' is not a number"]),
    ({"rows": ("500\t0,5\t0.01\t0.6\t0.02",)}, ["line 7, column 2", "'0,5' is not a number"]),
    ({"rows": ("5x0\t0.5\t0.01\t0.6\t0.02",)}, ["line 7, column 1", "'5x0'"]),
    ({"rows": ("500\tinf\t0.01\t0.6\t0.02",)}, ["line 7, column 2", "not a finite number"]),
    ({"rows": ("500\t-0.5\t0.01\t0.6\t0.02",)}, ["line 7, column 2", "[0, inf)"]),
    ({"rows": ("500\t0.5\t-0.01\t0.6\t0.02",)}, ["line 7, column 3", "(error): -0.01"]),
    ({"rows": ("-500\t0.5\t0.01\t0.6\t0.02",)}, ["line 7, column 1", "(0, inf)"]),
    ({"em": "30\tx\t"}, ["line 4, column 3", "Emergence", "'x' is not a number"]),
    ({"em": "30\tnan\t"}, ["line 4, column 3", "not a finite number"]),
    ({"az": "0\t"}, ["line 5", "1 azimuth values", "Incidence row (line 3) has 2"]),
    ({"header": "3", "first": ""}, ["line 1, column 1", "3 geometries announced",
                                    "angle rows have 2"]),
    ({"header": "Angles\tsigned"}, ["line 2, column 2", "'signed' is not known"]),
    ({"columns": "Wavelength_S\tRefl_S_i20e30a0\tErr_S_i20e30a0\tRefl_S_i20e30a180"},
     ["line 6", "3 columns after the wavelength", "expected 4", "or 2"]),
    ({"columns": "Wavelength_S\tRefl_S_i20e30a0\tErr_S_i20e30a0\tRefl_S_i20e35a180\t"
                 "Err_S_i20e35a180"},
     ["line 6, column 4", "'Refl_S_i20e35a180' disagrees with the angle rows",
      "emergence 30", "geometry 2", "lines 3-5, column 3"]),
    ({"columns": "Wavelength_S\tRefl_S_i20e30a0\tErr_S_i20e30a0\tErr_S_i20e30a180\t"
                 "Refl_S_i20e30a180"}, ["line 6, column 4", "is not a column name Refl_"]),
    ({"columns": "Wavelength_S\tRefl_S_i20e30a0\tErr_S_i20e30a0\tRefl_T_i20e30a180\t"
                 "Err_T_i20e30a180"}, ["line 6, column 4", "sample 'T'", "one sample"]),
    ({"columns": "Lambda\tRefl_S_i20e30a0\tErr_S_i20e30a0\tRefl_S_i20e30a180\t"
                 "Err_S_i20e30a180"}, ["line 6, column 1", "expected 'Wavelength_<sample>'"]),
    ({"inc": "95\t20\t", "columns": "Wavelength_S\tRefl_S_i95e30a0\tErr_S_i95e30a0\t"
                                     "Refl_S_i20e30a180\tErr_S_i20e30a180"},
     ["column 2 of the angle rows", "column 'theta_i'", "[0, 90)"]),
    ({"em": "-30\t30\t", "columns": "Wavelength_S\tRefl_S_i20e-30a0\tErr_S_i20e-30a0\t"
                                    "Refl_S_i20e30a180\tErr_S_i20e30a180"},
     ["column 2 of the angle rows", "emergence -30 < 0", "physical convention",
      "convention='signed'"]),
])
def test_malformed_multi_files(tmp_path, kwargs, fragments):
    assert_load_error(write(tmp_path, multi_text(**kwargs)), fragments)


def test_malformed_angle_rows(tmp_path):
    text = "Angles\tphysical\r\nIncidence\t20\r\nAzimuth\t0\r\nElevation\t3\r\n"
    with pytest.raises(MeasurementError, match=r"line 4, column 1: expected the rows "
                                               r"Incidence, Emergence and Azimuth"):
        load_measurements(write(tmp_path, text))
    text = "Angles\tphysical\r\nIncidence\t20\r\nEmergence\t0\r\nAzimuth\t0\r\n"
    with pytest.raises(MeasurementError, match="no 'Wavelength_<sample>' header line"):
        load_measurements(write(tmp_path, text, "b_geo.txt"))


def test_unknown_file(tmp_path):
    path = write(tmp_path, "hello\r\n1\t2\r\n", "notes.txt")
    with pytest.raises(MeasurementError) as info:
        load_measurements(path)
    assert str(path) in str(info.value) and "<sample>_i<inc>e<em>a<az>_c.txt" in str(info.value)


# ------------------------------------------------------------------ conventions


def single(tmp_path: Path, name: str, rows=("500\t0.5\t0.01",), header=(), nl="\r\n"):
    path = tmp_path / name
    path.write_bytes((nl.join([*header, *rows]) + nl).encode())
    return path


def test_single_file_conventions(tmp_path):
    a = load_measurements(single(tmp_path, "S_i20e-30a0_c.txt"))
    assert a.convention == "signed" and a.theta_o[0] == 30.0 and a.phi[0] == 0.0
    b = load_measurements(single(tmp_path, "S_i20e30a180_c.txt"))
    assert b.convention == "physical" and b.theta_o[0] == 30.0 and b.phi[0] == 180.0
    c = load_measurements(single(tmp_path, "S_i20e0a0_c.txt"))
    assert c.convention == "any" and c.theta_o[0] == 0.0
    undecided = single(tmp_path, "S_i20e30a0_c.txt")
    with pytest.raises(MeasurementError) as info:
        load_measurements(undecided)
    msg = str(info.value)
    for fragment in (str(undecided), "cannot decide the angle convention",
                     "every emergence is >= 0 and every azimuth is 0",
                     "convention='signed'", "convention='physical'", "--convention"):
        assert fragment in msg, msg
    assert load_measurements(undecided, convention="signed").theta_o[0] == -30.0
    assert load_measurements(undecided, convention="physical").theta_o[0] == 30.0
    with pytest.raises(MeasurementError, match="azimuth 180: the signed convention"):
        load_measurements(tmp_path / "S_i20e30a180_c.txt", convention="signed")
    with pytest.raises(MeasurementError, match="convention = 'sshade' is not known"):
        load_measurements(undecided, convention="sshade")


def test_folder_conventions_and_replicates(tmp_path):
    folder = tmp_path / "S"
    folder.mkdir()
    single(folder, "S_i20e-30a0_c.txt", header=("Sample data file : S_i20e-30a0.txt",
                                                "Corrected by: spectralon 2019"))
    single(folder, "S_i20e30a0_c.txt", rows=("500\t0.4\t0.01", "600\t0.45\t0.01"))
    single(folder, "S_i20e30a0_2_c.txt", rows=("500\t0.41\t0.01",), nl="\r")
    single(folder, "S_i20e0a0_c.txt", rows=("500\t0.3\t0.01",), nl="\n")
    (folder / "notes.pdf").write_bytes(b"%PDF")
    data = load_measurements(folder)
    assert data.convention == "signed"
    assert data.geometry_summary() == {"rows": 5, "geometries": 4, "directions": 3,
                                       "replicated_rows": 1, "replicated_geometries": 1}
    assert "Corrected by: spectralon 2019" in data.comments
    assert any("ignored 1 entries" in c and "notes.pdf" in c for c in data.comments)
    # a mixed folder: a negative emergence and an azimuth not 0
    single(folder, "S_i20e30a90_c.txt")
    with pytest.raises(MeasurementError, match="negative emergence .* azimuth 90"):
        load_measurements(folder)


@pytest.mark.parametrize("files,fragments", [
    ({"S_i20e-30a0_c.txt": ["500\t0.5\t0.01\t3"]}, ["line 1", "4 columns, expected 3"]),
    ({"S_i20e-30a0_c.txt": ["500\t0.5\t0.01", "600\t0.5"]},
     ["line 2", "2 columns, expected 3 like line 1"]),
    ({"S_i20e-30a0_c.txt": ["Corrected by: x", "500\t0.5\t0.01", "end"]},
     ["line 3, column 1", "'end' is not a number"]),
    ({"S_i20e-30a0_c.txt": ["500\t0.5\tzero"]}, ["line 1, column 3", "'zero'"]),
    ({"S_i20e-30a0_c.txt": ["Corrected by: x"]}, ["no data rows"]),
    ({"S_i20e-30a0_c.txt": ["500\t0.5\t0.01"], "readme.txt": ["x"]},
     ["readme.txt", "must be named <sample>_i<inc>e<em>a<az>_c.txt"]),
    ({"S_i20e-30a0_c.txt": ["500\t0.5\t0.01"], "T_i20e30a0_c.txt": ["500\t0.5\t0.01"]},
     ["T_i20e30a0_c.txt", "sample 'T'", "differs from 'S'", "one sample"]),
    ({"S_i20e-30a0_c.txt": ["Corrected by: ref A", "500\t0.5\t0.01"],
      "S_i20e-30a0_b_c.txt": ["Corrected by: ref B", "500\t0.5\t0.01"]},
     ["S_i20e-30a0_c.txt, line 1", "'corrected by: ref A' contradicts",
      "S_i20e-30a0_b_c.txt, line 1", "same geometry"]),
    ({"S_i95e-30a0_c.txt": ["500\t0.5\t0.01"]}, ["S_i95e-30a0_c.txt (file name)", "theta_i"]),
    ({"S_i20e-30a0_c.txt": ["0\t0\t0"]}, ["no data left", "wavelength is 0"]),
    ({}, ["holds no .txt file"]),
])
def test_malformed_single_files(tmp_path, files, fragments):
    folder = tmp_path / "S"
    folder.mkdir()
    for name, rows in files.items():
        single(folder, name, rows=rows)
    assert_load_error(folder, fragments)


def test_count_line_with_azimuths_is_undecidable(tmp_path):
    path = write(tmp_path, multi_text(header="2", first=""))
    with pytest.raises(MeasurementError) as info:
        load_measurements(path)
    msg = str(info.value)
    assert "cannot decide the angle convention" in msg and "azimuth 180 is not 0" in msg
    assert load_measurements(path, convention="physical").phi.tolist() == [0, 180, 0, 180]


def test_no_header_line_decides_from_angles(tmp_path):
    data = load_measurements(write(tmp_path, multi_text(header="", first="")))
    assert data.convention == "physical"
    assert "some azimuth not 0" in " ".join(data.comments)


# ------------------------------------------------------------------ writer errors


def test_writer_errors(simulated, tmp_path):
    with pytest.raises(ValueError, match="outside the plane of incidence"):
        save_ipag(tmp_path / "a.txt", simulated, convention="signed")
    partial = simulated.subset(~((simulated.wavelength == 700) & (simulated.theta_i == 60)))
    with pytest.raises(ValueError, match="needs every geometry at every wavelength: 700 nm "
                                         "lacks incidence 60"):
        save_ipag(tmp_path / "b.txt", partial)
    save_ipag(tmp_path / "c", partial, layout="single")           # any set fits 'single'
    assert_same(load_measurements(tmp_path / "c"), partial)
    with pytest.raises(ValueError, match="new or empty folder"):
        save_ipag(tmp_path / "c", partial, layout="single")
    for kwargs, fragment in (({"sample": "a b"}, "sample = 'a b'"),
                             ({"newline": "\n\r"}, "newline"),
                             ({"layout": "table"}, "layout = 'table'"),
                             ({"convention": "sshade"}, "convention = 'sshade'")):
        with pytest.raises(ValueError, match=fragment):
            save_ipag(tmp_path / "d.txt", simulated, **kwargs)


# ------------------------------------------------------------------ command line


def test_cli_simulate_ipag_and_fit_reads_it(tmp_path, capsys):
    params = tmp_path / "p.json"
    params.write_text('{"amplitude_volume": 1.3}')
    out = tmp_path / "S"
    assert main(["simulate", "--params", str(params), "--protocol", "backscatter",
                 "--format", "ipag", "--layout", "single", "--convention", "signed",
                 "--out", str(out)]) == 0
    files = sorted(out.iterdir())
    assert len(files) == 33 and all(f.name.startswith("synthetic_i") for f in files)
    geo = tmp_path / "m_geo.txt"
    assert main(["simulate", "--params", str(params), "--protocol", "backscatter",
                 "--format", "ipag", "--out", str(geo)]) == 0
    assert_same(load_measurements(geo), load_measurements(out))
    assert main(["fit", str(out), "--free", "amplitude_volume", "--starts", "1",
                 "--out", str(tmp_path / "fit")]) == 0
    printed = capsys.readouterr().out
    assert "angle convention signed" in printed and "33 values, 33 unique geometries" in printed
    fitted = json.loads((tmp_path / "fit" / "fit.json").read_text())
    assert fitted["parameters"]["amplitude_volume"] == pytest.approx(1.3, rel=1e-3)


def test_cli_reports_undecidable_convention(tmp_path, capsys):
    path = single(tmp_path, "S_i20e30a0_c.txt")
    assert main(["compare-models", str(path), "--out", str(tmp_path / "c")]) == 2
    assert "cannot decide the angle convention" in capsys.readouterr().err


def test_conventions_figure_script(tmp_path):
    """docs/scripts/ipag_conventions.py runs (its labels come from the package's mapping and
    it checks that the loader reads them back as the same directions)."""
    import subprocess
    import sys

    script = Path(__file__).resolve().parents[2] / "docs" / "scripts" / "ipag_conventions.py"
    proc = subprocess.run([sys.executable, str(script), "--out", str(tmp_path)],
                          capture_output=True, text=True, timeout=300)
    assert proc.returncode == 0, proc.stderr[-3000:]
    assert (tmp_path / "ipag_conventions.png").stat().st_size > 20000


def test_compare_models_and_render_gonio_read_ipag_files(tmp_path):
    """The other commands that take measurement files accept an IPAG file too."""
    params = tmp_path / "p.json"
    params.write_text('{"radius": 0.05, "amplitude_surface": 2e-4}')
    geo = tmp_path / "S_geo.txt"
    assert main(["simulate", "--params", str(params), "--protocol", "backscatter",
                 "--noise", "0.01", "--format", "ipag", "--out", str(geo)]) == 0
    assert main(["compare-models", str(geo), "--set", "radius=0.05", "--starts", "4",
                 "--out", str(tmp_path / "cmp")]) == 0
    rows = json.loads((tmp_path / "cmp" / "model_comparison.json").read_text())
    assert {r["model"] for r in rows} >= {"powder", "lambertian"}
    assert all(r["n"] == 33 for r in rows)
    assert main(["render-gonio", "--data", str(geo), "--params", str(params), "--spp", "4",
                 "--resolution", "2", "--variant", "llvm_ad_mono",
                 "--out", str(tmp_path / "gonio")]) == 0
    assert any((tmp_path / "gonio").iterdir())
