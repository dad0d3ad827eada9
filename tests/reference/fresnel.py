"""Exact unpolarised dielectric Fresnel reflectance (reference implementation).

Derivation
----------
A plane wave in a medium of index n1 hits an interface to index n2; the relative
index is ``eta = n2 / n1``. With cos_i the cosine of the angle of incidence,
Snell's law gives sin_t = sin_i / eta. If sin_t >= 1 the wave is totally
internally reflected and R = 1. Otherwise, with cos_t = sqrt(1 - sin_t^2), the
amplitude reflection coefficients are

    r_s = (cos_i - eta cos_t) / (cos_i + eta cos_t)      (TE, s-polarised)
    r_p = (eta cos_i - cos_t) / (eta cos_i + cos_t)      (TM, p-polarised)

and unpolarised light is reflected with R = (r_s^2 + r_p^2) / 2. Transmitted
power is 1 - R (no absorption in the interface).

Conventions in this project: light entering the medium from air uses
``fresnel_reflectance(cos_i, eta)``; light leaving the medium from inside uses
``fresnel_reflectance(cos_inside, 1 / eta)``.

Checks: R(1, 1.5) = 0.04; r_p = 0 at Brewster's angle tan(theta_B) = eta;
R = 1 for sin_i > eta (TIR, only possible for eta < 1); R -> 1 at grazing.

Units: dimensionless. Valid for cos_i in [0, 1] and eta > 0.
"""

from __future__ import annotations

import math
from fractions import Fraction

import numpy as np

__all__ = [
    "fresnel_amplitudes",
    "fresnel_reflectance",
    "fresnel_reflectance_array",
    "critical_cosine",
    "refracted_cosine",
]


def fresnel_amplitudes(cos_i: float, eta: float) -> tuple[float, float] | None:
    """Amplitude coefficients (r_s, r_p) for incidence cosine ``cos_i`` and relative
    index ``eta = n_transmitted / n_incident``; ``None`` under total internal reflection.
    """
    cos_i = float(cos_i)
    eta = float(eta)
    if not (0.0 <= cos_i <= 1.0):
        raise ValueError(f"cos_i must be in [0, 1], got {cos_i}")
    if eta <= 0.0:
        raise ValueError(f"eta must be positive, got {eta}")
    sin2_i = max(0.0, 1.0 - cos_i * cos_i)
    sin2_t = sin2_i / (eta * eta)
    if sin2_t >= 1.0:
        return None
    cos_t = math.sqrt(1.0 - sin2_t)
    rs = (cos_i - eta * cos_t) / (cos_i + eta * cos_t)
    rp = (eta * cos_i - cos_t) / (eta * cos_i + cos_t)
    return rs, rp


def fresnel_reflectance(cos_i: float, eta: float) -> float:
    """Unpolarised Fresnel reflectance R in [0, 1] (scalar, plain Python math).

    ``cos_i``: cosine of the angle of incidence, in [0, 1].
    ``eta``: relative index n_transmitted / n_incident (> 0).
    Returns 1.0 under total internal reflection.
    """
    amp = fresnel_amplitudes(cos_i, eta)
    if amp is None:
        return 1.0
    if cos_i == 0.0:
        return 1.0  # grazing: both coefficients have modulus 1
    rs, rp = amp
    return 0.5 * (rs * rs + rp * rp)


def fresnel_reflectance_array(cos_i, eta: float) -> np.ndarray:
    """Vectorised version of :func:`fresnel_reflectance` over ``cos_i`` (same formula)."""
    c = np.clip(np.asarray(cos_i, dtype=np.float64), 0.0, 1.0)
    sin2_t = (1.0 - c * c) / (eta * eta)
    tir = sin2_t >= 1.0
    cos_t = np.sqrt(np.where(tir, 0.0, 1.0 - sin2_t))
    with np.errstate(divide="ignore", invalid="ignore"):
        rs = (c - eta * cos_t) / (c + eta * cos_t)
        rp = (eta * c - cos_t) / (eta * c + cos_t)
        r = 0.5 * (rs * rs + rp * rp)
    r = np.where(tir | (c == 0.0), 1.0, r)
    return r


def critical_cosine(eta: float) -> float:
    """Cosine (inside the medium) below which light leaving a medium of relative index
    ``eta`` is totally internally reflected: sqrt(1 - 1/eta^2) for eta > 1, else 0."""
    if eta <= 1.0:
        return 0.0
    return math.sqrt(1.0 - 1.0 / (eta * eta))


def refracted_cosine(cos_i: float, eta: float) -> float:
    """Cosine of the refracted angle for incidence cosine ``cos_i`` into relative index
    ``eta`` (Snell); raises under total internal reflection."""
    # Exact rational arithmetic on the float inputs, one rounding before the square root: the
    # float form 1 - sin2_t keeps only rounding noise near the critical angle.
    c, e = Fraction(cos_i), Fraction(eta)
    cos2_t = 1 - (1 - c * c) / (e * e)
    if cos2_t < 0:
        raise ValueError("total internal reflection: no refracted ray")
    return math.sqrt(float(cos2_t))
