"""The tiles of a capture (:class:`Tile`, :func:`plan_tiles`) and their files on disk: each
written whole or not at all (:func:`write_atomic`), found again on resume
(:func:`finished_tiles`) and put together into the maps of the whole capture
(:func:`assemble`); :mod:`mitsuba_powder.rti.tiles` fits them."""

from __future__ import annotations

import json
from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from ..outputs import output_path, replace_whole
from .blocks import merge_fit_settings
from .checks import check_count
from .maps import _json_default
from .result import MapsResult

__all__ = ["GAINS_FILE", "KIND", "TILES_FOLDER", "TILE_SIZE_MIN", "Tile", "assemble",
           "check_tile_size", "finished_tiles", "meta_array", "plan_tiles", "read_meta",
           "refused", "tile_arrays", "tiles_of", "tiles_to_fit", "write_atomic"]

#: Smallest tile side (pixels)
TILE_SIZE_MIN = 8
#: The folder of tile files under the output folder
TILES_FOLDER = "tiles"
#: The gains' file in :data:`TILES_FOLDER`
GAINS_FILE = "gains.npz"
#: What every tile and gains file says it is
KIND = "mitsuba-powder tile"


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
    return check_count(name, value, TILE_SIZE_MIN)


def plan_tiles(shape: tuple[int, int], tile_size: int) -> list[Tile]:
    """The tiles of an (H, W) image, row by row; tiles of the last row and column are cut at
    the image's edge."""
    return tiles_of(shape, check_tile_size(tile_size))


def tiles_of(shape: tuple[int, int], size: int) -> list[Tile]:
    """:func:`plan_tiles` of a checked tile size."""
    h, w = shape
    return [Tile(r, c, r0, min(r0 + size, h), c0, min(c0 + size, w))
            for r, r0 in enumerate(range(0, h, size)) for c, c0 in enumerate(range(0, w, size))]


# ---------------------------------------------------------------------------
#  Tile files
# ---------------------------------------------------------------------------

def meta_array(meta: dict) -> np.ndarray:
    return np.array(json.dumps(meta, default=_json_default))


def tile_arrays(result: MapsResult | None, tile: Tile, settings_hash: str,
                 lights: int = 0) -> dict[str, np.ndarray]:
    """A tile file's arrays: the result's maps (``map_<name>``), ``normals``, ``albedo``,
    ``residual_rms``, ``used``, ``mask`` and ``meta`` (JSON: the hash, the window, the
    settings and the fit's diagnostics); ``result`` None: a tile with no masked pixel."""
    h, w = tile.row1 - tile.row0, tile.col1 - tile.col0
    meta = {"kind": KIND, "settings_hash": settings_hash, "window": list(tile.window),
            "empty": result is None}
    if result is None:
        nan = np.full((h, w, 3), np.nan, np.float32)
        return {"meta": meta_array(meta), "normals": nan, "albedo": nan,
                "residual_rms": nan[..., 0], "used": np.zeros((lights, h, w), bool),
                "mask": np.zeros((h, w), bool)}
    meta.update(free=result.free, settings=result.settings, variant=result.variant,
                fit_settings=result.fit_settings)
    arrays = {"meta": meta_array(meta), "normals": result.normals, "albedo": result.albedo,
              "residual_rms": result.residual_rms, "used": result.used, "mask": result.mask}
    arrays.update({f"map_{name}": v for name, v in result.maps.items()})
    return arrays


def write_atomic(out: Path, name: str, arrays: Mapping[str, np.ndarray]) -> Path:
    """Write ``arrays`` to ``out/TILES_FOLDER/name`` (.npz) through a temporary file renamed
    into place: the file is whole or absent."""
    return replace_whole(output_path(out, f"{TILES_FOLDER}/{name}"),
                         lambda f: np.savez(f, **arrays))


def read_meta(path: Path) -> dict | None:
    """A tile or gains file's meta (None when the file is absent or unreadable)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            meta = json.loads(str(f["meta"]))
    except (OSError, ValueError, KeyError):
        return None
    return meta if meta.get("kind") == KIND else None


def refused(path: Path, expected: str, found: str) -> ValueError:
    return ValueError(f"resume: {path} was written with other settings (settings hash "
                      f"{found[:12]}, this run's {expected[:12]}: another capture, mask, fit "
                      "option, gains or tile size); rerun without resume to fit every tile "
                      "again, or give another output folder")


def finished_tiles(out: Path, tiles: Iterable[Tile], settings_hash: str) -> set[Tile]:
    """The tiles whose file exists with this run's settings; a file of other settings is an
    error (:func:`refused`)."""
    done = set()
    for tile in tiles:
        path = out / TILES_FOLDER / tile.name
        if not path.exists():
            continue
        meta = read_meta(path)
        if meta is None:
            continue  # not a whole tile file: fitted again
        if meta.get("settings_hash") != settings_hash or meta.get("window") != list(
                tile.window):
            raise refused(path, settings_hash, str(meta.get("settings_hash")))
        done.add(tile)
    return done


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
    """The fit's options (as a tile's) and diagnostics summed or maximised over the tiles
    (:func:`~mitsuba_powder.rti.blocks.merge_fit_settings`), with ``extra``."""
    out = merge_fit_settings([m["fit_settings"] for m in metas])
    for name in ("seconds", "stages"):
        out.pop(name)
    out.update(extra)
    return out


def assemble(out: Path, tiles: list[Tile], shape: tuple[int, int], gains: np.ndarray,
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


def tiles_to_fit(out: Path, tiles: list[Tile], fit_mask: np.ndarray, settings_hash: str,
                  lights: int, resume: bool) -> list[Tile]:
    """The tiles still to fit: those not finished with these settings (``resume``) that
    have masked pixels; a tile without any is written at once as empty."""
    done = finished_tiles(out, tiles, settings_hash) if resume else set()
    for tile in tiles:
        r0, r1, c0, c1 = tile.window
        if tile not in done and not fit_mask[r0:r1, c0:c1].any():
            write_atomic(out, tile.name, tile_arrays(None, tile, settings_hash, lights))
            done.add(tile)
    return [t for t in tiles if t not in done]
