"""The measurement CSV: replicates, geometry counts, line endings, exact writing, dispatch."""

from __future__ import annotations

import numpy as np
import pytest

from mitsuba_powder.io.measurements import (
    MeasurementError,
    Measurements,
    format_number,
    load_measurements,
    save_measurements,
)

HEADER = "theta_i,theta_o,phi,wavelength,brf,sigma"


def test_replicates_are_separate_observations(tmp_path):
    """SHADOWS-style: theta_o = 0 once in every azimuth plane, and repeated geometries."""
    rows = [
        "20,-35,0,700,0.95,0.02",     # line 2
        "20,35,180,700,0.97,0.02",    # same direction as line 2: replicate
        "20,0,0,700,0.80,0.02",
        "20,0,30,700,0.81,0.02",      # theta_o = 0 in another plane: same direction
        "20,0,90,700,0.79,0.02",
        "20,-35,0,700,0.96,0.02",     # plain repeat of line 2
        "20,-35,0,500,0.90,0.02",     # another wavelength: not a replicate
    ]
    path = tmp_path / "rep.csv"
    path.write_text("\n".join([HEADER, *rows]) + "\n")
    data = load_measurements(path)
    assert len(data) == 7 and data.convention == "project"
    np.testing.assert_array_equal(data.brf[:2], [0.95, 0.97])
    assert data.geometry_summary() == {"rows": 7, "geometries": 3, "directions": 2,
                                       "replicated_rows": 4, "replicated_geometries": 2}
    ids = data.geometry_keys()
    assert ids[0] == ids[1] == ids[5] and ids[2] == ids[3] == ids[4] and ids[6] != ids[0]
    assert data.subset(data.wavelength == 700).geometry_summary()["replicated_rows"] == 4


def test_geometry_summary_counts_distinct_directions():
    d = Measurements([0, 0, 30, 30], [10, 10, 10, -10], [0, 180, 0, 0], [700, 700, 700, 700],
                     [1, 1, 1, 1])
    # (0, 10, 0) and (0, 10, 180) differ (normal incidence, opposite views); 30 deg: two views
    assert d.geometry_summary() == {"rows": 4, "geometries": 4, "directions": 4,
                                    "replicated_rows": 0, "replicated_geometries": 0}
    empty = d.subset(np.zeros(4, dtype=bool))
    assert empty.geometry_summary()["rows"] == 0 and empty.geometry_summary()["geometries"] == 0


@pytest.mark.parametrize("newline", ["\r\n", "\n", "\r"])
def test_csv_line_endings_and_exact_values(tmp_path, newline):
    rng = np.random.default_rng(1)
    n = 50
    data = Measurements(rng.uniform(0, 89, n), rng.uniform(-89, 89, n), rng.uniform(0, 360, n),
                        np.full(n, 532.0), rng.uniform(0, 2, n), rng.uniform(0.001, 0.1, n),
                        ["synthetic random values"])
    path = save_measurements(tmp_path / "x.csv", data, digits=None, newline=newline)
    raw = path.read_bytes()
    assert raw.count(newline.encode()) == n + 2
    if newline != "\r\n":
        assert (b"\r" if newline == "\n" else b"\n") not in raw
    back = load_measurements(path)
    for name in ("theta_i", "theta_o", "phi", "wavelength", "brf", "sigma"):
        np.testing.assert_array_equal(getattr(back, name), getattr(data, name))
    assert back.comments == ["synthetic random values"]
    # the default 10 significant digits is lossy for such values, and says so by its name
    lossy = load_measurements(save_measurements(tmp_path / "y.csv", data))
    assert not np.array_equal(lossy.brf, data.brf)
    np.testing.assert_allclose(lossy.brf, data.brf, rtol=1e-9)


def test_format_number():
    assert format_number(700.0) == "700"
    assert format_number(0.1) == "0.1"
    x = 0.1 + 0.2
    assert float(format_number(x)) == x and format_number(x, 10) == "0.3"


def test_csv_rejects_convention_and_bad_newline(tmp_path):
    path = tmp_path / "a.csv"
    path.write_text(HEADER + "\n20,10,0,700,0.9,0.01\n")
    with pytest.raises(MeasurementError, match="convention = 'signed' applies to IPAG files"):
        load_measurements(path, convention="signed")
    with pytest.raises(ValueError, match="newline"):
        save_measurements(tmp_path / "b.csv", load_measurements(path), newline="\n\n")


def test_csv_content_in_a_txt_file_and_missing_path(tmp_path):
    path = tmp_path / "data.txt"
    path.write_text("# c\n" + HEADER + "\n20,10,0,700,0.9,0.01\n")
    assert len(load_measurements(path)) == 1
    with pytest.raises(FileNotFoundError, match="does not exist"):
        load_measurements(tmp_path / "nothing")
