"""Powder maps on disk: a :func:`mitsuba_powder.rti.fit_maps` result as EXR maps, ``fit.json``
and a Mitsuba scene, read back for relighting.

A maps folder holds:

- ``<property>.exr``: one single-channel float32 map per fitted (or per-pixel) float property,
  in the plugin's units; ``albedo.exr`` (RGB, the single-scattering albedo per channel);
  ``normal.exr`` (RGB, the unit normal's x, y, z in the image frame: x to the right, y up, z
  towards the camera); ``normal_tangent.exr`` (the same encoded as ``(n + 1) / 2`` for
  Mitsuba's ``normalmap`` BSDF); ``residual.exr`` (RMS residual per pixel, linear units);
  ``mask.exr`` (1 where fitted);
- ``fit.json``: the settings held for every pixel, the free properties, the per-light gains, the
  capture's encoding / bit depth / file format (so that relit images match it), per-map
  statistics and the fit's diagnostics;
- with a relief (:mod:`mitsuba_powder.rti.relief`; fit-maps keeps one with any ``shadows``):
  ``relief.exr`` (the height field, pixel units), ``relief.ply`` (its mesh,
  :func:`write_relief_ply`); ``scene.xml`` then renders the mesh with the powder BSDF by the
  ``path`` integrator (cast shadows and interreflections; ``$max_depth``, default 4), and
  ``scene_flat.xml`` is the flat patch below;
- ``scene.xml``: the surface as a unit-height rectangle (width / height = the image's aspect)
  with a ``normalmap`` BSDF around ``<bsdf type="powder">`` whose properties are the maps as
  ``raw`` bitmap textures, seen by an orthographic camera straight above (one pixel per texel)
  and lit by a directional emitter of irradiance ``$irradiance`` from ``($lx, $ly, $lz)``
  (towards the light, image frame). It renders with ``mitsuba scene.xml -D lx=... -D ly=...
  -D lz=...`` and with ``mitsuba-powder render``; with the ``direct`` integrator a pixel is the
  model's ``E f (n . l)``, as :func:`mitsuba_powder.rti.relight` predicts. A fit with lights
  at a finite distance r (image widths) lights the scene instead by a ``point`` emitter at
  ``($px, $py, $pz)`` of intensity ``$intensity``: light k of gain ``E_k`` is at ``p = r l_k
  (2 W / H)`` (an image width is ``2 W / H`` scene units) with ``intensity = E_k (r 2 W /
  H)^2``, so that ``I / D^2 = E_k`` at the image's centre
  (:func:`mitsuba_powder.rti.lights.point_lights`).

Maps are written with row 0 at the top of the image (as the capture); the scene's bitmaps map
them onto the rectangle with ``to_uv`` flipping v (Mitsuba's rectangle has v up, its bitmaps
row 0 at v = 0).
"""

from __future__ import annotations

import json
import math
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np

from ..outputs import check_complete, guarding_inputs, note_input, note_inputs, output_path
from ..readers import read_bitmap, read_json
from ..rendering.scene_description import xml_property
from ..variants import use_variant
from .capture import Capture, write_images
from .gains import GainModel
from .lights import LightRig, distance_from_json, distance_to_json, point_lights, read_lp_rig
from .properties import GRAIN_MAPS, MAP_GRAIN_SETTINGS
from .relief import Relief, horizon_map
from .result import MapsResult

#: File written for the scene's normal map (tangent space, encoded (n + 1) / 2)
NORMAL_TANGENT = "normal_tangent.exr"

#: Files of a fit's relief: the height field (pixel units), its mesh, and the flat patch's
#: scene (scene.xml renders the mesh)
RELIEF_EXR, RELIEF_PLY, FLAT_SCENE = "relief.exr", "relief.ply", "scene_flat.xml"

#: The scene of a maps folder (module docstring); ``str.format`` fields: the image size
#: ``w``, ``h`` and ``aspect`` (w / h); the textures ``normalmap``, ``albedo`` and ``maps``
#: and the held settings ``props`` as XML
_SCENE = """<!--
  Powder maps fitted by mitsuba-powder fit-maps ({w} x {h} px). Render under a light from
  (lx, ly, lz) (towards the light; x right, y up, z towards the camera), e.g.
    mitsuba scene.xml -D lx=0.5 -D ly=0 -D lz=0.866 -o relit.exr
    mitsuba-powder render scene.xml -o relit.exr -D lx=0.5 -D ly=0 -D lz=0.866
  A pixel is E f (n . l) (direct illumination; E = $irradiance), as
  mitsuba_powder.rti.relight predicts.
-->
<scene version="3.0.0">
    <default name="spp" value="4"/>
{defaults}

{integrator}

    <sensor type="orthographic">
        <!-- the camera spans x in [-s, s] and y in [-s h / w, s h / w] for scale s = w / h:
             the rectangle exactly, one pixel per texel -->
        <transform name="to_world">
            <scale x="{aspect!r}" y="{aspect!r}"/>
            <lookat origin="0, 0, {camera_z!r}" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <sampler type="independent">
            <integer name="sample_count" value="$spp"/>
        </sampler>
        <film type="hdrfilm">
            <integer name="width" value="{w}"/>
            <integer name="height" value="{h}"/>
            <rfilter type="box"/>
        </film>
    </sensor>

{emitter}

{shape}
</scene>
"""

#: The flat patch: a rectangle with the fitted normals as a normal map
_FLAT = ("""    <integrator type="direct">
        <integer name="emitter_samples" value="1"/>
        <integer name="bsdf_samples" value="0"/>
    </integrator>""", """    <shape type="rectangle">
        <transform name="to_world">
            <scale x="{aspect!r}" y="1"/>
        </transform>
        <!-- no shadow-terminator term: the fitted model is f (n . l) exactly -->
        <bsdf type="normalmap">
            <boolean name="use_shadowing_function" value="false"/>
{normalmap}            <bsdf type="powder">
{albedo}{maps}{props}
            </bsdf>
        </bsdf>
    </shape>""")

#: The relief: the height field's mesh (relief.ply: a vertex at each pixel's centre with its
#: fitted normal as the shading normal, and a ring on the image's edges), path traced: cast
#: shadows and interreflections (``$max_depth``: 2 is direct light only)
_RELIEF = ("""    <default name="max_depth" value="4"/>
    <integrator type="path">
        <integer name="max_depth" value="$max_depth"/>
    </integrator>""", """    <shape type="ply">
        <string name="filename" value="{ply}"/>
        <boolean name="face_normals" value="false"/>
        <bsdf type="powder">
{albedo}{maps}{props}
        </bsdf>
    </shape>""")


_DISTANT = ("""    <emitter type="directional">
        <!-- emits along its local +z: from (lx, ly, lz) towards the origin -->
        <transform name="to_world">
            <lookat origin="$lx, $ly, $lz" target="0, 0, 0" up="0, 1, 0"/>
        </transform>
        <rgb name="irradiance" value="$irradiance"/>
    </emitter>""", """    <default name="lx" value="0"/>
    <default name="ly" value="0"/>
    <default name="lz" value="1"/>
    <default name="irradiance" value="1"/>""")

#: The point light of a near-field fit (module docstring); fields: the zenith light's
#: position height ``pz`` and ``intensity``, the distance ``r`` and the scene width ``sw``
_NEAR = ("""    <!-- lights at r = {r!r} image widths: light k of unit direction l and gain E is at
         p = {r!r} x {sw!r} x l (scene units) with intensity = E ({r!r} x {sw!r})^2 -->
    <emitter type="point">
        <point name="position" x="$px" y="$py" z="$pz"/>
        <rgb name="intensity" value="$intensity"/>
    </emitter>""", """    <default name="px" value="0"/>
    <default name="py" value="0"/>
    <default name="pz" value="{pz!r}"/>
    <default name="intensity" value="{intensity!r}"/>""")


def _write_exr(path: Path, data: np.ndarray) -> None:
    import mitsuba as mi

    with use_variant("scalar_rgb"):
        arr = np.ascontiguousarray(np.asarray(data, dtype=np.float32))
        if arr.ndim == 2:
            arr = arr[..., None]
        fmt = mi.Bitmap.PixelFormat.Y if arr.shape[2] == 1 else mi.Bitmap.PixelFormat.RGB
        mi.Bitmap(arr, fmt).write(str(path))


def _read_exr(path: Path) -> np.ndarray:

    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such map (the folder must come from fit-maps)")
    note_input(path)
    with use_variant("scalar_rgb"):
        arr = np.array(read_bitmap(path, "map"), dtype=np.float32)
    return arr[..., 0] if arr.ndim == 3 and arr.shape[2] == 1 else arr


def _stats(values: np.ndarray) -> dict:
    v = values[np.isfinite(values)]
    if v.size == 0:
        return {"median": None}
    p = np.percentile(v, [5, 50, 95])
    return {"p5": float(p[0]), "median": float(p[1]), "p95": float(p[2])}


def _bitmap_xml(name: str, filename: str) -> str:
    """A raw, nearest-filtered bitmap texture of a map, its rows flipped onto the rectangle's
    v (module docstring)."""
    return (f'        <texture type="bitmap" name="{name}">\n'
            f'            <string name="filename" value="{filename}"/>\n'
            f'            <boolean name="raw" value="true"/>\n'
            f'            <string name="filter_type" value="nearest"/>\n'
            f'            <transform name="to_uv">\n'
            f'                <scale y="-1"/>\n'
            f'                <translate y="1"/>\n'
            f'            </transform>\n'
            f'        </texture>\n')


def _indented(xml: str) -> str:
    """``xml`` indented by one more level (inside the powder BSDF)."""
    return "".join("    " + line + "\n" for line in xml.splitlines())


def _property_xml(settings: dict) -> str:
    """The powder's held settings (strings and finite numbers) as the XML properties of
    :func:`mitsuba_powder.rendering.scene_description.xml_property`."""
    props = []
    for key, value in settings.items():
        if isinstance(value, str) or (isinstance(value, (int, float)) and
                                      not isinstance(value, bool) and math.isfinite(value)):
            element = ET.tostring(xml_property(key, value), encoding="unicode")
            props.append("            " + element.replace(" />", "/>"))
    return "\n".join(props)


def scene_xml(result: MapsResult, settings: dict, relief: bool | None = None) -> str:
    """The Mitsuba scene of a maps folder (module docstring): the relief's mesh
    (``relief.ply``) when ``relief`` (default: when the fit has one), else the flat patch."""
    relief = result.relief is not None if relief is None else relief
    h, w = result.mask.shape
    grain_maps = [name for name in result.maps if name in GRAIN_MAPS]
    if not grain_maps:  # the albedo map replaces the grains: the plugin takes one or the other
        settings = {k: v for k, v in settings.items() if k not in MAP_GRAIN_SETTINGS}
    maps = "".join(_indented(_bitmap_xml(name, f"{name}.exr")) for name in sorted(result.maps))
    albedo = "" if grain_maps else _indented(_bitmap_xml("albedo", "albedo.exr"))
    r = float(np.median(result.light_distance))
    if math.isinf(r):
        emitter, defaults = _DISTANT
    else:  # the defaults: a light of gain 1 at the zenith
        sw = 2.0 * w / h
        position, intensity = point_lights(LightRig(np.array([[0.0, 0.0, 1.0]]), r), sw)
        emitter = _NEAR[0].format(r=r, sw=sw)
        defaults = _NEAR[1].format(pz=float(position[0, 2]), intensity=float(intensity[0]))
    integrator, shape = _RELIEF if relief else _FLAT
    props = _property_xml(settings)
    if relief:  # one level less deep than in the normal map
        albedo, maps = _dedented(albedo), _dedented(maps)
        props = _dedented(props + "\n").rstrip("\n")
    shape = shape.format(aspect=w / h, normalmap=_bitmap_xml("normalmap", NORMAL_TANGENT),
                         albedo=albedo, maps=maps, props=props, ply=RELIEF_PLY)
    top = 0.0 if not relief else float(np.max(result.relief.height)) * 2.0 / h
    return _SCENE.format(w=w, h=h, aspect=w / h, emitter=emitter, defaults=defaults,
                         integrator=integrator, shape=shape, camera_z=2.0 + max(top, 0.0))


def _dedented(xml: str) -> str:
    """``xml`` indented by one level less."""
    return "".join(line[4:] + "\n" for line in xml.splitlines())


def maps_files(map_names, relief: bool = False) -> list[str]:
    """The files :func:`write_maps` writes for maps of these property names (and a
    relief)."""
    return ([f"{name}.exr" for name in map_names]
            + ["albedo.exr", "normal.exr", NORMAL_TANGENT, "residual.exr", "mask.exr",
               "scene.xml", "fit.json"]
            + ([RELIEF_EXR, RELIEF_PLY, FLAT_SCENE] if relief else []))


def write_maps(result: MapsResult, out_dir: str | Path, capture: Capture | None = None,
               light_names: list[str] | None = None, pixel_size: float | None = None) -> Path:
    """Write a fit to ``out_dir`` (module docstring); returns the path of ``fit.json``.

    Args:
        result: a :func:`mitsuba_powder.rti.fit_maps` result.
        out_dir: output folder (created).
        capture: the fitted capture (its encoding, bit depth and file format are recorded, so
            that :func:`relight_files` writes matching images).
        light_names: the capture's image names, in the order of ``result.gains``.
        pixel_size: the size of a pixel in the unit of the ``.lp`` light positions (recorded
            so that :func:`relight_files` can read a positions ``.lp``).
    """
    out = Path(out_dir)
    # every output checked before anything is written
    relief = result.relief is not None
    target = {name: output_path(out, name) for name in maps_files(result.maps, relief)}
    _write_map_files(result, target)
    settings = {k: v for k, v in result.settings.items()
                if isinstance(v, (str, int, float)) and not isinstance(v, bool)}
    target["scene.xml"].write_text(scene_xml(result, settings))
    if relief:
        _write_exr(target[RELIEF_EXR], result.relief.height)
        write_relief_ply(target[RELIEF_PLY], result.relief.height, result.as_maps()["normal"])
        target[FLAT_SCENE].write_text(scene_xml(result, settings, relief=False))
    info = _fit_info(result, settings, capture, light_names, pixel_size)
    path = target["fit.json"]
    path.write_text(json.dumps(info, indent=1, default=_json_default))
    return path


def _write_map_files(result: MapsResult, target: dict[str, Path]) -> None:
    """The EXR maps of :func:`write_maps` (``target``: file name -> path)."""
    maps = result.as_maps()
    for name in result.maps:
        _write_exr(target[f"{name}.exr"], np.asarray(maps[name], dtype=np.float32))
    # the albedo per channel (with a grain-size map: the grains', for reading only)
    _write_exr(target["albedo.exr"], np.clip(np.where(result.mask[..., None], result.albedo,
                                                      0.0), 0.0, 1.0))
    normals = np.asarray(maps["normal"], dtype=np.float32)
    _write_exr(target["normal.exr"], normals)
    _write_exr(target[NORMAL_TANGENT], 0.5 * (normals + 1.0))
    _write_exr(target["residual.exr"], result.residual_rms)
    _write_exr(target["mask.exr"], result.mask.astype(np.float32))


def _fit_info(result: MapsResult, settings: dict, capture: Capture | None,
              light_names: list[str] | None, pixel_size: float | None) -> dict:
    """The contents of ``fit.json`` (module docstring)."""
    mask = result.mask
    return {
        "kind": "mitsuba-powder maps",
        "size": {"height": int(mask.shape[0]), "width": int(mask.shape[1])},
        "free": list(result.free),
        "parameters_per_pixel": result.n_parameters,
        "maps": sorted(result.maps),
        "settings": settings,
        "variant": result.variant,
        "gains": [float(g) for g in result.gains],
        "exposure": float(result.exposure),
        "lights": light_names,
        "capture": None if capture is None else {
            "encoding": capture.encoding, "bit_depth": capture.bit_depth,
            "file_format": capture.file_format,
            "lp": None if capture.lp_path is None else str(capture.lp_path)},
        "statistics": {**{name: _stats(v[mask]) for name, v in result.maps.items()},
                       **{f"albedo[{c}]": _stats(result.albedo[..., c][mask])
                          for c in range(3)},
                       "residual_rms": _stats(result.residual_rms[mask])},
        "used_observations": float(result.used[:, mask].mean()) if mask.any() else 0.0,
        "fit": result.fit_settings,
        "light_rig": {
            "model": "distant" if np.all(np.isinf(result.light_distance)) else "near",
            "distance": distance_to_json(result.light_distance),
            "distance_source": result.fit_settings.get("light_distance_source", "distant"),
            "pixel_size": pixel_size,
            "units": "distance in image widths from the image's centre (null: distant); "
                     "pixel_size in the .lp positions' unit per pixel"},
        "gain_model": None if result.gain_model is None else result.gain_model.to_dict(),
        "relief": None if result.relief is None else {
            "height": RELIEF_EXR, "mesh": RELIEF_PLY, "flat_scene": FLAT_SCENE,
            "units": "pixels (a pixel's width; times pixel_size: the .lp positions' unit)",
            "light_size_deg": result.relief.light_radius_deg,
            "azimuths": int(result.relief.horizon.shape[2])},
    }


def _json_default(value):
    if isinstance(value, np.generic):
        return value.item()
    if isinstance(value, np.ndarray):
        return value.tolist()
    raise TypeError(f"not JSON serialisable: {type(value).__name__}")


def read_maps(maps_dir: str | Path) -> tuple[MapsResult, dict]:
    """A maps folder written by :func:`write_maps`: the result (enough to relight) and the
    contents of ``fit.json``.

    Raises:
        FileNotFoundError: the folder lacks ``fit.json`` or a map it lists.
        ValueError: ``fit.json`` is not a maps description.
    """
    folder = Path(maps_dir)
    check_complete(folder)
    path = folder / "fit.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no such file; give a folder written by fit-maps")
    note_inputs(p for p in folder.iterdir() if p.is_file())  # the whole maps folder is input
    info = read_json(path, "maps description")
    if not isinstance(info, dict) or info.get("kind") != "mitsuba-powder maps":
        kind = info.get("kind") if isinstance(info, dict) else type(info).__name__
        raise ValueError(f"{path}: not a fit-maps result (kind = {kind!r})")
    mask = _read_exr(folder / "mask.exr") > 0.5
    result = MapsResult(
        normals=_read_exr(folder / "normal.exr"),
        albedo=_read_exr(folder / "albedo.exr"),
        maps={name: _read_exr(folder / f"{name}.exr") for name in info["maps"]},
        settings=dict(info["settings"]),
        residual_rms=_read_exr(folder / "residual.exr"),
        gains=np.asarray(info["gains"], dtype=np.float64),
        used=np.zeros((0,) + mask.shape, dtype=bool),
        free=list(info["free"]),
        mask=mask,
        variant=info.get("variant", "llvm_ad_rgb"),
        fit_settings=info.get("fit", {}),
        light_distance=distance_from_json((info.get("light_rig") or {}).get("distance")),
        gain_model=(GainModel.from_dict(info["gain_model"]) if info.get("gain_model")
                    else None),
        exposure=float(info.get("exposure", 1.0)),
        relief=_read_relief(folder, info.get("relief")),
    )
    return result, info


def _read_relief(folder: Path, info: dict | None) -> Relief | None:
    """The relief of a maps folder (its horizon map computed again), or None."""
    if not info:
        return None
    height = _read_exr(folder / info["height"]).astype(np.float64)
    return Relief(height, horizon_map(height, int(info["azimuths"])),
                  float(info["light_size_deg"]))


def write_relief_ply(path: Path, height: np.ndarray, normals: np.ndarray) -> None:
    """The relief's mesh as a binary PLY in the scene's units (module docstring): a vertex at
    each pixel's centre (x right, y up, the height; ``2 / H`` scene units a pixel) with its
    fitted normal and the maps' UV (``u = (j + 1/2) / W``, ``v = 1 - (i + 1/2) / H``, as the
    rectangle's), and a ring of vertices on the image's edges repeating their neighbour's
    height and normal, so that the mesh covers the image; two triangles per quad."""
    h, w = height.shape
    unit = 2.0 / h
    cols = np.concatenate([[0.0], np.arange(w) + 0.5, [float(w)]])
    rows = np.concatenate([[0.0], np.arange(h) + 0.5, [float(h)]])
    ci = np.concatenate([[0], np.arange(w), [w - 1]])
    ri = np.concatenate([[0], np.arange(h), [h - 1]])
    cc, rr = np.meshgrid(cols, rows)
    pick = np.ix_(ri, ci)
    n = np.asarray(normals, dtype=np.float64)[pick]
    vertex = np.zeros(cc.shape, dtype=[(c, "<f4") for c in ("x", "y", "z", "nx", "ny", "nz",
                                                             "u", "v")])
    vertex["x"], vertex["y"] = (cc - w / 2) * unit, (h / 2 - rr) * unit
    vertex["z"] = np.asarray(height, dtype=np.float64)[pick] * unit
    vertex["nx"], vertex["ny"], vertex["nz"] = n[..., 0], n[..., 1], n[..., 2]
    vertex["u"], vertex["v"] = cc / w, 1.0 - rr / h
    nr, nc = cc.shape
    idx = np.arange(nr * nc).reshape(nr, nc)
    a, b = idx[:-1, :-1].ravel(), idx[:-1, 1:].ravel()
    c, d = idx[1:, :-1].ravel(), idx[1:, 1:].ravel()
    faces = np.zeros(2 * len(a), dtype=[("n", "u1"), ("i", "<i4", (3,))])
    faces["n"] = 3
    # counter-clockwise seen from the camera (+z): rows go down the image
    faces["i"][0::2] = np.stack([a, c, b], axis=1)
    faces["i"][1::2] = np.stack([b, c, d], axis=1)
    header = ("ply\nformat binary_little_endian 1.0\ncomment mitsuba-powder relief\n"
              f"element vertex {nr * nc}\n"
              + "".join(f"property float {c}\n" for c in ("x", "y", "z", "nx", "ny", "nz",
                                                          "u", "v"))
              + f"element face {len(faces)}\nproperty list uchar int vertex_indices\n"
              "end_header\n")
    with open(path, "wb") as f:
        f.write(header.encode("ascii"))
        f.write(vertex.ravel().tobytes())
        f.write(faces.tobytes())


def relight_files(maps_dir: str | Path, lights_lp: str | Path, out_dir: str | Path,
                  pixel_size: float | None = None,
                  light_distance: float | None = None, shadows: bool | None = None,
                  render: dict | None = None) -> list[Path]:
    """One predicted image per line of ``lights_lp``, with the fitted capture's encoding and
    bit depth (PNG 8 bit sRGB when the capture is not recorded), written under ``out_dir`` only.

    The images are named as the ``.lp`` file names them, reduced to their base name when a name
    is absolute or has ``..`` (dome software writes absolute paths); an ``.lp`` file of the
    written names goes beside them. Nothing is written over the maps, the ``.lp`` file or the
    photographs it names (:func:`mitsuba_powder.rti.write_images`).

    The ``.lp`` vectors are directions (at the fit's light distance unless ``light_distance``
    is given, image widths), or, when a pixel size is known (``pixel_size``, default the fit's),
    directions if all are unit and light positions (each its own distance) if none is; the
    gains are the fit's gain model's. The images are the per-pixel model's, shaded by the
    fit's relief (``shadows``: default when the fit was made with it, fit.json's
    ``fit.shadows == "relief"``: ``shadows="relief"``, or ``"auto"`` where it chose the
    relief), or, with ``render``
    (``spp``, ``variant``: :func:`mitsuba_powder.rti.rendered.render_maps`), the folder's
    ``scene.xml`` path traced under each light.

    Returns:
        The paths written.
    """
    with guarding_inputs(lights_lp):
        result, info = read_maps(maps_dir)
        size = pixel_size if pixel_size is not None else (
            (info.get("light_rig") or {}).get("pixel_size"))
        width = result.mask.shape[1]
        fit_r = result.light_distance if np.ndim(result.light_distance) == 0 else math.inf
        r = fit_r if light_distance is None else light_distance
        # without the positions' unit the vectors are directions (normalised), as always
        names, rig, kind = read_lp_rig(lights_lp, "auto" if size is not None else "directions",
                                       None if size is None else size * width)
        if kind == "directions":
            rig = rig.with_distance(r)
        if render is None:
            images = result.predict(rig.directions, light_distance=rig.distance,
                                    shadows=shadows)
        else:
            from .rendered import render_maps

            images = render_maps(maps_dir, result, rig.directions,
                                 light_distance=rig.distance, **render)
        cap = info.get("capture") or {"encoding": "srgb", "bit_depth": 8, "file_format": "png"}
        like = Capture(images=np.zeros((0, 1, 1, 3), np.float32), directions=rig.directions,
                       names=list(names), encoding=cap["encoding"],
                       file_format=cap["file_format"], bit_depth=int(cap["bit_depth"]))
        return write_images(like, images, lights_lp, out_dir)
