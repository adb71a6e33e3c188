"""mitsuba_powder.variants: the one helper the package switches Mitsuba variants with."""

from __future__ import annotations

from pathlib import Path

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

import mitsuba_powder
from mitsuba_powder.rendering.render import render_scene
from mitsuba_powder.variants import check_variant, set_variant, use_variant

SCENE = Path(__file__).resolve().parents[2] / "scenes" / "powder_patch.xml"


@pytest.fixture
def calls(monkeypatch):
    """Count the calls of mi.set_variant and mitsuba_powder.register (both still run)."""
    counts = {"set_variant": 0, "register": 0}
    real_set, real_register = mi.set_variant, mitsuba_powder.register

    def counted_set(*names):
        counts["set_variant"] += 1
        return real_set(*names)

    def counted_register():
        counts["register"] += 1
        return real_register()

    monkeypatch.setattr(mi, "set_variant", counted_set)
    monkeypatch.setattr(mitsuba_powder, "register", counted_register)
    return counts


def test_use_variant_restores_the_previous_variant(calls):
    set_variant("scalar_rgb")
    before = calls["set_variant"]  # 1, or 0 when an earlier test left scalar_rgb selected
    with use_variant("scalar_spectral") as name:
        assert name == "scalar_spectral" and mi.variant() == "scalar_spectral"
        assert calls["register"] == 2  # set_variant above, then the switch into the block
        assert mi.load_dict({"type": "powder"}).class_name() == "Powder"
    assert mi.variant() == "scalar_rgb"
    assert calls["set_variant"] == before + 2  # into the block, back


def test_use_variant_restores_after_an_exception_and_a_switch_inside():
    set_variant("scalar_rgb")
    with pytest.raises(KeyError, match="boom"), use_variant("scalar_spectral"):
        mi.set_variant("scalar_spectral_polarized")  # the block switches on its own
        raise KeyError("boom")
    assert mi.variant() == "scalar_rgb"


def test_nested_use(calls):
    set_variant("scalar_rgb")
    before, registered = calls["set_variant"], calls["register"]
    with use_variant("scalar_rgb"):  # already selected: nothing switches or registers
        assert (calls["set_variant"], calls["register"]) == (before, registered)
        with use_variant("scalar_spectral"):
            assert mi.variant() == "scalar_spectral"
            with use_variant("scalar_spectral"):
                assert mi.variant() == "scalar_spectral"
            assert mi.variant() == "scalar_spectral"
            with use_variant("scalar_rgb"):
                assert mi.variant() == "scalar_rgb"
            assert mi.variant() == "scalar_spectral"
        assert mi.variant() == "scalar_rgb"
    assert mi.variant() == "scalar_rgb"
    # into spectral, into rgb, back to spectral, back to rgb: the same-variant blocks are free
    assert calls["set_variant"] - before == 4
    assert calls["register"] - registered == 2  # on the way in only


def test_set_variant_leaves_the_variant_selected_and_returns_the_previous(calls):
    mi.set_variant("scalar_rgb")
    assert set_variant("scalar_spectral") == "scalar_rgb"
    assert mi.variant() == "scalar_spectral"
    assert set_variant("scalar_spectral") == "scalar_spectral"
    assert calls["register"] == 2  # every call makes the plugin findable


@pytest.mark.parametrize("bad", ["scalar_rbg", "", None])
def test_unknown_variant_is_a_clear_error(bad):
    set_variant("scalar_rgb")
    for call in (lambda: check_variant(bad), lambda: set_variant(bad),
                 lambda: use_variant(bad).__enter__()):
        with pytest.raises(ValueError) as info:
            call()
        message = str(info.value)
        assert f"variant = {bad!r} is not available" in message
        assert all(v in message for v in mi.variants())  # the valid choices are listed
        assert mi.variant() == "scalar_rgb"  # nothing switched


def test_cuda_variant_without_a_device_is_a_clear_error():
    if "cuda_ad_rgb" not in mi.variants() or dr.has_backend(dr.JitBackend.CUDA):
        pytest.skip("needs a Mitsuba build with cuda variants and no CUDA device")
    set_variant("scalar_rgb")
    with pytest.raises(RuntimeError, match="'cuda_ad_rgb' needs a CUDA device"):
        set_variant("cuda_ad_rgb")
    assert mi.variant() == "scalar_rgb"


@pytest.mark.parametrize("caller", ["scalar_spectral", "scalar_rgb"])
def test_render_scene_restores_the_callers_variant(tmp_path, caller):
    set_variant(caller)
    out = tmp_path / "a.exr"
    result = render_scene(SCENE, out, variant="scalar_rgb", spp=1,
                          defines={"res_x": "8", "res_y": "4"})
    assert mi.variant() == caller
    assert result.variant == "scalar_rgb" and (result.width, result.height) == (8, 4)
    img = np.array(mi.Bitmap(str(out)))
    assert img.shape[:2] == (4, 8) and img.shape[2] >= 3 and np.all(np.isfinite(img))
    with pytest.raises(ValueError, match="'no_such_variant' is not available"):
        render_scene(SCENE, out, variant="no_such_variant")
    assert mi.variant() == caller
