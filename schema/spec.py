"""The simulation spec: medium, incidence angles, bins, photon budget, sharding and options.

A spec fully determines a dataset: same spec (including ``seed``, ``shards`` and
``batches_per_shard``) gives bitwise-identical tables whatever machines run it. Shards and
batches therefore belong to the spec, not to the deployment: shard i simulates photons
[floor(i N / S), floor((i + 1) N / S)) of N per incidence angle and channel, and each shard
splits its range the same way into ``batches_per_shard`` batches, the independent samples the
standard errors are estimated from.

Incidence angles theta_i are in degrees in the x-z plane, 0 = normal; the incoming ray travels
along (sin theta_i, 0, -cos theta_i) (workers/walk/conventions.py, "Directions").
"""

from __future__ import annotations

import hashlib
import json
import math
from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    AfterValidator,
    BaseModel,
    ConfigDict,
    Field,
    ValidationInfo,
    field_validator,
    model_validator,
)
from pydantic_core import PydanticCustomError

from .bins import (
    MAX_TOTAL_BINS,
    BinSpec,
    azimuth_edges,
    channel_radial_edges_mm,
    theta_s_count,
    uniform_edges,
)
from .groups import SHARED_ESTIMATORS
from .constraints import Interval
from .errors import ShardIndexError
from . import groups as _groups
from . import media as _media
from .medium import ChannelOptics, MediumSpec
from .names import NAME_MAX, NAME_PATTERN, NAME_RULE, InvalidName, check_name
from .sweep import SweepSpec
from .roulette import PathRoulette
from .stretch import Stretch
from .target import TargetSpec, check_radial_target

__all__ = ["SimulationSpec", "MAX_PHOTONS", "MAX_INCIDENCE", "MAX_TASKS"]

MAX_PHOTONS = 2**40
"""Most photons per incidence angle per channel (photon indices must fit the random streams)."""

MAX_INCIDENCE = 32
"""Most incidence angles in one spec."""

MAX_TASKS = 1_000_000
"""Most shard tasks (media * shards) of one job."""

_INCIDENCE = Interval(0, 90, hi_open=True, what="incidence angle [deg]")


def _check_name(v: str) -> str:
    try:
        return check_name(v)
    except InvalidName as exc:
        raise PydanticCustomError("bad_name", str(exc).replace("{", "{{").replace("}", "}}")) from None


class SimulationSpec(BaseModel):
    """Everything a run needs; the fully-defaulted model is what :meth:`spec_hash` hashes."""

    model_config = ConfigDict(
        frozen=True, extra="forbid",
        json_schema_extra={"oneOf": [{"required": ["medium"]}, {"required": ["sweep"]}]},
    )

    name: Annotated[str, AfterValidator(_check_name)] = Field(
        description=f"Dataset name: {NAME_RULE.format(n=NAME_MAX)}.",
        json_schema_extra={"pattern": NAME_PATTERN},
    )
    description: str | None = Field(None, max_length=2000, description="Free text for humans.")
    medium: MediumSpec | None = Field(
        None, description='The medium; exactly one of "medium" and "sweep" is given.'
    )
    sweep: SweepSpec | None = Field(
        None, description="A grid of media albedo x g x eta in optical units (sigma_t = 1/mm), "
        "measured in one job; instead of medium."
    )
    incidence_deg: list[Annotated[float, _INCIDENCE]] = Field(
        default_factory=lambda: [0.0],
        description="Incidence angles theta_i in degrees, each in [0, 90); 1..32 distinct values, "
        "stored sorted ascending.",
        validate_default=True,
    )
    bins: BinSpec = Field(default_factory=BinSpec, validate_default=True)
    photons: Annotated[int, Interval(1, MAX_PHOTONS, what="photons")] = Field(
        100_000, description="Photons per incidence angle per channel (per medium of a sweep), "
        "1..2**40."
    )
    seed: Annotated[int, Interval(0, 2**63 - 1, what="seed")] = 0
    shards: Annotated[int, Interval(1, 100_000, what="shards")] = Field(
        8, description="Independent work units (per medium of a sweep), 1..100000 and <= photons; "
        "media * shards <= 1000000.", validate_default=True
    )
    batches_per_shard: Annotated[int, Interval(1, 1024, what="batches_per_shard")] = Field(
        4, description="Batches per shard for standard errors, 1..1024; shards * batches_per_shard "
        "must be in [2, photons].", validate_default=True,
    )
    estimator: Literal["hybrid", "exits", "connections", "both"] = Field(
        "hybrid", description="hybrid (default): single scattering by connections from the first "
        "vertex, multiple by the exit tally; exits: the exit tally alone; connections: every "
        "vertex connected to every bin; both: exits and connections on one walk.",
    )
    absorption: Literal["weights", "analog"] = Field(
        "weights", description="Weights with Russian roulette (default) or analog absorption."
    )
    max_scatter: Annotated[int, Interval(1, 10_000_000, what="max_scatter")] = Field(
        100_000, description="Path cap in scattering events; the truncated weight is reported."
    )
    path_roulette: PathRoulette | None = Field(
        None, description="Russian roulette on path length (off by default): a photon still in flight "
        "after start steps survives with probability survival, weight divided by it, and again at every "
        "doubling of its step count; unbiased; see schema/roulette.py.",
    )
    stretch: Stretch | None = Field(
        None, description="Radial path stretching (off by default): an exponential transform of the free "
        "paths outward at low albedo, weights carrying the likelihood ratio; unbiased; see schema/stretch.py.",
    )
    target: TargetSpec | None = Field(
        None, description="Run shards in order until these relative standard errors are reached "
        "(photons is then the cap); see schema/target.py.",
    )

    @property
    def table_estimators(self) -> tuple[str, ...]:
        """The values of the tables' ``estimator`` column this spec gives: ``"both"`` is exits
        and connections on one walk, every other estimator itself."""
        return ("exits", "connections") if self.estimator == "both" else (self.estimator,)

    @model_validator(mode="before")
    @classmethod
    def _one_medium_form(cls, data: Any) -> Any:
        """Exactly one of "medium" and "sweep"."""
        if isinstance(data, dict):
            given = [k for k in ("medium", "sweep") if data.get(k) is not None]
            if len(given) != 1:
                raise PydanticCustomError(
                    "medium_or_sweep",
                    'give exactly one of "medium" (one medium) or "sweep" (a grid of media); '
                    "received {received}", {"received": " and ".join(given) or "neither"})
        return data

    @model_validator(mode="after")
    def _shared_walks_need_reweightable_tallies(self) -> SimulationSpec:
        """A sweep's shared walks reweight each photon's exit and first vertex: only the exits
        and hybrid estimators with weights absorption can be reweighted (schema.groups)."""
        sweep = self.sweep
        if sweep is not None and sweep.walks == "shared":
            if self.estimator not in SHARED_ESTIMATORS or self.absorption != "weights":
                raise PydanticCustomError(
                    "shared_walks",
                    'sweep.walks "shared" needs estimator "exits" or "hybrid" and absorption '
                    '"weights"; received estimator {estimator}, absorption {absorption}: '
                    'set "walks": "independent" for this estimator or absorption',
                    {"estimator": self.estimator, "absorption": self.absorption})
        return self

    @field_validator("incidence_deg")
    @classmethod
    def _incidence_list(cls, v: list[float]) -> list[float]:
        if not 1 <= len(v) <= MAX_INCIDENCE:
            raise PydanticCustomError(
                "incidence_count",
                "give between 1 and {n} incidence angles (allowed range [1, {n}]); "
                "received {got}", {"n": MAX_INCIDENCE, "got": len(v)})
        if len(set(v)) != len(v):
            raise PydanticCustomError(
                "incidence_duplicate", "incidence angles must be distinct; received {value}",
                {"value": repr(v)[:80]})
        return sorted(float(x) for x in v)

    @field_validator("bins")
    @classmethod
    def _total_bins(cls, bins: BinSpec, info: ValidationInfo) -> BinSpec:
        incidence = info.data.get("incidence_deg")
        if incidence is None or "medium" not in info.data or "sweep" not in info.data:
            return bins  # already reported as their own errors
        medium = info.data["medium"]
        n_channels = medium.n_channels if medium is not None else 1  # per medium of a sweep
        n_theta = theta_s_count(bins, incidence)
        factors = [bins.radial.count, n_theta, bins.cos_theta_o.count, bins.phi_o.count,
                   n_channels, len(incidence)]
        total = math.prod(factors)
        if total > MAX_TOTAL_BINS:
            raise PydanticCustomError(
                "too_many_bins",
                "total bin count n_r * n_theta_s * n_cos * n_phi * n_channels * n_incidence = "
                "{product} = {total} exceeds the limit 2**24 = {limit}; use fewer bins",
                {"product": " * ".join(map(str, factors)), "total": total,
                 "limit": MAX_TOTAL_BINS})
        return bins

    @field_validator("target")
    @classmethod
    def _target_selects_radial_bins(cls, target: TargetSpec | None, info: ValidationInfo) -> TargetSpec | None:
        """A radial target must cover at least one radial bin of every channel."""
        medium, bins = info.data.get("medium"), info.data.get("bins")
        if target is None or target.radial is None or medium is None or bins is None:
            return target
        check_radial_target(target, channel_radial_edges_mm(bins, medium.channels()), medium.channels())
        return target

    @field_validator("target")
    @classmethod
    def _target_selects_radial_bins_of_every_medium(cls, target: TargetSpec | None, info: ValidationInfo) -> TargetSpec | None:
        """A sweep's radial target must cover at least one radial bin of every medium (their
        radial extents differ with the transport mean free path, 1 / (1 - albedo g) mm)."""
        sweep, bins = info.data.get("sweep"), info.data.get("bins")
        if target is None or target.radial is None or sweep is None or bins is None:
            return target
        pairs = sorted({(a, g) for a in sweep.albedos() for g in sweep.g})
        channels = [ChannelOptics(name=f"albedo {a:g}, g {g:g}", sigma_a=1.0 - a, sigma_s=a, g=g) for a, g in pairs]
        check_radial_target(target, channel_radial_edges_mm(bins, channels), channels)
        return target

    @field_validator("shards")
    @classmethod
    def _shards_vs_photons(cls, v: int, info: ValidationInfo) -> int:
        photons = info.data.get("photons")
        if photons is not None and v > photons:
            raise PydanticCustomError(
                "shards_vs_photons",
                "shards must be in the allowed range [1, photons = {photons}]; received {value}",
                {"photons": photons, "value": v})
        return v

    @field_validator("shards")
    @classmethod
    def _tasks_of_sweep(cls, v: int, info: ValidationInfo) -> int:
        sweep = info.data.get("sweep")
        if sweep is not None and sweep.n_media * v > MAX_TASKS:
            raise PydanticCustomError(
                "too_many_tasks",
                "shard tasks media * shards = {media} * {value} must be in the allowed range "
                "[1, {limit}]; received {total} tasks: use fewer shards per medium or split "
                "the sweep",
                {"media": sweep.n_media, "value": v, "total": sweep.n_media * v, "limit": MAX_TASKS})
        return v

    @field_validator("batches_per_shard")
    @classmethod
    def _total_batches(cls, v: int, info: ValidationInfo) -> int:
        photons, shards = info.data.get("photons"), info.data.get("shards")
        if photons is None or shards is None:
            return v
        total = shards * v
        if not 2 <= total <= photons:
            raise PydanticCustomError(
                "total_batches",
                "shards * batches_per_shard must be in the allowed range [2, photons = "
                "{photons}] (at least 2 batches are needed for standard errors); received "
                "{shards} * {value} = {total}",
                {"photons": photons, "shards": shards, "value": v, "total": total})
        return v

    # ---- derived quantities ---------------------------------------------------------------

    def channels(self) -> list[ChannelOptics]:
        """Resolved optics, one per spectral channel (see :meth:`MediumSpec.channels`); a
        sweep's media each have their own: ``spec.medium_spec(m).channels()``."""
        if self.medium is None:
            raise ValueError("a sweep has no single medium: use spec.media() or "
                             "spec.medium_spec(index).channels()")
        return self.medium.channels()

    # ---- media and tasks (schema.media) ---------------------------------------------------

    @property
    def is_sweep(self) -> bool:
        """Whether the spec gives a sweep (a grid of media) rather than one medium."""
        return self.sweep is not None

    @property
    def n_media(self) -> int:
        """Media of the job: 1, or n_albedo * n_g * n_eta of a sweep."""
        return 1 if self.sweep is None else self.sweep.n_media

    def media(self) -> list[_media.Medium]:
        """Every medium with its index, coordinates and own spec (:func:`schema.media.media`)."""
        return _media.media(self)

    def medium_spec(self, index: int) -> SimulationSpec:
        """Medium ``index``'s own single-medium spec (:func:`schema.media.medium_spec`)."""
        return _media.medium_spec(self, index)

    def walk_groups(self) -> list[tuple[int, ...]]:
        """The media walked together, leader last (:func:`schema.groups.walk_groups`)."""
        return _groups.walk_groups(self)

    def walk_mode(self) -> str:
        """"shared" or "independent" walks (:func:`schema.groups.walk_mode`)."""
        return _groups.walk_mode(self)

    def task_count(self) -> int:
        """Shard tasks of the job: walk groups * shards (media * shards with independent walks)."""
        return _media.task_count(self)

    def task_of(self, task: int) -> tuple[int, int]:
        """(walk group, shard) of a task index t = group * shards + shard."""
        return _media.task_of(self, task)

    def task_index(self, group: int, shard: int) -> int:
        """Task index of (walk group, shard)."""
        return _media.task_index(self, group, shard)

    def theta_s_count(self) -> int:
        """theta_s bin count, "auto" resolved: 1 if every incidence angle is 0, else 12."""
        return theta_s_count(self.bins, self.incidence_deg)

    def radial_edges_mm(self) -> np.ndarray:
        """Radial edges [mm], float64 array [n_channels, n_r + 1]; column 0 is 0."""
        return channel_radial_edges_mm(self.bins, self.channels())

    def theta_s_edges(self) -> np.ndarray:
        """Exit-azimuth edges [rad], :meth:`theta_s_count` bins centred on +x
        (:func:`schema.bins.azimuth_edges`: from -h/2 to 2 pi - h/2)."""
        return azimuth_edges(self.theta_s_count())

    def cos_theta_o_edges(self) -> np.ndarray:
        """Edges in cos(theta_o), from 0 (grazing) to 1 (normal)."""
        return uniform_edges(0.0, 1.0, self.bins.cos_theta_o.count)

    def phi_o_edges(self) -> np.ndarray:
        """Outgoing-azimuth edges [rad], bins centred on the outward radial direction
        (:func:`schema.bins.azimuth_edges`: from -h/2 to 2 pi - h/2)."""
        return azimuth_edges(self.bins.phi_o.count)

    # ---- sharding -------------------------------------------------------------------------

    def shard_photon_range(self, shard_index: int) -> tuple[int, int]:
        """Photons [floor(i N / S), floor((i + 1) N / S)) of shard i; ShardIndexError if i is
        not in [0, shards)."""
        if not (isinstance(shard_index, int) and 0 <= shard_index < self.shards):
            raise ShardIndexError(
                f"shard_index must be in the allowed range [0, {self.shards}); "
                f"received {shard_index!r}")
        return _media.split_range(0, self.photons, self.shards, shard_index)

    def batch_photon_ranges(self, shard_index: int) -> list[tuple[int, int]]:
        """The shard's range split the same way into ``batches_per_shard`` non-empty pieces."""
        start, stop = self.shard_photon_range(shard_index)
        b = self.batches_per_shard
        return [_media.split_range(start, stop, b, j) for j in range(b)]

    # ---- identity -------------------------------------------------------------------------

    def canonical_json(self) -> str:
        """The fully-defaulted, normalised model as JSON with sorted keys and no whitespace.

        Of "medium" and "sweep" only the one given appears, so a single-medium spec hashes as
        it did before sweeps existed; likewise "target", "path_roulette" and "stretch" (and its "gamma_inward") only when given."""
        data = self.model_dump(mode="json")
        for form in ("medium", "sweep", "target", "path_roulette", "stretch"):
            if data[form] is None:
                del data[form]
        if "stretch" in data and data["stretch"]["gamma_inward"] is None:  # added later: absent, old hashes hold
            del data["stretch"]["gamma_inward"]
        return json.dumps(data, sort_keys=True,
                          separators=(",", ":"), ensure_ascii=False, allow_nan=False)

    def spec_hash(self) -> str:
        """sha256 hex digest of :meth:`canonical_json` (UTF-8)."""
        return hashlib.sha256(self.canonical_json().encode("utf-8")).hexdigest()
