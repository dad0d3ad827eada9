"""Plain records returned by the job store (storage rows, not API models).

Times are seconds since the Unix epoch (float) from the database clock.
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field
from typing import Any

from service.store.states import JobState, TaskKind

__all__ = [
    "JobRecord", "Lease", "JobProgress", "DatasetVersionRecord", "DatasetRecord", "ExportRecord", "Submission",
    "StoredFile", "FoldPosition", "MediumProgress",
]


@dataclass(frozen=True)
class JobRecord:
    """One row of ``jobs``."""

    id: str
    name: str
    state: JobState
    spec_json: str
    spec_hash: str
    shards: int
    idempotency_key: str | None
    created_at: float
    updated_at: float
    started_at: float | None
    finished_at: float | None
    error: str | None
    dataset_name: str | None
    dataset_version: int | None
    photons_total: int | None = None  # photons the whole job walks (None: not known at submission)

    @property
    def spec_dict(self) -> dict[str, Any]:
        """The submitted spec as a JSON object."""
        return json.loads(self.spec_json)

    @classmethod
    def from_row(cls, row) -> "JobRecord":
        m = row._mapping
        return cls(**{k: m[k] for k in cls.__dataclass_fields__ if k != "state"}, state=JobState(m["state"]))


@dataclass(frozen=True)
class Submission:
    """What a submission got: a new job (``existing`` None), or the job it duplicates.

    ``existing``: ``"idempotency_key"`` (the key names this job), ``"job"`` (a live job with the
    same spec hash, seed included), ``"version"`` (a published version of the same spec hash;
    ``job`` is the job that published it).
    """

    job: JobRecord
    existing: str | None = None


@dataclass(frozen=True)
class Lease:
    """A claimed task: present ``(task_id, token)`` on every heartbeat and commit."""

    task_id: int
    token: int  # fencing token: increases on every claim of this task
    job_id: str
    kind: TaskKind
    shard_index: int | None
    attempts: int  # claims so far, this one included
    max_attempts: int
    lease_expires_at: float
    spec_json: str
    owner: str


@dataclass(frozen=True)
class JobProgress:
    """What a progress display needs: shard counts, photons, rate and ETA."""

    job_id: str
    state: JobState
    shards_total: int
    shards_queued: int  # queued, or leased with an expired lease (will be re-claimed)
    shards_running: int  # leased, lease live, heartbeat within half the lease
    shards_stalled: int  # leased, lease live, no heartbeat for half the lease (worker dead or hung)
    shards_done: int
    shards_failed: int  # attempts exhausted
    shards_cancelled: int  # the job was cancelled (or failed) before they ran
    merge_state: str  # TaskState of the merge task
    photons_done: int  # done shards plus photons reported by heartbeats of running shards
    photons_total: int | None  # photons of the whole job (None: not recorded at submission)
    elapsed_s: float  # since the first claim (0 before)
    rate_photons_per_s: float | None
    eta_s: float | None  # None before any photon is reported or when the job failed/was cancelled; 0 once succeeded
    error: str | None
    dataset_name: str | None = None
    dataset_version: int | None = None
    shards_skipped: int = 0  # cancelled by an early stop: their medium met its target first
    tasks_folded: int = 0  # tasks the merge has folded, in task order (it is past them)
    media_total: int = 1  # media of the job (a sweep's grid; 1 for a single medium)
    media_merged: int = 0  # media the merge is past (their tables are final)
    shards_compiling: int = 0  # running shards whose worker reports a phase (compiling a kernel)
    phase: str | None = None  # one such phase ("compiling the walk for eta = 1.3 ..."), None when none


@dataclass(frozen=True)
class DatasetVersionRecord:
    """One published dataset version (row of ``dataset_versions``)."""

    name: str
    version: int
    uri: str  # directory of the version on the storage filesystem
    created_at: float
    job_id: str | None
    meta: dict[str, Any] = field(repr=False)  # metadata.json content (+ "metadata_sha256")
    deleted_at: float | None = None  # set on a tombstone: files removed, row kept
    deleted_by: str | None = None

    @property
    def spec_hash(self) -> str | None:
        return self.meta.get("spec_hash")

    @classmethod
    def from_row(cls, row) -> "DatasetVersionRecord":
        m = row._mapping
        return cls(m["name"], m["version"], m["uri"], m["created_at"], m["job_id"], m["meta"],
                   m.get("deleted_at"), m.get("deleted_by"))


@dataclass(frozen=True)
class DatasetRecord:
    """A dataset name with its versions."""

    name: str
    latest_version: int
    versions: int
    updated_at: float


@dataclass(frozen=True)
class ExportRecord:
    """A stored export of a version (row of ``dataset_exports``): its archive ``filename``
    (relative to the version's directory), sha256, size and manifest."""

    name: str
    version: int
    format: str
    filename: str
    sha256: str
    bytes: int
    created_at: float
    meta: dict[str, Any] = field(repr=False)  # export.json: provenance and the archive's files


@dataclass(frozen=True)
class StoredFile:
    """A file the job store points to (a shard result, a fold): its path relative to the storage
    root, size and sha256 (checked by whoever reads it: service.datasets.storage.verified_bytes)."""

    uri: str
    bytes: int
    sha256: str


@dataclass(frozen=True)
class FoldPosition:
    """Where a job's merge stands: tasks folded in task order so far and the file of that fold."""

    folded: int  # the next task the fold needs
    fold: StoredFile | None  # None before the first fold round committed
    tasks: int  # shard tasks of the job (media x shards)
    shards_done: int
    shards_skipped: int  # cancelled by an early stop (their results never counted)


@dataclass(frozen=True)
class MediumProgress:
    """Shard counts of one medium of a job (task t belongs to medium t // shards)."""

    medium: int
    shards_total: int
    shards_done: int
    shards_running: int  # leased, lease live
    shards_skipped: int  # cancelled: the medium met its target first, or the job ended
    folded: int  # where the merge stands in the medium: shards folded (shards_total once past it)
    merged: bool  # the merge is past the medium: its tables are final
    photons_done: int = 0  # photons of its done shards plus those reported by its running shards
