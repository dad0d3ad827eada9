"""The media of a job and its task index: what :class:`SimulationSpec` says about either form.

A spec measures one medium (``"medium"``) or a grid of them (``"sweep"``,
:mod:`schema.sweep`). Either way the job is a list of media, each with an index (0 for a single
medium), coordinates per channel (albedo, g, eta: a sweep medium has one channel) and its own
single-medium :class:`SimulationSpec`: the same spec with ``"medium"`` in place of ``"sweep"``.
With independent walks a sweep's entry is that single-medium job bit for bit: each medium's
shards are exactly its own spec's shards (same photons, batches and random streams: the streams
are keyed by the seed and the medium's coefficients, never by its index in the sweep).  With
shared walks this holds for each group's leader; the other members are its walk reweighted.

Tasks: the media are walked in G *walk groups* (:mod:`schema.groups`: one medium per group
with independent walks, a range of albedos sharing one walk with shared walks); a job of G
groups and S shards per medium has G * S shard tasks, group-major:

    task t  <->  (group k, shard s)   with   t = k S + s,   0 <= s < S,

so a single-medium job's task index is its shard index, and a worker running tasks in order
finishes one group before the next (the merge folds them in that order).  Shard s of a group
is shard s of its leader's own spec, tallied for every member.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING

from .errors import ShardIndexError
from .sweep import sweep_point, sweep_points

if TYPE_CHECKING:
    from .spec import SimulationSpec

__all__ = ["Medium", "media", "medium_spec", "split_range", "task_count", "task_of", "task_index"]


@dataclass(frozen=True)
class Medium:
    """Medium ``index`` of a job: coordinates per channel and its own single-medium spec.

    ``albedo`` and ``g`` have one entry per channel (one for a sweep medium); ``eta`` is the
    medium's relative index. :attr:`spec` builds the single-medium spec on first use.
    """

    index: int
    albedo: tuple[float, ...]
    g: tuple[float, ...]
    eta: float
    parent: "SimulationSpec" = field(repr=False, compare=False)

    @property
    def spec(self) -> "SimulationSpec":
        """The medium's own single-medium spec (the parent itself for a single-medium job)."""
        return medium_spec(self.parent, self.index)


def media(spec: "SimulationSpec") -> list[Medium]:
    """Every medium of the job, in index order."""
    if spec.sweep is None:
        ch = spec.medium.channels()
        return [Medium(0, tuple(c.albedo for c in ch), tuple(c.g for c in ch), float(spec.medium.eta), spec)]
    return [Medium(p.index, (p.albedo,), (p.g,), p.eta, spec) for p in sweep_points(spec.sweep)]


def medium_spec(spec: "SimulationSpec", index: int) -> "SimulationSpec":
    """The single-medium spec of medium ``index``: every field of ``spec``, with the medium
    (sigma_s = albedo, sigma_a = 1 - albedo, g, eta; :meth:`SweepPoint.medium`) in place of
    the sweep. ShardIndexError if ``index`` is not in [0, media)."""
    n = spec.n_media
    if not (isinstance(index, int) and 0 <= index < n):
        raise ShardIndexError(f"medium index must be in the allowed range [0, {n}); received {index!r}")
    if spec.sweep is None:
        return spec
    point = sweep_point(spec.sweep, index)
    data = spec.model_dump(mode="json", exclude={"sweep"})
    data["medium"] = point.medium()
    return type(spec).model_validate(data)


def task_count(spec: "SimulationSpec") -> int:
    """Shard tasks of the job: walk groups * shards (media * shards with independent walks)."""
    return len(spec.walk_groups()) * spec.shards


def task_of(spec: "SimulationSpec", task: int) -> tuple[int, int]:
    """(walk group, shard) of task index ``task`` = group * shards + shard (the group is the
    medium with independent walks); ShardIndexError if ``task`` is not in [0, groups * shards)."""
    n = task_count(spec)
    if not (isinstance(task, int) and 0 <= task < n):
        raise ShardIndexError(f"task index must be in the allowed range [0, {n}); received {task!r}")
    return divmod(task, spec.shards)


def task_index(spec: "SimulationSpec", group: int, shard: int) -> int:
    """Task index of (walk group, shard): group * shards + shard (both range-checked)."""
    n_groups = len(spec.walk_groups())
    if not (isinstance(group, int) and 0 <= group < n_groups):
        raise ShardIndexError(f"walk group index must be in the allowed range [0, {n_groups}); received {group!r}")
    if not (isinstance(shard, int) and 0 <= shard < spec.shards):
        raise ShardIndexError(f"shard_index must be in the allowed range [0, {spec.shards}); received {shard!r}")
    return group * spec.shards + shard


def split_range(start: int, stop: int, pieces: int, i: int) -> tuple[int, int]:
    """Piece i of [start, stop) cut at start + floor(k n / pieces), exact integer arithmetic."""
    n = stop - start
    return start + i * n // pieces, start + (i + 1) * n // pieces
