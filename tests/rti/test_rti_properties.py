"""What may vary per pixel (mitsuba_powder.rti.properties): the valid ranges are the plugin's
own (no copy in Python), a per-pixel map is refused where the plugin would refuse it (the
first bad pixel named), the grain size of the settings, and the albedo of a per-pixel grain
size."""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest

from mitsuba_powder.plugin import registry
from mitsuba_powder.rti.properties import (
    FREE_PROPERTIES,
    GRAIN_MAPS,
    MAP_PROPERTIES,
    SPECS,
    GrainAlbedo,
    grain_map_name,
    property_map,
    valid_range,
)
from mitsuba_powder.variants import use_variant


def test_the_plugin_s_ranges_are_read_not_copied():
    for name in MAP_PROPERTIES:
        assert valid_range(name) is registry.INTERVALS[name]
    for name in GRAIN_MAPS:  # the fit's table of the grains' albedo, inside the plugin's range
        table = valid_range(name)
        assert (table.lower, table.upper) == (SPECS[name].lower, SPECS[name].upper)
        assert registry.INTERVALS[name].contains([table.lower, table.upper]).all()
    assert str(valid_range("albedo")) == "[0, 1]"
    assert set(FREE_PROPERTIES) == {"albedo", *MAP_PROPERTIES, *GRAIN_MAPS}


@pytest.mark.parametrize("name", MAP_PROPERTIES)
def test_a_map_is_refused_where_the_plugin_refuses_it(name):
    """At each end: the value just outside is refused in the map (naming the pixel), as the
    plugin refuses it (mi.load_dict); the end itself when it is open."""
    interval = valid_range(name)
    for end, closed, toward in ((interval.lower, interval.lower_closed, -1),
                                (interval.upper, interval.upper_closed, 1)):
        if math.isinf(end) and closed:
            continue  # nothing lies beyond
        bad = end if not closed else float(np.nextafter(np.float32(end),
                                                        np.float32(toward * math.inf)))
        values = np.full((2, 3), _inside(interval))
        values[1, 2] = bad
        with pytest.raises(ValueError, match=rf"^{name}\[1, 2\] = .* is out of range; valid "
                                             rf"range is {_re(str(interval))}$"):
            property_map(name, values, (2, 3))
        with use_variant("scalar_rgb"), pytest.raises(RuntimeError, match="out of range"):
            mi.load_dict({"type": "powder", "albedo": 0.5, name: bad})
    np.testing.assert_array_equal(property_map(name, _inside(interval), (2, 3)),
                                  np.full((2, 3), _inside(interval)))


def _inside(interval: registry.Interval) -> float:
    lo, hi = interval.lower, interval.upper
    return 0.5 * (lo + hi) if math.isfinite(hi) else lo + 1.0


def _re(text: str) -> str:
    import re

    return re.escape(text)


def test_a_map_of_another_shape_or_nan_is_refused():
    with pytest.raises(ValueError, match=r"g has shape \(3, 3\); expected a scalar or \(2, 2\)"):
        property_map("g", np.zeros((3, 3)), (2, 2))
    with pytest.raises(ValueError, match=r"tau_o\[0, 1\] = nan is out of range"):
        property_map("tau_o", np.array([[1.0, np.nan], [1.0, 1.0]]), (2, 2))


def test_the_grain_size_of_the_settings():
    assert grain_map_name({}) == "radius"
    assert grain_map_name({"grains": "slab"}) == "radius"
    assert grain_map_name({"grains": "agglomerate"}) == "agglomerate_radius"
    with pytest.raises(ValueError, match="grains = 'sand' is not valid"):
        grain_map_name({"grains": "sand"})


def test_grain_albedo_follows_the_plugin_and_refuses_another_model():
    """The table's albedo at its nodes is the plugin's (the grains' own optics, through
    _optics) to the table's accuracy; a grain size of another grain model is refused."""
    grain = GrainAlbedo("radius", {})
    sizes = np.array([0.03, 0.1, 1.0])
    rho, drho = grain(sizes)
    exact, _ = grain._theory(sizes, False)
    np.testing.assert_allclose(rho, exact, rtol=10 * max(grain.max_error, 1e-9))
    step = 1e-6
    numeric = (grain(sizes * (1 + step))[0] - grain(sizes * (1 - step))[0]) / (2 * step * sizes)[
        :, None]
    np.testing.assert_allclose(drho, numeric, rtol=1e-3, atol=1e-6)
    with pytest.raises(ValueError, match="a per-pixel agglomerate_radius needs grains = "
                                         "agglomerate"):
        GrainAlbedo("agglomerate_radius", {"grains": "sphere"})
