"""The relief of fitted normals (rti/relief.py): heights integrated from normals, the horizon
map and the lights' visibility, against closed forms."""

import math

import numpy as np
import pytest

from mitsuba_powder.rti.relief import (
    horizon_map,
    horizon_spread,
    integrate_normals,
    make_relief,
    residual_weights,
    visibility,
)


def normals_of_slopes(zx, zrow):
    """Unit normals of a surface of slopes zx (along columns) and zrow (along rows, down)."""
    n = np.stack([-zx, zrow, np.ones_like(zx)], axis=-1)  # z_y = -z_row
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def centred(z, sel=None):
    sel = np.ones(z.shape, bool) if sel is None else sel
    return z - z[sel].mean()


def test_quadratic_surface_is_integrated_exactly():
    h, w = 40, 50
    r, c = np.mgrid[0:h, 0:w].astype(float)
    z = 0.01 * (c - 20) ** 2 - 0.02 * (r - 10) * (c - 5) + 0.3 * r
    n = normals_of_slopes(0.02 * (c - 20) - 0.02 * (r - 10), -0.02 * (c - 5) + 0.3)
    np.testing.assert_allclose(centred(integrate_normals(n)), centred(z), atol=1e-9)


def test_gaussian_bump_heights():
    h, w = 64, 64
    r, c = np.mgrid[0:h, 0:w].astype(float)
    s = 8.0
    z = 6.0 * np.exp(-((r - 30) ** 2 + (c - 34) ** 2) / (2 * s * s))
    n = normals_of_slopes(-z * (c - 34) / s**2, -z * (r - 30) / s**2)
    err = np.abs(centred(integrate_normals(n)) - centred(z))
    assert err.max() < 0.02 * 6.0  # second-order differences: 2 % of the bump's height


def test_badly_fitted_pixels_do_not_bend_the_rest():
    """A block of wrong normals with a large residual: the weights from the residual map keep
    the heights outside it where they were; with equal weights they are pulled away."""
    h, w = 48, 48
    r, c = np.mgrid[0:h, 0:w].astype(float)
    z = 0.2 * c - 0.1 * r
    n = normals_of_slopes(np.full((h, w), 0.2), np.full((h, w), -0.1))
    bad = np.zeros((h, w), bool)
    bad[10:22, 14:26] = True
    n[bad] = [0.6, -0.3, 0.74]
    n[bad] /= np.linalg.norm(n[bad], axis=-1, keepdims=True)
    residual = np.where(bad, 0.5, 0.01)
    residual[0, 0] = np.nan  # an undetermined pixel: the floor weight
    wt = residual_weights(residual)
    assert wt[0, 0] == pytest.approx(1e-3) and wt[bad].max() < 0.004 and wt[~bad][1:].min() > 0.89
    good = ~bad
    robust = np.abs(centred(integrate_normals(n, wt), good) - centred(z, good))[good]
    plain = np.abs(centred(integrate_normals(n), good) - centred(z, good))[good]
    assert robust.max() < 0.2 and plain.max() > 5 * robust.max()


def test_horizon_of_a_step_and_a_ridge():
    """A wall of height 10 px: a pixel d px before it sees it at atan(10 / d) (integer d:
    bilinear interpolation is exact on the grid); away from it, at 0. A ridge of height H
    and half-width b: from a pixel at distance d from its crest, atan(H / d) towards it."""
    z = np.zeros((64, 64))
    z[:, 40:] = 10.0
    hor = horizon_map(z, azimuths=8)
    for col in (26, 30, 36):  # within 16 px: sampled every pixel
        d = 40 - col
        assert math.degrees(hor[32, col, 0]) == pytest.approx(math.degrees(math.atan(10 / d)),
                                                              abs=1e-3)
    assert np.all(hor[32, 10:40, 4] == 0)       # looking away (-x): flat horizon
    assert np.all(hor[:, 40:, 0] == 0)          # on the plateau
    # a triangular ridge along the columns: crest at column 32, height 12, half-width 6
    c = np.arange(64, dtype=float)
    ridge = np.maximum(0.0, 12.0 * (1 - np.abs(c - 32) / 6.0))
    hor = horizon_map(np.tile(ridge, (64, 1)), azimuths=4)
    for col in (16, 20, 24):
        assert math.degrees(hor[30, col, 0]) == pytest.approx(
            math.degrees(math.atan(12 / (32 - col))), abs=1e-3)
        assert math.degrees(hor[30, 64 - col, 2]) == pytest.approx(
            math.degrees(math.atan(12 / (32 - col))), abs=1e-3)
    # along the ridge (+y): no occluder
    assert np.all(hor[30, :, 1] == 0)


def test_visibility_has_a_soft_edge_of_the_light_size():
    z = np.zeros((32, 32))
    z[:, 20:] = 10.0
    hor = horizon_map(z, azimuths=8)
    e = math.atan(10 / 10)  # column 10 sees the wall at 45 degrees towards +x
    sel = np.zeros((32, 32), bool)
    sel[16, 10] = True
    lights = [[math.cos(e + a), 0.0, math.sin(e + a)] for a in np.radians([-5, -2, 0, 2, 5])]
    v = visibility(hor, np.array(lights), 2.0, sel)[0]
    np.testing.assert_allclose(v, [0.0, 0.0, 0.5, 1.0, 1.0], atol=1e-4)
    # a point light (radius 0): the edge is as wide as the horizon's spread over the pixel
    # (half its change to the next pixel towards the wall: atan(10 / 9) - 45 degrees)
    spread = horizon_spread(hor)[16, 10, 0]
    assert math.degrees(spread) == pytest.approx(0.5 * (math.degrees(math.atan(10 / 9)) - 45),
                                                 abs=1e-3)
    one = np.array([[math.cos(e + math.radians(1)), 0.0, math.sin(e + math.radians(1))]])
    v0 = visibility(hor, one, 0.0, sel)[0, 0]
    assert v0 == pytest.approx(0.5 + math.radians(1) / (2 * spread), abs=1e-4)
    # per-pixel directions (lights at a distance) give the same
    per_pixel = visibility(hor, np.array(lights)[None], 2.0, sel)
    np.testing.assert_allclose(per_pixel[0], v, atol=1e-6)
    with pytest.raises(ValueError, match="light_radius_deg = 50"):
        visibility(hor, np.array(lights), 50.0)


def test_make_relief_bridges_the_masked_pixels():
    h, w = 32, 40
    r, c = np.mgrid[0:h, 0:w].astype(float)
    n = normals_of_slopes(np.full((h, w), 0.1), np.zeros((h, w)))
    mask = np.ones((h, w), bool)
    mask[:, :4] = False
    n[~mask] = np.nan
    rel = make_relief(n, np.full((h, w), 0.01), mask)
    assert np.all(np.isfinite(rel.height)) and rel.horizon.shape == (h, w, 32)
    np.testing.assert_allclose(np.diff(rel.height[:, 4:], axis=1), 0.1, atol=1e-6)
