"""End to end: the bundled scene renders through the CLI, and pixels agree with closed forms."""

from __future__ import annotations

from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from helpers import use_variant
from mitsuba_powder.cli import main

SCENE = Path(__file__).resolve().parents[1] / "scenes" / "powder_patch.xml"


def test_cli_renders_the_bundled_scene(tmp_path, capsys):
    out = tmp_path / "patch.exr"
    assert main(["render", str(SCENE), "-o", str(out), "--spp", "4",
                 "-D", "res_x=96", "-D", "res_y=48"]) == 0
    assert out.is_file()
    assert "96x48" in capsys.readouterr().out
    img = np.array(mi.Bitmap(str(out)))
    assert img.shape[:2] == (48, 96) and np.all(np.isfinite(img))


def test_cli_reports_bad_input(tmp_path, capsys):
    assert main(["render", str(tmp_path / "missing.xml"), "-o", str(tmp_path / "a.exr")]) == 2
    assert "does not exist" in capsys.readouterr().err
    assert main(["render", str(SCENE), "-o", str(tmp_path / "a.exr"), "--spp", "0"]) == 2
    assert "spp = 0" in capsys.readouterr().err


def expected_image(scene, width: int, height: int, light_dir: np.ndarray,
                   irradiance: float) -> np.ndarray:
    """Closed form of the direct-lighting render with a box filter: for points of each pixel,
    trace the camera ray and average f(-ray.d, light) cos(theta_light) E at the hits (with
    the hit's own BSDF); 0 where nothing is hit, NaN where the pixel straddles an edge."""
    sensor = scene.sensors()[0]
    ctx = mi.BSDFContext()
    out = np.full((height, width, 3), np.nan)
    for i in range(height):
        for j in range(width):
            vals = []
            # box filter: the pixel is the mean over its area (5-point rule); the corners
            # only detect pixels that straddle an edge
            for dx, dy in [(0.5, 0.5), (0.2, 0.2), (0.8, 0.2), (0.2, 0.8), (0.8, 0.8),
                           (0.0, 0.0), (1.0, 0.0), (0.0, 1.0), (1.0, 1.0)]:
                ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f((j + dx) / width,
                                                               (i + dy) / height),
                                           mi.Point2f(0.5, 0.5))
                si = scene.ray_intersect(ray)
                if not si.is_valid():
                    vals.append(None)
                    continue
                wi_local = si.to_local(mi.Vector3f(light_dir))
                value = si.bsdf().eval(ctx, si, wi_local)  # si.wi = towards the camera
                vals.append((si.shape.id(), np.array(value).ravel() * irradiance))
            if all(v is None for v in vals):
                out[i, j] = 0.0
            elif all(v is not None and v[0] == vals[0][0] for v in vals):
                out[i, j] = np.mean([v[1] for v in vals[:5]], axis=0)
    return out


@pytest.mark.parametrize("variant", ["scalar_rgb", "llvm_ad_rgb"])
def test_scene_pixels_match_closed_form(variant):
    """Directional light and direct illumination: each pixel is f(wi, wo) E cos(theta_i),
    a closed form (the Lambertian patch: 0.8 / pi E cos(theta_i))."""
    use_variant(variant)
    width, height = 48, 24
    theta = np.radians(30.0 + 2.0)  # theta_i + light_offset
    light = np.array([np.sin(theta), 0.0, np.cos(theta)])
    scene = mi.load_file(str(SCENE), spp="256", res_x=str(width), res_y=str(height),
                         rfilter="box")
    img = np.array(mi.render(scene), dtype=np.float64)
    assert np.all(np.isfinite(img))
    if variant.startswith("scalar"):
        want = expected_image(scene, width, height, light, 3.0)
    else:
        mi.set_variant("scalar_rgb")
        want = expected_image(mi.load_file(str(SCENE), res_x=str(width), res_y=str(height),
                                           rfilter="box"), width, height, light, 3.0)
        mi.set_variant(variant)
    inside = np.all(np.isfinite(want), axis=2) & np.all(want > 0, axis=2)
    assert inside.sum() > 0.3 * width * height
    lambert = np.isclose(want[..., 0], want[..., 2]) & inside
    np.testing.assert_allclose(want[lambert], 0.8 / np.pi * 3.0 * np.cos(theta), rtol=1e-5)
    assert lambert.sum() > 100 and (inside & ~lambert).sum() > 100
    np.testing.assert_allclose(img[inside], want[inside], rtol=0.02)
