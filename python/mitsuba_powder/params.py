"""Plugin properties from a JSON file: plain properties or a ``fit.json``."""

from __future__ import annotations

import json
from pathlib import Path


def load_properties(path: str | Path | None, wavelength: float | None = None,
                    overrides: dict | None = None) -> dict:
    """``powder`` properties (``mi.load_dict`` form, without ``type`` and ``wavelength``).

    Args:
        path: a JSON object of plugin properties, or a ``fit.json`` written by
            ``mitsuba-powder fit`` (its ``parameters``, or ``parameters_by_wavelength`` at
            ``wavelength`` when the fit had per-wavelength values); ``None``: plugin defaults.
        wavelength: nm, selects per-wavelength fitted values when present.
        overrides: properties that replace the file's.

    Raises:
        FileNotFoundError, ValueError: missing file or not a JSON object.
    """
    props: dict = {}
    if path is not None:
        path = Path(path)
        if not path.is_file():
            raise FileNotFoundError(f"parameter file {path} does not exist")
        try:
            spec = json.loads(path.read_text())
        except json.JSONDecodeError as exc:
            raise ValueError(f"parameter file {path}: not valid JSON ({exc})") from None
        if not isinstance(spec, dict):
            raise ValueError(f"parameter file {path}: expected a JSON object of properties")
        by_wl = spec.get("parameters_by_wavelength", {})
        chosen = by_wl.get(f"{wavelength:g}") if wavelength is not None else None
        props = dict(chosen or spec.get("parameters", spec))
    props.update(overrides or {})
    return {k: v for k, v in props.items() if k not in ("type", "wavelength")}
