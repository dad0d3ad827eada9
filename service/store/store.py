"""``JobStore``: the job store and lease queue behind the API, the workers and ``bssrdf run``."""

from __future__ import annotations

from pathlib import Path

import sqlalchemy as sa
from alembic import command
from alembic.config import Config

from service.store.catalog import CatalogMixin
from service.store.exports import ExportsMixin
from service.store.fold import FoldMixin
from service.store.jobs import JobsMixin
from service.store.lifecycle import LifecycleMixin
from service.store.queue import QueueMixin
from service.store.retry import RetryPolicy
from service.store.states import JobState, TaskKind, TaskState
from service.store.tables import jobs, tasks

__all__ = ["JobStore", "MIGRATIONS_DIR"]

MIGRATIONS_DIR = Path(__file__).resolve().parent.parent / "migrations"
_PG_MIGRATION_LOCK = 0x6273_7372_6466  # arbitrary advisory-lock key ("bssrdf")


class JobStore(JobsMixin, QueueMixin, FoldMixin, CatalogMixin, ExportsMixin, LifecycleMixin):
    """Jobs, the shard/merge lease queue, the dataset catalog and its exports in one SQL database.

    ``JobStore(url)`` works for ``sqlite:///FILE`` (one host) and ``postgresql+psycopg://...``
    (many hosts) with the same code; ``migrate=True`` applies the Alembic migrations on open.
    ``fold_batch``: done shards in task order the merge waits for before a fold round
    (``BSSRDF_FOLD_BATCH``); ``pool_size``: connections kept open, ``max_overflow``: more opened
    when needed (:func:`service.store.engine.make_engine`). Create one store per process.
    """

    def __init__(
        self, url: str, *, max_attempts: int = 3, retry_policy: RetryPolicy = RetryPolicy(),
        migrate: bool = True, fold_batch: int = 8, pool_size: int = 2, max_overflow: int | None = None,
    ) -> None:
        super().__init__(url, max_attempts=max_attempts, retry_policy=retry_policy, pool_size=pool_size,
                         max_overflow=max_overflow)
        if fold_batch < 1:
            raise ValueError(f"fold_batch must be >= 1; received {fold_batch}")
        self.fold_batch = fold_batch
        if migrate:
            self.migrate()

    def migrate(self) -> None:
        """Bring the schema to the newest Alembic revision (safe to call from many processes)."""
        if self.dialect_name == "sqlite":
            Path(self.engine.url.database).parent.mkdir(parents=True, exist_ok=True)
        cfg = Config()
        cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
        with self._tx() as conn:  # BEGIN IMMEDIATE on SQLite serialises concurrent migrations
            if self.dialect_name == "postgresql":
                conn.execute(sa.select(sa.func.pg_advisory_xact_lock(_PG_MIGRATION_LOCK)))
            cfg.attributes["connection"] = conn
            command.upgrade(cfg, "head")

    def ping(self) -> None:
        """Raise if the database cannot be reached or is not migrated (for ``/readyz``)."""
        with self._read() as conn:
            conn.execute(sa.select(sa.func.count()).select_from(jobs)).scalar_one()

    def metrics(self) -> dict[str, object]:
        """Counters for ``/metrics``, derived from the tables (no hot counter rows).

        ``jobs_by_state``: jobs per JobState; ``tasks_claimed``: claims (attempts) of all tasks;
        ``shards_completed`` / ``merges_completed``: tasks done; ``leases_expired``: leases that
        ran out and were re-claimed or failed; ``photons_simulated``: photons of completed shards.
        """
        t = tasks.c
        with self._read() as conn:
            by_state = dict(conn.execute(sa.select(jobs.c.state, sa.func.count()).group_by(jobs.c.state)).all())
            claimed, expired, shards_done, merges_done, photons = conn.execute(
                sa.select(
                    sa.func.coalesce(sa.func.sum(t.attempts), 0),
                    sa.func.coalesce(sa.func.sum(t.expirations), 0),
                    sa.func.count().filter(t.kind == TaskKind.SHARD, t.state == TaskState.DONE),
                    sa.func.count().filter(t.kind == TaskKind.MERGE, t.state == TaskState.DONE),
                    sa.func.coalesce(
                        sa.func.sum(t.photons).filter(t.kind == TaskKind.SHARD, t.state == TaskState.DONE), 0
                    ),
                )
            ).one()
        return {
            "jobs_by_state": {str(s): int(by_state.get(str(s), 0)) for s in JobState},
            "tasks_claimed": int(claimed),
            "shards_completed": int(shards_done),
            "merges_completed": int(merges_done),
            "leases_expired": int(expired),
            "photons_simulated": int(photons),
        }
