"""Dome lights at a finite distance (mitsuba_powder.rti.lights): pixel coordinates, per-pixel
directions and irradiance against closed-form geometry, derivatives against finite
differences, .lp directions / positions, and point lights rendered by Mitsuba."""

from __future__ import annotations

import math

import mitsuba as mi
import numpy as np
import pytest

from mitsuba_powder.rti.capture import write_lp
from mitsuba_powder.rti.lights import (
    UNIT_TOLERANCE,
    LightRig,
    check_distance,
    half_diagonal,
    image_light_field,
    light_field,
    light_field_derivatives,
    pixel_coordinates,
    point_lights,
    read_lp_rig,
    rig_from_vectors,
)
from mitsuba_powder.variants import use_variant


def _dir(elevation: float, azimuth: float) -> np.ndarray:
    """Unit vector at elevation / azimuth (degrees; azimuth from +x towards +y)."""
    e, a = math.radians(elevation), math.radians(azimuth)
    return np.array([math.cos(e) * math.cos(a), math.cos(e) * math.sin(a), math.sin(e)])


DIRS = np.array([_dir(15, 10), _dir(35, 130), _dir(60, 250), _dir(80, 300)])


# ---------------------------------------------------------------------------
#  Pixel coordinates and valid distances
# ---------------------------------------------------------------------------

def test_pixel_coordinates_frame():
    h, w = 4, 6
    xy = pixel_coordinates((h, w))
    assert xy.shape == (h, w, 2) and xy.dtype == np.float64
    # column 0 is the image's left, row 0 its top; one pixel = 1 / W in x and in y
    np.testing.assert_allclose(xy[0, 0], [-0.5 + 0.5 / w, (h / 2 - 0.5) / w])
    np.testing.assert_allclose(xy[-1, -1], [0.5 - 0.5 / w, -(h / 2 - 0.5) / w])
    np.testing.assert_allclose(np.diff(xy[..., 0], axis=1), 1.0 / w)
    np.testing.assert_allclose(np.diff(xy[..., 1], axis=0), -1.0 / w)
    np.testing.assert_allclose(xy.mean(axis=(0, 1)), 0.0, atol=1e-15)
    # the convention of rti_fit.synthetic_maps: u = (j + 0.5) / W, v = 1 - (i + 0.5) / H
    i, j = np.mgrid[0:h, 0:w]
    np.testing.assert_allclose(xy[..., 0], (j + 0.5) / w - 0.5)
    np.testing.assert_allclose(xy[..., 1], (1.0 - (i + 0.5) / h - 0.5) * h / w)


def test_half_diagonal_and_check_distance():
    assert half_diagonal((10, 10)) == pytest.approx(math.sqrt(2) / 2)
    assert half_diagonal((32, 48)) == pytest.approx(0.5 * math.hypot(1.0, 32 / 48))
    check_distance(0.75, (10, 10))
    check_distance(math.inf, (10, 10))
    with pytest.raises(ValueError, match=r"--light-distance = 0.7 image widths is out of range; "
                                         r"valid range is \(0.707107, inf\]"):
        check_distance(0.7, (10, 10), name="--light-distance")
    with pytest.raises(ValueError, match=r"distance\[1\] = nan"):
        check_distance(np.array([2.0, np.nan]), (10, 10))
    with pytest.raises(ValueError, match="shape"):
        pixel_coordinates((0, 3))


def test_rig_validation():
    rig = LightRig(2.0 * DIRS, 3.0)
    np.testing.assert_allclose(np.linalg.norm(rig.directions, axis=1), 1.0)
    assert rig.count == 4 and rig.distance == 3.0 and not rig.is_distant
    np.testing.assert_allclose(rig.positions, 3.0 * DIRS)
    with pytest.raises(ValueError):
        rig.directions[0, 0] = 1.0  # read-only
    assert LightRig(DIRS).is_distant
    part = LightRig(DIRS, [2.0, 3.0, 4.0, math.inf]).take([3, 1])
    np.testing.assert_allclose(part.directions, DIRS[[3, 1]], rtol=0, atol=1e-15)
    np.testing.assert_array_equal(part.distances, [math.inf, 3.0])
    assert rig.take([2]).distance == 3.0 and rig.with_distance(5.0).distance == 5.0
    np.testing.assert_array_equal(LightRig(DIRS).inverse_distances, 0.0)
    for bad in (0.0, -1.0, math.nan):
        with pytest.raises(ValueError, match=r"distance = .* out of range; valid range is "
                                             r"\(0, inf\]"):
            LightRig(DIRS, bad)
    with pytest.raises(ValueError, match=r"distance has shape \(3,\); expected a number or "
                                         r"\(4,\)"):
        LightRig(DIRS, [2.0, 2.0, 2.0])
    with pytest.raises(ValueError, match=r"directions\[1\] = \[0.0, 0.0, 0.0\] is not a finite "
                                         "non-zero vector"):
        LightRig([[0, 0, 1], [0, 0, 0]])
    with pytest.raises(ValueError, match="light 0 is distant"):
        _ = LightRig(DIRS).positions


# ---------------------------------------------------------------------------
#  Directions and irradiance against closed-form geometry
# ---------------------------------------------------------------------------

def test_distant_rig_is_todays_model_exactly():
    xy = pixel_coordinates((5, 7))
    rig = LightRig(DIRS)
    d, s = light_field(rig, xy)
    assert d.shape == (4, 5, 7, 3) and s.shape == (4, 5, 7)
    # the directions normalised as the forward model does (d / |d|), to the last bit
    np.testing.assert_array_equal(rig.directions, DIRS / np.linalg.norm(DIRS, axis=1)[:, None])
    np.testing.assert_array_equal(d, np.broadcast_to(rig.directions[:, None, None], d.shape))
    np.testing.assert_array_equal(s, 1.0)


def test_hand_computed_point():
    # light at the zenith, 2 image widths up; point half an image width to the right
    d, s = light_field(LightRig([[0.0, 0.0, 1.0]], 2.0), np.array([[0.5, 0.0]]))
    np.testing.assert_allclose(d[0, 0], np.array([-0.5, 0.0, 2.0]) / math.sqrt(4.25))
    np.testing.assert_allclose(s[0, 0], 4.0 / 4.25)


def test_light_field_against_point_by_point_geometry():
    r = np.array([2.0, 3.0, 4.5, math.inf])
    rig = LightRig(DIRS, r)
    rng = np.random.default_rng(3)
    xy = rng.uniform(-0.5, 0.5, (9, 2))
    d, s = light_field(rig, xy)
    for k in range(4):
        for p in range(len(xy)):
            x = np.array([xy[p, 0], xy[p, 1], 0.0])
            if math.isinf(r[k]):
                want_d, want_s = DIRS[k], 1.0
            else:
                to_light = r[k] * DIRS[k] - x          # the light's position minus the point
                dist = np.linalg.norm(to_light)
                want_d, want_s = to_light / dist, (r[k] / dist) ** 2
            np.testing.assert_allclose(d[k, p], want_d, rtol=0, atol=1e-14)
            assert s[k, p] == pytest.approx(want_s, rel=1e-13)
    # 1 at the centre; bounded by (r / (r +- rho))^2 over the image
    _, s0 = light_field(rig, np.zeros((1, 2)))
    np.testing.assert_allclose(s0, 1.0)
    rho = half_diagonal((30, 40))
    _, s_img = image_light_field(LightRig(DIRS, 2.0), (30, 40))
    assert np.all(s_img >= (2.0 / (2.0 + rho)) ** 2) and np.all(s_img <= (2.0 / (2.0 - rho)) ** 2)


def test_near_light_turns_by_degrees_and_converges_to_distant():
    xy = pixel_coordinates((16, 16))
    angles = []
    for r in (3.0, 30.0, 300.0):
        d, s = light_field(LightRig(DIRS, r), xy)
        cos = np.clip(np.einsum("kpqc,kc->kpq", d, DIRS), -1.0, 1.0)
        angles.append(np.degrees(np.max(np.arccos(cos))))
        assert np.max(np.abs(s - 1.0)) < 3.0 / r
    # a dome 3 image widths away turns its lights by several degrees across the image
    assert 5.0 < angles[0] < 15.0
    # the turn falls as 1 / r
    assert angles[1] == pytest.approx(angles[0] / 10, rel=0.15)
    assert angles[2] == pytest.approx(angles[1] / 10, rel=0.02)


def test_derivatives_against_finite_differences():
    rng = np.random.default_rng(5)
    xy = rng.uniform(-0.5, 0.5, (6, 2))
    for r in (2.5, math.inf):
        rig = LightRig(DIRS, r)
        dd, ds = light_field_derivatives(rig, xy)
        u, h = rig.inverse_distances[0], 1e-6
        dp, sp = light_field(LightRig(DIRS, 1.0 / (u + h)), xy)
        # u - h < 0 has no light behind the camera: one-sided at u = 0, central otherwise
        if u > 0:
            dm, sm = light_field(LightRig(DIRS, 1.0 / (u - h)), xy)
            np.testing.assert_allclose(dd, (dp - dm) / (2 * h), atol=1e-8)
            np.testing.assert_allclose(ds, (sp - sm) / (2 * h), atol=1e-8)
        else:
            d0, s0 = light_field(rig, xy)
            np.testing.assert_allclose(dd, (dp - d0) / h, atol=1e-5)
            np.testing.assert_allclose(ds, (sp - s0) / h, atol=1e-5)


def test_points_must_be_closer_than_the_lights():
    with pytest.raises(ValueError, match=r"distance of light 0 = 0.5 image widths is out of "
                                         r"range for these points; valid range is \(0.6"):
        light_field(LightRig(DIRS, 0.5), np.array([[0.6, 0.0]]))
    with pytest.raises(ValueError, match=r"valid range is \(0.707107, inf\]"):
        image_light_field(LightRig(DIRS, 0.7), (8, 8))


# ---------------------------------------------------------------------------
#  .lp vectors: directions or positions
# ---------------------------------------------------------------------------

def test_vectors_classified_by_norm():
    rig, kind = rig_from_vectors(DIRS * (1 + 0.5 * UNIT_TOLERANCE))
    assert kind == "directions" and rig.is_distant
    np.testing.assert_allclose(rig.directions, DIRS)
    rig, kind = rig_from_vectors(DIRS, distance=2.5)
    assert kind == "directions" and rig.distance == 2.5
    # positions in mm, a dome of 300 mm radius over an image 100 mm wide: r = 3
    rig, kind = rig_from_vectors(300.0 * DIRS, image_width=100.0)
    assert kind == "positions"
    np.testing.assert_allclose(rig.distances, 3.0)
    np.testing.assert_allclose(rig.directions, DIRS)
    # lights at their own distances
    radii = np.array([280.0, 300.0, 310.0, 330.0])
    rig, _ = rig_from_vectors(radii[:, None] * DIRS, image_width=100.0)
    np.testing.assert_allclose(rig.distances, radii / 100.0)
    # a 1 m dome written in metres looks like directions unless the kind is given
    rig, kind = rig_from_vectors(DIRS, kind="positions", image_width=0.25)
    assert kind == "positions" and np.allclose(rig.distances, 4.0)


def test_vector_errors():
    mixed = DIRS.copy()
    mixed[2] *= 250.0
    where = [f"dome.lp, line {n}" for n in (2, 3, 4, 5)]
    with pytest.raises(ValueError, match=r"dome.lp, line 4: light vector of length 250 is a "
                                         r"position .* but dome.lp, line 2 has length 1, a unit "
                                         r"direction; .* \(3 of 4 are unit\)"):
        rig_from_vectors(mixed, where=where)
    with pytest.raises(ValueError, match="vector 0: the lights are positions .* give "
                                         "image_width"):
        rig_from_vectors(300.0 * DIRS)
    with pytest.raises(ValueError, match=r"image_width = 0.0 is out of range"):
        rig_from_vectors(300.0 * DIRS, image_width=0.0)
    with pytest.raises(ValueError, match="positions set each light's distance"):
        rig_from_vectors(300.0 * DIRS, image_width=100.0, distance=3.0)
    with pytest.raises(ValueError, match="kind = 'pos' is not valid"):
        rig_from_vectors(DIRS, kind="pos")


def test_read_lp_rig(tmp_path):
    names = [f"img{k}.png" for k in range(4)]
    write_lp(tmp_path / "unit.lp", names, DIRS)
    got, rig, kind = read_lp_rig(tmp_path / "unit.lp", distance=4.0)
    assert got == names and kind == "directions" and rig.distance == 4.0
    np.testing.assert_allclose(rig.directions, DIRS, atol=1e-9)
    write_lp(tmp_path / "pos.lp", names, 250.0 * DIRS)
    _, rig, kind = read_lp_rig(tmp_path / "pos.lp", image_width=50.0)
    assert kind == "positions"
    np.testing.assert_allclose(rig.distances, 5.0, rtol=1e-9)
    mixed = DIRS.copy()
    mixed[3] *= 250.0
    (tmp_path / "mixed.lp").write_text(
        "4\n\n" + "".join(f"{n} {x!r} {y!r} {z!r}\n" for n, (x, y, z) in zip(names, mixed)))
    with pytest.raises(ValueError, match=r"mixed.lp, line 6: light vector of length 250 is a "
                                         r"position .*mixed.lp, line 3 has length 1"):
        read_lp_rig(tmp_path / "mixed.lp")


# ---------------------------------------------------------------------------
#  Point lights of a Mitsuba scene
# ---------------------------------------------------------------------------

def test_point_lights_values():
    rig = LightRig(DIRS, [2.0, 3.0, 4.0, 5.0])
    pos, inten = point_lights(rig, 3.0, gains=np.array([1.0, 2.0, 0.5, 1.5]))
    np.testing.assert_allclose(pos, rig.positions * 3.0)
    np.testing.assert_allclose(inten, [1.0 * 36, 2.0 * 81, 0.5 * 144, 1.5 * 225])
    # I / D^2 at the centre is the gain
    np.testing.assert_allclose(inten / np.sum(pos**2, axis=1), [1.0, 2.0, 0.5, 1.5])
    with pytest.raises(ValueError, match="light 0 is distant .* directional emitter"):
        point_lights(LightRig(DIRS), 1.0)
    with pytest.raises(ValueError, match=r"scene_width = -1.0 is out of range"):
        point_lights(rig, -1.0)
    with pytest.raises(ValueError, match=r"gains\[1\] = 0.0 is out of range"):
        point_lights(rig, 1.0, gains=np.array([1.0, 0.0, 1.0, 1.0]))


def _render_plane(emitter: dict, height: int, width: int, reflectance: float) -> np.ndarray:
    """A Lambertian rectangle spanning the image (as rti_maps' scene.xml: x in [-a, a], y in
    [-1, 1], a = W / H) under an orthographic camera straight above, direct light only."""
    a = width / height
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {
            "type": "orthographic",
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 2], target=[0, 0, 0],
                                                        up=[0, 1, 0]).scale([a, a, 1]),
            "sampler": {"type": "independent", "sample_count": 64},
            "film": {"type": "hdrfilm", "width": width, "height": height,
                     "rfilter": {"type": "box"}, "pixel_format": "rgb"},
        },
        "plane": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale([a, 1, 1]),
                  "bsdf": {"type": "diffuse",
                           "reflectance": {"type": "rgb", "value": [reflectance] * 3}}},
        "light": emitter,
    })
    return np.array(mi.render(scene, seed=1), dtype=np.float64)[..., 0]


def test_point_light_render_matches_prediction():
    """A plane lit by point_lights' emitter, rendered by Mitsuba: the per-pixel radiance is
    the analytic ``rho / pi I cos(theta) / D^2`` and the module's ``rho / pi E s d_z``."""
    h, w, albedo, gain = 32, 48, 0.5, 0.8
    scene_width = 2.0 * w / h
    xy = pixel_coordinates((h, w))
    with use_variant("scalar_rgb"):
        for light, r in ((_dir(30, 40), 2.0), (_dir(20, 200), 1.5)):
            rig = LightRig(light[None], r)
            pos, inten = point_lights(rig, scene_width, np.array([gain]))
            img = _render_plane({"type": "point", "position": pos[0].tolist(),
                                 "intensity": {"type": "rgb", "value": [inten[0]] * 3}},
                                h, w, albedo)
            # analytic: the point light seen from each pixel's centre, in scene units
            to_light = pos[0] - np.concatenate([xy * scene_width, np.zeros((h, w, 1))], axis=-1)
            dist = np.linalg.norm(to_light, axis=-1)
            analytic = albedo / math.pi * inten[0] * (to_light[..., 2] / dist) / dist**2
            d, s = light_field(rig, xy)
            model = albedo / math.pi * gain * s[0] * d[0, ..., 2]
            np.testing.assert_allclose(model, analytic, rtol=1e-12)
            # Monte Carlo over each pixel's footprint (64 samples): 0.15 % per pixel
            np.testing.assert_allclose(img, analytic, rtol=1e-2)
            assert abs(np.mean(img / analytic - 1.0)) < 5e-4
            # the near-field term matters: the distant light is off by far more
            distant = albedo / math.pi * gain * light[2]
            assert np.max(np.abs(distant / img - 1.0)) > 0.2
            # and the directional emitter of the same gain is the distant model
            far = _render_plane({"type": "directional", "direction": (-light).tolist(),
                                 "irradiance": {"type": "rgb", "value": [gain] * 3}},
                                h, w, albedo)
            np.testing.assert_allclose(far, distant, rtol=1e-5)
