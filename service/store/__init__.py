"""Job store and lease queue (SQLite or PostgreSQL through SQLAlchemy 2).

    from service.store import JobStore
    store = JobStore("sqlite:///.bssrdf/jobs.sqlite")     # migrates on open
    job = store.submit(spec, idempotency_key="abc")
    lease = store.claim("worker-1", lease_seconds=60)
"""

from service.store.errors import (
    ChecksumMismatch,
    DatasetError,
    IdempotencyConflict,
    JobNotActive,
    JobNotFound,
    JobPublished,
    LeaseLost,
    StoreError,
    VersionDeleted,
    VersionNotFound,
)
from service.store.records import (
    DatasetRecord, DatasetVersionRecord, ExportRecord, FoldPosition, JobProgress, JobRecord, Lease, MediumProgress,
    StoredFile, Submission,
)
from service.store.retry import RetryDecision, RetryPolicy, decide_retry
from service.store.states import ACTIVE_JOB_STATES, TERMINAL_JOB_STATES, JobState, TaskKind, TaskState
from service.store.store import JobStore
from service.store.opening import StoreUnavailable, StoreUnreachable, check_store_url, open_store

__all__ = [
    "JobStore",
    "open_store",
    "StoreUnavailable",
    "StoreUnreachable",
    "check_store_url",
    "JobRecord",
    "JobProgress",
    "Submission",
    "Lease",
    "StoredFile",
    "FoldPosition",
    "MediumProgress",
    "DatasetRecord",
    "DatasetVersionRecord",
    "ExportRecord",
    "JobState",
    "TaskState",
    "TaskKind",
    "ACTIVE_JOB_STATES",
    "TERMINAL_JOB_STATES",
    "RetryPolicy",
    "RetryDecision",
    "decide_retry",
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
