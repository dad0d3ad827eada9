"""Deleting jobs and dataset versions.

    delete_job(job_id)              cancel it if it is live; remove its tasks and stored shard
                                    results; refused (JobPublished) while a version it published
                                    exists, which the job row documents
    delete_version(name, v, by)     tombstone: the row stays with its metadata (spec hash) and
                                    who deleted it when; the caller removes the files

Version numbers are never reused: the next version is max + 1 over tombstones too.
"""

from __future__ import annotations

import time

import sqlalchemy as sa

from service.store.base import StoreBase
from service.store.errors import JobPublished, VersionNotFound
from service.store.records import DatasetVersionRecord, JobRecord
from service.store.states import ACTIVE_JOB_STATES, JobState, TaskState
from service.store.tables import dataset_versions, jobs, shard_results, tasks

__all__ = ["LifecycleMixin", "DELETE_CHUNK"]

DELETE_CHUNK = 5000
"""Rows of a job deleted per transaction (about 50 ms on SQLite, BENCHMARKS.md)."""


class LifecycleMixin(StoreBase):
    """Deletion of jobs and of dataset versions."""

    def delete_job(self, job_id: str) -> JobRecord:
        """Delete a job (cancelling it first if it is live); returns the job as it was deleted.

        Its shard tasks and stored shard results go with it (a worker still running one gets
        LeaseLost or JobNotFound at its next heartbeat or commit). Raises :class:`JobNotFound`,
        or :class:`JobPublished` while a version it published exists (delete that first).

        In short transactions, so that deleting the largest job holds the store for
        milliseconds at a time, never for the seconds its rows take in all: the first cancels a
        live job (its row, its leased and waiting tasks: no commit of it is accepted any more);
        then its shard results and tasks go :data:`DELETE_CHUNK` rows at a time (on SQLite a
        pause as long as each chunk took lets other writers in; a queued task claimed meanwhile
        is refused at its first heartbeat); the last removes the job row and what is left. Cut
        short (a crash), the job stays cancelled and a second delete finishes it.
        """
        with self._tx() as conn:
            state = self._lock_job(conn, job_id)
            v = dataset_versions.c
            live = conn.execute(
                sa.select(v.name, v.version).where(v.job_id == job_id, v.deleted_at.is_(None))
            ).first()
            if live is not None:
                raise JobPublished(
                    f"job {job_id} published dataset {live.name!r} version {live.version}, which records it as its "
                    f"provenance; delete the version first (DELETE /v1/datasets/{live.name}/versions/{live.version})")
            if state in ACTIVE_JOB_STATES:
                now = self._now()
                conn.execute(sa.update(jobs).where(jobs.c.id == job_id).values(
                    state=JobState.CANCELLED, error="deleted", finished_at=now, updated_at=now))
                conn.execute(sa.update(tasks).where(
                    tasks.c.job_id == job_id, tasks.c.state.in_([TaskState.LEASED, TaskState.WAITING]),
                ).values(state=TaskState.CANCELLED, lease_expires_at=None, finished_at=now))
            job = JobRecord.from_row(conn.execute(sa.select(jobs).where(jobs.c.id == job_id)).one())
        for table in (shard_results, tasks):
            self._delete_in_chunks(table, job_id)
        with self._tx() as conn:
            self._lock_job(conn, job_id)
            conn.execute(sa.update(dataset_versions).where(dataset_versions.c.job_id == job_id)
                         .values(job_id=None))  # tombstones
            conn.execute(sa.delete(jobs).where(jobs.c.id == job_id))  # the rest: ON DELETE CASCADE
        return job

    def _delete_in_chunks(self, table: sa.Table, job_id: str) -> None:
        """Delete the job's rows of ``table`` (tasks or shard_results), DELETE_CHUNK per transaction,
        lowest shard index first."""
        key = table.c.shard_index
        while True:
            t0 = time.perf_counter()
            with self._tx() as conn:
                batch = sa.select(key).where(table.c.job_id == job_id, key.is_not(None)).order_by(key).limit(DELETE_CHUNK)
                top = conn.execute(sa.select(sa.func.max(batch.subquery().c.shard_index))).scalar_one_or_none()
                if top is None:
                    return
                conn.execute(sa.delete(table).where(table.c.job_id == job_id, key <= top))
            if self.dialect_name == "sqlite":
                time.sleep(time.perf_counter() - t0)  # other writers' turn: SQLite has one write lock

    def delete_version(self, name: str, version: int, deleted_by: str) -> DatasetVersionRecord:
        """Make version ``version`` of ``name`` a tombstone (idempotent); returns it.

        Raises :class:`VersionNotFound` if there never was such a version.
        """
        v = dataset_versions.c
        where = sa.and_(v.name == name, v.version == int(version))
        with self._tx() as conn:
            row = conn.execute(sa.select(dataset_versions).where(where).with_for_update()).first()
            if row is None:
                raise VersionNotFound(f"dataset {name!r} has no version {version}; list them with GET "
                                      f"/v1/datasets/{name}/versions")
            if row.deleted_at is None:
                conn.execute(sa.update(dataset_versions).where(where).values(deleted_at=self._now(),
                                                                            deleted_by=deleted_by))
            row = conn.execute(sa.select(dataset_versions).where(where)).one()
        return DatasetVersionRecord.from_row(row)

    def tombstone(self, name: str, version: int) -> DatasetVersionRecord:
        """The tombstone of a deleted version (:class:`VersionNotFound` if it is not deleted)."""
        v = dataset_versions.c
        with self._read() as conn:
            row = conn.execute(sa.select(dataset_versions).where(
                v.name == name, v.version == int(version), v.deleted_at.is_not(None))).first()
        if row is None:
            raise VersionNotFound(f"dataset {name!r} version {version} is not deleted")
        return DatasetVersionRecord.from_row(row)

