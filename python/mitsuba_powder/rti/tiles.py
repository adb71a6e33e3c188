"""Per-pixel powder maps of captures larger than one machine: :func:`fit_maps_tiled`.

The capture is cut into square tiles of ``tile_size`` pixels (the last row and column of
tiles smaller); each tile is an independent :func:`mitsuba_powder.rti.fit_maps` run, scheduled
on a Dask cluster (:mod:`mitsuba_powder.rti.cluster`: a local cluster by default, or an
existing one by its scheduler's address), and the tiles are put back together into one
:class:`~mitsuba_powder.rti.result.MapsResult`, the one :func:`fit_maps` returns.

**Gains are held.** Per-light gains are shared by all pixels, so tiles fitted independently
would each find their own. They are therefore fitted first, once, on a subsample of the whole
capture: ``gain_subsample`` pixels drawn at random (``seed``) among the masked pixels
(:meth:`GainPolicy.draw <mitsuba_powder.rti.gains.GainPolicy.draw>`), fitted with the gains
fitted (:meth:`~mitsuba_powder.rti.gains.GainPolicy.on_subsample`: the same options as the
tiles); every tile is then fitted with these gains held
(:meth:`~mitsuba_powder.rti.gains.GainPolicy.held`). With ``gains="fixed"`` the given
``initial_gains`` (default 1) are held and no subsample is fitted. A pixel's fit depends only
on its own observations once the gains are held, so a tiled fit equals an untiled one under
the same gains. **The exposure** (not given) is scanned on that subsample likewise
(:mod:`mitsuba_powder.rti.exposure`), even with the gains held, and held in every tile.
**The free set** (not given) is chosen on that subsample too, by the cross-validation an
untiled fit runs (:mod:`mitsuba_powder.rti.selection`), and every tile fits the set chosen
(one choice per capture, none per tile). Each
worker runs the fit's plan (:func:`mitsuba_powder.rti.plan.run_fit`) with
the tiled fit's own :class:`~mitsuba_powder.rti.options.FitOptions`.

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
import math
import os
import time
import uuid
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..outputs import note_inputs, output_path
from .capture import Capture, full_scale, lp_image_paths, read_image_window, read_lp, read_mask
from .checks import check_gains
from .cluster import open_client, worker_threads
from .gains import GAIN_PIXELS
from .options import FitOptions, fit_options
from .pixelfit import Log
from .plan import make_plan, run_fit, run_stages
from .result import MapsResult
from .tile_files import (
    GAINS_FILE,
    KIND,
    TILE_SIZE_MIN,
    TILES_FOLDER,
    Tile,
    assemble,
    check_tile_size,
    meta_array,
    plan_tiles,
    read_meta,
    refused,
    tile_arrays,
    tiles_of,
    tiles_to_fit,
    write_atomic,
)

__all__ = ["GAIN_PIXELS", "TILE_SIZE_MIN", "TILES_FOLDER", "Tile", "check_tile_size",
           "fit_maps_tiled", "plan_tiles"]

#: The stages of the subsample's fit where its gains are held: what the tiles take from it
_CHOICES = ("exposure scan", "free choice", "exposure check")
#: The options of the gain policy (kept apart from the others in the settings' hash)
_POLICY = ("gains", "initial_gains", "gain_subsample", "seed")


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
    options: FitOptions        # the fit's options (each tile's, its gains held)
    initial_gains: np.ndarray | None  # (K,) checked

    def settings_key(self, mask: np.ndarray) -> dict:
        """What the held gains (and so every tile) depend on: the capture's files, the mask,
        the options as given and the gain policy."""
        policy = self.options.gains
        given = {k: v for k, v in self.options.given.items() if k not in _POLICY}
        return {"capture": self.capture_key(), "mask": mask, "options": given,
                "gains": policy.mode, "initial_gains": self.initial_gains,
                "gain_pixels": policy.subsample, "seed": policy.seed}

    def capture_key(self) -> dict:
        """What identifies the capture's files (paths, sizes, modification times)."""
        stats = [os.stat(p) for p in self.paths]
        return {"lp": str(self.lp), "names": self.names, "directions": self.directions,
                "encoding": self.encoding, "sizes": [s.st_size for s in stats],
                "mtimes": [s.st_mtime_ns for s in stats]}


def _check_tiled(options: FitOptions) -> None:
    """What a tiled fit does not take: lights at a finite distance (a tile, and the gains'
    pixel sample, is fitted as an image of its own, whose pixel positions are not those of
    the whole image that near-field lights depend on)."""
    distance = options.light_distance
    if isinstance(distance, str) or np.ndim(distance) != 0 or not math.isinf(distance):
        raise ValueError(f"{options.name('light_distance')} = {distance!r} is not supported "
                         "by tiled fits; valid value: inf (distant lights); fit near-field "
                         "lights untiled")


def _plan(capture, encoding: str, mask, options: FitOptions) -> _Plan:
    """Read the .lp of a tiled fit's capture; its images must exist."""
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
    initial = options.gains.initial
    initial = None if initial is None else check_gains(initial, len(names))
    return _Plan(lp, paths, list(names), directions, encoding, mask, options, initial)


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


def _fit_gains(surveys: list[dict], directions: np.ndarray, options: FitOptions) -> dict:
    """The gains fitted on the sampled pixels (a worker task; ``options``: the subsample's,
    :meth:`~mitsuba_powder.rti.gains.GainPolicy.on_subsample`), or held (the exposure scanned
    and the free set chosen on them, no maps fitted): ``gains`` (K,), ``stages``,
    ``exposure``, ``free`` and ``free_choice``."""
    _prepare_worker(options.variant)
    images = np.stack([s["samples"] for s in surveys])[:, None]  # (K, 1, N, 3)
    if options.gains.fitted:
        result = run_fit(images, directions, options)
        return {"gains": result.gains, "stages": result.fit_settings.get("stages", []),
                "exposure": result.fit_settings.get("exposure"), "free": list(result.free),
                "free_choice": result.fit_settings.get("free_choice")}
    # the gains held: only the stages before the maps (the exposure, the free set); the
    # subsample's maps would be fitted for nothing
    log = Log()
    state = run_stages(make_plan(images, directions, options), log, _CHOICES)
    return {"gains": np.asarray(state.gains), "stages": log.stages,
            "exposure": state.exposure, "free": list(state.options.free),
            "free_choice": state.free_choice}


def _fit_tile(paths: list[str], encoding: str, tile: Tile, shape: tuple[int, int],
              mask: np.ndarray, directions: np.ndarray, options: FitOptions,
              settings_hash: str) -> dict[str, np.ndarray]:
    """Fit one tile (a worker task): its images' window read from ``paths``, with ``options``
    (the tile's held maps and the gains held); returns the tile file's arrays
    (:func:`tile_arrays`)."""
    _prepare_worker(options.variant)
    images = []
    for path in paths:
        values, _, _, full = read_image_window(path, encoding, tile.window)
        if full != shape:
            raise ValueError(f"image {path}: {full[1]} x {full[0]} px; expected {shape[1]} x "
                             f"{shape[0]} px as the capture's first image")
        images.append(values)
    result = run_fit(np.stack(images), directions, options, mask)
    return tile_arrays(result, tile, settings_hash)


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
                key: str, resume: bool, log: Callable[[str], None]
                ) -> tuple[np.ndarray, dict | None, dict | None]:
    """The gains every tile holds: ``initial_gains`` (mode ``fixed``, the exposure given),
    or those fitted (or the exposure scanned: :mod:`mitsuba_powder.rti.exposure`) on the gain
    policy's subsample of the masked pixels, where the free set (not given) is chosen too
    (read back from ``gains.npz`` on resume); the exposure's record (None: not fitted) and
    the free choice's (None: the free set given)."""
    policy = plan.options.gains
    o = plan.options
    if not policy.fitted and not o.fits_exposure and not o.chooses_free:
        exposure = 1.0 if o.exposure is None else float(o.exposure)
        gains = np.ones(len(plan.paths)) if plan.initial_gains is None else plan.initial_gains
        return exposure * gains, None, None
    path = out / TILES_FOLDER / GAINS_FILE
    if resume and path.exists():
        meta = read_meta(path)
        if meta is not None and meta.get("settings_hash") != key:
            raise refused(path, key, str(meta.get("settings_hash")))
        if meta is not None:
            with np.load(path, allow_pickle=False) as f:
                gains = np.array(f["gains"])
            log(f"gains: read from {path}")
            return gains, meta.get("exposure"), meta.get("free_choice")
    flat = policy.draw(mask)
    options = plan.options.replace(fixed=_sampled_fixed(plan.options.fixed, shape, flat),
                                   gains=policy.on_subsample() if policy.fitted else policy)
    surveys = [client.submit(_survey, p, plan.encoding, flat, pure=False) for p in plan.paths]
    _check_surveys(client.gather(surveys), plan.names, plan.lp)
    fitted = client.submit(_fit_gains, surveys, plan.directions, options, pure=False).result()
    meta = {"kind": KIND, "settings_hash": key, "pixels": len(flat), "seed": policy.seed,
            "stages": fitted["stages"], "exposure": fitted["exposure"],
            "free_choice": fitted["free_choice"]}
    write_atomic(out, GAINS_FILE, {"meta": meta_array(meta), "gains": fitted["gains"]})
    for line in fitted["stages"]:
        if line.startswith(("exposure", "free set")):
            log(line)
    span = f"range {np.min(fitted['gains']):.4g}-{np.max(fitted['gains']):.4g}"
    if policy.fitted or o.fits_exposure:
        what = "fitted" if policy.fitted else "the exposure scanned"
        log(f"gains: {what} on {len(flat)} pixels of the whole capture, held in every tile "
            f"({span})")
    else:
        log(f"gains: held as given in every tile ({span}); the free set chosen on "
            f"{len(flat)} pixels of the whole capture")
    return np.asarray(fitted["gains"]), fitted["exposure"], fitted["free_choice"]


def _run_tiles(client, plan: _Plan, out: Path, todo: list[Tile], shape: tuple[int, int],
               mask: np.ndarray, gains: np.ndarray, settings_hash: str, bar,
               on_tile: Callable[[str, int, int], None] | None, total: int) -> int:
    """Fit the tiles ``todo`` on the cluster, writing each as it arrives; returns the count.
    Tiles still queued are cancelled when this stops (an error or an interrupt)."""
    from distributed import as_completed

    futures = {}
    held = plan.options.gains.held(gains)
    for tile in todo:
        r0, r1, c0, c1 = tile.window
        options = plan.options.replace(fixed=_window_fixed(plan.options.fixed, shape, tile),
                                       gains=held, exposure=None)  # (in the held gains)
        fut = client.submit(_fit_tile, plan.paths, plan.encoding, tile, shape,
                            mask[r0:r1, c0:c1], plan.directions, options, settings_hash,
                            key=f"fit-tile-r{tile.row}-c{tile.col}-{uuid.uuid4().hex[:8]}")
        futures[fut] = tile
    fitted = 0
    try:
        for fut in as_completed(futures):
            tile = futures[fut]
            write_atomic(out, tile.name, fut.result())
            fitted += 1
            bar.update(1)
            if on_tile is not None:
                on_tile(tile.name, total - len(todo) + fitted, total)
    finally:
        client.cancel(list(futures))
    return fitted


def fit_maps_tiled(capture: str | Path | Capture, out_dir: str | Path, tile_size: int = 256,
                   *, encoding: str = "srgb", mask=None, client=None,
                   scheduler: str | None = None, workers: int | None = None,
                   resume: bool = False, progress: bool = True,
                   log: Callable[[str], None] | None = None,
                   on_tile: Callable[[str, int, int], None] | None = None,
                   options: FitOptions | None = None, **fit) -> MapsResult:
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
        client: a :class:`distributed.Client` to use (left open).
        scheduler: an existing cluster's ``tcp://HOST:PORT`` (when ``client`` is None).
        workers: processes of the local cluster, >= 1 (default one per core).
        resume: keep the tile files of an earlier run of the same settings (others are an
            error); False: fit every tile again.
        progress: a progress bar (tiles done, ETA) on a terminal's stderr.
        log: called with a line of text after each stage.
        on_tile: called with (tile file name, tiles done, tiles in all) after each tile is
            written.
        options: the fit's options (:func:`~mitsuba_powder.rti.options.fit_options`), or
        **fit: the options of :func:`fit_maps` (``free``, ``fixed``, ``gains``: ``fit``
            fitted on ``gain_subsample`` pixels of the whole capture then held, or ``fixed``,
            ``initial_gains``, ``seed``, ``max_iterations``, ``rounds``, ...; distant lights
            only); per-pixel ``fixed`` maps are (H, W) (or (H, W, 3)) as there;
            ``full_scale`` (default: the files', 1 for PNG and JPEG, ``inf`` for EXR).

    Returns:
        The :class:`~mitsuba_powder.rti.result.MapsResult` of the whole capture;
        ``fit_settings["tiles"]`` says how many tiles were fitted and how many resumed.
    """
    t0 = time.perf_counter()
    log = log or (lambda line: None)
    options = _options_of(options, fit)
    size = check_tile_size(tile_size, options.name("tile_size"))
    _check_tiled(options)
    plan = _plan(capture, encoding, mask, options)
    out = Path(out_dir)
    with open_client(client, scheduler, workers,
                     names=(options.name("scheduler"), options.name("workers"))) as cl:
        output_path(out, f"{TILES_FOLDER}/{GAINS_FILE}")  # a refused output: before fitting
        if client is None:
            log(f"cluster: {cl.scheduler.address}, {len(cl.scheduler_info()['workers'])} "
                f"worker(s), dashboard {cl.dashboard_link}")
        tiles, shape, held, extra = _fit_on(cl, plan, out, size, resume, progress, log,
                                            on_tile)
    result = assemble(out, tiles, shape, held,
                      {"seconds": time.perf_counter() - t0, **extra})
    record = extra.get("exposure")
    if record is None:
        record = result.fit_settings["exposure"] = _given_exposure(plan, held)
    result.exposure = float(record["value"])
    return result


def _options_of(options: FitOptions | None, fit: dict) -> FitOptions:
    """The tiled fit's options: ``options`` as given, or built from the keywords ``fit``
    (not both), with the ratio test for shadows (no relief; ``auto`` is ``ratio`` here)."""
    if options is None:
        options = fit_options(**fit)
    elif fit:
        raise ValueError(f"give the fit's options as options or as keywords, not both (got "
                         f"options and {sorted(fit)})")
    if options.given.get("shadows") == "relief":
        raise ValueError(f"{options.name('shadows')} = 'relief' is not supported with tiles "
                         "(each tile would integrate a relief cut at its edges); tiled fits "
                         "use the ratio test (shadows = 'ratio')")
    return options.replace(shadows="ratio")


def _given_exposure(plan: _Plan, held: np.ndarray) -> dict:
    """The exposure record of a tiled fit that did not scan it: given (the held gains' mean
    relative to the initial gains') or 1 (the initial gains)."""
    start = np.ones(len(held)) if plan.initial_gains is None else plan.initial_gains
    given = plan.options.exposure is not None
    return {"value": float(np.mean(held) / np.mean(start)) if given else 1.0, "sigma": 0.0,
            "source": "given" if given else "initial gains", "determined": True}


def _fit_on(client, plan: _Plan, out: Path, size: int, resume: bool, progress: bool,
            log: Callable[[str], None], on_tile: Callable[[str, int, int], None] | None
            ) -> tuple[list[Tile], tuple[int, int], np.ndarray, dict]:
    """The held gains and every tile fitted on the cluster of ``client``, written under
    ``out``: the tiles, the image's shape, the gains and the tiled fit's record."""
    from tqdm import tqdm

    first = client.submit(_survey, plan.paths[0], plan.encoding, pure=False).result()
    shape = first["shape"][:2]
    log(f"{plan.lp}: {len(plan.paths)} lights, {shape[1]} x {shape[0]} px, "
        f"{first['format']} {first['depth']} bit, encoding {plan.encoding}")
    fit_mask = _mask(plan, shape)
    if "full_scale" not in plan.options.given:  # the files' full scale, unless given
        plan.options = plan.options.replace(full_scale=full_scale(first["format"]))
    key = _hash(plan.settings_key(fit_mask))
    held, exposure, choice = _held_gains(client, plan, out, shape, fit_mask, key, resume, log)
    # every tile fits the same free set: the one chosen on the subsample, or given
    free = list(plan.options.free) if choice is None else list(choice["chosen"])
    plan.options = plan.options.replace(free=tuple(free),
                                        given={**plan.options.given, "free": free})
    settings_hash = _hash({"gains_key": key, "held": held, "tile_size": size, "free": free})
    tiles = tiles_of(shape, size)
    todo = tiles_to_fit(out, tiles, fit_mask, settings_hash, len(plan.paths), resume)
    log(f"tiles: {len(tiles)} of up to {size} x {size} px, {len(todo)} to fit, "
        f"{len(tiles) - len(todo)} done already or without masked pixels")
    with tqdm(total=len(tiles), initial=len(tiles) - len(todo), unit="tile", desc="tiles",
              disable=None if progress else True) as bar:
        fitted = _run_tiles(client, plan, out, todo, shape, fit_mask, held, settings_hash,
                            bar, on_tile, len(tiles))
    policy = plan.options.gains
    return tiles, shape, held, {
        "gains": policy.mode, "exposure": exposure,
        **({} if choice is None else {"free_choice": choice}),
        "tiles": {"tile_size": size, "count": len(tiles), "fitted": fitted,
                  "resumed": len(tiles) - len(todo), "gain_pixels": policy.subsample,
                  "gains": policy.mode, "settings_hash": settings_hash, "out": str(out)},
        "capture": {"encoding": plan.encoding, "file_format": first["format"],
                    "bit_depth": first["depth"], "lp": str(plan.lp)}}
