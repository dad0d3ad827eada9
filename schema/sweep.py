"""Sweeps: a grid of media in optical units, measured in one job (a BSSRDF *database*).

A sweep replaces the spec's ``"medium"`` by a grid over the single-scattering albedo, the
Henyey-Greenstein g and the relative index eta, in optical units: every medium has extinction
sigma_t = 1/mm, so lengths in its tables are in mean free paths (``r_lo_mm`` reads as r sigma_t)::

    "sweep": {"albedo": [0.5, 0.9, 0.99], "g": [0.0, 0.9], "eta": [1.33]}
    "sweep": {"albedo": {"count": 100, "spacing": "pbrt"}, "g": [0.0], "eta": [1.33]}

``albedo`` is a list of values in [0, 1] or a grid of ``count`` values:

* ``"pbrt"``: rho_i = (1 - exp(-8 i / (N - 1))) / (1 - exp(-8)), i = 0..N-1 (pbrt's
  ``BSSRDFTable`` rho samples: dense near albedo 1, where the profile changes fastest);
* ``"linear"``: rho_i = i / (N - 1).

Both include 0 and 1 exactly. Lists are stored sorted ascending and must be distinct.

Medium m of the grid (:func:`sweep_points`) has index m = (i_eta n_g + i_g) n_albedo + i_albedo:
albedo varies fastest, eta slowest (so consecutive media share an eta, which is what a compiled
walk kernel is specialised on). Its own single-medium form is ``sigma_s = albedo``,
``sigma_a = 1 - albedo``, ``g``, ``eta``, one channel; then sigma_a + sigma_s rounds to exactly 1
for every albedo in [0, 1] (fl(1 - a) + a has an error below half an ulp of 1), so the medium's
albedo sigma_s / sigma_t is the grid value to the last bit.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Annotated, Any, Literal, Union

from pydantic import BaseModel, ConfigDict, Discriminator, Field, Tag, field_validator
from pydantic_core import PydanticCustomError

from .constraints import Interval
from .medium import ETA_RANGE, G_RANGE

__all__ = [
    "SweepSpec",
    "AlbedoGrid",
    "SweepPoint",
    "sweep_points",
    "sweep_point",
    "pbrt_albedos",
    "linear_albedos",
    "ALBEDO_RANGE",
    "MAX_ALBEDOS",
    "MAX_AXIS",
    "MAX_MEDIA",
]

ALBEDO_RANGE = Interval(0, 1, what="albedo (single-scattering albedo)")
MAX_ALBEDOS = 1024
"""Most albedo values of a sweep."""
MAX_AXIS = 64
"""Most g values, and most eta values, of a sweep."""
MAX_MEDIA = 65536
"""Most media (n_albedo * n_g * n_eta) of a sweep."""

_CONFIG = ConfigDict(frozen=True, extra="forbid")

PBRT_RHO_EXPONENT = 8.0
"""The 8 of pbrt's rho spacing (1 - exp(-8 i/(N-1))) / (1 - exp(-8))."""


def pbrt_albedos(n: int) -> list[float]:
    """pbrt's albedo samples rho_i = (1 - exp(-8 i/(N-1))) / (1 - exp(-8)), i = 0..n-1, n >= 2.

    Source: pbrt-v3 ``ComputeBeamDiffusionBSSRDF`` (Pharr, Jakob, Humphreys, *Physically Based
    Rendering*, 3rd ed., section 15.5.7). Evaluated as expm1(-8 i/(N-1)) / expm1(-8): 1 - exp(-x)
    loses digits to cancellation for small x (a relative error of 5e-15 at rho ~ 0.02), expm1
    does not. rho_0 = 0 and rho_{n-1} = 1 exactly (the same expression over itself:
    8 (n - 1) / (n - 1) is exactly 8).
    """
    if n < 2:
        raise ValueError(f"pbrt_albedos needs n >= 2; received {n}")
    denom = math.expm1(-PBRT_RHO_EXPONENT)
    return [math.expm1(-PBRT_RHO_EXPONENT * i / (n - 1)) / denom for i in range(n)]


def linear_albedos(n: int) -> list[float]:
    """rho_i = i / (n - 1), i = 0..n-1, n >= 2 (0 and 1 exact)."""
    if n < 2:
        raise ValueError(f"linear_albedos needs n >= 2; received {n}")
    return [i / (n - 1) for i in range(n)]


class AlbedoGrid(BaseModel):
    """``count`` albedos spaced ``"pbrt"`` (default) or ``"linear"`` from 0 to 1."""

    model_config = _CONFIG

    count: Annotated[int, Interval(2, MAX_ALBEDOS, what="albedo count")] = Field(
        description=f"Number of albedos, 2..{MAX_ALBEDOS}."
    )
    spacing: Literal["pbrt", "linear"] = Field(
        "pbrt", description="pbrt: rho_i = (1 - exp(-8 i/(N-1))) / (1 - exp(-8)); "
        "linear: rho_i = i/(N-1)."
    )

    def values(self) -> list[float]:
        """The albedos, ascending."""
        return pbrt_albedos(self.count) if self.spacing == "pbrt" else linear_albedos(self.count)


def _albedo_form(v: Any) -> str | None:
    """Which albedo form an input is: "list", "grid", or None (neither: one clear error)."""
    if isinstance(v, (list, tuple)):
        return "list"
    if isinstance(v, (dict, AlbedoGrid)):
        return "grid"
    return None


Albedo = Annotated[float, ALBEDO_RANGE]
AlbedoAxis = Annotated[
    Union[Annotated[list[Albedo], Tag("list")], Annotated[AlbedoGrid, Tag("grid")]],
    Discriminator(
        _albedo_form, custom_error_type="albedo_form",
        custom_error_message='albedo must be a list of values in [0, 1] or {"count": N, '
        '"spacing": "pbrt" | "linear"}',
    ),
]


def _axis(values: list[float], what: str, n_max: int) -> list[float]:
    """Check an axis of the grid (1..n_max distinct values) and sort it ascending."""
    if not 1 <= len(values) <= n_max:
        raise PydanticCustomError(
            "sweep_axis_count",
            "give between 1 and {n} {what} values (allowed range [1, {n}]); received {got}",
            {"n": n_max, "what": what, "got": len(values)})
    if len(set(values)) != len(values):
        raise PydanticCustomError(
            "sweep_axis_duplicate", "{what} values must be distinct; received {value}",
            {"what": what, "value": repr(values)[:80]})
    return sorted(float(x) for x in values)


class SweepSpec(BaseModel):
    """A grid albedo x g x eta of media in optical units (sigma_t = 1/mm); see the module."""

    model_config = _CONFIG

    albedo: AlbedoAxis = Field(
        description=f"Single-scattering albedos in [0, 1]: a list (1..{MAX_ALBEDOS} distinct "
        'values, stored ascending) or {"count": N, "spacing": "pbrt" | "linear"}.'
    )
    g: list[Annotated[float, G_RANGE]] = Field(
        description=f"Henyey-Greenstein mean cosines in {G_RANGE}, 1..{MAX_AXIS} distinct values."
    )
    eta: list[Annotated[float, ETA_RANGE]] = Field(
        description=f"Relative indices of refraction in {ETA_RANGE}, 1..{MAX_AXIS} distinct values."
    )

    walks: Literal["shared", "independent"] | None = Field(
        None, description='"shared": each group of albedos (see group_edges) is walked once, at '
        'its largest albedo, and every albedo of the group is tallied from that walk by '
        'reweighting (schema/groups.py); "independent": every albedo has its own walk (each row '
        'equals the single-medium job bit for bit). Default: shared for the exits and hybrid '
        'estimators with weights absorption, else independent.'
    )
    group_edges: list[Albedo] | None = Field(
        None, description="Shared walks: albedos in [0, 1] where a new walk group starts (1..64 "
        "distinct values, stored ascending); default (0.3, 0.7)."
    )

    @field_validator("group_edges")
    @classmethod
    def _group_edges(cls, v: list[float] | None) -> list[float] | None:
        return None if v is None else _axis(v, "group_edges", MAX_AXIS)

    @field_validator("albedo")
    @classmethod
    def _albedo_axis(cls, v: list[float] | AlbedoGrid) -> list[float] | AlbedoGrid:
        return v if isinstance(v, AlbedoGrid) else _axis(v, "albedo", MAX_ALBEDOS)

    @field_validator("g")
    @classmethod
    def _g_axis(cls, v: list[float]) -> list[float]:
        return _axis(v, "g", MAX_AXIS)

    @field_validator("eta")
    @classmethod
    def _eta_axis(cls, v: list[float], info) -> list[float]:
        v = _axis(v, "eta", MAX_AXIS)
        albedo, g = info.data.get("albedo"), info.data.get("g")
        if albedo is None or g is None:
            return v  # reported as their own errors
        n_albedo = albedo.count if isinstance(albedo, AlbedoGrid) else len(albedo)
        total = n_albedo * len(g) * len(v)
        if total > MAX_MEDIA:
            raise PydanticCustomError(
                "sweep_media",
                "media n_albedo * n_g * n_eta = {n_a} * {n_g} * {n_e} must be in the allowed "
                "range [1, {limit}]; received {total} media: split it into several sweeps",
                {"n_a": n_albedo, "n_g": len(g), "n_e": len(v), "total": total, "limit": MAX_MEDIA})
        return v

    def albedos(self) -> list[float]:
        """The albedo axis as values, ascending."""
        return self.albedo.values() if isinstance(self.albedo, AlbedoGrid) else list(self.albedo)

    @property
    def n_media(self) -> int:
        """n_albedo * n_g * n_eta."""
        n_albedo = self.albedo.count if isinstance(self.albedo, AlbedoGrid) else len(self.albedo)
        return n_albedo * len(self.g) * len(self.eta)


@dataclass(frozen=True)
class SweepPoint:
    """Medium ``index`` of a sweep: its coordinates (optical units, sigma_t = 1/mm)."""

    index: int
    albedo: float
    g: float
    eta: float

    def medium(self) -> dict[str, Any]:
        """Its single-medium form: sigma_s = albedo, sigma_a = 1 - albedo [1/mm], g, eta.

        sigma_a + sigma_s is exactly 1.0 (module docstring), so the medium's albedo and
        sigma_t are the coordinates to the last bit.
        """
        return {"sigma_a": 1.0 - self.albedo, "sigma_s": self.albedo, "g": self.g, "eta": self.eta}


def sweep_points(sweep: SweepSpec) -> list[SweepPoint]:
    """Every medium of the grid in index order m = (i_eta n_g + i_g) n_albedo + i_albedo."""
    albedos = sweep.albedos()
    return [SweepPoint((i_e * len(sweep.g) + i_g) * len(albedos) + i_a, a, g, eta)
            for i_e, eta in enumerate(sweep.eta) for i_g, g in enumerate(sweep.g)
            for i_a, a in enumerate(albedos)]


def sweep_point(sweep: SweepSpec, index: int) -> SweepPoint:
    """Medium ``index`` of the grid without listing the others; IndexError outside [0, n_media)."""
    if not 0 <= index < sweep.n_media:
        raise IndexError(f"medium index must be in the allowed range [0, {sweep.n_media}); received {index}")
    albedos = sweep.albedos()
    i_a, rest = index % len(albedos), index // len(albedos)
    return SweepPoint(index, albedos[i_a], sweep.g[rest % len(sweep.g)], sweep.eta[rest // len(sweep.g)])
