"""Per-pixel powder maps of captures larger than one machine: :func:`fit_maps_tiled`.

The capture is cut into square tiles of ``tile_size`` pixels (the last row and column of
tiles smaller); each tile is an independent :func:`mitsuba_powder.rti.fit_maps` run, scheduled
on a Dask cluster (:mod:`mitsuba_powder.rti.cluster`: a local cluster by default, or an
existing one by its scheduler's address), and the tiles are put back together into one
:class:`~mitsuba_powder.rti.result.MapsResult`, the one :func:`fit_maps` returns.

**Gains are held.** Per-light gains are shared by all pixels, so tiles fitted independently
would each find their own. They are therefore fitted first, once, on a subsample of the whole
capture: ``gain_pixels`` pixels drawn at random (``seed``) among the masked pixels, fitted by
:func:`fit_maps` with ``gains="fit"`` (the same model, rounds and options as the tiles); every
tile is then fitted with these gains held (``gains="fixed"``). With ``gains="fixed"`` the
given ``initial_gains`` (default 1) are held and no subsample is fitted. A pixel's fit depends
only on its own observations once the gains are held, so a tiled fit equals an untiled one
under the same gains.

**Workers read the images.** Tasks carry the image paths and the tile's window, never image
arrays: each tile's worker decodes the K images (the whole file: PNG and JPEG cannot be
decoded in part) and keeps its window, so the images must be at the same path on every
worker (a shared folder). Decoding costs one read of every image per tile: larger tiles
read less often.

**Tiles on disk, resume.** Each finished tile is written by the submitting process as it
arrives to ``out_dir/tiles/tile_r<row>_c<col>.npz`` (a temporary file renamed into place: a
tile file is whole or absent), with a hash of every setting that shapes it (the capture's
files, names, sizes and modification times, the mask, the fit options, the held gains, the
tile size). A run interrupted (or a worker lost: Dask re-runs its tile elsewhere) loses at
most the tiles in flight; ``resume=True`` keeps the tiles whose hash matches and refuses,
with an error, tiles written with other settings. The held gains are kept likewise in
``out_dir/tiles/gains.npz``. The maps are always assembled from the tile files, so a resumed
run gives the same maps, bit for bit, as an uninterrupted one.
"""

from __future__ import annotations

import hashlib
import inspect
import json
import math
import os
import time
import uuid
from collections.abc import Callable, Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..outputs import note_inputs, output_path
from .blocks import GAIN_PIXELS, gain_sample
from .capture import Capture, lp_image_paths, read_image_window, read_lp, read_mask
from .checks import check_count, check_gains
from .cluster import open_client, worker_threads
from .fit import GAIN_MODES, fit_maps
from .forward import VARIANT
from .maps import _json_default
from .result import MapsResult

__all__ = ["GAIN_PIXELS", "TILE_SIZE_MIN", "TILES_FOLDER", "Tile", "check_gain_pixels",
           "check_tile_size", "fit_maps_tiled", "plan_tiles"]

#: Smallest tile side (pixels)
TILE_SIZE_MIN = 8
#: The folder of tile files under the output folder
TILES_FOLDER = "tiles"
#: The gains' file in :data:`TILES_FOLDER`
GAINS_FILE = "gains.npz"
#: What every tile and gains file says it is
_KIND = "mitsuba-powder tile"
#: fit_maps arguments a tiled fit sets itself
_OWN = ("images", "directions", "mask", "gains", "initial_gains", "progress")


@dataclass(frozen=True)
class Tile:
    """A window of the capture: rows ``row0:row1``, columns ``col0:col1`` (pixels, end
    exclusive); ``row``, ``col``: its place in the grid of tiles."""

    row: int
    col: int
    row0: int
    row1: int
    col0: int
    col1: int

    @property
    def window(self) -> tuple[int, int, int, int]:
        """``(row0, row1, col0, col1)``."""
        return self.row0, self.row1, self.col0, self.col1

    @property
    def name(self) -> str:
        """The tile's file name under :data:`TILES_FOLDER`."""
        return f"tile_r{self.row:04d}_c{self.col:04d}.npz"


def check_tile_size(value, name: str = "tile_size") -> int:
    """A tile side in pixels: a whole number >= :data:`TILE_SIZE_MIN`."""
    if isinstance(value, bool):
        raise ValueError(f"{name} = {value!r} is not a whole number; valid range is "
                         f"[{TILE_SIZE_MIN}, inf] pixels")
    return check_count(name, value, TILE_SIZE_MIN)


def check_gain_pixels(value, name: str = "gain_pixels") -> int:
    """Pixels the gains are fitted on: a whole number >= 1."""
    if isinstance(value, bool):
        raise ValueError(f"{name} = {value!r} is not a whole number; valid range is [1, inf]")
    return check_count(name, value, 1)


def plan_tiles(shape: tuple[int, int], tile_size: int) -> list[Tile]:
    """The tiles of an (H, W) image, row by row; tiles of the last row and column are cut at
    the image's edge."""
    size = check_tile_size(tile_size)
    h, w = shape
    return [Tile(r, c, r0, min(r0 + size, h), c0, min(c0 + size, w))
            for r, r0 in enumerate(range(0, h, size)) for c, c0 in enumerate(range(0, w, size))]


# ---------------------------------------------------------------------------
#  Settings and their hash
# ---------------------------------------------------------------------------

def _digest(value) -> str:
    """A stable text of ``value`` for hashing (arrays by their bytes, shape and type)."""
    if isinstance(value, np.ndarray) or (np.ndim(value) > 0 and not isinstance(value, str)):
        a = np.ascontiguousarray(value)
        return f"array{a.shape}{a.dtype}:{hashlib.sha256(a.tobytes()).hexdigest()}"
    if isinstance(value, Mapping):
        return "{" + ",".join(f"{k!r}:{_digest(v)}" for k, v in sorted(value.items())) + "}"
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(_digest(v) for v in value) + "]"
    if isinstance(value, np.generic):
        value = value.item()
    return repr(value)


def _hash(value) -> str:
    return hashlib.sha256(_digest(value).encode()).hexdigest()


@dataclass
class _Plan:
    """The capture as the workers read it, and the settings of the fit."""

    lp: Path
    paths: list[str]           # absolute image paths, in .lp order
    names: list[str]
    directions: np.ndarray     # (K, 3)
    encoding: str
    mask_source: object        # the ``mask`` argument (a path, an array or None)
    options: dict              # fit_maps options besides those in _OWN
    gain_mode: str
    initial_gains: np.ndarray | None
    gain_pixels: int
    seed: int

    def capture_key(self) -> dict:
        """What identifies the capture's files (paths, sizes, modification times)."""
        stats = [os.stat(p) for p in self.paths]
        return {"lp": str(self.lp), "names": self.names, "directions": self.directions,
                "encoding": self.encoding, "sizes": [s.st_size for s in stats],
                "mtimes": [s.st_mtime_ns for s in stats]}


def _plan(capture, encoding: str, mask, options: Mapping, gains: str, initial_gains,
          gain_pixels: int, seed: int) -> _Plan:
    """Check the arguments of :func:`fit_maps_tiled` that need no image, and read the .lp."""
    if isinstance(capture, Capture):
        if capture.lp_path is None:
            raise ValueError("capture has no .lp file (lp_path is None): the workers read the "
                             "images from disk; write it with write_lp and write_images")
        encoding = capture.encoding
        mask = capture.mask if mask is None else mask
        capture = capture.lp_path
    lp = Path(capture).expanduser().resolve()
    names, directions = read_lp(lp)
    paths = [str(p.resolve()) for p in lp_image_paths(lp, names)]
    note_inputs(paths)  # nothing is written over the photographs
    for name, path in zip(names, paths):
        if not Path(path).is_file():
            raise FileNotFoundError(f"{lp}: image {name!r} not found (looked for {path})")
    allowed = set(inspect.signature(fit_maps).parameters) - set(_OWN)
    unknown = sorted(set(options) - allowed)
    if unknown:
        raise ValueError(f"fit option(s) {unknown} are not fit_maps options; valid are "
                         f"{sorted(allowed)}")
    if gains not in GAIN_MODES:
        raise ValueError(f"gains = {gains!r} is not a gain mode; choose one of {GAIN_MODES}")
    distance = options.get("light_distance", math.inf)
    if not (isinstance(distance, (int, float)) and math.isinf(distance)):
        # a tile (and the gains' pixel sample) is fitted as an image of its own, whose pixel
        # positions are not those of the whole image that near-field lights depend on
        raise ValueError(f"light_distance = {distance!r} is not supported by tiled fits; valid "
                         "value: inf (distant lights); fit near-field lights untiled")
    if initial_gains is not None:
        initial_gains = check_gains(initial_gains, len(names))
    return _Plan(lp, paths, list(names), directions, encoding, mask, dict(options), gains,
                 initial_gains, check_gain_pixels(gain_pixels),
                 check_count("seed", seed, 0))


# ---------------------------------------------------------------------------
#  Worker tasks
# ---------------------------------------------------------------------------

def _prepare_worker(variant: str) -> None:
    """Select ``variant`` for the worker's process (a fit inside a variant already selected
    skips the plugin's registration, about 1 s per fit), and run Dr.Jit on as many threads
    as the calling Dask worker has, but at least two: with a pool of one thread the
    plugin's evaluation waits on itself (Dr.Jit 1.5 hangs)."""
    import drjit as dr
    import mitsuba as mi

    from ..variants import set_variant

    if mi.variant() != variant:
        set_variant(variant)
    n = worker_threads()
    if n and dr.thread_count() != max(n, 2):
        dr.set_thread_count(max(n, 2))


def _survey(path: str, encoding: str, flat: np.ndarray | None = None) -> dict:
    """An image's size, format and bit depth, and its values at the flat pixel indices
    ``flat`` (float32 (N, C)) when given."""
    values, file_format, depth, shape = read_image_window(path, encoding)
    samples = None if flat is None else values.reshape(-1, values.shape[2])[flat]
    return {"shape": shape + (int(values.shape[2]),), "format": file_format, "depth": depth,
            "samples": samples}


def _check_surveys(surveys: list[dict], names: list[str], lp: Path) -> None:
    """Every image of one size, channel count, format and bit depth (RGB)."""
    first = surveys[0]
    for name, s in zip(names, surveys):
        if (s["shape"], s["format"], s["depth"]) != (first["shape"], first["format"],
                                                     first["depth"]):
            h, w, c = s["shape"]
            h0, w0, c0 = first["shape"]
            raise ValueError(f"{lp}: image {name!r} is {w} x {h} px, {c} channels, "
                             f"{s['format']} {s['depth']} bit; expected {w0} x {h0} px, {c0} "
                             f"channels, {first['format']} {first['depth']} bit as "
                             f"{names[0]!r}")
    if first["shape"][2] != 3:
        raise ValueError(f"{lp}: the images have {first['shape'][2]} channel(s); the fit needs "
                         "RGB (3)")


def _sampled_fixed(fixed: Mapping | None, shape: tuple[int, int], flat: np.ndarray) -> dict:
    """``fixed`` with its per-pixel maps (leading shape (H, W)) at the flat pixels ``flat``,
    as (1, N, ...) maps."""
    out = {}
    for name, value in (fixed or {}).items():
        if np.ndim(value) >= 2 and np.shape(value)[:2] == shape:
            v = np.asarray(value)
            out[name] = v.reshape((-1,) + v.shape[2:])[flat][None]
        else:
            out[name] = value
    return out


def _window_fixed(fixed: Mapping | None, shape: tuple[int, int], tile: Tile) -> dict:
    """``fixed`` with its per-pixel maps (leading shape (H, W)) cut to the tile."""
    r0, r1, c0, c1 = tile.window
    return {name: np.asarray(v)[r0:r1, c0:c1]
            if np.ndim(v) >= 2 and np.shape(v)[:2] == shape else v
            for name, v in (fixed or {}).items()}


def _fit_gains(surveys: list[dict], directions: np.ndarray, options: Mapping,
               initial_gains: np.ndarray | None) -> dict:
    """The gains fitted on the sampled pixels (a worker task): ``gains`` (K,), ``stages``."""
    _prepare_worker(options.get("variant", VARIANT))
    images = np.stack([s["samples"] for s in surveys])[:, None]  # (K, 1, N, 3)
    result = fit_maps(images, directions, gains="fit", initial_gains=initial_gains,
                      gain_pixels=None, **options)
    return {"gains": result.gains, "stages": result.fit_settings.get("stages", [])}


def _fit_tile(paths: list[str], encoding: str, tile: Tile, shape: tuple[int, int],
              mask: np.ndarray, directions: np.ndarray, gains: np.ndarray, options: Mapping,
              settings_hash: str) -> dict[str, np.ndarray]:
    """Fit one tile (a worker task): its images' window read from ``paths``, the gains held;
    returns the tile file's arrays (:func:`_tile_arrays`)."""
    _prepare_worker(options.get("variant", VARIANT))
    images = []
    for path in paths:
        values, _, _, full = read_image_window(path, encoding, tile.window)
        if full != shape:
            raise ValueError(f"image {path}: {full[1]} x {full[0]} px; expected {shape[1]} x "
                             f"{shape[0]} px as the capture's first image")
        images.append(values)
    fixed = _window_fixed(options.get("fixed"), shape, tile)
    result = fit_maps(np.stack(images), directions, mask=mask, gains="fixed",
                      initial_gains=gains, **{**options, "fixed": fixed})
    return _tile_arrays(result, tile, settings_hash)


# ---------------------------------------------------------------------------
#  Tile files
# ---------------------------------------------------------------------------

def _meta_array(meta: dict) -> np.ndarray:
    return np.array(json.dumps(meta, default=_json_default))


def _tile_arrays(result: MapsResult | None, tile: Tile, settings_hash: str,
                 lights: int = 0) -> dict[str, np.ndarray]:
    """A tile file's arrays: the result's maps (``map_<name>``), ``normals``, ``albedo``,
    ``residual_rms``, ``used``, ``mask`` and ``meta`` (JSON: the hash, the window, the
    settings and the fit's diagnostics); ``result`` None: a tile with no masked pixel."""
    h, w = tile.row1 - tile.row0, tile.col1 - tile.col0
    meta = {"kind": _KIND, "settings_hash": settings_hash, "window": list(tile.window),
            "empty": result is None}
    if result is None:
        nan = np.full((h, w, 3), np.nan, np.float32)
        return {"meta": _meta_array(meta), "normals": nan, "albedo": nan,
                "residual_rms": nan[..., 0], "used": np.zeros((lights, h, w), bool),
                "mask": np.zeros((h, w), bool)}
    meta.update(free=result.free, settings=result.settings, variant=result.variant,
                fit_settings=result.fit_settings)
    arrays = {"meta": _meta_array(meta), "normals": result.normals, "albedo": result.albedo,
              "residual_rms": result.residual_rms, "used": result.used, "mask": result.mask}
    arrays.update({f"map_{name}": v for name, v in result.maps.items()})
    return arrays


def _write_atomic(out: Path, name: str, arrays: Mapping[str, np.ndarray]) -> Path:
    """Write ``arrays`` to ``out/TILES_FOLDER/name`` (.npz) through a temporary file renamed
    into place: the file is whole or absent."""
    final = output_path(out, f"{TILES_FOLDER}/{name}")
    part = output_path(out, f"{TILES_FOLDER}/.{name}.{uuid.uuid4().hex[:8]}.part")
    try:
        with open(part, "wb") as f:
            np.savez(f, **arrays)
            f.flush()
            os.fsync(f.fileno())
        os.replace(part, final)
    finally:
        part.unlink(missing_ok=True)
    return final


def _read_meta(path: Path) -> dict | None:
    """A tile or gains file's meta (None when the file is absent or unreadable)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            meta = json.loads(str(f["meta"]))
    except (OSError, ValueError, KeyError):
        return None
    return meta if meta.get("kind") == _KIND else None


def _refuse(path: Path, expected: str, found: str) -> ValueError:
    return ValueError(f"resume: {path} was written with other settings (settings hash "
                      f"{found[:12]}, this run's {expected[:12]}: another capture, mask, fit "
                      "option, gains or tile size); rerun without resume to fit every tile "
                      "again, or give another output folder")


def _finished(out: Path, tiles: Iterable[Tile], settings_hash: str) -> set[Tile]:
    """The tiles whose file exists with this run's settings; a file of other settings is an
    error (:func:`_refuse`)."""
    done = set()
    for tile in tiles:
        path = out / TILES_FOLDER / tile.name
        if not path.exists():
            continue
        meta = _read_meta(path)
        if meta is None:
            continue  # not a whole tile file: fitted again
        if meta.get("settings_hash") != settings_hash or meta.get("window") != list(
                tile.window):
            raise _refuse(path, settings_hash, str(meta.get("settings_hash")))
        done.add(tile)
    return done


# ---------------------------------------------------------------------------
#  Gains, tiles, assembly
# ---------------------------------------------------------------------------

def _mask(plan: _Plan, shape: tuple[int, int]) -> np.ndarray:
    """The pixels to fit, bool (H, W)."""
    m = plan.mask_source
    if m is None:
        return np.ones(shape, bool)
    if isinstance(m, np.ndarray):
        if m.shape != shape:
            raise ValueError(f"mask of shape {m.shape}: expected {shape} as the images")
        if not m.any():
            raise ValueError("mask selects no pixel; it needs at least one True")
        return m.astype(bool)
    return read_mask(m, shape)


def _held_gains(client, plan: _Plan, out: Path, shape: tuple[int, int], mask: np.ndarray,
                key: str, resume: bool, log: Callable[[str], None]) -> np.ndarray:
    """The gains every tile holds: ``initial_gains`` (mode ``fixed``), or those fitted on
    ``gain_pixels`` masked pixels (read back from ``gains.npz`` on resume)."""
    k = len(plan.paths)
    if plan.gain_mode == "fixed":
        return check_gains(plan.initial_gains, k)
    path = out / TILES_FOLDER / GAINS_FILE
    if resume and path.exists():
        meta = _read_meta(path)
        if meta is not None and meta.get("settings_hash") != key:
            raise _refuse(path, key, str(meta.get("settings_hash")))
        if meta is not None:
            with np.load(path, allow_pickle=False) as f:
                gains = np.array(f["gains"])
            log(f"gains: read from {path}")
            return gains
    flat = gain_sample(mask, plan.gain_pixels, plan.seed)
    options = {**plan.options, "fixed": _sampled_fixed(plan.options.get("fixed"), shape, flat)}
    surveys = [client.submit(_survey, p, plan.encoding, flat, pure=False) for p in plan.paths]
    _check_surveys(client.gather(surveys), plan.names, plan.lp)
    fitted = client.submit(_fit_gains, surveys, plan.directions, options, plan.initial_gains,
                           pure=False).result()
    meta = {"kind": _KIND, "settings_hash": key, "pixels": len(flat), "seed": plan.seed,
            "stages": fitted["stages"]}
    _write_atomic(out, GAINS_FILE, {"meta": _meta_array(meta), "gains": fitted["gains"]})
    log(f"gains: fitted on {len(flat)} pixels of the whole capture, held in every tile "
        f"(range {np.min(fitted['gains']):.4g}-{np.max(fitted['gains']):.4g})")
    return np.asarray(fitted["gains"])


def _run_tiles(client, plan: _Plan, out: Path, todo: list[Tile], shape: tuple[int, int],
               mask: np.ndarray, gains: np.ndarray, settings_hash: str, bar,
               on_tile: Callable[[str, int, int], None] | None, total: int) -> int:
    """Fit the tiles ``todo`` on the cluster, writing each as it arrives; returns the count.
    Tiles still queued are cancelled when this stops (an error or an interrupt)."""
    from distributed import as_completed

    futures = {}
    for tile in todo:
        r0, r1, c0, c1 = tile.window
        fut = client.submit(_fit_tile, plan.paths, plan.encoding, tile, shape,
                            mask[r0:r1, c0:c1], plan.directions, gains, plan.options,
                            settings_hash, key=f"fit-tile-r{tile.row}-c{tile.col}-"
                            f"{uuid.uuid4().hex[:8]}")
        futures[fut] = tile
    fitted = 0
    try:
        for fut in as_completed(futures):
            tile = futures[fut]
            _write_atomic(out, tile.name, fut.result())
            fitted += 1
            bar.update(1)
            if on_tile is not None:
                on_tile(tile.name, total - len(todo) + fitted, total)
    finally:
        client.cancel(list(futures))
    return fitted


def _place(full: dict, arrays, tile: Tile, shape: tuple[int, int], lights: int) -> None:
    """Put a tile file's arrays into the full maps ``full`` (created on first use)."""
    r0, r1, c0, c1 = tile.window
    for name in arrays.files:
        if name == "meta":
            continue
        a = arrays[name]
        if name not in full:
            if name == "used":
                full[name] = np.zeros((lights,) + shape, bool)
            elif name == "mask":
                full[name] = np.zeros(shape, bool)
            else:
                full[name] = np.full(shape + a.shape[2:], np.nan, np.float32)
        if name == "used":
            full[name][:, r0:r1, c0:c1] = a
        else:
            full[name][r0:r1, c0:c1] = a


def _fit_settings(metas: list[dict], extra: dict) -> dict:
    """The fit's options (as a tile's) and diagnostics summed or maximised over the tiles."""
    per_tile = [m["fit_settings"] for m in metas]
    out = {k: v for k, v in per_tile[0].items() if k not in ("seconds", "stages")}
    out["iterations_last_round"] = max(f["iterations_last_round"] for f in per_tile)
    for name in ("evaluations", "underdetermined_pixels", "chunks"):
        out[name] = sum(int(f[name]) for f in per_tile)
    out.update(extra)
    return out


def _assemble(out: Path, tiles: list[Tile], shape: tuple[int, int], gains: np.ndarray,
              extra: dict) -> MapsResult:
    """The maps of the whole capture, read back from the tile files."""
    full: dict = {}
    metas = []
    for tile in tiles:
        with np.load(out / TILES_FOLDER / tile.name, allow_pickle=False) as arrays:
            meta = json.loads(str(arrays["meta"]))
            _place(full, arrays, tile, shape, len(gains))
        if not meta["empty"]:
            metas.append(meta)
    first = metas[0]
    return MapsResult(
        normals=full["normals"], albedo=full["albedo"],
        maps={n[4:]: v for n, v in full.items() if n.startswith("map_")},
        settings=first["settings"], residual_rms=full["residual_rms"], gains=gains,
        used=full["used"], free=first["free"], mask=full["mask"], variant=first["variant"],
        fit_settings=_fit_settings(metas, extra))


def _tiles_to_fit(out: Path, tiles: list[Tile], fit_mask: np.ndarray, settings_hash: str,
                  lights: int, resume: bool) -> list[Tile]:
    """The tiles still to fit: those not finished with these settings (``resume``) that
    have masked pixels; a tile without any is written at once as empty."""
    done = _finished(out, tiles, settings_hash) if resume else set()
    for tile in tiles:
        r0, r1, c0, c1 = tile.window
        if tile not in done and not fit_mask[r0:r1, c0:c1].any():
            _write_atomic(out, tile.name, _tile_arrays(None, tile, settings_hash, lights))
            done.add(tile)
    return [t for t in tiles if t not in done]


def fit_maps_tiled(capture: str | Path | Capture, out_dir: str | Path, tile_size: int = 256,
                   *, encoding: str = "srgb", mask=None, gains: str = "fit",
                   initial_gains: np.ndarray | None = None, gain_pixels: int = GAIN_PIXELS,
                   seed: int = 0, client=None, scheduler: str | None = None,
                   workers: int | None = None, resume: bool = False, progress: bool = True,
                   log: Callable[[str], None] | None = None,
                   on_tile: Callable[[str, int, int], None] | None = None,
                   **options) -> MapsResult:
    """:func:`mitsuba_powder.rti.fit_maps` of a capture on disk, tile by tile on a Dask
    cluster, the gains held (module docstring).

    Args:
        capture: the capture's ``.lp`` file, or a :class:`~mitsuba_powder.rti.Capture` read
            from one (its ``.lp`` file, encoding and mask are used; not its images).
        out_dir: output folder; the tiles go to ``out_dir/tiles/``.
        tile_size: tile side, pixels, >= :data:`TILE_SIZE_MIN`.
        encoding: the images' ``srgb`` or ``linear`` encoding.
        mask: pixels to fit: an image file (:func:`~mitsuba_powder.rti.read_mask`), a bool
            (H, W) array, or None (all).
        gains: ``fit`` (fitted on ``gain_pixels`` pixels of the whole capture, then held)
            or ``fixed`` (``initial_gains``, default 1, held).
        initial_gains: (K,) start (``fit``) or value (``fixed``) of the gains, > 0.
        gain_pixels: pixels the gains are fitted on, >= 1 (all masked pixels if fewer).
        seed: seed of the gain pixels' draw, >= 0.
        client: a :class:`distributed.Client` to use (left open).
        scheduler: an existing cluster's ``tcp://HOST:PORT`` (when ``client`` is None).
        workers: processes of the local cluster, >= 1 (default one per core).
        resume: keep the tile files of an earlier run of the same settings (others are an
            error); False: fit every tile again.
        progress: a progress bar (tiles done, ETA) on a terminal's stderr.
        log: called with a line of text after each stage.
        on_tile: called with (tile file name, tiles done, tiles in all) after each tile is
            written.
        **options: :func:`fit_maps` options (``free``, ``fixed``, ``max_iterations``,
            ``rounds``, ``saturation``, ``shadow_ratio``, ``shadow_floor``, ``variant``,
            ``max_lanes``); per-pixel ``fixed`` maps are (H, W) (or (H, W, 3)) as there.

    Returns:
        The :class:`~mitsuba_powder.rti.result.MapsResult` of the whole capture;
        ``fit_settings["tiles"]`` says how many tiles were fitted and how many resumed.
    """
    from tqdm import tqdm

    t0 = time.perf_counter()
    log = log or (lambda line: None)
    size = check_tile_size(tile_size)
    plan = _plan(capture, encoding, mask, options, gains, initial_gains, gain_pixels, seed)
    out = Path(out_dir)
    output_path(out, f"{TILES_FOLDER}/{GAINS_FILE}")  # a refused output fails before fitting
    with open_client(client, scheduler, workers) as cl:
        first = cl.submit(_survey, plan.paths[0], plan.encoding, pure=False).result()
        shape = first["shape"][:2]
        log(f"{plan.lp}: {len(plan.paths)} lights, {shape[1]} x {shape[0]} px, "
            f"{first['format']} {first['depth']} bit, encoding {plan.encoding}")
        fit_mask = _mask(plan, shape)
        key = _hash({"capture": plan.capture_key(), "mask": fit_mask, "options": plan.options,
                     "gains": plan.gain_mode, "initial_gains": plan.initial_gains,
                     "gain_pixels": plan.gain_pixels, "seed": plan.seed})
        held = _held_gains(cl, plan, out, shape, fit_mask, key, resume, log)
        settings_hash = _hash({"gains_key": key, "held": held, "tile_size": size})
        tiles = plan_tiles(shape, size)
        todo = _tiles_to_fit(out, tiles, fit_mask, settings_hash, len(plan.paths), resume)
        log(f"tiles: {len(tiles)} of up to {size} x {size} px, {len(todo)} to fit, "
            f"{len(tiles) - len(todo)} done already or without masked pixels")
        with tqdm(total=len(tiles), initial=len(tiles) - len(todo), unit="tile", desc="tiles",
                  disable=None if progress else True) as bar:
            fitted = _run_tiles(cl, plan, out, todo, shape, fit_mask, held, settings_hash,
                                bar, on_tile, len(tiles))
    extra = {"seconds": time.perf_counter() - t0, "gains": plan.gain_mode,
             "tiles": {"tile_size": size, "count": len(tiles), "fitted": fitted,
                       "resumed": len(tiles) - len(todo), "gain_pixels": plan.gain_pixels,
                       "gains": plan.gain_mode, "settings_hash": settings_hash,
                       "out": str(out)},
             "capture": {"encoding": plan.encoding, "file_format": first["format"],
                         "bit_depth": first["depth"], "lp": str(plan.lp)}}
    return _assemble(out, tiles, shape, held, extra)
