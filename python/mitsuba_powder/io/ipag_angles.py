"""IPAG angle conventions (:mod:`mitsuba_powder.io.ipag` describes them): deciding which one a
file uses, and mapping IPAG (incidence, emergence, azimuth) to and from the project's
(theta_i, theta_o, phi), all in degrees."""

from __future__ import annotations

import numpy as np

from .dataset import MeasurementError
from .ipag_text import CONVENTIONS


def decide_convention(raw_geometries: list[tuple[float, float, float]], header: str | None,
                      override: str | None, where: list[str]) -> tuple[str, str]:
    """(convention, reason) for a set of IPAG geometries (incidence, emergence, azimuth).

    Args:
        raw_geometries: the geometries as the file writes them, degrees.
        header: ``"physical"`` (an ``Angles physical`` line), ``"count"`` (a geometry-count
            line) or ``None`` (single-geometry files, or neither line).
        override: ``"signed"``, ``"physical"`` or ``None`` (decide).
        where: per geometry, where it was read (for messages).

    Raises:
        MeasurementError: the convention cannot be decided, or the angles contradict it.
    """
    em = np.array([g[1] for g in raw_geometries])
    az = np.array([g[2] for g in raw_geometries])
    az0 = np.isclose(np.mod(az + 180.0, 360.0) - 180.0, 0.0, atol=1e-9)
    how = ("pass convention='signed' (older files: emergence signed, positive on the forward "
           "side) or convention='physical' (newer files and SSHADE: emergence >= 0, azimuth 0 "
           "at opposition); on the command line --convention signed|physical")
    if override is not None:
        if override not in CONVENTIONS:
            raise MeasurementError(f"convention = {override!r} is not known; valid: "
                                   f"{', '.join(CONVENTIONS)} or None (decide from the file)")
        said = {"physical": "physical", "count": "signed"}.get(header or "")
        convention = override
        reason = "chosen by the caller" + (f"; the file's header says {said}"
                                           if said and said != override else "")
    elif header == "physical":
        convention, reason = "physical", "the file's 'Angles physical' line"
    elif header == "count":
        if not az0.all():
            g = int(np.argmax(~az0))
            raise MeasurementError(
                f"{where[g]}: cannot decide the angle convention: a geometry-count line marks "
                f"an older file with a signed emergence and every azimuth 0, but azimuth "
                f"{az[g]:g} is not 0; {how}")
        convention, reason = "signed", "a geometry-count line (older IPAG file)"
    elif np.all(em == 0):
        return "any", "every emergence is 0, where both conventions agree"
    elif np.any(em < 0):
        if not az0.all():
            g, h = int(np.argmax(em < 0)), int(np.argmax(~az0))
            raise MeasurementError(
                f"cannot decide the angle convention: a negative emergence ({em[g]:g}, "
                f"{where[g]}) means signed, but signed files have every azimuth 0 and "
                f"{where[h]} has azimuth {az[h]:g}; {how}")
        convention, reason = "signed", "a negative emergence (signed, older IPAG file)"
    elif not az0.all():
        convention, reason = "physical", "every emergence >= 0 and some azimuth not 0"
    else:
        raise MeasurementError(
            f"{where[0]}: cannot decide the angle convention: every emergence is >= 0 and "
            "every azimuth is 0, which in the signed convention are views on the forward "
            "(specular) side (theta_o = -emergence) and in the physical convention views on "
            f"the light's side (theta_o = +emergence); {how}")
    _check_convention(convention, em, az, az0, where)
    return convention, reason


def _check_convention(convention: str, em: np.ndarray, az: np.ndarray, az0: np.ndarray,
                      where: list[str]) -> None:
    """The emergences ``em`` and azimuths ``az`` (``az0``: azimuth 0) allowed by the chosen
    convention: every azimuth 0 when signed, no negative emergence when physical."""
    if convention == "signed" and not az0.all():
        g = int(np.argmax(~az0))
        raise MeasurementError(f"{where[g]}: azimuth {az[g]:g}: the signed convention (older "
                               "IPAG files) has every azimuth 0; use convention='physical'")
    if convention == "physical" and np.any(em < 0):
        g = int(np.argmax(em < 0))
        raise MeasurementError(f"{where[g]}: emergence {em[g]:g} < 0: the physical convention "
                               "has emergences >= 0; use convention='signed'")


def to_project(incidence, emergence, azimuth, convention: str
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """IPAG angles (degrees) -> the project's (theta_i, theta_o, phi), degrees."""
    ti = np.asarray(incidence, dtype=np.float64)
    e = np.asarray(emergence, dtype=np.float64)
    a = np.asarray(azimuth, dtype=np.float64)
    if convention == "signed":
        return ti, -e, np.zeros_like(e)
    if convention in ("physical", "any"):
        return ti, e.copy(), a.copy()
    raise ValueError(f"convention = {convention!r}; valid: {', '.join(CONVENTIONS)}")


def from_project(theta_i, theta_o, phi, convention: str
                 ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The project's angles (degrees) -> IPAG (incidence, emergence, azimuth) in a convention.

    ``physical``: emergence ``|theta_o|``, azimuth in [0, 360) (``phi + 180`` where
    ``theta_o < 0``). ``signed``: only the plane of incidence (``phi`` 0 or 180, or
    ``theta_o = 0``): emergence ``-theta_o`` at ``phi = 0``, ``+theta_o`` at 180.

    Raises:
        ValueError: ``signed`` and a direction outside the plane of incidence.
    """
    ti = np.asarray(theta_i, dtype=np.float64)
    to = np.asarray(theta_o, dtype=np.float64)
    ph = np.asarray(phi, dtype=np.float64)
    if convention == "physical":
        a = np.mod(np.where(to < 0, ph + 180.0, ph), 360.0)
        return ti, np.abs(to), a + 0.0
    if convention == "signed":
        wrapped = np.mod(ph + 90.0, 360.0) - 90.0          # in [-90, 270)
        on0 = np.isclose(wrapped, 0.0, atol=1e-9)
        on180 = np.isclose(wrapped, 180.0, atol=1e-9)
        bad = ~(on0 | on180 | (to == 0))
        if bad.any():
            k = int(np.argmax(bad))
            raise ValueError(f"row {k}: phi = {ph[k]:g} with theta_o = {to[k]:g} is outside "
                             "the plane of incidence, which is all the signed convention "
                             "(older IPAG files, every azimuth 0) holds; use "
                             "convention='physical'")
        return ti, np.where(on180, to, -to) + 0.0, np.zeros_like(to)
    raise ValueError(f"convention = {convention!r}; valid: {', '.join(CONVENTIONS)}")


