"""Reflectance Transformation Imaging (RTI): captures, per-pixel powder maps, baselines.

Modules, one job each, in the order a fit passes them:

* :mod:`~mitsuba_powder.rti.capture`: ``.lp`` files and their images, read and written;
* :mod:`~mitsuba_powder.rti.lights`: dome lights at a finite distance;
* :mod:`~mitsuba_powder.rti.options`: the fit's options, checked once (:class:`FitOptions`);
* :mod:`~mitsuba_powder.rti.inputs`: the capture checked once against them, and the data of a
  set of its pixels;
* :mod:`~mitsuba_powder.rti.plan`: the fit's stages (distance scan, gain subsample, blocks),
  run by small named steps;
* :mod:`~mitsuba_powder.rti.pixelfit`: the fit of one set of pixels (start, rounds, maps);
* :mod:`~mitsuba_powder.rti.solvers`: the per-pixel solvers behind one interface
  (:mod:`~mitsuba_powder.rti.engine`, Dr.Jit, the default; :mod:`~mitsuba_powder.rti.problem`,
  NumPy, the reference), on one data holder (:mod:`~mitsuba_powder.rti.pixels`);
* :mod:`~mitsuba_powder.rti.gains`: the per-light gains: how they are found, their step in
  the alternation, their trend in the light direction;
* :mod:`~mitsuba_powder.rti.properties`: what may vary per pixel, bounds and valid ranges (the
  plugin's), the albedo of per-pixel grain sizes;
* :mod:`~mitsuba_powder.rti.forward`: the per-pixel forward model (:func:`render_capture`);
* :mod:`~mitsuba_powder.rti.starts`: Lambertian photometric stereo and the grain-size search;
* :mod:`~mitsuba_powder.rti.distance`: the scan and polish of the light distance;
* :mod:`~mitsuba_powder.rti.blocks`: pixels in blocks within a memory budget;
* :mod:`~mitsuba_powder.rti.fit`: :func:`fit_maps` (the public API) and what a dome of
  lights determines;
* :mod:`~mitsuba_powder.rti.result`: :class:`MapsResult` and :func:`relight`;
* :mod:`~mitsuba_powder.rti.tiles`: :func:`~mitsuba_powder.rti.tiles.fit_maps_tiled`, the fit
  in tiles on a Dask cluster (:mod:`~mitsuba_powder.rti.cluster`; the tiles on disk:
  :mod:`~mitsuba_powder.rti.tile_files`), imported from there (not here: importing this
  package does not import Dask);
* :mod:`~mitsuba_powder.rti.synthetic`: SYNTHETIC captures of known maps;
* :mod:`~mitsuba_powder.rti.maps`: fitted maps on disk (EXR, ``fit.json``, a scene);
* :mod:`~mitsuba_powder.rti.baselines`: PTM, HSH and Lambertian per-pixel baselines;
* :mod:`~mitsuba_powder.rti.comparison`: the held-out-light comparison of models.

The names of the capture, the forward model, the fit, relighting and synthetic captures are
importable from here (``from mitsuba_powder.rti import Capture, read_lp, fit_maps``).
"""

from __future__ import annotations

from .capture import (
    ENCODINGS,
    MIN_LZ_DEFAULT,
    Capture,
    decode,
    encode,
    load_capture,
    lp_image_paths,
    read_image,
    read_lp,
    read_mask,
    write_images,
    write_lp,
)
from .fit import GAIN_MODES, GAIN_PIXELS, SOLVERS, fit_maps, max_correlation_length
from .forward import MAX_LANES, VARIANT, render_capture
from .gains import GainPolicy, GainTrend
from .options import FitOptions, fit_options
from .properties import (
    FREE_PROPERTIES,
    GRAIN_MAPS,
    MAP_DEFAULT_FREE,
    MAP_GRAIN_SETTINGS,
    MAP_PROPERTIES,
    SLOPE_LIMIT,
    SPECS,
    GrainAlbedo,
    grain_map_name,
)
from .result import MapsResult, relight
from .starts import START_EXTINCTIONS, START_SIZES, lambertian_start
from .synthetic import (
    SYNTHETIC_GRAIN_REGIONS,
    SYNTHETIC_REGION_SETS,
    SYNTHETIC_REGIONS,
    dome_directions,
    synthetic_capture,
    synthetic_maps,
)

__all__ = [
    # capture
    "Capture", "ENCODINGS", "MIN_LZ_DEFAULT", "decode", "encode", "load_capture",
    "lp_image_paths", "read_image", "read_lp", "read_mask", "write_images", "write_lp",
    # per-pixel properties
    "FREE_PROPERTIES", "GRAIN_MAPS", "GrainAlbedo", "MAP_DEFAULT_FREE", "MAP_GRAIN_SETTINGS",
    "MAP_PROPERTIES", "SLOPE_LIMIT", "SPECS", "grain_map_name",
    # forward model, starts, fit, result
    "MAX_LANES", "VARIANT", "render_capture", "START_EXTINCTIONS", "START_SIZES",
    "lambertian_start", "GAIN_MODES", "GAIN_PIXELS", "SOLVERS", "FitOptions", "GainPolicy",
    "GainTrend", "fit_maps", "fit_options", "max_correlation_length", "MapsResult", "relight",
    # synthetic captures
    "SYNTHETIC_GRAIN_REGIONS", "SYNTHETIC_REGIONS", "SYNTHETIC_REGION_SETS", "dome_directions",
    "synthetic_capture", "synthetic_maps",
]
