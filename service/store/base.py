"""Shared plumbing of the store mixins: engine, transactions, clock, job-row lock."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import sqlalchemy as sa
from sqlalchemy.engine import Connection, Engine

from service.store.engine import READ_ONLY, db_now, make_engine
from service.store.errors import JobNotFound
from service.store.retry import RetryPolicy
from service.store.states import JobState, TaskState
from service.store.tables import jobs, tasks

__all__ = ["StoreBase"]


class StoreBase:
    """Engine, transaction helper and the operations every mixin needs."""

    def __init__(self, url: str, *, max_attempts: int = 3, retry_policy: RetryPolicy = RetryPolicy(),
                 pool_size: int = 2, max_overflow: int | None = None) -> None:
        if max_attempts < 1:
            raise ValueError(f"max_attempts must be >= 1; received {max_attempts}")
        self.url = url
        self.engine: Engine = make_engine(url, pool_size, max_overflow)
        self.max_attempts = max_attempts
        self.retry_policy = retry_policy

    @property
    def dialect_name(self) -> str:
        """``sqlite`` or ``postgresql``."""
        return self.engine.dialect.name

    def _now(self) -> sa.ColumnElement[float]:
        return db_now(self.engine.dialect)

    @contextmanager
    def _tx(self) -> Iterator[Connection]:
        """One short transaction (``BEGIN IMMEDIATE`` on SQLite)."""
        with self.engine.begin() as conn:
            yield conn

    @contextmanager
    def _read(self) -> Iterator[Connection]:
        """A connection for reads only. On SQLite its transaction is a deferred ``BEGIN``: WAL
        readers see a snapshot without taking the write lock, so a status read never queues
        behind a worker's commit (:data:`service.store.engine.READ_ONLY`); on PostgreSQL it
        runs in autocommit."""
        options: dict = {READ_ONLY: True}
        if self.dialect_name == "postgresql":
            # No BEGIN and ROLLBACK around the reads: two round trips fewer per read, each a wait
            # for the server process's turn on a busy machine. At READ COMMITTED every statement
            # sees its own snapshot either way.
            options["isolation_level"] = "AUTOCOMMIT"
        with self.engine.connect() as conn:
            conn.execution_options(**options)
            yield conn

    def now(self) -> float:
        """The database clock, seconds since the Unix epoch."""
        with self._read() as conn:
            return float(conn.execute(sa.select(self._now())).scalar_one())

    def _lock_job(self, conn: Connection, job_id: str) -> JobState:
        """Lock the job row until the end of the transaction (serialises commits of one job)."""
        state = conn.execute(
            sa.select(jobs.c.state).where(jobs.c.id == job_id).with_for_update()
        ).scalar_one_or_none()
        if state is None:
            raise JobNotFound(job_id)
        return JobState(state)

    def _end_job(self, conn: Connection, job_id: str, state: JobState, error: str | None = None) -> None:
        """Move a job to a terminal state and cancel its unfinished tasks."""
        now = self._now()
        conn.execute(
            sa.update(jobs)
            .where(jobs.c.id == job_id)
            .values(state=state, error=error, finished_at=now, updated_at=now)
        )
        conn.execute(
            sa.update(tasks)
            .where(
                tasks.c.job_id == job_id,
                tasks.c.state.in_([TaskState.WAITING, TaskState.QUEUED, TaskState.LEASED]),
            )
            .values(state=TaskState.CANCELLED, lease_expires_at=None, finished_at=now)
        )

    def dispose(self) -> None:
        """Close pooled connections (call before forking or at exit)."""
        self.engine.dispose()
