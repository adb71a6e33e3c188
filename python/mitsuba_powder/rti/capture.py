"""RTI captures on disk: light-position (``.lp``) files and their images, read and written.

A Reflectance Transformation Imaging (RTI) capture is a fixed camera and K photographs, each
lit from one known direction, listed in an ``.lp`` file:

.. code-block:: text

    48
    image00.jpg 0.536425 0.831366 0.145184
    image01.jpg 0.26473 0.942088 0.205887
    ...

* line 1: the number of lights K (an integer; trailing blanks allowed);
* then one line per light: ``filename lx ly lz``, the file relative to the ``.lp`` file's
  folder (or absolute), and the direction towards the light in the camera frame: x to the
  image's right, y to its top, z towards the camera. Directions are normalised on read; their
  length carries no meaning (some tools write unit vectors, others positions).
* blank lines are skipped anywhere (real files end with some: RealRTI items 3, 4, 5, 8, ...).
  There is no comment syntax: a ``#`` line is a malformed line.
* a file name may contain spaces: the last three fields are the direction, the rest is the name.

Checks (each a ``ValueError`` naming the file, the line number, the value and what was
expected): the count line, a line without a name and three numbers, a field that is not a
finite number, a zero vector, a light more than :data:`MIN_LZ_DEFAULT` below the surface plane
(``lz < -0.1`` after normalising, about 5.7 degrees below the horizon: dome calibrations put
near-horizon lights a little below it, e.g. RealRTI item 7's ``image16.jpg`` at
``lz = -0.0012``, while a capture with all z negative is a sign convention error), a repeated
file name, and fewer or more light lines than the count.

Images: PNG (8 or 16 bit), JPEG (8 bit) or OpenEXR (half or float), read and written with
Mitsuba's ``mi.Bitmap`` (in the caller's variant, else ``scalar_rgb``). ``mi.Bitmap`` tags
every PNG/JPEG it reads ``srgb_gamma = True`` whatever the file says and returns the stored
integers untouched, so this module does the transfer function itself, explicitly:

* ``encoding="srgb"``: the file's values are sRGB-encoded (IEC 61966-2-1); they are divided
  by 255 (65535 for 16 bit) and linearised on read, and linear values are re-encoded on write.
* ``encoding="linear"``: the file's values divided by 255 (65535) are taken as linear and
  written back as such.

The encoding applies to EXR files too (their values are normally linear: use ``linear``).
"""

from __future__ import annotations

import math
import shutil
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import NamedTuple

import colour
import mitsuba as mi
import numpy as np

from ..outputs import guarding_inputs, note_input, note_inputs, output_names, output_path
from ..readers import read_bitmap
from ..variants import use_variant

__all__ = ["Capture", "ENCODINGS", "LpFile", "MIN_LZ_DEFAULT", "decode", "encode",
           "full_scale", "load_capture", "lp_image_paths", "read_image", "read_image_window",
           "read_lp", "read_lp_file", "read_mask", "write_images", "write_lp"]

#: the transfer functions between file values and linear values
ENCODINGS = ("srgb", "linear")
#: the lowest z accepted for a normalised light direction (about 5.7 degrees below the horizon)
MIN_LZ_DEFAULT = -0.1
#: file formats by suffix
_FORMATS = {".png": "png", ".jpg": "jpeg", ".jpeg": "jpeg", ".exr": "exr"}


@dataclass
class Capture:
    """An RTI capture in memory.

    Attributes:
        images: linear values, float32 (K, H, W, C), C = 1 (grey) or 3 (RGB); 1.0 is the
            file's full scale (255, 65535, or 1.0 for EXR); alpha channels are dropped.
        directions: unit vectors towards the lights, float64 (K, 3), camera frame (x right,
            y up in the image, z towards the camera).
        names: the image file names as written in the ``.lp`` file, in its order.
        encoding: ``srgb`` or ``linear`` (see the module docstring).
        file_format: ``png``, ``jpeg`` or ``exr`` (the source images').
        bit_depth: bits per component of the source: 8 or 16 (PNG, JPEG), 16 or 32 (EXR half
            or float).
        mask: pixels to use, bool (H, W), or None (all).
        lp_path: the ``.lp`` file read (None for a capture built in memory).
    """

    images: np.ndarray
    directions: np.ndarray
    names: list[str]
    encoding: str = "srgb"
    file_format: str = "png"
    bit_depth: int = 8
    mask: np.ndarray | None = None
    lp_path: Path | None = None

    @property
    def shape(self) -> tuple[int, int]:
        """(height, width) in pixels."""
        return int(self.images.shape[1]), int(self.images.shape[2])

    @property
    def channels(self) -> int:
        """Channels per pixel (1 or 3)."""
        return int(self.images.shape[3])

    @property
    def full_scale(self) -> float:
        """The largest linear value its files record (:func:`full_scale`)."""
        return full_scale(self.file_format)


def full_scale(file_format: str) -> float:
    """The largest linear value a file of ``file_format`` records: 1.0 in an integer format
    (``png``, ``jpeg``: the full scale, where a camera saturates), ``inf`` in ``exr``."""
    return math.inf if file_format == "exr" else 1.0


def _check_encoding(encoding: str) -> None:
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding = {encoding!r} is not valid; choose one of {ENCODINGS}")


def decode(values: np.ndarray, encoding: str) -> np.ndarray:
    """Linear values of file values in [0, 1] (float32).

    Args:
        values: file values, 1.0 = full scale.
        encoding: ``srgb`` (IEC 61966-2-1 decoding, through colour-science) or ``linear``
            (unchanged).
    """
    _check_encoding(encoding)
    if encoding == "linear":
        return np.asarray(values, dtype=np.float32)
    return np.asarray(colour.cctf_decoding(np.asarray(values, dtype=np.float64),
                                           function="sRGB"), dtype=np.float32)


def encode(values: np.ndarray, encoding: str) -> np.ndarray:
    """File values of linear values (float64), the inverse of :func:`decode`.

    Negative linear values are encoded with the sign kept (``-encode(-x)``), so that the
    encoding of an unclamped model prediction is defined; writing to an integer format clips
    to [0, 1] afterwards (:func:`write_images`).
    """
    _check_encoding(encoding)
    x = np.asarray(values, dtype=np.float64)
    if encoding == "linear":
        return x
    return np.sign(x) * colour.cctf_encoding(np.abs(x), function="sRGB")


class LpFile(NamedTuple):
    """An ``.lp`` file as read (:func:`read_lp_file`): the K file names, the unit directions
    (float64 (K, 3)), the vectors as written (float64 (K, 3): directions or positions) and the
    line number of each light."""

    names: list[str]
    directions: np.ndarray
    vectors: np.ndarray
    lines: list[int]


def _parse_lp_text(text: str, where: str, min_lz: float) -> LpFile:
    """The lights of the text of an .lp file ``where`` (format and checks: module docstring)."""
    numbered = [(i, ln.strip()) for i, ln in enumerate(text.splitlines(), start=1) if ln.strip()]
    count = _lp_count(numbered, where)
    names: list[str] = []
    dirs: list[tuple[float, ...]] = []
    vectors: list[list[float]] = []
    numbers: list[int] = []
    seen: dict[str, int] = {}
    for lineno, line in numbered[1:]:
        name, vec, unit = _lp_line(line, f"{where}, line {lineno}", min_lz)
        if name in seen:
            raise ValueError(f"{where}, line {lineno}: file name {name!r} repeats line "
                             f"{seen[name]}; expected one line per image")
        seen[name] = lineno
        names.append(name)
        dirs.append(unit)
        vectors.append(vec)
        numbers.append(lineno)
    if len(names) != count:
        raise ValueError(f"{where}, line {numbered[0][0]}: the count says {count} lights but "
                         f"the file has {len(names)} light lines (up to line "
                         f"{numbered[-1][0]})")
    return LpFile(names, np.array(dirs, dtype=np.float64),
                  np.array(vectors, dtype=np.float64).reshape(-1, 3), numbers)


def _lp_count(numbered: list[tuple[int, str]], where: str) -> int:
    """The number of lights on the first non-blank line."""
    if not numbered:
        raise ValueError(f"{where}: empty file; expected the number of lights on line 1, then "
                         "'filename lx ly lz' per light")
    first_no, first = numbered[0]
    try:
        count = int(first)
    except ValueError:
        raise ValueError(f"{where}, line {first_no}: {first!r} is not the number of lights "
                         "(an integer >= 1)") from None
    if count < 1:
        raise ValueError(f"{where}, line {first_no}: number of lights {count}; expected >= 1")
    return count


def _lp_line(line: str, where: str, min_lz: float
             ) -> tuple[str, list[float], tuple[float, ...]]:
    """(name, vector as written, unit direction) of a light line ``where`` (file, line)."""
    fields = line.split()
    if len(fields) < 4:
        raise ValueError(f"{where}: {line!r} has {len(fields)} fields; expected 'filename lx "
                         "ly lz' (a name and 3 numbers)")
    vec = []
    for axis, text_value in zip("xyz", fields[-3:]):
        try:
            v = float(text_value)
        except ValueError:
            raise ValueError(f"{where}: l{axis} = {text_value!r} is not a number; expected "
                             "'filename lx ly lz'") from None
        if not math.isfinite(v):
            raise ValueError(f"{where}: l{axis} = {text_value!r} is not finite")
        vec.append(v)
    shown = f"({fields[-3]}, {fields[-2]}, {fields[-1]})"
    norm = math.hypot(*vec)  # no overflow: (1e300, 0, 0) has norm 1e300
    if norm == 0.0:
        raise ValueError(f"{where}: light direction {shown} is the zero vector; expected a "
                         "non-zero vector towards the light")
    unit = tuple(v / norm for v in vec)
    if unit[2] < min_lz:
        raise ValueError(f"{where}: light direction {shown} has normalised lz = "
                         f"{unit[2]:.4g} < {min_lz:g} (more than "
                         f"{math.degrees(math.asin(-min_lz)):.1f} degrees below the surface "
                         "plane); z points towards the camera")
    return line.rsplit(maxsplit=3)[0], vec, unit


def read_lp(path: str | Path, min_lz: float = MIN_LZ_DEFAULT
            ) -> tuple[list[str], np.ndarray]:
    """File names and unit light directions of an ``.lp`` file (format: module docstring).

    Args:
        path: the ``.lp`` file.
        min_lz: the lowest z accepted for a normalised direction (default -0.1).

    Returns:
        (names, directions): K names as written; float64 (K, 3) unit vectors towards the lights
        (x to the image's right, y to its top, z towards the camera).

    Raises:
        FileNotFoundError: no such file.
        ValueError: a malformed file (the message names the file and line).
    """
    lp = read_lp_file(path, min_lz)
    return lp.names, lp.directions


def read_lp_file(path: str | Path, min_lz: float = MIN_LZ_DEFAULT) -> LpFile:
    """An ``.lp`` file's names, unit directions, vectors as written and line numbers
    (:func:`read_lp`'s checks)."""
    p = Path(path)
    if not p.is_file():
        raise FileNotFoundError(f"light-position file {p} does not exist")
    note_input(p)
    return _parse_lp_text(p.read_text(encoding="utf-8", errors="replace"), str(p), min_lz)


def write_lp(path: str | Path, names: Sequence[str], directions: np.ndarray) -> Path:
    """Write an ``.lp`` file: the count, then ``name lx ly lz`` per light (9 decimals).

    Args:
        path: output file.
        names: K image file names (relative to the ``.lp`` file's folder).
        directions: (K, 3) vectors towards the lights (written as given).
    """
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3 or d.shape[0] != len(names):
        raise ValueError(f"directions of shape {d.shape}: expected ({len(names)}, 3), one per "
                         "name")
    p = Path(path)
    p.parent.mkdir(parents=True, exist_ok=True)
    lines = [str(len(names))] + [f"{n} {x:.9f} {y:.9f} {z:.9f}" for n, (x, y, z) in
                                 zip(names, d)]
    p.write_text("\n".join(lines) + "\n", encoding="utf-8")
    return p


def _bitmap(path: Path):
    """(raw array (H, W, C), file format, bit depth) of an image file, through mi.Bitmap."""
    with use_variant(mi.variant() or "scalar_rgb"):
        bmp = read_bitmap(path)
        fmt = bmp.component_format()
        pixel = bmp.pixel_format()
        arr = np.array(bmp)
    depth = {mi.Struct.Type.UInt8: 8, mi.Struct.Type.UInt16: 16, mi.Struct.Type.Float16: 16,
             mi.Struct.Type.Float32: 32}.get(fmt)
    if depth is None:
        raise ValueError(f"image {path}: component format {fmt} is not supported (8 or 16 bit "
                         "integer, half or float)")
    if arr.ndim == 2:
        arr = arr[..., None]
    keep = {mi.Bitmap.PixelFormat.Y: 1, mi.Bitmap.PixelFormat.YA: 1,
            mi.Bitmap.PixelFormat.RGB: 3, mi.Bitmap.PixelFormat.RGBA: 3}.get(pixel)
    if keep is None:
        raise ValueError(f"image {path}: pixel format {pixel} is not supported (Y, YA, RGB, "
                         "RGBA)")
    return arr[..., :keep], depth


def read_image(path: str | Path, encoding: str = "srgb") -> tuple[np.ndarray, str, int]:
    """Linear values of one image file.

    Args:
        path: ``.png`` (8/16 bit), ``.jpg``/``.jpeg`` or ``.exr``.
        encoding: ``srgb`` or ``linear`` (module docstring).

    Returns:
        (values float32 (H, W, C) with 1.0 = full scale, file format, bit depth).
    """
    values, file_format, depth, _ = read_image_window(path, encoding)
    return values, file_format, depth


def read_image_window(path: str | Path, encoding: str = "srgb",
                      window: tuple[int, int, int, int] | None = None
                      ) -> tuple[np.ndarray, str, int, tuple[int, int]]:
    """Linear values of a window of one image file (the file is decoded whole, the window
    cut out before the transfer function is applied).

    Args:
        path: ``.png`` (8/16 bit), ``.jpg``/``.jpeg`` or ``.exr``.
        encoding: ``srgb`` or ``linear`` (module docstring).
        window: ``(row0, row1, col0, col1)`` pixels (end exclusive), or None (all).

    Returns:
        (values float32 (row1 - row0, col1 - col0, C) with 1.0 = full scale, file format,
        bit depth, (H, W) of the whole image).
    """
    _check_encoding(encoding)
    p = Path(path)
    file_format = _FORMATS.get(p.suffix.lower())
    if file_format is None:
        raise ValueError(f"image {p}: format {p.suffix!r} is not supported; use .png, .jpg or "
                         ".exr")
    if not p.is_file():
        raise FileNotFoundError(f"image {p} does not exist")
    note_input(p)
    raw, depth = _bitmap(p)
    shape = (int(raw.shape[0]), int(raw.shape[1]))
    if window is not None:
        r0, r1, c0, c1 = window
        if not (0 <= r0 < r1 <= shape[0] and 0 <= c0 < c1 <= shape[1]):
            raise ValueError(f"image {p}: window rows {r0}-{r1}, columns {c0}-{c1} is not "
                             f"inside its {shape[1]} x {shape[0]} pixels")
        raw = raw[r0:r1, c0:c1]
    if raw.dtype == np.uint8:
        values = raw.astype(np.float32) / np.float32(255.0)
    elif raw.dtype == np.uint16:
        values = raw.astype(np.float32) / np.float32(65535.0)
    else:
        values = raw.astype(np.float32)
    return decode(values, encoding), file_format, depth, shape


def read_mask(path: str | Path, shape: tuple[int, int] | None = None) -> np.ndarray:
    """A pixel mask (H, W) bool from an image: True where the first channel is above half
    its full scale (PNG: > 127 of 255).

    Args:
        path: mask image (PNG usually).
        shape: (H, W) it must have, or None.
    """
    values, _, _ = read_image(path, "linear")
    mask = values[..., 0] > 0.5
    if shape is not None and mask.shape != tuple(shape):
        raise ValueError(f"mask {path}: {mask.shape[1]} x {mask.shape[0]} pixels; the capture's "
                         f"images are {shape[1]} x {shape[0]}")
    if not mask.any():
        raise ValueError(f"mask {path}: no pixel selected (none above half scale)")
    return mask


def load_capture(lp_path: str | Path, encoding: str = "srgb",
                 mask: str | Path | np.ndarray | None = None,
                 min_lz: float = MIN_LZ_DEFAULT) -> Capture:
    """Read an RTI capture: the ``.lp`` file and its K images.

    Args:
        lp_path: the ``.lp`` file; image names are relative to its folder.
        encoding: ``srgb`` (file values sRGB-encoded, linearised) or ``linear``.
        mask: pixel mask: an image file (see :func:`read_mask`), a bool (H, W) array, or None.
        min_lz: see :func:`read_lp`.

    Returns:
        A :class:`Capture` (images linear float32 (K, H, W, C)).

    Raises:
        FileNotFoundError: the ``.lp`` file or an image is missing (the line is named).
        ValueError: a malformed ``.lp`` line, images of different sizes, channel counts,
            formats or bit depths (the line is named), a mask of another size.
    """
    _check_encoding(encoding)
    lp = Path(lp_path)
    names, dirs, _, linenos = read_lp_file(lp, min_lz)
    images: np.ndarray | None = None
    first: tuple | None = None
    for k, (name, lineno) in enumerate(zip(names, linenos)):
        path = Path(name) if Path(name).is_absolute() else lp.parent / name
        where = f"{lp}, line {lineno}"
        if not path.is_file():
            raise FileNotFoundError(f"{where}: image {name!r} not found (looked for {path})")
        try:
            values, file_format, depth = read_image(path, encoding)
        except ValueError as exc:
            raise ValueError(f"{where}: {exc}") from None
        props = (values.shape, file_format, depth)
        if first is None:
            first = (*props, name, lineno)
            images = np.empty((len(names), *values.shape), dtype=np.float32)
        elif props != first[:3]:
            h, w, c = values.shape
            h0, w0, c0 = first[0]
            raise ValueError(f"{where}: image {name!r} is {w} x {h} px, {c} channels, "
                             f"{file_format} {depth} bit; expected {w0} x {h0} px, {c0} "
                             f"channels, {first[1]} {first[2]} bit as {first[3]!r} (line "
                             f"{first[4]})")
        images[k] = values
    assert images is not None and first is not None
    h, w = first[0][:2]
    if mask is not None and not isinstance(mask, np.ndarray):
        mask = read_mask(mask, (h, w))
    elif mask is not None:
        mask = np.asarray(mask, dtype=bool)
        if mask.shape != (h, w):
            raise ValueError(f"mask of shape {mask.shape}: expected ({h}, {w}) as the images")
    return Capture(images, dirs, names, encoding, first[1], first[2], mask, lp)


def lp_image_paths(lp_path: str | Path, names: Sequence[str]) -> list[Path]:
    """Where the images named by an ``.lp`` file are (absolute names as given, relative ones
    beside the ``.lp`` file)."""
    lp = Path(lp_path)
    return [Path(n) if Path(n).is_absolute() else lp.parent / n for n in names]


def write_images(capture_like: Capture, images: np.ndarray,
                 lp_path_or_names: str | Path | Sequence[str], out_dir: str | Path,
                 jpeg_quality: int = 100) -> list[Path]:
    """Write images (e.g. model predictions) with the capture's encoding and bit depth.

    Each image goes to ``out_dir/name``; the file format follows the name's suffix (PNG, JPEG,
    EXR) and the bit depth the capture's (PNG: 8 or 16 as the capture, 16 if it was EXR; JPEG:
    8; EXR: half or float as the capture, float if it was PNG/JPEG). Values are encoded with
    ``capture_like.encoding`` (:func:`encode`); integer formats clip the encoded values to
    [0, 1] and round to the nearest level.

    Nothing is written outside ``out_dir`` nor over an input: names read from an ``.lp`` file
    are reduced by :func:`mitsuba_powder.outputs.output_names` (an absolute name or one with
    ``..`` to its base name; two lights of one base name are an error naming both lines); the
    images the ``.lp`` file names and the ``.lp`` file itself are protected, and every target
    is checked before the first file is written.

    Args:
        capture_like: anything with ``encoding``, ``bit_depth`` and ``file_format`` (a
            :class:`Capture`).
        images: linear values (K, H, W, C) or (K, H, W), C = 1 or 3.
        lp_path_or_names: an ``.lp`` file (its names are used and an ``.lp`` file of the
            written names is put into ``out_dir``, so that the output is itself a capture), or
            K relative file names.
        out_dir: output folder (created).
        jpeg_quality: JPEG quality 1-100 (Mitsuba's writer; 100 by default).

    Returns:
        The paths written, in order.

    Raises:
        ValueError: bad shapes, suffixes or quality; :class:`mitsuba_powder.outputs.OutputError`
            (a ValueError) for a name or target that is refused.
    """
    imgs = _image_stack(images, jpeg_quality)
    with guarding_inputs():
        names, lp_copy, read_names, directions = _output_names_of(lp_path_or_names)
        if len(names) != imgs.shape[0]:
            raise ValueError(f"{len(names)} file names for {imgs.shape[0]} images")
        for name in names:
            if Path(name).suffix.lower() not in _FORMATS:
                raise ValueError(f"output name {name!r}: suffix not supported; use .png, .jpg "
                                 "or .exr")
        out = Path(out_dir)
        paths = [output_path(out, name, mkdir=False) for name in names]
        lp_out = None
        if lp_copy is not None:
            same = (out / lp_copy.name).resolve() == lp_copy.resolve()
            # the .lp itself is the output's .lp when the names are kept: nothing to write
            if not (same and names == read_names):
                lp_out = output_path(out, lp_copy.name, mkdir=False)
        with use_variant(mi.variant() or "scalar_rgb"):
            for path, img in zip(paths, imgs):
                _write_image(path, img, capture_like, jpeg_quality)
        if lp_out is not None:
            if names == read_names:
                shutil.copyfile(lp_copy, lp_out)
            else:
                write_lp(lp_out, names, directions)
    return paths


def _image_stack(images: np.ndarray, jpeg_quality: int) -> np.ndarray:
    """Images to write as (K, H, W, C), C = 1 or 3, with the JPEG quality checked."""
    imgs = np.asarray(images)
    if imgs.ndim == 3:
        imgs = imgs[..., None]
    if imgs.ndim != 4 or imgs.shape[3] not in (1, 3):
        raise ValueError(f"images of shape {np.shape(images)}: expected (K, H, W, C) with "
                         "C = 1 or 3")
    if not 1 <= int(jpeg_quality) <= 100:
        raise ValueError(f"jpeg_quality = {jpeg_quality}: expected 1-100")
    return imgs


def _output_names_of(lp_path_or_names: str | Path | Sequence[str]
                     ) -> tuple[list[str], Path | None, list[str], np.ndarray | None]:
    """(output names, the ``.lp`` file or None, the names it lists, its directions) of
    :func:`write_images`' ``lp_path_or_names``; the ``.lp`` file's photographs are noted as
    inputs (those that exist: a relight into the folder of an earlier relight's ``.lp`` may
    replace its own images)."""
    if not isinstance(lp_path_or_names, (str, Path)):
        return list(lp_path_or_names), None, [], None
    lp = Path(lp_path_or_names)
    read_names, directions, _, linenos = read_lp_file(lp)
    note_inputs(p for p in lp_image_paths(lp, read_names) if p.exists())
    names = list(output_names(read_names, [f"{lp}, line {n}" for n in linenos]))
    return names, lp, list(read_names), directions


def _write_image(path: Path, img: np.ndarray, capture_like: Capture, jpeg_quality: int) -> None:
    """Write one image (H, W, C) of linear values with the capture's encoding and bit depth
    (:func:`write_images`); in a Mitsuba variant."""
    path.parent.mkdir(parents=True, exist_ok=True)
    fmt = _FORMATS[path.suffix.lower()]
    values = encode(img, capture_like.encoding)
    quality = -1
    if fmt == "exr":
        dtype = np.float16 if (capture_like.file_format == "exr"
                               and capture_like.bit_depth == 16) else np.float32
        data = values.astype(dtype)
    else:
        depth = 8 if fmt == "jpeg" else (16 if capture_like.bit_depth >= 16 else 8)
        full = 255.0 if depth == 8 else 65535.0
        dtype = np.uint8 if depth == 8 else np.uint16
        data = np.rint(np.clip(values, 0.0, 1.0) * full).astype(dtype)
        quality = int(jpeg_quality) if fmt == "jpeg" else -1
    pixel = mi.Bitmap.PixelFormat.Y if img.shape[2] == 1 else mi.Bitmap.PixelFormat.RGB
    bmp = mi.Bitmap(np.ascontiguousarray(data), pixel)
    bmp.set_srgb_gamma(capture_like.encoding == "srgb" and fmt != "exr")
    bmp.write(str(path), quality=quality)
