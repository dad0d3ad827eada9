"""A task of a job: shard s of walk group k's leader's own single-medium spec, t = k S + s.

The task numbering is :mod:`schema.media` / :mod:`schema.groups`; a task's tally holds the
leader's quantities and, from the same walk, its group's other albedos
(:mod:`workers.fold.reweight`); :class:`workers.fold.job.JobFold` folds the tallies in task order.
"""

from __future__ import annotations

from typing import Callable

from schema import SimulationSpec

from workers.fold.tally import ShardTally
from .shard import run_shard

__all__ = ["run_task", "group_walk"]


def group_walk(spec: SimulationSpec, group: int) -> tuple[int, tuple[float, ...]]:
    """(leader medium, the other members' albedos in medium order) of walk group ``group``."""
    media = spec.walk_groups()[group]
    if len(media) == 1:
        return media[0], ()
    albedos = spec.sweep.albedos()
    return media[-1], tuple(albedos[m % len(albedos)] for m in media[:-1])


def run_task(spec: SimulationSpec, task: int, *, progress: Callable[[int], None] | None = None) -> ShardTally:
    """Task ``task`` of the job: shard s of walk group k's leader's own spec (t = k * shards + s),
    tallying the group's other members from that walk."""
    group, shard = spec.task_of(task)
    leader, members = group_walk(spec, group)
    return run_shard(spec.medium_spec(leader), shard, progress=progress, members=members)
