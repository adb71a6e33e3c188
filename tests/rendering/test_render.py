"""End to end: the bundled scene renders through the CLI, and pixels agree with closed forms."""

from __future__ import annotations

import json
from pathlib import Path

import mitsuba as mi
import numpy as np
import pytest

from helpers import use_variant
from mitsuba_powder import variants
from mitsuba_powder.cli import main

SCENE = Path(__file__).resolve().parents[2] / "scenes" / "powder_patch.xml"


def read_exr(path: Path) -> np.ndarray:
    """Linear RGB of an EXR file written by the render command."""
    use_variant("scalar_rgb")
    return np.array(mi.Bitmap(str(path)), dtype=np.float64)[..., :3]


def powder_props(parsed) -> dict:
    """{name: value} of the first powder BSDF of a parsed scene description."""
    props = parsed.powders()[0].props
    return {k: props[k] for k in props.keys()}


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
        with variants.use_variant("scalar_rgb"):
            want = expected_image(mi.load_file(str(SCENE), res_x=str(width),
                                               res_y=str(height), rfilter="box"),
                                  width, height, light, 3.0)
        assert mi.variant() == variant
    inside = np.all(np.isfinite(want), axis=2) & np.all(want > 0, axis=2)
    assert inside.sum() > 0.3 * width * height
    lambert = np.isclose(want[..., 0], want[..., 2]) & inside
    np.testing.assert_allclose(want[lambert], 0.8 / np.pi * 3.0 * np.cos(theta), rtol=1e-5)
    assert lambert.sum() > 100 and (inside & ~lambert).sum() > 100
    np.testing.assert_allclose(img[inside], want[inside], rtol=0.02)


def test_showcase_scene_renders_in_a_spectral_variant(tmp_path):
    """The seven hematite dishes, tiny and few samples: it loads, every powder is a distinct
    two- or one-population BSDF, and the image is finite."""
    use_variant("llvm_ad_spectral")
    showcase = SCENE.parent / "showcase.xml"
    scene = mi.load_file(str(showcase), res_x="96", res_y="30", spp="2")
    powders = [s for s in scene.shapes() if s.id().startswith("powder")]
    assert len(powders) == 7
    img = np.array(mi.render(scene))
    assert img.shape == (30, 96, 3) and np.all(np.isfinite(img)) and img.max() > 0


def test_render_applies_fitted_parameters(tmp_path, capsys):
    """--params writes every property into the scene's powder BSDF before loading: the
    differentiable ones give the image the closed form says (the scene with the same values
    as its own defaults), the others (eta, k) reach the plugin's constructor and its
    validation."""
    import json

    out = tmp_path / "a.exr"
    base = ["render", str(SCENE), "-o", str(out), "--variant", "llvm_ad_rgb", "--spp", "4",
            "-D", "res_x=48", "-D", "res_y=24", "-D", "rfilter=box"]
    params = tmp_path / "p.json"
    params.write_text(json.dumps({"parameters": {"extinction": 3.0, "albedo": 0.5}}))
    assert main(base + ["--params", str(params)]) == 0
    assert "set on every powder BSDF: extinction = 3, albedo = 0.5" in capsys.readouterr().out
    use_variant("llvm_ad_rgb")
    a = mi.load_file(str(SCENE), res_x="48", res_y="24", albedo="0.5, 0.5, 0.5",
                     extinction="3.0", rfilter="box")
    expected = np.array(mi.render(a, spp=4))
    np.testing.assert_allclose(read_exr(out), expected, rtol=1e-5, atol=1e-7)
    # eta without k: the plugin's own error reaches the user, nothing is written
    out.unlink()
    params.write_text(json.dumps({"parameters": {"extinction": 3.0, "eta": 1.35}}))
    assert main(base + ["--params", str(params)]) == 2
    assert 'give both "eta" and "k"' in capsys.readouterr().err and not out.exists()
    # with k, the powder's tau_o comes from Fresnel of eta = 1.35, not from hematite
    params.write_text(json.dumps({"parameters": {"extinction": 3.0, "eta": 1.35, "k": 0.0}}))
    assert main(base + ["--params", str(params)]) == 0
    from mitsuba_powder.rendering.render import scene_with_properties

    parsed, count, removed = scene_with_properties(SCENE, {"eta": 1.35, "k": 0.0})
    assert count == 1 and removed == [] and powder_props(parsed)["eta"] == 1.35
    # grains given without an albedo: the scene's albedo goes, so the albedo is Mie's
    parsed, _, removed = scene_with_properties(SCENE, {"radius": 0.08, "extinction": 1.0})
    assert removed == ["albedo"] and "albedo" not in powder_props(parsed)
    parsed, _, removed = scene_with_properties(SCENE, {"radius": 0.08, "albedo": 0.5})
    assert removed == [] and powder_props(parsed)["albedo"] == 0.5


def test_apply_properties_after_loading():
    """Scenes whose powder comes from an <include>: what mi.traverse exposes is set."""
    from mitsuba_powder.rendering.render import apply_properties

    use_variant("llvm_ad_rgb")
    a = mi.load_file(str(SCENE), res_x="48", res_y="24", albedo="0.5, 0.5, 0.5",
                     extinction="3.0", rfilter="box")
    b = mi.load_file(str(SCENE), res_x="48", res_y="24", rfilter="box")
    applied, missing = apply_properties(b, {"albedo": 0.5, "extinction": 3.0, "eta": 1.35})
    assert applied == ["albedo", "extinction"] and missing == ["eta"]
    with pytest.raises(ValueError, match="'extinction' = 'abc': expected a number"):
        apply_properties(b, {"extinction": "abc"})
    np.testing.assert_allclose(np.array(mi.render(b, spp=4)), np.array(mi.render(a, spp=4)),
                               rtol=1e-5, atol=1e-7)


def test_render_sets_properties_on_included_powders(tmp_path, capsys):
    """A powder BSDF from an <include> gets the properties too (the include is read into the
    description first), and its relative textures still resolve beside the included file."""
    (tmp_path / "sub").mkdir()
    use_variant("scalar_rgb")
    mi.Bitmap(np.full((2, 2, 3), 0.5, np.float32)).write(str(tmp_path / "sub" / "tex.exr"))
    (tmp_path / "sub" / "powder.xml").write_text(
        '<scene version="3.0.0"><bsdf type="powder" id="p"><texture type="bitmap" '
        'name="albedo"><string name="filename" value="tex.exr"/></texture></bsdf></scene>\n')
    (tmp_path / "main.xml").write_text("""<scene version="3.0.0">
  <include filename="sub/powder.xml"/>
  <integrator type="direct"/>
  <sensor type="orthographic"><film type="hdrfilm"><integer name="width" value="4"/>
    <integer name="height" value="4"/></film></sensor>
  <shape type="rectangle"><ref id="p"/></shape>
  <emitter type="directional"><vector name="direction" value="0, 0, -1"/></emitter>
</scene>
""")
    from mitsuba_powder.rendering.render import scene_with_properties

    parsed, count, _ = scene_with_properties(tmp_path / "main.xml", {"lobes": "single"})
    assert count == 1 and powder_props(parsed)["lobes"] == "single"
    out = tmp_path / "i.exr"
    assert main(["render", str(tmp_path / "main.xml"), "-o", str(out), "--spp", "1", "--set",
                 "extinction=2", "--set", "lobes=single"]) == 0
    assert "set on every powder BSDF: extinction = 2, lobes = single" in capsys.readouterr().out
    # the included file's texture is an input: not overwritten
    before = (tmp_path / "sub" / "tex.exr").read_bytes()
    assert main(["render", str(tmp_path / "main.xml"), "-o", str(tmp_path / "sub" / "tex.exr"),
                 "--spp", "1"]) == 2
    assert "is an input file" in capsys.readouterr().err
    assert (tmp_path / "sub" / "tex.exr").read_bytes() == before


def test_render_protects_textures_named_through_defaults(tmp_path, capsys):
    """A texture named by a $substitution (a <default> or -D) is protected too."""
    use_variant("scalar_rgb")
    for name in ("t1.exr", "t2.exr"):
        mi.Bitmap(np.full((2, 2, 3), 0.5, np.float32)).write(str(tmp_path / name))
    (tmp_path / "s.xml").write_text("""<scene version="3.0.0">
  <default name="tex" value="t1.exr"/>
  <integrator type="direct"/>
  <sensor type="orthographic"><film type="hdrfilm"><integer name="width" value="4"/>
    <integer name="height" value="4"/></film></sensor>
  <shape type="rectangle"><bsdf type="diffuse"><texture type="bitmap" name="reflectance">
    <string name="filename" value="$tex"/></texture></bsdf></shape>
  <emitter type="constant"/>
</scene>
""")
    for args in ([], ["-D", "tex=t2.exr"]):
        target = tmp_path / ("t2.exr" if args else "t1.exr")
        before = target.read_bytes()
        assert main(["render", str(tmp_path / "s.xml"), "-o", str(target), *args]) == 2
        assert "is an input file" in capsys.readouterr().err
        assert target.read_bytes() == before


def test_property_values_in_the_description():
    """rgb_wavelengths as text and a fit.json's irregular albedo spectrum become the scene
    elements the plugin reads."""
    from mitsuba_powder.rendering.render import scene_with_properties

    use_variant("scalar_spectral")
    parsed, _, _ = scene_with_properties(SCENE, {
        "rgb_wavelengths": "600, 550, 450",
        "albedo": {"type": "irregular", "wavelengths": [400.0, 700.0], "values": [0.2, 0.8]}})
    props = powder_props(parsed)
    assert props["rgb_wavelengths"] == "600, 550, 450"
    assert list(props["albedo"].wavelengths) == [400.0, 700.0]
    assert list(props["albedo"].values) == pytest.approx([0.2, 0.8])
    assert parsed.load() is not None  # the plugin takes what was written
    with pytest.raises(ValueError, match="a spectrum must be"):
        scene_with_properties(SCENE, {"albedo": {"type": "blackbody"}})


def test_render_rejects_a_name_that_is_not_a_property(tmp_path, capsys):
    """A typo in --set is an error (exit 2) that names the property meant; nothing is
    written."""
    out = tmp_path / "typo.exr"
    assert main(["render", str(SCENE), "-o", str(out), "--set", "radiu=0.1"]) == 2
    err = capsys.readouterr().err
    assert "'radiu' is not a property of the powder plugin" in err and "'radius'" in err
    assert not out.exists()


def test_render_reports_the_scenes_sample_count(tmp_path, capsys):
    out = tmp_path / "s.exr"
    assert main(["render", str(SCENE), "-o", str(out), "-D", "res_x=16", "-D", "res_y=8",
                 "-D", "spp=3"]) == 0
    assert "16x8, 3 spp (the scene's)" in capsys.readouterr().out


SCENES = Path(__file__).resolve().parents[2] / "scenes"

#: Small renders of each bundled scene (its own -D names)
_SMALL = {"gonio.xml": ["-D", "res=4", "-D", "spp=1"],
          "powder_patch.xml": ["-D", "res_x=8", "-D", "res_y=4", "-D", "spp=1"],
          "showcase.xml": ["-D", "res_x=8", "-D", "res_y=4", "-D", "spp=1"],
          "showcase_grains.xml": ["-D", "res_x=8", "-D", "res_y=4", "-D", "spp=1"]}


@pytest.mark.parametrize("name", sorted(_SMALL))
def test_bundled_scenes_take_set_and_params(tmp_path, capsys, name):
    """Issue 33, case 1: every bundled scene takes --set and --params (their comments hold
    '--', which Mitsuba's parser accepts and Python's XML parser does not); the value set
    reaches the plugin (the image changes)."""
    assert "--" in (SCENES / name).read_text()  # the case this test is about
    base = ["render", str(SCENES / name), *_SMALL[name]]
    plain, changed, from_json = (tmp_path / f"{k}.exr" for k in ("plain", "set", "json"))
    assert main([*base, "-o", str(plain)]) == 0
    assert main([*base, "-o", str(changed), "--set", "g=0.6", "--set", "extinction=0.25"]) == 0
    out = capsys.readouterr().out
    assert "set on every powder BSDF: g = 0.6, extinction = 0.25" in out
    params = tmp_path / "fit.json"
    params.write_text(json.dumps({"parameters": {"g": 0.6, "extinction": 0.25}}))
    assert main([*base, "-o", str(from_json), "--params", str(params)]) == 0
    a, b, c = (read_exr(p) for p in (plain, changed, from_json))
    assert np.all(np.isfinite(b)) and not np.array_equal(a, b)
    np.testing.assert_allclose(b, c, rtol=1e-6)  # threads may sum in another order


def test_render_names_a_scene_mitsuba_cannot_parse(tmp_path, capsys):
    """A scene that is not XML: an error naming the file (Mitsuba's parser's message), exit 2,
    nothing written."""
    bad = tmp_path / "bad.xml"
    bad.write_text('<scene version="3.0.0"><bsdf type="powder">\n')
    out = tmp_path / "o.exr"
    assert main(["render", str(bad), "-o", str(out), "--set", "g=0.1"]) == 2
    err = capsys.readouterr().err
    assert "bad.xml" in err and "Traceback" not in err and not out.exists()
