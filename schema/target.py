"""Run to a target error: the ``"target"`` field of a spec.

    "target": {"rel_stderr": 0.002}
    "target": {"rel_stderr": 0.002, "radial": {"rel_stderr": 0.02, "r_min_mm": 0.05, "r_max_mm": 2}}

With a target, the job runs its shards in shard order and stops after the first K shards whose
merged statistics meet it; the result is exactly the merge of shards 0..K-1, so it is bitwise
reproducible from the spec and the seed, and ``photons`` becomes the cap (all ``shards`` shards).
The target holds when, for every estimator row and every configuration (incidence angle x
channel), the ``total`` component has

- total diffuse reflectance Rd with relative standard error <= ``rel_stderr``, and, if
  ``radial`` is given,
- Rd(r) with relative standard error <= ``radial.rel_stderr`` in every radial bin lying within
  [``r_min_mm``, ``r_max_mm``] (r_lo >= r_min_mm and r_hi <= r_max_mm).

A quantity with no contributing event (standard error NaN) or an estimate of 0 does not meet
any target, nor does one whose standard error rests on fewer than 30 independent units (29
degrees of freedom: photons for the exit tally and the hybrid, batches for connections, whose
runs therefore stop no sooner than after 30 batches).  The decision is :func:`workers.fold.target.target_status`; shards should be small enough
(photons / shards) for the stop to come close to the photons actually needed.
"""

from __future__ import annotations

from typing import Annotated

import numpy as np
from pydantic import BaseModel, ConfigDict, Field, model_validator
from pydantic_core import PydanticCustomError

from .constraints import Interval

__all__ = ["TargetSpec", "RadialTarget", "check_radial_target"]

_REL = Interval(0, 1, lo_open=True, hi_open=True, what="rel_stderr")


class RadialTarget(BaseModel):
    """Relative standard error wanted for Rd(r) in every radial bin within [r_min_mm, r_max_mm]."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    rel_stderr: Annotated[float, _REL] = Field(
        description="Largest relative standard error of Rd(r) (total component), in (0, 1)."
    )
    r_min_mm: Annotated[float, Interval(0, None, what="r_min_mm")] = Field(
        0.0, description="Bins with r_lo >= r_min_mm [mm] are checked."
    )
    r_max_mm: Annotated[float, Interval(0, None, lo_open=True, what="r_max_mm")] = Field(
        description="Bins with r_hi <= r_max_mm [mm] are checked."
    )

    @model_validator(mode="after")
    def _range(self) -> RadialTarget:
        if not self.r_min_mm < self.r_max_mm:
            raise PydanticCustomError(
                "radial_target_range",
                "r_min_mm must be below r_max_mm; received r_min_mm={lo}, r_max_mm={hi}",
                {"lo": self.r_min_mm, "hi": self.r_max_mm},
            )
        return self


class TargetSpec(BaseModel):
    """Stop the run once the errors are this small (see the module docstring)."""

    model_config = ConfigDict(frozen=True, extra="forbid")

    rel_stderr: Annotated[float, _REL] = Field(
        description="Largest relative standard error of the total diffuse reflectance Rd of "
        "every configuration (total component), in (0, 1)."
    )
    radial: RadialTarget | None = Field(
        None, description="Optional: also a relative standard error for Rd(r) per radial bin "
        "within a radius range."
    )


def check_radial_target(target: TargetSpec, edges_mm: np.ndarray, channels) -> None:
    """PydanticCustomError unless target.radial's range holds a whole radial bin of each channel
    (edges_mm: [n_channels, n_r + 1] radial edges of the ``channels``, which have a ``name``)."""
    t = target.radial
    for ch, edges in zip(channels, edges_mm):
        if not np.any((edges[:-1] >= t.r_min_mm) & (edges[1:] <= t.r_max_mm)):
            raise PydanticCustomError(
                "radial_target_empty",
                "radial target range [{lo}, {hi}] mm holds no whole radial bin of channel "
                "{ch} (edges {edges} mm); widen it",
                {"lo": t.r_min_mm, "hi": t.r_max_mm, "ch": ch.name,
                 "edges": np.array2string(edges, precision=4, threshold=8)[:120]})
