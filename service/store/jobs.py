"""Jobs: submit (with idempotency key), read, list, cancel, progress."""

from __future__ import annotations

import uuid
from typing import Protocol

import sqlalchemy as sa
from sqlalchemy.exc import IntegrityError

from service.store.base import StoreBase
from service.store.errors import IdempotencyConflict, JobNotActive, JobNotFound
from service.store.records import JobProgress, JobRecord
from service.store.states import TERMINAL_JOB_STATES, JobState, TaskKind, TaskState
from service.store.tables import jobs, tasks

__all__ = ["JobsMixin", "SpecLike"]


class SpecLike(Protocol):
    """What the store needs of a ``schema.SimulationSpec``."""

    name: str
    shards: int

    def canonical_json(self) -> str: ...

    def spec_hash(self) -> str: ...


class JobsMixin(StoreBase):
    """Job-level operations."""

    def submit(self, spec: SpecLike, *, idempotency_key: str | None = None) -> JobRecord:
        """Store a job: ``spec.shards`` queued shard tasks plus one waiting merge task.

        With an ``idempotency_key``, submitting again returns the job first stored under that key
        (raises :class:`IdempotencyConflict` if its spec differs). Without one, every submission
        is a new job and, once merged, a new dataset version.
        """
        if spec.shards < 1:
            raise ValueError(f"spec.shards must be >= 1; received {spec.shards}")
        if idempotency_key is not None:
            existing = self._job_by_key(idempotency_key)
            if existing is not None:
                return self._check_same_spec(existing, spec)
        job_id = str(uuid.uuid4())
        spec_json, spec_hash = spec.canonical_json(), spec.spec_hash()
        now = self._now()
        try:
            with self._tx() as conn:
                conn.execute(
                    sa.insert(jobs).values(
                        id=job_id, name=spec.name, spec_json=spec_json, spec_hash=spec_hash,
                        shards=spec.shards, state=JobState.QUEUED, idempotency_key=idempotency_key,
                        created_at=now, updated_at=now,
                    )
                )
                rows = [
                    dict(job_id=job_id, kind=TaskKind.SHARD, shard_index=i, state=TaskState.QUEUED,
                         max_attempts=self.max_attempts)
                    for i in range(spec.shards)
                ]
                rows.append(dict(job_id=job_id, kind=TaskKind.MERGE, shard_index=None,
                                 state=TaskState.WAITING, max_attempts=self.max_attempts))
                conn.execute(sa.insert(tasks), rows)  # executemany keeps shard order in ids
        except IntegrityError:
            # A concurrent submit stored the same idempotency key first.
            existing = self._job_by_key(idempotency_key) if idempotency_key else None
            if existing is None:
                raise
            return self._check_same_spec(existing, spec)
        return self.get_job(job_id)

    def job_by_idempotency_key(self, key: str) -> JobRecord | None:
        """The job stored under this idempotency key, or None (lets the API answer 200 vs 201)."""
        return self._job_by_key(key)

    def _job_by_key(self, key: str) -> JobRecord | None:
        with self.engine.connect() as conn:
            row = conn.execute(sa.select(jobs).where(jobs.c.idempotency_key == key)).first()
        return None if row is None else JobRecord.from_row(row)

    @staticmethod
    def _check_same_spec(job: JobRecord, spec: SpecLike) -> JobRecord:
        if job.spec_hash != spec.spec_hash():
            raise IdempotencyConflict(
                f"idempotency key {job.idempotency_key!r} already names job {job.id} with spec hash "
                f"{job.spec_hash}; this spec hashes to {spec.spec_hash()}: use a new key"
            )
        return job

    def get_job(self, job_id: str) -> JobRecord:
        """The job with this id (raises :class:`JobNotFound`)."""
        with self.engine.connect() as conn:
            row = conn.execute(sa.select(jobs).where(jobs.c.id == job_id)).first()
        if row is None:
            raise JobNotFound(job_id)
        return JobRecord.from_row(row)

    def list_jobs(self, *, state: JobState | None = None, limit: int = 100, offset: int = 0) -> list[JobRecord]:
        """Jobs, newest first, optionally of one state."""
        q = sa.select(jobs).order_by(jobs.c.created_at.desc(), jobs.c.id).limit(limit).offset(offset)
        if state is not None:
            q = q.where(jobs.c.state == JobState(state))
        with self.engine.connect() as conn:
            return [JobRecord.from_row(r) for r in conn.execute(q)]

    def cancel(self, job_id: str) -> JobRecord:
        """Cancel a job: no further claims, leases released, late commits refused.

        Cancelling a cancelled job is a no-op; a succeeded or failed job raises
        :class:`JobNotActive`.
        """
        with self._tx() as conn:
            state = self._lock_job(conn, job_id)
            if state == JobState.CANCELLED:
                pass
            elif state in TERMINAL_JOB_STATES:
                raise JobNotActive(f"job {job_id} already {state}; only queued/running/merging jobs can be cancelled")
            else:
                self._end_job(conn, job_id, JobState.CANCELLED, error="cancelled")
        return self.get_job(job_id)

    def progress(self, job_id: str) -> JobProgress:
        """Shard counts, photons done, rate (photons/s since the first claim) and ETA."""
        now = self._now()
        live = sa.and_(tasks.c.state == TaskState.LEASED, tasks.c.lease_expires_at >= now)
        with self.engine.connect() as conn:
            job = conn.execute(sa.select(jobs, now.label("now")).where(jobs.c.id == job_id)).first()
            if job is None:
                raise JobNotFound(job_id)
            counts = conn.execute(
                sa.select(
                    sa.func.count().filter(tasks.c.state == TaskState.DONE),
                    sa.func.count().filter(live),
                    sa.func.count().filter(tasks.c.state.in_([TaskState.FAILED, TaskState.CANCELLED])),
                    sa.func.coalesce(sa.func.sum(tasks.c.photons), 0),
                    sa.func.coalesce(sa.func.sum(tasks.c.photons).filter(tasks.c.state == TaskState.DONE), 0),
                ).where(tasks.c.job_id == job_id, tasks.c.kind == TaskKind.SHARD)
            ).one()
            merge_state = conn.execute(
                sa.select(tasks.c.state).where(tasks.c.job_id == job_id, tasks.c.kind == TaskKind.MERGE)
            ).scalar_one()
        m = job._mapping
        done, running, failed, photons, photons_done_shards = (int(x) for x in counts)
        total = int(m["shards"])
        end = m["finished_at"] if m["finished_at"] is not None else m["now"]
        elapsed = max(0.0, end - m["started_at"]) if m["started_at"] is not None else 0.0
        rate = photons / elapsed if elapsed > 0 and photons > 0 else None
        state = JobState(m["state"])
        eta = None
        if state in TERMINAL_JOB_STATES:
            eta = 0.0
        elif done and rate:
            expected = photons_done_shards / done * total  # photons of the whole job, extrapolated
            eta = max(0.0, expected - photons) / rate
        return JobProgress(
            job_id=job_id, state=state, shards_total=total,
            shards_queued=total - done - running - failed, shards_running=running, shards_done=done,
            shards_failed=failed, merge_state=merge_state, photons_done=photons, elapsed_s=elapsed,
            rate_photons_per_s=rate, eta_s=eta, error=m["error"],
            dataset_name=m["dataset_name"], dataset_version=m["dataset_version"],
        )
