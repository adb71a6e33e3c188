"""Plugin properties from a JSON file: plain properties or a ``fit.json``."""

from __future__ import annotations

from pathlib import Path

from ..outputs import note_input
from ..readers import read_json

#: Every property the ``powder`` plugin's constructor reads (its doc comment's parameter table;
#: tests/plugin/test_params_doc.py checks that the two lists agree)
POWDER_PROPERTIES = (
    "amplitude_volume", "g", "extinction", "radius", "radius2", "fraction2", "radius3",
    "fraction3", "radius4", "fraction4", "material2", "material3", "material4", "eta2", "k2",
    "eta3", "k3", "eta4", "k4", "grains",
    "agglomerate_radius", "agglomerate_fill", "mixing", "material", "eta", "k", "albedo",
    "tau_o", "thickness", "amplitude_surface", "correlation_length", "specular",
    "surface_fresnel", "sigma",
    "lobes", "sampling", "energy", "wavelength", "rgb_wavelengths",
)


def check_property_names(names, what: str = "property") -> None:
    """Raise if a name is not a property of the ``powder`` plugin.

    Args:
        names: property names (e.g. the keys of ``--params`` or ``--set``).
        what: how the names were given, for the message (e.g. ``--set``).

    Raises:
        ValueError: naming the unknown property, the closest valid names and every valid one.
    """
    import difflib

    for name in names:
        if name not in POWDER_PROPERTIES:
            close = difflib.get_close_matches(name, POWDER_PROPERTIES, n=3)
            hint = f"did you mean {', '.join(repr(c) for c in close)}? " if close else ""
            raise ValueError(f"{what} {name!r} is not a property of the powder plugin; {hint}"
                             f"valid properties are {', '.join(POWDER_PROPERTIES)}")


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
        note_input(path)
        spec = read_json(path, "parameter file")
        if not isinstance(spec, dict):
            raise ValueError(f"parameter file {path}: expected a JSON object of properties")
        by_wl = spec.get("parameters_by_wavelength", {})
        chosen = by_wl.get(f"{wavelength:g}") if wavelength is not None else None
        props = dict(chosen or spec.get("parameters", spec))
    props.update(overrides or {})
    return {k: v for k, v in props.items() if k not in ("type", "wavelength")}
