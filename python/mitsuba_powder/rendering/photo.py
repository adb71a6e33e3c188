"""Compare a render with a photograph: read, linearise, calibrate, align, CIEDE2000.

Steps (each one a function, :func:`compare_images` chains them):

1. :func:`read_image`: OpenEXR files through the ``OpenEXR`` package (linear), PNG and JPEG
   (8 or 16 bit) through Mitsuba's bitmap reader; integer images are sRGB-encoded unless
   the caller says ``linear``. The result is linear RGB, float64, (H, W, 3).
2. :func:`calibrate_with_chart` (optional): the photo's ColorChecker 24 (the four corner
   patch centres given in pixels) is sampled and a 3 x 3 matrix (Cheung 2004, through
   colour-science) maps the camera's linear RGB to linear sRGB of colour-science's reference
   chart data (``ColorChecker24 - After November 2014``, D50, Bradford-adapted to D65).
3. :func:`align`: per-channel gains (``white-balance``) or one gain (``exposure``) that best
   map the photo onto the render in the least-squares sense; reported as stops and ratios.
4. :func:`delta_e_2000`: CIE L*a*b* (D65, the white at a given linear level) and CIEDE2000
   per pixel (colour-science).
"""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass
from pathlib import Path

import colour
import numpy as np

from .._checks import check_range
from ..outputs import note_input, output_file, output_path
from ..readers import read_bitmap

ENCODINGS = ("auto", "linear", "srgb")
ALIGNMENTS = ("none", "exposure", "white-balance")
CHART = "ColorChecker24 - After November 2014"
#: corner patches of the 6 x 4 chart, in the order the corners are given
CHART_CORNERS = ("dark skin (top left)", "bluish green (top right)",
                 "black (bottom right)", "white (bottom left)")


def read_image(path: str | Path, encoding: str = "auto") -> np.ndarray:
    """Linear RGB (H, W, 3) float64 of an image file.

    Args:
        path: ``.exr`` (OpenEXR), ``.png`` or ``.jpg``/``.jpeg`` (8 or 16 bit).
        encoding: ``auto`` (EXR linear, integer formats sRGB), ``linear`` or ``srgb``.

    Raises:
        FileNotFoundError, ValueError: missing file, unknown format or encoding, no RGB.
    """
    path = Path(path)
    if encoding not in ENCODINGS:
        raise ValueError(f"encoding = {encoding!r} is not valid; choose one of {ENCODINGS}")
    if not path.is_file():
        raise FileNotFoundError(f"image {path} does not exist")
    note_input(path)
    suffix = path.suffix.lower()
    if suffix == ".exr":
        rgb = _read_exr(path)
        is_float = True
    elif suffix in (".png", ".jpg", ".jpeg"):
        import mitsuba as mi

        from ..variants import use_variant

        # mi.Bitmap needs a variant, any will do: the caller's, else scalar_rgb
        with use_variant(mi.variant() or "scalar_rgb"):
            bmp = read_bitmap(path)
            scale = {mi.Struct.Type.UInt8: 255.0, mi.Struct.Type.UInt16: 65535.0}.get(
                bmp.component_format())
            if scale is None:
                raise ValueError(f"image {path}: component format {bmp.component_format()} "
                                 "is not 8 or 16 bit")
            arr = np.array(bmp, dtype=np.float64) / scale
        if arr.ndim == 2:
            arr = arr[..., None]
        if arr.shape[2] in (1, 2):  # grey (+ alpha)
            arr = np.repeat(arr[..., :1], 3, axis=2)
        rgb = arr[..., :3]
        is_float = False
    else:
        raise ValueError(f"image {path}: format {suffix!r} is not supported; use .exr, .png "
                         "or .jpg")
    if encoding == "srgb" or (encoding == "auto" and not is_float):
        rgb = colour.cctf_decoding(np.clip(rgb, 0.0, None), function="sRGB")
    return np.asarray(rgb, dtype=np.float64)


def _read_exr(path: Path) -> np.ndarray:
    import OpenEXR

    with OpenEXR.File(str(path)) as f:
        channels = f.channels()
        if "RGB" in channels:
            arr = np.asarray(channels["RGB"].pixels, dtype=np.float64)
        elif "RGBA" in channels:
            arr = np.asarray(channels["RGBA"].pixels, dtype=np.float64)[..., :3]
        elif all(c in channels for c in "RGB"):
            arr = np.stack([np.asarray(channels[c].pixels, dtype=np.float64) for c in "RGB"],
                           axis=-1)
        elif "Y" in channels:
            arr = np.repeat(np.asarray(channels["Y"].pixels, dtype=np.float64)[..., None],
                            3, axis=-1)
        else:
            raise ValueError(f"image {path}: no R, G, B (or Y) channels; it has "
                             f"{sorted(channels)}")
    return arr


def write_exr(path: str | Path, rgb: np.ndarray) -> Path:
    """Write linear RGB (H, W, 3) as a float32 OpenEXR file."""
    import OpenEXR

    path = output_file(path)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": np.ascontiguousarray(rgb, dtype=np.float32)}) as f:
        f.write(str(path))
    return path


def chart_reference_rgb() -> np.ndarray:
    """Linear sRGB (24, 3) of colour-science's ColorChecker 24 reference, D50 -> D65
    (Bradford), rows in the chart's order (dark skin ... black)."""
    chart = colour.CCS_COLOURCHECKERS[CHART]
    xyy = np.array(list(chart.data.values()), dtype=np.float64)
    xyz = colour.xyY_to_XYZ(xyy)
    return colour.XYZ_to_RGB(xyz, "sRGB", illuminant=chart.illuminant,
                             chromatic_adaptation_transform="Bradford",
                             apply_cctf_encoding=False)


def chart_patch_centres(corners) -> np.ndarray:
    """Pixel centres (24, 2) of the 6 x 4 patches from the four corner patch centres
    ``(x, y)`` in :data:`CHART_CORNERS` order (bilinear, so a tilted chart works)."""
    c = np.asarray(corners, dtype=np.float64)
    if c.shape != (4, 2):
        raise ValueError(f"chart corners: expected 4 (x, y) points ({', '.join(CHART_CORNERS)})"
                         f", got an array of shape {c.shape}")
    tl, tr, br, bl = c
    out = []
    for row in range(4):
        v = row / 3.0
        for col in range(6):
            u = col / 5.0
            out.append((1 - u) * (1 - v) * tl + u * (1 - v) * tr + u * v * br + (1 - u) * v * bl)
    return np.array(out)


def sample_patches(image: np.ndarray, centres: np.ndarray, half: int) -> np.ndarray:
    """Mean RGB (24, 3) in a ``(2 half + 1)^2`` pixel window around each centre."""
    check_range("chart window half-size (--chart-window)", half, 0, unit="px")
    h, w = image.shape[:2]
    out = []
    for x, y in centres:
        xi, yi = int(round(x)), int(round(y))
        if not (half <= xi < w - half and half <= yi < h - half):
            raise ValueError(f"chart patch centre ({x:.1f}, {y:.1f}) with a {2 * half + 1} px "
                             f"window is outside the {w} x {h} image")
        out.append(image[yi - half:yi + half + 1, xi - half:xi + half + 1].reshape(-1, 3)
                   .mean(axis=0))
    return np.array(out)


def calibrate_with_chart(photo: np.ndarray, corners, half: int = 3
                         ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Colour-correct ``photo`` (linear camera RGB) with the ColorChecker in it.

    Returns:
        (calibrated photo, the 3 x 3 matrix, CIEDE2000 of the 24 corrected patches against
        the reference).
    """
    measured = sample_patches(photo, chart_patch_centres(corners), half)
    reference = chart_reference_rgb()
    matrix = colour.characterisation.matrix_colour_correction_Cheung2004(measured, reference,
                                                                          terms=3)
    corrected = photo @ matrix.T
    patches = measured @ matrix.T
    de = delta_e_2000(patches[None], reference[None], white=1.0)[0]
    return corrected, matrix, de


def align(render: np.ndarray, photo: np.ndarray, mode: str = "white-balance",
          mask: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
    """Gains ``g`` (3,) minimising ``|render - g photo|^2`` over ``mask`` (per channel for
    ``white-balance``, one for ``exposure``, ones for ``none``); returns (g photo, g)."""
    if mode not in ALIGNMENTS:
        raise ValueError(f"align = {mode!r} is not valid; choose one of {ALIGNMENTS}")
    if mode == "none":
        return photo, np.ones(3)
    m = np.ones(render.shape[:2], bool) if mask is None else mask
    r, p = render[m], photo[m]
    for name, values in (("render", r), ("photo", p)):
        dark = np.sum(values * values, axis=0) <= 0
        if (dark.all() if mode == "exposure" else dark.any()):
            channels = "every channel" if dark.all() else "channel " + ", ".join(
                "RGB"[c] for c in np.nonzero(dark)[0])
            raise ValueError(f"alignment failed: the {name} has no signal ({channels} is 0 in "
                             "the compared region)" + (
                                 ": is the scene lit, and does the camera see the powder?"
                                 if name == "render" else ""))
    if mode == "exposure":
        g = np.full(3, np.sum(r * p) / max(np.sum(p * p), 1e-300))
    else:
        g = np.sum(r * p, axis=0) / np.maximum(np.sum(p * p, axis=0), 1e-300)
    if not np.all(np.isfinite(g)) or np.any(g <= 0):
        raise ValueError(f"alignment failed (gains {g.tolist()}): the photo has no signal in "
                         "the compared region")
    return photo * g, g


def delta_e_2000(a: np.ndarray, b: np.ndarray, white: float) -> np.ndarray:
    """CIEDE2000 per pixel between linear sRGB images ``a`` and ``b``; ``white`` is the
    linear value that maps to L* = 100 (Y = 1), D65."""
    check_range("white", white, 0.0, closed="()")
    d65 = colour.CCS_ILLUMINANTS["CIE 1931 2 Degree Standard Observer"]["D65"]

    def lab(x: np.ndarray) -> np.ndarray:
        xyz = colour.RGB_to_XYZ(np.clip(x / white, 0.0, None), "sRGB",
                                apply_cctf_decoding=False)
        return colour.XYZ_to_Lab(xyz, d65)

    return colour.delta_E(lab(a), lab(b), method="CIE 2000")


@dataclass
class Comparison:
    """What :func:`compare_images` found (JSON-serialisable, except the arrays)."""

    mean: float
    median: float
    p95: float
    max: float
    pixels: int
    gains: list[float]
    exposure_stops: float
    white_balance: list[float]
    white: float
    saturated_pixels: int = 0
    region_pixels: int = 0
    clipped_fraction: float = 0.0
    chart_matrix: list[list[float]] | None = None
    chart_delta_e_mean: float | None = None
    chart_delta_e_max: float | None = None


def _region_mask(h: int, w: int, region) -> np.ndarray:
    """(H, W) booleans: the pixels of ``region`` ``(x0, y0, x1, y1)`` (all when None)."""
    mask = np.zeros((h, w), bool)
    if region is None:
        mask[:] = True
        return mask
    x0, y0, x1, y1 = (int(v) for v in region)
    if not (0 <= x0 < x1 <= w and 0 <= y0 < y1 <= h):
        raise ValueError(f"region = {tuple(region)} is out of range; valid: 0 <= x0 < x1 <= "
                         f"{w}, 0 <= y0 < y1 <= {h}")
    mask[y0:y1, x0:x1] = True
    return mask


def _leave_out_clipped(photo: np.ndarray, mask: np.ndarray, saturation: float | None,
                       max_clipped: float) -> int:
    """Clear from ``mask`` (in place) the photo pixels with a channel at or above
    ``saturation``; returns how many were cleared.

    Raises:
        ValueError: every pixel clipped, or more than ``max_clipped`` of them.
    """
    if saturation is None:
        return 0
    region_pixels = int(mask.sum())
    clipped = np.any(photo >= saturation, axis=2) & mask
    saturated = int(clipped.sum())
    mask &= ~clipped
    if not mask.any():
        raise ValueError(f"saturation = {saturation}: every compared photo pixel is clipped")
    if saturated > max_clipped * region_pixels:
        raise ValueError(
            f"{saturated} of the {region_pixels} compared photo pixels "
            f"({100 * saturated / region_pixels:.1f} %) are clipped (a channel >= "
            f"{saturation:g}), more than max_clipped (--max-clipped) = {max_clipped:g}: "
            "the comparison would leave out the brightest parts of the sample. Take the "
            "photo at a lower exposure, or give --region, or raise --max-clipped")
    return saturated


def compare_images(render: np.ndarray, photo: np.ndarray, *, corners=None, chart_half: int = 3,
                   align_mode: str = "white-balance", region=None, white: float | None = None,
                   saturation: float | None = None, max_clipped: float = 0.1
                   ) -> tuple[Comparison, np.ndarray, np.ndarray]:
    """Compare linear RGB images of the same size.

    Args:
        render, photo: (H, W, 3) linear RGB.
        corners: ColorChecker corner patch centres in the photo (see :data:`CHART_CORNERS`),
            or ``None`` for no calibration.
        chart_half: half-size of the patch sampling window, px.
        align_mode: ``none``, ``exposure`` or ``white-balance``.
        region: ``(x0, y0, x1, y1)`` pixels to compare (default: the whole image).
        white: linear level of L* = 100; default the render's 99th percentile of luminance.
        saturation: photo pixels with a channel at or above this linear value (before
            calibration) are clipped and left out of the alignment and the statistics (e.g.
            0.99 for 8/16-bit photos); ``None`` keeps every pixel.
        max_clipped: the largest fraction (0-1) of the region's pixels that may be clipped;
            more is an error, since the statistics would then describe what is left (often
            the background) rather than the sample (lower the photo's exposure, or give a
            region). 1 never stops.

    Returns:
        (:class:`Comparison`, the aligned photo, the CIEDE2000 map (NaN outside the region)).
    """
    if render.shape != photo.shape:
        raise ValueError(f"the render is {render.shape[1]} x {render.shape[0]} px and the photo "
                         f"{photo.shape[1]} x {photo.shape[0]} px: crop or register them to the "
                         "same size first")
    h, w = render.shape[:2]
    mask = _region_mask(h, w, region)
    check_range("max_clipped (--max-clipped)", max_clipped, 0.0, 1.0, "[]")
    mask &= np.all(np.isfinite(render), axis=2) & np.all(np.isfinite(photo), axis=2)
    region_pixels = int(mask.sum())
    saturated = _leave_out_clipped(photo, mask, saturation, max_clipped)
    matrix = chart_de = None
    if corners is not None:
        photo, matrix, chart_de = calibrate_with_chart(photo, corners, chart_half)
    aligned, gains = align(render, photo, align_mode, mask)
    lum = render[mask] @ np.array([0.2126, 0.7152, 0.0722])
    if white is None:
        white = float(np.percentile(lum, 99.0)) if lum.size else 1.0
        if white <= 0:
            raise ValueError("the render is black in the compared region: give white")
    de = np.full((h, w), np.nan)
    de[mask] = delta_e_2000(render[mask], aligned[mask], white)
    vals = de[mask]
    stats = Comparison(
        mean=float(vals.mean()), median=float(np.median(vals)),
        p95=float(np.percentile(vals, 95)), max=float(vals.max()), pixels=int(vals.size),
        gains=[float(g) for g in gains], exposure_stops=float(np.log2(gains[1])),
        white_balance=[float(gains[0] / gains[1]), 1.0, float(gains[2] / gains[1])],
        white=float(white), saturated_pixels=saturated, region_pixels=region_pixels,
        clipped_fraction=saturated / max(region_pixels, 1),
        chart_matrix=None if matrix is None else np.asarray(matrix).tolist(),
        chart_delta_e_mean=None if chart_de is None else float(np.mean(chart_de)),
        chart_delta_e_max=None if chart_de is None else float(np.max(chart_de)))
    return stats, aligned, de


def write_report(out_dir: str | Path, stats: Comparison, render: np.ndarray,
                 photo: np.ndarray, de: np.ndarray) -> Path:
    """``photo_comparison.json``, ``delta_e.png`` (the map) and ``side_by_side.png`` (render,
    aligned photo, map) into ``out_dir``; returns the JSON path."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    out = Path(out_dir)
    target = {n: output_path(out, n) for n in ("photo_comparison.json", "delta_e.png",
                                                "side_by_side.png")}
    path = target["photo_comparison.json"]
    path.write_text(json.dumps(asdict(stats), indent=1))
    show = lambda x: np.clip(colour.cctf_encoding(np.clip(x / stats.white, 0, 1),  # noqa: E731
                                                  function="sRGB"), 0, 1)
    from matplotlib.patches import Patch

    vmax = max(5.0, float(np.nanpercentile(de, 99)))
    # pixels left out (outside the region, clipped, not finite) in a neutral grey, not at an
    # end of the colour scale
    cmap = plt.get_cmap("viridis").with_extremes(bad="0.6")
    left_out = Patch(facecolor="0.6", edgecolor="0.3",
                     label=f"left out ({stats.saturated_pixels} clipped; outside the region)")
    fig, ax = plt.subplots(figsize=(6, 4.5))
    im = ax.imshow(np.ma.masked_invalid(de), cmap=cmap, vmin=0, vmax=vmax)
    fig.colorbar(im, ax=ax, label="CIEDE2000")
    ax.set_title(f"Delta E 2000: mean {stats.mean:.2f}, p95 {stats.p95:.2f}")
    ax.legend(handles=[left_out], loc="upper center", bbox_to_anchor=(0.5, -0.02),
              fontsize=8, frameon=False)
    ax.axis("off")
    fig.savefig(target["delta_e.png"], dpi=120, bbox_inches="tight")
    plt.close(fig)
    fig, axes = plt.subplots(1, 3, figsize=(13, 4))
    for a, img, title in zip(axes[:2], (render, photo), ("render", "photo (aligned)"),
                             strict=True):
        a.imshow(show(img))
        a.set_title(title)
        a.axis("off")
    im = axes[2].imshow(np.ma.masked_invalid(de), cmap=cmap, vmin=0, vmax=vmax)
    axes[2].set_title("CIEDE2000 (grey: left out)")
    axes[2].axis("off")
    fig.colorbar(im, ax=axes[2], fraction=0.046)
    fig.savefig(target["side_by_side.png"], dpi=110, bbox_inches="tight")
    plt.close(fig)
    return path
