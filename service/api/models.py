"""Request and response models of the HTTP API, named by role and separate from store records.

``JobCreate`` is what a client sends; ``JobPublic`` / ``JobList`` / ``DatasetPublic`` /
``DatasetVersionPublic`` / ``DatasetVersionDetail`` are what it gets back. ``Problem`` is one
entry of a 422 body. The ``from_record`` constructors are the only place that knows both sides.
"""

from __future__ import annotations

from typing import Any

from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool

from schema import SimulationSpec
from service.store import DatasetRecord, DatasetVersionRecord, JobProgress, JobRecord, JobState

__all__ = [
    "JobCreate",
    "JobProgressPublic",
    "JobPublic",
    "JobList",
    "DatasetPublic",
    "DatasetVersionPublic",
    "DatasetVersionDetail",
    "FileInfo",
    "Problem",
    "ErrorMessage",
    "ValidationErrorBody",
    "Health",
    "Readiness",
    "VersionInfo",
    "API_VERSION",
]

API_VERSION = "1"

IDEMPOTENCY_KEY_MAX = 200
IDEMPOTENCY_KEY_PATTERN = "^[!-~]+$"
"""Printable ASCII without spaces (what an HTTP header carries safely; no NUL for PostgreSQL)."""


class JobCreate(BaseModel):
    """A job submission: a simulation spec and an optional idempotency key."""

    model_config = ConfigDict(extra="forbid")

    spec: SimulationSpec = Field(description="The simulation spec (the schema package's SimulationSpec).")
    force: StrictBool = Field(
        False, description="Run it even if a published version or a live job has the same spec hash (seed "
        "included); without it such a submission returns that job (200, `existing` says which).")
    idempotency_key: str | None = Field(
        None, min_length=1, max_length=IDEMPOTENCY_KEY_MAX, pattern=IDEMPOTENCY_KEY_PATTERN,
        description="1..200 printable ASCII characters, no spaces. Submitting again with the same key and spec returns the same job (200); "
        "the same key with another spec is refused (409). Also accepted as the Idempotency-Key header.",
    )


class JobProgressPublic(BaseModel):
    """Progress of a job: shard counts, photons, rate and ETA."""

    shards_total: int
    shards_queued: int = Field(description="Queued, or leased with an expired lease (will be re-claimed).")
    shards_running: int = Field(description="Leased with a live lease, heartbeat within half the lease.")
    shards_stalled: int = Field(description="Leased with a live lease but no heartbeat for half of it: the "
                                "worker died or hangs; the shard is claimed again when the lease expires.")
    shards_done: int
    shards_failed: int = Field(description="Attempts exhausted.")
    shards_cancelled: int = Field(description="Not run: the job was cancelled or failed first.")
    merge_state: str = Field(description="State of the merge task (waiting, queued, leased, done, ...).")
    photons_done: int = Field(description="Photons of done shards plus those reported by running shards.")
    photons_total: int | None = Field(description="Photons of the whole job (photons x angles x channels x media).")
    elapsed_s: float = Field(description="Seconds since the first claim (0 before).")
    rate_photons_per_s: float | None
    shards_skipped: int = Field(0, description="Not counted: their medium met its target error with fewer shards.")
    tasks_folded: int = Field(0, description="Shard tasks the merge has folded so far, in task order.")
    media_total: int = Field(1, description="Media of the job (the sweep's grid; 1 for a single medium); "
                             "shards_total = media_total x the spec's shards.")
    media_merged: int = Field(0, description="Media the merge is past: their tables are final.")
    eta_s: float | None = Field(description="Seconds left at the current rate: None before the first photons are "
                                "reported and once the job failed or was cancelled; 0 once it succeeded.")
    shards_compiling: int = Field(0, description="Running shards whose worker is compiling a kernel (the first "
                                  "run of a kernel on a machine: one to two minutes) instead of walking.")
    phase: str | None = Field(None, description="What such a shard reports, e.g. \"compiling the walk for eta = "
                              "1.3 (first run on this machine, ~1-2 min)\"; null when no shard compiles.")

    @classmethod
    def from_record(cls, p: JobProgress) -> "JobProgressPublic":
        return cls(**{k: getattr(p, k) for k in cls.model_fields})


class JobPublic(BaseModel):
    """A job as the API shows it."""

    id: str
    name: str
    state: JobState
    shards: int
    idempotency_key: str | None
    created_at: float = Field(description="Seconds since the Unix epoch (database clock).")
    updated_at: float
    started_at: float | None
    finished_at: float | None
    error: str | None
    dataset_name: str | None = Field(description="Set once the job succeeded.")
    dataset_version: int | None
    spec: dict[str, Any] = Field(description="The stored (fully defaulted) spec.")
    progress: JobProgressPublic | None = Field(
        None, description="Shards, photons, rate and ETA (in GET /v1/jobs/{id} and submit/cancel answers; "
        "null in lists)."
    )
    existing: Literal["idempotency_key", "job", "version"] | None = Field(
        None, description="On a submission answered 200: why this job was returned instead of a new one: "
        "its idempotency key, a live job with the same spec hash, or a published version of it (nothing "
        "is recomputed; `force` runs it again).")

    @classmethod
    def from_record(cls, job: JobRecord, progress: JobProgress | None = None,
                    existing: str | None = None) -> "JobPublic":
        fields = {k: getattr(job, k) for k in cls.model_fields if k not in ("spec", "progress", "existing")}
        return cls(**fields, spec=job.spec_dict, existing=existing,
                   progress=None if progress is None else JobProgressPublic.from_record(progress))


class MediumProgressPublic(BaseModel):
    """Progress of one medium of a job (a sweep's grid point; the only one of a single medium)."""

    medium: int = Field(description="Index of the medium in the job (the sweep's grid order).")
    albedo: list[float] = Field(description="Single-scattering albedo per channel (one entry for a sweep medium).")
    g: list[float] = Field(description="HG mean cosine per channel.")
    eta: float = Field(description="Relative index of refraction.")
    shards_total: int
    shards_done: int
    shards_running: int = Field(description="Leased with a live lease.")
    shards_skipped: int = Field(description="Not run: the medium met its target error first, or the job ended.")
    shards_folded: int = Field(description="Shards of this medium the merge has folded, in shard order.")
    merged: bool = Field(description="The merge is past this medium: its rows of the tables are final.")
    photons_done: int = Field(description="Photons of its done shards plus those reported by running ones.")
    photons_total: int = Field(description="Photons of the medium if every shard runs (photons x angles x channels).")


class MediumList(BaseModel):
    """One page of a job's media, in index order."""

    job_id: str
    media_total: int
    items: list[MediumProgressPublic]
    limit: int
    offset: int
    next_offset: int | None = Field(description="Offset of the next page, None on the last page.")


class JobList(BaseModel):
    """One page of jobs, newest first."""

    items: list[JobPublic]
    limit: int
    offset: int
    next_offset: int | None = Field(description="Offset of the next page, None on the last page.")


class DatasetPublic(BaseModel):
    """A dataset name with its versions."""

    name: str
    latest_version: int
    versions: int
    updated_at: float


class FileInfo(BaseModel):
    """One stored file of a version."""

    sha256: str
    bytes: int | None = None


class DatasetVersionPublic(BaseModel):
    """One immutable dataset version."""

    name: str
    version: int
    created_at: float
    job_id: str | None
    spec_hash: str | None
    photons: int | None
    shards: int | None
    files: dict[str, FileInfo] = Field(description="Downloadable files (metadata.json included) and their sha256; "
                                       "empty once deleted.")
    deleted_at: float | None = Field(None, description="Set on a deleted version (a tombstone: no files).")
    deleted_by: str | None = Field(None, description="Who deleted it: the fingerprint of their token.")

    @classmethod
    def from_record(cls, v: DatasetVersionRecord) -> "DatasetVersionPublic":
        meta = v.meta
        files = {k: FileInfo(**f) for k, f in meta.get("files", {}).items()}
        if "metadata_sha256" in meta:
            files["metadata.json"] = FileInfo(sha256=meta["metadata_sha256"])
        return cls(name=v.name, version=v.version, created_at=v.created_at, job_id=v.job_id,
                   spec_hash=meta.get("spec_hash"), photons=meta.get("photons"), shards=meta.get("shards"),
                   files={} if v.deleted_at is not None else files, deleted_at=v.deleted_at,
                   deleted_by=v.deleted_by)


class DatasetVersionDetail(DatasetVersionPublic):
    """A version with its metadata (spec, seed, photons, code version, timings) and its summary."""

    metadata: dict[str, Any]
    summary: Any = Field(description="Rd per estimator, incidence, channel and component, with errors.")

    @classmethod
    def from_record(cls, v: DatasetVersionRecord) -> "DatasetVersionDetail":
        base = DatasetVersionPublic.from_record(v)
        metadata = {k: x for k, x in v.meta.items() if k not in ("summary", "metadata_sha256")}
        return cls(**base.model_dump(), metadata=metadata, summary=v.meta.get("summary"))


def dataset_from_record(d: DatasetRecord) -> DatasetPublic:
    return DatasetPublic(name=d.name, latest_version=d.latest_version, versions=d.versions, updated_at=d.updated_at)


class Problem(BaseModel):
    """One invalid field: where, what is wrong, what is allowed, what was received."""

    field: str = Field(description="Dotted path, e.g. spec.medium.sigma_a or query.limit.")
    message: str
    allowed: str | None = Field(None, description="The allowed range or values, when known.")
    received: Any = Field(None, description="The value received.")


class ValidationErrorBody(BaseModel):
    """422: every invalid field."""

    detail: list[Problem]


class ErrorMessage(BaseModel):
    """Any other error: what went wrong and what to do."""

    detail: str


class Health(BaseModel):
    status: str = "ok"


class Readiness(BaseModel):
    status: str
    checks: dict[str, str]


class VersionInfo(BaseModel):
    """What code answers: the API version, the package version and its git commit."""

    api: str
    package: str | None
    git_commit: str | None
