"""Exceptions of the job store and dataset storage.

    StoreError
    ├── JobNotFound            no job with that id
    ├── JobNotActive           the job already ended (succeeded, failed, cancelled)
    ├── IdempotencyConflict    an idempotency key reused with a different spec
    ├── JobPublished           the job's dataset version is published: delete the version first
    ├── LeaseLost              the fencing token no longer matches: another worker owns the task,
    │                          or its job was cancelled; the caller must discard its result
    └── DatasetError
        ├── VersionNotFound    no such dataset name / version in the catalog
        │   └── VersionDeleted the version was deleted (its tombstone: who, when, spec hash)
        └── ChecksumMismatch   a stored file does not match the sha256 recorded at publish time
"""

from __future__ import annotations

__all__ = [
    "StoreError",
    "JobNotFound",
    "JobNotActive",
    "IdempotencyConflict",
    "JobPublished",
    "LeaseLost",
    "DatasetError",
    "VersionNotFound",
    "VersionDeleted",
    "ChecksumMismatch",
]


class StoreError(Exception):
    """Base class of every job store and dataset storage error."""


class JobNotFound(StoreError, KeyError):
    """No job has this id. Check the id returned by ``submit``."""

    def __init__(self, job_id: str) -> None:
        super().__init__(f"no job with id {job_id!r}")
        self.job_id = job_id

    def __str__(self) -> str:  # KeyError would quote the message
        return str(self.args[0])


class JobNotActive(StoreError):
    """The job already ended; it cannot be changed any more."""


class IdempotencyConflict(StoreError):
    """The idempotency key already names a job with a different spec; use a new key."""


class JobPublished(StoreError):
    """The job published a dataset version that still exists: it is that version's provenance.
    Delete the version first (its tombstone then no longer needs the job)."""


class LeaseLost(StoreError):
    """The lease of a task is no longer held by this token: discard the work, do not retry it."""

    def __init__(self, task_id: int, token: int, reason: str = "lease lost") -> None:
        super().__init__(f"task {task_id} (lease token {token}): {reason}; the result was refused")
        self.task_id = task_id
        self.token = token


class DatasetError(StoreError):
    """Base class of dataset storage errors."""


class VersionNotFound(DatasetError, KeyError):
    """No such dataset version in the catalog."""

    def __str__(self) -> str:
        return str(self.args[0])


class VersionDeleted(VersionNotFound):
    """The version was deleted; ``record`` is its tombstone (deleted_at, deleted_by, spec hash)."""

    def __init__(self, record) -> None:
        super().__init__(f"dataset {record.name!r} version {record.version} was deleted by {record.deleted_by} "
                         f"(spec hash {record.spec_hash}); its files are gone: submit the spec again to remake it")
        self.record = record


class ChecksumMismatch(DatasetError):
    """A stored file's sha256 differs from the one recorded at publish time: the copy is corrupt."""
