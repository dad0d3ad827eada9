"""Radial path stretching: the ``"stretch"`` field of a spec.

    "stretch": {"gamma": 0.6, "r_min_mfp": 0.0, "albedo_max": 0.7, "gamma_inward": 0.2}

An exponential transform of the free paths: a flight that starts ``r_min_mfp`` mean free paths or
more from the entry axis, after the first scattering, at an albedo below ``albedo_max``, draws its
length from sigma* exp(-sigma* s) with sigma* = 1 - gamma mu (mu: the outward horizontal cosine of
its direction; ``gamma_inward`` in place of gamma for inward flights, mu < 0, when given), and the
photon's weight carries the likelihood ratio.  Unbiased for every tally;
it sends more photons to the far radial bins, which at low albedo otherwise take 1e8-1e9 photons
(workers.walk.stretch derives it and bounds the weights' spread: 1 / (1 - gamma^2) per flight in
second moment; ``gamma_inward`` <= 0.3 keeps the fourth moment finite as well, which makes the
per-bin error estimates themselves steady).  Geometry only: a shared walk's members reweight as before.

Off (``null``) by default: a spec without it runs bit for bit as before; likewise a ``stretch``
without ``gamma_inward`` (inward flights then use gamma) hashes and runs as before.
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field

from .constraints import Interval

__all__ = ["Stretch", "MAX_GAMMA", "MAX_GAMMA_INWARD"]

MAX_GAMMA = 0.95
MAX_GAMMA_INWARD = 0.3  # below 1/3: an inward flight's weight ratio keeps a finite fourth moment


class Stretch(BaseModel):
    """Radial path stretching (exponential transform of the free paths outward)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    gamma: Annotated[float, Interval(0, MAX_GAMMA, lo_open=True, what="gamma")] = Field(
        0.6, description=f"Strength, in (0, {MAX_GAMMA}]: sigma* = 1 - gamma mu; the weights' second moment "
        "grows by at most 1 / (1 - gamma^2) per stretched flight.")
    r_min_mfp: Annotated[float, Interval(0, 10_000, what="r_min_mfp")] = Field(
        0.0, description="Flights starting at least this far from the entry axis (mean free paths, in [0, 10000]) "
        "are stretched.")
    albedo_max: Annotated[float, Interval(0, 1, lo_open=True, what="albedo_max")] = Field(
        0.7, description="Only walks at albedos below it are stretched (the walked albedo of a shared walk); in (0, 1].")
    gamma_inward: Annotated[float, Interval(0, MAX_GAMMA_INWARD, what="gamma_inward")] | None = Field(
        None, description=f"Strength for inward flights (mu < 0), in [0, {MAX_GAMMA_INWARD}]: sigma* = 1 - gamma_inward mu "
        "there. Absent: gamma, as before. At most 0.3 keeps the fourth moment of the weights finite, so per-bin "
        "error estimates (and a target's stop) do not jump; 0 leaves inward flights unstretched.")

    def inward(self) -> float:
        """The strength of inward flights: gamma_inward, or gamma when it is absent."""
        return self.gamma if self.gamma_inward is None else self.gamma_inward
