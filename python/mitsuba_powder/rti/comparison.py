"""Held-out-light comparison of per-pixel models of an RTI capture: interpolation between the
lights and extrapolation to grazing light.

Protocols (K lights, indices in ``.lp`` order from 0):

* ``interpolation``: every fifth light is held out, the lights ``k`` with ``k % 5 == phase``,
  ``phase = 4`` by default (the 5th, 10th, 15th, ... lines of the ``.lp`` file: indices 4, 9,
  14, ...); the others are fitted. Scores depend on the phase (docs/rti.md gives RealRTI
  scores for ``phase = 2``, indices 2, 7, 12, ..., and 4).
* ``grazing`` (extrapolation to grazing light): the ``ceil(K / 6)`` lights of lowest
  elevation (smallest normalised ``lz``; ties broken by ``.lp`` order) are held out; the
  others are fitted.

Score: the held-out RMSE in 8-bit levels, ``255 * sqrt(mean((encode(prediction) -
encode(image))^2))`` over the held-out lights, the pixels of the mask (all without one) and
the channels, where ``encode`` is the capture's encoding (:func:`mitsuba_powder.rti.encode`):
the error on the file's value scale (0-255 for 8-bit files; 16-bit files and EXR on the same
0-255 scale of full scale 1.0). With ``encoding="linear"`` (pixel / 255 taken as linear, as
docs/rti.md's RealRTI scores) this is also the linear error; with ``srgb`` it is the error of the
sRGB-encoded values, and ``rmse_linear_8bit`` (255 x the linear RMSE) is reported beside it.
Predictions are scored as the file would record them: above the full scale (1.0) of an
integer format (PNG, JPEG) a camera records the full scale, so a prediction above it is
scored as 1.0 (:func:`recorded`; EXR files hold any value and are scored as predicted);
otherwise as the model gives them (not clamped below, except by the model itself:
``lambertian_clamped``).

A model is a callable ``fit(images, directions, mask) -> predictor`` (``images`` linear
(K, H, W, C), ``directions`` (K, 3), ``mask`` (H, W) bool or None) whose result has
``predict(directions) -> images`` and, optionally, ``n_parameters`` (per pixel): the
baselines are :func:`baseline_fitter`, and another model (the powder fit) plugs in as one
more entry of the ``models`` dict of :func:`compare`.
"""

from __future__ import annotations

import json
import math
import time
from collections.abc import Callable, Mapping, Sequence
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from ..outputs import output_path
from .baselines import BASELINES, fit_baseline
from .capture import Capture, encode, full_scale
from .checks import check_directions
from .inputs import check_lights, check_signal
from .lights import distance_to_json
from .options import DEFAULTS

__all__ = ["PROTOCOLS", "Comparison", "Row", "baseline_fitter", "compare", "held_out",
           "recorded", "write_comparison"]

PROTOCOLS = ("interpolation", "grazing")

#: a model: fit(images (K, H, W, C), directions (K, 3), mask (H, W) or None) -> predictor
Fitter = Callable[[np.ndarray, np.ndarray, "np.ndarray | None"], Any]


def held_out(protocol: str, directions: np.ndarray, phase: int = 4) -> np.ndarray:
    """Indices (ascending) of the lights a protocol holds out (module docstring).

    Args:
        protocol: ``interpolation`` or ``grazing``.
        directions: (K, 3) light directions in ``.lp`` order.
        phase: interpolation only: hold out the lights ``k % 5 == phase`` (0-4).
    """
    if not isinstance(phase, (int, np.integer)) or not 0 <= phase <= 4:
        raise ValueError(f"phase = {phase!r}: expected an integer 0-4")
    d = np.asarray(directions, dtype=np.float64)
    if d.ndim != 2 or d.shape[1] != 3:
        raise ValueError(f"directions of shape {d.shape}: expected (K, 3)")
    k = d.shape[0]
    if protocol == "interpolation":
        idx = np.arange(int(phase), k, 5)
    elif protocol == "grazing":
        lz = d[:, 2] / np.linalg.norm(d, axis=1)
        idx = np.sort(np.argsort(lz, kind="stable")[:math.ceil(k / 6)])
    else:
        raise ValueError(f"protocol {protocol!r} is not known; choose one of {PROTOCOLS}")
    if len(idx) == 0:
        raise ValueError(f"protocol {protocol!r} holds out no light of {k}; it needs >= 5 "
                         "lights")
    return idx


def baseline_fitter(name: str, light_distance: float = math.inf) -> Fitter:
    """The fit callable of baseline ``name`` (``ptm``, ``hsh``, ``lambertian``) with lights at
    ``light_distance`` image widths (``inf``: distant lights); the pixel mask is not used by
    the fit (every pixel is fitted independently)."""
    if name not in BASELINES:
        raise ValueError(f"model {name!r} is not a baseline; choose among {list(BASELINES)}")

    def fit(images: np.ndarray, directions: np.ndarray, mask: np.ndarray | None = None):
        return fit_baseline(name, images, directions, light_distance=light_distance)

    fit.__name__ = f"fit_{name}" + ("" if math.isinf(light_distance) else "_near")
    return fit


@dataclass
class Row:
    """One model under one protocol.

    Attributes:
        model, protocol: names.
        held_out: indices of the held-out lights (``.lp`` order).
        n_fit: lights fitted.
        n_parameters: fitted numbers per pixel (all channels), or None if the model says not.
        rmse_8bit: held-out RMSE on the file's encoded scale, 8-bit levels (0-255).
        rmse_linear_8bit: 255 x held-out RMSE of the linear values.
        per_light_8bit: held-out RMSE per held-out light, 8-bit levels (encoded scale).
        seconds: fit and prediction time, s.
        note: what the model says of its fit (the powder rows: the shadows it used), or "".
    """

    model: str
    protocol: str
    held_out: list[int]
    n_fit: int
    n_parameters: int | None
    rmse_8bit: float
    rmse_linear_8bit: float
    per_light_8bit: list[float]
    seconds: float
    note: str = ""


@dataclass
class Comparison:
    """Rows of a comparison, the capture's description, and per-pixel error maps.

    ``error_maps[(protocol, model)]`` is float32 (H, W): RMSE over held-out lights and channels
    at each pixel, 8-bit levels on the encoded scale (NaN outside the mask).
    """

    rows: list[Row]
    capture: dict
    error_maps: dict = field(default_factory=dict)


def compare(capture: Capture, models: Mapping[str, Fitter] | Sequence[str] | None = None,
            protocols: Sequence[str] = PROTOCOLS, phase: int = 4,
            light_distance: float = math.inf, saturation: float = DEFAULTS["saturation"],
            saturation_name: str = "saturation") -> Comparison:
    """Fit each model on the kept lights and score it on the held-out ones, per protocol.

    Args:
        capture: the capture (:func:`mitsuba_powder.rti.load_capture`); its mask selects the
            scored pixels.
        models: names of baselines, or a dict name -> fit callable (module docstring);
            default: all baselines.
        protocols: among :data:`PROTOCOLS`.
        phase: the interpolation protocol's phase (:func:`held_out`).
        light_distance: the distance of the lights (image widths) that the near-field models
            (rows ``<model>_near``) use, recorded in the capture's description (``inf``:
            none).
        saturation: the level at or above which an observation is saturated; a capture
            whose pixels mostly see fewer than 3 lights below it (or above 0) is refused
            (:func:`~mitsuba_powder.rti.inputs.check_signal`), as is one of fewer than 3
            lights or lights in one plane (:func:`~mitsuba_powder.rti.inputs.check_lights`).
        saturation_name: how messages name ``saturation`` (e.g. ``--saturation``).

    Returns:
        A :class:`Comparison`.
    """
    if models is None:
        models = list(BASELINES)
    if not isinstance(models, Mapping):
        models = {name: baseline_fitter(name) for name in models}
    if not models:
        raise ValueError("no model to compare")
    dirs, mask = capture.directions, capture.mask
    sel = np.ones(capture.shape, dtype=bool) if mask is None else np.asarray(mask, dtype=bool)
    check_lights(check_directions(dirs))
    check_signal(capture.images, sel, saturation, saturation_name)
    rows: list[Row] = []
    maps: dict = {}
    for protocol in protocols:
        idx = held_out(protocol, dirs, phase)
        for name, fit in models.items():
            row, maps[(protocol, name)] = _score(capture, name, fit, protocol, idx, sel)
            rows.append(row)
    info = {
        "lp": str(capture.lp_path) if capture.lp_path else None,
        "lights": int(len(dirs)),
        "width": capture.shape[1], "height": capture.shape[0], "channels": capture.channels,
        "encoding": capture.encoding, "file_format": capture.file_format,
        "bit_depth": capture.bit_depth,
        "pixels_scored": int(sel.sum()),
        "interpolation_phase": int(phase),
        "light_distance": distance_to_json(light_distance),
    }
    return Comparison(rows, info, maps)


def _score(capture: Capture, name: str, fit: Fitter, protocol: str, idx: np.ndarray,
           sel: np.ndarray) -> tuple[Row, np.ndarray]:
    """Model ``name`` fitted on the lights kept by ``protocol`` and scored on the held-out
    ones ``idx`` at the pixels ``sel``: its row and its error map (8-bit levels)."""
    images, dirs = capture.images, capture.directions
    keep = np.setdiff1d(np.arange(len(dirs)), idx)
    truth = images[idx]
    t0 = time.perf_counter()
    model = fit(images[keep], dirs[keep], capture.mask)
    pred = np.asarray(model.predict(dirs[idx]), dtype=np.float64)
    seconds = time.perf_counter() - t0
    if pred.shape != truth.shape:
        raise ValueError(f"model {name!r}: prediction of shape {pred.shape}, expected "
                         f"{truth.shape}")
    pred = recorded(pred, capture.file_format)
    err = encode(pred, capture.encoding) - encode(truth, capture.encoding)  # (L, H, W, C)
    sq = err[:, sel] ** 2  # (L, P, C)
    rmse = 255.0 * float(np.sqrt(np.mean(sq)))
    rmse_lin = 255.0 * float(np.sqrt(np.mean((pred - truth)[:, sel] ** 2)))
    per_light = (255.0 * np.sqrt(np.mean(sq, axis=(1, 2)))).tolist()
    emap = np.full(capture.shape, np.nan, dtype=np.float32)
    emap[sel] = 255.0 * np.sqrt(np.mean(err[:, sel] ** 2, axis=(0, 2)))
    npar = getattr(model, "n_parameters", None)
    return Row(name, protocol, idx.tolist(), int(len(keep)),
               None if npar is None else int(npar), rmse, rmse_lin, per_light,
               seconds, str(getattr(model, "note", "") or "")), emap


def recorded(values: np.ndarray, file_format: str) -> np.ndarray:
    """Linear ``values`` as a file of ``file_format`` records them: at most the full scale
    (1.0) in an integer format (``png``, ``jpeg``: a camera saturates there), as they are in
    ``exr``."""
    scale = full_scale(file_format)
    return values if math.isinf(scale) else np.minimum(values, scale)


def _markdown(comp: Comparison) -> str:
    c = comp.capture
    scale = ("sRGB-encoded values" if c["encoding"] == "srgb" else
             "linear values (file value / full scale taken as linear)")
    lines = [
        "# Held-out-light comparison",
        "",
        f"Capture: `{c['lp']}`, {c['lights']} lights, {c['width']} x {c['height']} px, "
        f"{c['channels']} channels, {c['file_format']} {c['bit_depth']} bit, encoding "
        f"`{c['encoding']}`; {c['pixels_scored']} pixels scored.",
        "",
        "Lights: distant" + ("." if c.get("light_distance") is None else
                             f"; rows `<model>_near` model them at r = {c['light_distance']:.4g}"
                             " image widths from the image's centre (per-pixel directions and"
                             " 1/d^2 irradiance)."),
        "",
        f"Held-out RMSE in 8-bit levels (0-255) of the {scale}; predictions "
        + ("unclamped" if c["file_format"] == "exr" else
           "above the full scale scored at the full scale (what the file records), "
           "unclamped below") + " (except lambertian_clamped's).",
        f"Protocols: interpolation holds out the lights k % 5 == {c['interpolation_phase']} "
        "(.lp order, from 0); grazing holds out the ceil(K/6) lights of smallest lz.",
    ]
    for protocol in dict.fromkeys(r.protocol for r in comp.rows):
        rows = sorted((r for r in comp.rows if r.protocol == protocol),
                      key=lambda r: r.rmse_8bit)
        lines += ["", f"## {protocol} (held out: {rows[0].held_out}; fitted on "
                  f"{rows[0].n_fit})", "",
                  "| model | parameters / pixel | RMSE (8-bit levels) | "
                  "255 x linear RMSE | time (s) |",
                  "|---|---:|---:|---:|---:|"]
        for r in rows:
            npar = "?" if r.n_parameters is None else str(r.n_parameters)
            lines.append(f"| {r.model} | {npar} | {r.rmse_8bit:.2f} | "
                         f"{r.rmse_linear_8bit:.2f} | {r.seconds:.2f} |")
        notes = [f"- {r.model}: {r.note}" for r in comp.rows
                 if r.protocol == protocol and r.note]
        lines += [""] + notes if notes else []
    return "\n".join(lines) + "\n"


def write_comparison(comp: Comparison, out_dir: str | Path, error_images: bool = True
                     ) -> Path:
    """Write ``compare.md``, ``compare.json`` and (optionally) ``error_<protocol>_<model>.png``
    (per-pixel held-out RMSE, 8-bit levels, colour scale 0 to the largest 99th percentile of
    all maps, magma; grey outside the mask) into ``out_dir``.

    Returns:
        The path of ``compare.md``.
    """
    out = Path(out_dir)
    names = ["compare.md", "compare.json"] + ([f"error_{protocol}_{name}.png" for protocol, name
                                               in comp.error_maps]
                                              if error_images else [])
    target = {n: output_path(out, n) for n in names}  # all checked before writing
    md = target["compare.md"]
    md.write_text(_markdown(comp), encoding="utf-8")
    doc = {"capture": comp.capture, "rows": [asdict(r) for r in comp.rows],
           "units": "RMSE in 8-bit levels (0-255) on the capture's encoded scale; "
                    "rmse_linear_8bit: 255 x RMSE of linear values"}
    target["compare.json"].write_text(json.dumps(doc, indent=2), encoding="utf-8")
    if error_images and comp.error_maps:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        vmax = max(float(np.nanpercentile(m, 99)) for m in comp.error_maps.values())
        cmap = plt.get_cmap("magma").with_extremes(bad="0.5")
        for (protocol, name), m in comp.error_maps.items():
            plt.imsave(target[f"error_{protocol}_{name}.png"], np.ma.masked_invalid(m),
                       cmap=cmap, vmin=0.0, vmax=max(vmax, 1e-6))
    return md
