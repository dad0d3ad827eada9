"""Path-length roulette: the ``"path_roulette"`` field of a spec.

    "path_roulette": {"start": 256, "survival": 0.75}

A photon still in flight after ``start`` interaction steps (free paths: scatterings and surface
reflections) plays Russian roulette: it survives with probability ``survival`` and its weight is
divided by it, else it ends (status absorbed, weight 0).  It plays again after 2 start, 4 start,
... steps.  Unbiased for every tally (the expected weight after a round is the weight before),
whatever the albedo; workers.walk.path_roulette has the proof and the reasons.

Why: at albedo ~1 a half-space walk's path lengths have a heavy tail (a photon that has wandered
deep takes a long time to come back), up to the path cap ``max_scatter``; the long paths take
most of the CPU of an albedo-1 walk but exit far from the entry point (outside a table's radii)
and, reweighted to a shared walk's smaller albedos, carry weights a^n ~ 0.  Off (``null``) by
default: a spec without it runs bit for bit as before.  ``survival`` defaults to 0.75, above
1/sqrt 2: at albedo 1 each doubling of the step count keeps ~1/sqrt 2 of the paths, so with a
smaller survival the weights 1 / survival^k of the paths that survive k rounds spread without
bound as the cap grows (unbiased still, but skewed).
"""

from __future__ import annotations

from typing import Annotated

from pydantic import BaseModel, ConfigDict, Field, field_validator
from pydantic_core import PydanticCustomError

from .constraints import Interval

__all__ = ["PathRoulette", "MIN_START", "MAX_START"]

MIN_START = 16
MAX_START = 1 << 24


class PathRoulette(BaseModel):
    """Russian roulette on path length: at steps start, 2 start, 4 start, ..."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    start: Annotated[int, Interval(MIN_START, MAX_START, what="start")] = Field(
        description=f"Steps before the first round, a power of two in [{MIN_START}, 2**24]; "
        "rounds follow at every doubling of the step count.")
    survival: Annotated[float, Interval(0, 1, lo_open=True, what="survival")] = Field(
        0.75, description="Survival probability of a round, in (0, 1]; survivors' weights are divided by "
        "it.  >= 1/sqrt 2 keeps the variance it adds at albedo 1 bounded (workers.walk.path_roulette).")

    @field_validator("start")
    @classmethod
    def _power_of_two(cls, v: int) -> int:
        if v & (v - 1):
            raise PydanticCustomError(
                "path_roulette_start",
                "path_roulette.start must be a power of two in [{lo}, {hi}]; received {value}",
                {"lo": MIN_START, "hi": "2**24", "value": v})
        return v
