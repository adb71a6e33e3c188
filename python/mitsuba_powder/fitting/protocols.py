"""Measurement protocols (gonio geometries) and simulated measurements.

- ``shadows``: the SHADOWS goniometer set of the paper: theta_i in {0, 20, 40, 60},
  azimuth planes phi in {0, 30, 60, 90, 135}, signed theta_o in [-70, 70] by 17.5 (9 values):
  180 geometries.
- ``backscatter``: the back-scattering rig: phi = 0, theta_o in [theta_i - 10, theta_i + 10]
  by 2 deg, theta_i in {0, 20, 40}: 33 geometries.
"""

from __future__ import annotations

import numpy as np

from .._checks import check_range
from ..io.measurements import Measurements

PROTOCOLS = ("shadows", "backscatter")


def geometries(protocol: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(theta_i, theta_o, phi) in degrees of a named protocol."""
    if protocol == "shadows":
        ti, ph, to = np.meshgrid([0.0, 20.0, 40.0, 60.0], [0.0, 30.0, 60.0, 90.0, 135.0],
                                 np.linspace(-70.0, 70.0, 9), indexing="ij")
        return ti.ravel(), to.ravel(), ph.ravel()
    if protocol == "backscatter":
        rows = [(ti, ti + d, 0.0) for ti in (0.0, 20.0, 40.0) for d in np.arange(-10, 11, 2)]
        a = np.array(rows, dtype=np.float64)
        return a[:, 0], a[:, 1], a[:, 2]
    raise ValueError(f"protocol {protocol!r} is not known; valid protocols: "
                     f"{', '.join(PROTOCOLS)}")


def protocol_geometries(names: list[str] | str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Geometries of several protocols, concatenated, without repeated directions."""
    if isinstance(names, str):
        names = [n.strip() for n in names.split(",") if n.strip()]
    if not names:
        raise ValueError("no protocol named; valid protocols: " + ", ".join(PROTOCOLS))
    parts = [geometries(n) for n in names]
    ti, to, ph = (np.concatenate([p[k] for p in parts]) for k in range(3))
    # (theta_o, phi) and (-theta_o, phi + 180) and theta_o = 0 at any phi coincide
    from ..io.measurements import gonio_directions

    wi, wo = gonio_directions(ti, to, ph)
    _, first = np.unique(np.round(np.concatenate([wi, wo], 1), 9), axis=0, return_index=True)
    keep = np.sort(first)
    return ti[keep], to[keep], ph[keep]


def simulate(properties: dict, protocols: list[str] | str, wavelengths=(700.0,),
             noise: float = 0.0, seed: int = 0) -> Measurements:
    """Synthetic measurements: the plugin's BRF at a protocol's geometries.

    Args:
        properties: plugin properties (``mi.load_dict`` form, without ``type``).
        protocols: protocol names (see :data:`PROTOCOLS`), a list or comma-separated.
        wavelengths: nm.
        noise: relative 1-sigma Gaussian noise on the BRF (0.02 = 2 %); also written as the
            ``sigma`` column when > 0.
        seed: random seed of the noise.

    Returns:
        :class:`Measurements` labelled as synthetic in its comments.
    """
    from ..plugin.brf import PowderBRF

    check_range("noise", noise, 0)
    ti, to, ph = protocol_geometries(protocols)
    n = len(ti)
    wl = np.repeat(np.asarray(wavelengths, dtype=np.float64), n)
    tile = lambda a: np.tile(a, len(wavelengths))  # noqa: E731
    data = Measurements(tile(ti), tile(to), tile(ph), wl, np.zeros(len(wl)))
    brf = PowderBRF(data, properties).brf()
    rng = np.random.default_rng(seed)
    sigma = None
    if noise > 0:
        sigma = noise * brf
        brf = brf + rng.normal(size=brf.shape) * sigma
        brf = np.maximum(brf, 0.0)
    comments = [
        "SYNTHETIC DATA (not a measurement): simulated by mitsuba_powder.protocols.simulate",
        f"protocols: {protocols if isinstance(protocols, str) else ','.join(protocols)}; "
        f"relative noise {noise:g} (seed {seed})",
        "properties: " + ", ".join(f"{k}={v}" for k, v in sorted(properties.items())),
    ]
    return Measurements(data.theta_i, data.theta_o, data.phi, wl, brf, sigma, comments,
                        "synthetic")
