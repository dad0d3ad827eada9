"""The merge's side of the queue: where the fold stands, the shard results it reads, its commits.

The merge task of a job is an incremental fold (service.datasets.publish): each time it is
claimed it folds, in task order, the done tasks from ``jobs.folded`` on, saves the fold to a
file and commits here, fenced by its lease, the new cursor and that file (:meth:`advance_fold`);
the task then waits again until the next ``fold_batch`` tasks are done (``_wake_merge`` in the
queue). A medium that met its target error ends early: the rest of its tasks are cancelled in the
same commit (``shards_skipped``) and their results are never read. The last round publishes the
version (``complete_merge``).
"""

from __future__ import annotations

import fcntl
import hashlib
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Protocol

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from service.store.base import StoreBase
from service.store.engine import SQLITE_BUSY_TIMEOUT_MS
from service.store.errors import LeaseLost, StoreError
from service.store.records import FoldPosition, Lease, MediumProgress, StoredFile
from service.store.states import JobState, TaskKind, TaskState
from service.store.tables import dataset_versions, jobs, shard_results, tasks

__all__ = ["FoldMixin", "StoredResult", "Publisher"]

StoredResult = StoredFile | bytes
"""A shard's stored result: its file, or (stored before migration 0004) the payload itself."""


class Publisher(Protocol):
    """Moves a staged dataset version into place (see ``service.datasets.StagedVersion``)."""

    def uri_for(self, version: int) -> str:
        """Where version ``version`` will live."""

    def publish(self, version: int) -> None:
        """Atomically make the staged files version ``version`` (before the commit of its row:
        inside the transaction on PostgreSQL, outside any on SQLite; ``complete_merge``)."""


class FoldMixin(StoreBase):
    """Reads and fenced commits of the incremental merge, and its publish (with QueueMixin's
    ``_fenced``, ``_finish`` and ``_wake_merge`` in :class:`service.store.JobStore`)."""

    def fold_position(self, job_id: str) -> FoldPosition:
        """The job's fold cursor, fold file and task counters."""
        with self._read() as conn:
            j = conn.execute(sa.select(jobs).where(jobs.c.id == job_id)).one()._mapping
        fold = None if j["fold_uri"] is None else StoredFile(j["fold_uri"], int(j["fold_bytes"]), j["fold_sha256"])
        return FoldPosition(int(j["folded"]), fold, int(j["shards"]), int(j["shards_done"]), int(j["shards_skipped"]))

    def shard_result(self, job_id: str, task: int) -> StoredResult | None:
        """The result of task ``task`` if it is done (its task row done, its result recorded), else None."""
        return self.shard_results_in(job_id, task, task + 1).get(int(task))

    def shard_results_in(self, job_id: str, start: int, stop: int) -> dict[int, StoredResult]:
        """The results of the done tasks in [start, stop), by task: one query for a window of
        the fold's reads (each read waits its turn for a pooled connection at fleet scale)."""
        r = shard_results.c
        with self._read() as conn:
            rows = conn.execute(
                sa.select(r.shard_index, r.uri, r.bytes, r.sha256, r.payload)
                .join(tasks, sa.and_(tasks.c.job_id == r.job_id, tasks.c.shard_index == r.shard_index,
                                     tasks.c.kind == TaskKind.SHARD))
                .where(r.job_id == job_id, r.shard_index >= int(start), r.shard_index < int(stop),
                       tasks.c.state == TaskState.DONE)
            ).all()
        return {int(i): bytes(p) if uri is None else StoredFile(uri, int(n), h) for i, uri, n, h, p in rows}

    def shard_files(self, job_id: str) -> list[tuple[int, StoredResult]]:
        """Every recorded ``(task, result)`` of a job, in task order (for tests and tools)."""
        r = shard_results.c
        with self._read() as conn:
            rows = conn.execute(
                sa.select(r.shard_index, r.uri, r.bytes, r.sha256, r.payload).where(r.job_id == job_id)
                .order_by(r.shard_index)
            ).all()
        return [(int(i), bytes(p) if uri is None else StoredFile(uri, int(n), h)) for i, uri, n, h, p in rows]

    def advance_fold(self, lease: Lease, *, folded: int, fold: StoredFile, skipped: list[range]) -> None:
        """Commit a fold round, fenced by the merge lease: the cursor ``folded`` and the fold's
        file; the tasks in ``skipped`` (a medium's shards past its early stop) cancelled, so
        they are not claimed and their late commits refused. The merge task waits again (queued
        at once if the next tasks are already done), its attempts reset: only consecutive failed
        rounds count. Raises :class:`LeaseLost` if the lease is not ours (nothing written).
        """
        if lease.kind != TaskKind.MERGE:
            raise ValueError(f"advance_fold needs a merge lease; received a {lease.kind} lease")
        now = self._now()
        with self._tx() as conn:
            self._lock_job(conn, lease.job_id)
            back = conn.execute(
                sa.update(tasks).where(self._fenced(lease))
                .values(state=TaskState.WAITING, attempts=0, lease_expires_at=None, lease_owner=None)
            )
            if back.rowcount != 1:
                raise LeaseLost(lease.task_id, lease.token, "lease expired and re-claimed, or job cancelled")
            cancelled = 0
            for r in skipped:
                cancelled += conn.execute(
                    sa.update(tasks).where(
                        tasks.c.job_id == lease.job_id, tasks.c.kind == TaskKind.SHARD,
                        tasks.c.shard_index >= r.start, tasks.c.shard_index < r.stop,
                        tasks.c.state.in_([TaskState.QUEUED, TaskState.LEASED, TaskState.WAITING]),
                    ).values(state=TaskState.CANCELLED, lease_expires_at=None, finished_at=now,
                             error="skipped: its medium met the target error with fewer shards")
                ).rowcount
            job = conn.execute(
                sa.update(jobs).where(jobs.c.id == lease.job_id)
                .values(folded=int(folded), fold_uri=fold.uri, fold_bytes=int(fold.bytes), fold_sha256=fold.sha256,
                        shards_skipped=jobs.c.shards_skipped + cancelled, updated_at=now)
                .returning(jobs.c.shards, jobs.c.shards_done, jobs.c.shards_skipped)
            ).one()
            self._wake_merge(conn, lease.job_id, int(folded), job.shards, job.shards_done, job.shards_skipped)

    def medium_progress(self, job_id: str, shards_per_medium: int, *, offset: int = 0,
                        limit: int = 1000) -> list[MediumProgress]:
        """Shard counts per medium (task t is medium t // shards_per_medium) for media
        [offset, offset + limit), with where the merge stands in each."""
        now = self._now()
        t = tasks.c
        medium = (t.shard_index // shards_per_medium).label("medium")  # integer division on both databases
        lo, hi = offset * shards_per_medium, (offset + limit) * shards_per_medium
        with self._read() as conn:
            folded = conn.execute(sa.select(jobs.c.folded).where(jobs.c.id == job_id)).scalar_one()
            rows = conn.execute(
                sa.select(
                    medium, sa.func.count(),
                    sa.func.count().filter(t.state == TaskState.DONE),
                    sa.func.count().filter(t.state == TaskState.LEASED, t.lease_expires_at >= now),
                    sa.func.count().filter(t.state == TaskState.CANCELLED),
                    sa.func.coalesce(sa.func.sum(t.photons), 0),
                ).where(t.job_id == job_id, t.kind == TaskKind.SHARD, t.shard_index >= lo, t.shard_index < hi)
                .group_by(medium).order_by(medium)
            ).all()
        return [
            MediumProgress(int(m), int(n), int(done), int(running), int(skipped),
                           max(0, min(shards_per_medium, folded - int(m) * shards_per_medium)),
                           folded >= (int(m) + 1) * shards_per_medium, int(photons))
            for m, n, done, running, skipped, photons in rows
        ]

    def complete_merge(self, lease: Lease, name: str, meta: dict, publisher: Publisher) -> int:
        """Publish a dataset version and end the job ``succeeded``; returns the version number.

        The version number is ``max + 1`` over the name's rows (tombstones included), read and
        inserted by one publisher of the name at a time (:meth:`_lock_name`): concurrent
        publishes of a name queue for it and each gets the next number, none fails. The staged
        files are moved into place (``publisher.publish``) before the commit that inserts the
        catalog row, fences the merge lease and marks the job succeeded. If the process dies
        between the move and the commit, the directory is an orphan no catalog row points to
        (the next publisher of that version replaces it).

        On both backends a stalled move holds no row lock and no write lock: only the next
        publish of the same name waits for it. SQLite, whose write lock is the whole database's: the name is locked in files beside
        the database (:meth:`_sqlite_name_lock`). PostgreSQL: by the name's advisory lock
        (:meth:`_lock_name`), taken by the publish's one transaction, which writes nothing until
        the files are in place and then locks the job row, finishes the lease and records the
        version (one connection: a publish never holds one while it waits for another).
        """
        if lease.kind != TaskKind.MERGE:
            raise ValueError(f"complete_merge needs a merge lease; received a {lease.kind} lease")
        if self.dialect_name == "sqlite":
            with self._sqlite_name_lock(name):
                with self._read() as conn:
                    self._check_lease(conn, lease)  # a stale worker moves nothing over a live one
                    version = self._next_version(conn, name)
                publisher.publish(version)
                with self._tx() as conn:
                    self._lock_job(conn, lease.job_id)
                    self._finish(conn, lease)
                    if self._next_version(conn, name) != version:  # only complete_merge inserts rows
                        raise StoreError(f"dataset {name!r} version {version} was taken during its publish")
                    self._record_version(conn, lease, name, version, meta, publisher.uri_for(version))
            return version
        # PostgreSQL: one transaction, one connection (a publish never waits for a second one
        # from a bounded pool while it holds the first). It takes the name's advisory lock and
        # reads the next number, writing nothing; the files move; only then does it lock the
        # job row, finish the lease and record the version, and commit.
        with self._tx() as conn:
            self._lock_name(conn, name)
            self._check_lease(conn, lease)
            version = self._next_version(conn, name)
            publisher.publish(version)
            self._lock_job(conn, lease.job_id)
            self._finish(conn, lease)
            self._record_version(conn, lease, name, version, meta, publisher.uri_for(version))
        return version

    def _check_lease(self, conn: Connection, lease: Lease) -> None:
        """LeaseLost unless the lease is still ours (a read: the commit fences it again)."""
        if conn.execute(sa.select(tasks.c.id).where(self._fenced(lease))).first() is None:
            raise LeaseLost(lease.task_id, lease.token, "lease expired and re-claimed, or job cancelled")

    @staticmethod
    def _next_version(conn: Connection, name: str) -> int:
        return 1 + conn.execute(
            sa.select(sa.func.coalesce(sa.func.max(dataset_versions.c.version), 0))
            .where(dataset_versions.c.name == name)
        ).scalar_one()

    def _record_version(self, conn: Connection, lease: Lease, name: str, version: int, meta: dict, uri: str) -> None:
        """The catalog row of the version, its job succeeded (the merge task already finished)."""
        now = self._now()
        conn.execute(
            sa.insert(dataset_versions).values(
                name=name, version=version, uri=uri, created_at=now, job_id=lease.job_id, meta=meta,
            )
        )
        # Shards the merge no longer needs (the last medium met its target early):
        # cancelled as skipped, so that every task of a finished job is resolved.
        skipped = conn.execute(
            sa.update(tasks).where(
                tasks.c.job_id == lease.job_id, tasks.c.kind == TaskKind.SHARD,
                tasks.c.state.in_([TaskState.QUEUED, TaskState.LEASED, TaskState.WAITING]),
            ).values(state=TaskState.CANCELLED, lease_expires_at=None, finished_at=now,
                     error="skipped: its medium met the target error with fewer shards")
        ).rowcount
        conn.execute(
            sa.update(jobs).where(jobs.c.id == lease.job_id).values(
                state=JobState.SUCCEEDED, finished_at=now, updated_at=now, folded=jobs.c.shards,
                dataset_name=name, dataset_version=version, shards_skipped=jobs.c.shards_skipped + skipped,
            )
        )

    @contextmanager
    def _sqlite_name_lock(self, name: str) -> Iterator[None]:
        """Hold the SQLite store's version lock of dataset ``name``: ``flock`` of one of 256 files
        in ``FILE-publish-locks/`` beside the database, chosen by the first byte of
        sha256("bssrdf-dataset-version:" + name) (two names sharing it only publish one after
        the other). Each call opens its own file, so threads exclude each other as processes do;
        the kernel releases it when its process dies (kill -9 included); an SQLite store is on one
        host, so every publisher sees the same files. Waits up to the busy timeout, then raises
        :class:`StoreError` (the merge task is retried)."""
        directory = Path(f"{self.engine.url.database}-publish-locks")
        directory.mkdir(exist_ok=True)
        digest = hashlib.sha256(f"bssrdf-dataset-version:{name}".encode()).hexdigest()
        path = directory / f"{digest[:2]}.lock"
        deadline = time.monotonic() + SQLITE_BUSY_TIMEOUT_MS / 1000
        with open(path, "a+b") as f:
            while True:
                try:
                    fcntl.flock(f, fcntl.LOCK_EX | fcntl.LOCK_NB)
                    break
                except BlockingIOError:
                    if time.monotonic() > deadline:
                        raise StoreError(f"dataset {name!r}: another worker's publish holds its version lock "
                                         f"({path}); the merge is retried") from None
                    time.sleep(0.02)
            try:
                yield
            finally:
                fcntl.flock(f, fcntl.LOCK_UN)

    def _lock_name(self, conn: Connection, name: str) -> None:
        """Hold the version lock of dataset ``name`` until the end of the transaction.

        PostgreSQL: ``pg_advisory_xact_lock(key)``, key = the first 8 bytes of
        sha256("bssrdf-dataset-version:" + name) as a signed 64-bit integer (two names sharing a
        key only publish one after the other); transaction-scoped, so it works through pgbouncer
        in transaction mode. At READ COMMITTED the ``max(version)`` read after the lock is a new
        snapshot that sees the previous holder's committed row. SQLite: nothing to do, the
        transaction's ``BEGIN IMMEDIATE`` already holds the database's single write lock.
        """
        if self.dialect_name == "postgresql":
            digest = hashlib.sha256(f"bssrdf-dataset-version:{name}".encode()).digest()
            key = int.from_bytes(digest[:8], "big", signed=True)
            conn.execute(sa.select(sa.func.pg_advisory_xact_lock(sa.literal(key, sa.BigInteger))))
