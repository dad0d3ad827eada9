"""The states of jobs and tasks: the queue is a small state machine.

Job:  queued -> running -> merging -> succeeded | failed | cancelled
Task: waiting (merge only) -> queued -> leased -> done | failed | cancelled
      leased -> queued      (released by a stopping worker, or retried after an error)
      leased -> leased      (lease expired and re-claimed by another worker: a new fencing token)
"""

from __future__ import annotations

from enum import StrEnum

__all__ = ["JobState", "TaskState", "TaskKind", "TERMINAL_JOB_STATES", "ACTIVE_JOB_STATES"]


class JobState(StrEnum):
    """Lifecycle of a job (N shard tasks plus one merge task)."""

    QUEUED = "queued"  # submitted; no task claimed yet
    RUNNING = "running"  # at least one shard task was claimed
    MERGING = "merging"  # every shard is done; the merge task is claimable or running
    SUCCEEDED = "succeeded"  # merge published a dataset version (dataset_name, dataset_version set)
    FAILED = "failed"  # a task failed max_attempts times; job.error keeps its last error
    CANCELLED = "cancelled"  # cancelled by a user; no further claims, late commits refused


class TaskState(StrEnum):
    """Lifecycle of one task (a shard or the merge)."""

    WAITING = "waiting"  # merge task before every shard is done: never claimable
    QUEUED = "queued"  # claimable (once not_before has passed)
    LEASED = "leased"  # claimed; the lease holder owns it until lease_expires_at (then claimable again)
    DONE = "done"  # result committed (shard payload stored, or dataset version published)
    FAILED = "failed"  # attempts exhausted; its error is kept and the job failed
    CANCELLED = "cancelled"  # its job was cancelled or failed before it finished


class TaskKind(StrEnum):
    """What a task computes."""

    SHARD = "shard"  # run_shard(spec, shard_index) -> a ShardTally payload
    MERGE = "merge"  # merge every shard tally in shard order and publish a dataset version


TERMINAL_JOB_STATES = frozenset({JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED})
ACTIVE_JOB_STATES = frozenset({JobState.QUEUED, JobState.RUNNING, JobState.MERGING})
