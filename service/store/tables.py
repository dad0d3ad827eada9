"""SQLAlchemy Core tables of the job store (the schema created by migrations 0001, 0002, 0003_lifecycle,
0004_shard_files, 0005_task_phase, 0006_idempotency_keys).

Times are seconds since the Unix epoch (float64) read from the *database* clock
(:func:`service.store.engine.db_now`), so leases are judged by one clock for every worker host.
"""

from __future__ import annotations

import sqlalchemy as sa

__all__ = ["metadata", "jobs", "tasks", "shard_results", "dataset_versions", "dataset_exports", "idempotency_keys"]

metadata = sa.MetaData()

jobs = sa.Table(
    "jobs",
    metadata,
    sa.Column("id", sa.String(36), primary_key=True),  # uuid4 text
    sa.Column("name", sa.String(200), nullable=False),  # dataset name (spec.name)
    sa.Column("spec_json", sa.Text, nullable=False),  # spec.canonical_json()
    sa.Column("spec_hash", sa.String(64), nullable=False),
    sa.Column("shards", sa.Integer, nullable=False),  # shard tasks: media x shards per medium
    sa.Column("state", sa.String(16), nullable=False),  # JobState
    sa.Column("idempotency_key", sa.String(200), unique=True, nullable=True),
    sa.Column("created_at", sa.Float, nullable=False),
    sa.Column("updated_at", sa.Float, nullable=False),
    sa.Column("started_at", sa.Float),
    sa.Column("finished_at", sa.Float),
    sa.Column("error", sa.Text),
    sa.Column("dataset_name", sa.String(200)),
    sa.Column("dataset_version", sa.Integer),
    sa.Column("photons_total", sa.BigInteger),  # photons x angles x channels x media (None: unknown)
    # Shard tasks are media x shards (column "shards"); counters kept by commits and the fold:
    sa.Column("shards_done", sa.Integer, nullable=False, server_default="0"),  # +1 per shard commit
    sa.Column("shards_skipped", sa.Integer, nullable=False, server_default="0"),  # cancelled by an early stop
    sa.Column("folded", sa.Integer, nullable=False, server_default="0"),  # tasks folded, in task order
    sa.Column("fold_uri", sa.Text),  # the fold of those tasks: file relative to the storage root
    sa.Column("fold_bytes", sa.BigInteger),
    sa.Column("fold_sha256", sa.String(64)),
    sa.Index("ix_jobs_spec_hash", "spec_hash"),
)

idempotency_keys = sa.Table(
    "idempotency_keys",
    metadata,
    # Every idempotency key and the job it was answered with: the job it created (also in
    # jobs.idempotency_key) or the existing job the duplicate check returned (migration 0006).
    sa.Column("key", sa.String(200), primary_key=True),
    sa.Column("job_id", sa.String(36), sa.ForeignKey("jobs.id", ondelete="CASCADE"), nullable=False),
    sa.Column("created_at", sa.Float, nullable=False),
    sa.Index("ix_idempotency_keys_job_id", "job_id"),
)

tasks = sa.Table(
    "tasks",
    metadata,
    # Autoincrement id: tasks are inserted job by job in shard order, merge last, so ORDER BY id is
    # the fair claim order (oldest job first, then shard index).
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("job_id", sa.String(36), sa.ForeignKey("jobs.id", ondelete="CASCADE"), nullable=False),
    sa.Column("kind", sa.String(8), nullable=False),  # TaskKind
    sa.Column("shard_index", sa.Integer),  # task index medium * shards + shard (schema.media); None: merge
    sa.Column("state", sa.String(16), nullable=False),  # TaskState
    sa.Column("attempts", sa.Integer, nullable=False, server_default="0"),  # claims so far
    sa.Column("max_attempts", sa.Integer, nullable=False),
    sa.Column("expirations", sa.Integer, nullable=False, server_default="0"),  # leases that expired
    sa.Column("lease_owner", sa.String(200)),
    sa.Column("lease_token", sa.Integer, nullable=False, server_default="0"),  # fencing: +1 per claim
    sa.Column("lease_expires_at", sa.Float),
    sa.Column("heartbeat_at", sa.Float),
    sa.Column("not_before", sa.Float),  # retry backoff: not claimable before this time
    sa.Column("started_at", sa.Float),  # time of the current (last) claim
    sa.Column("finished_at", sa.Float),
    sa.Column("photons", sa.BigInteger, nullable=False, server_default="0"),  # done so far / in total
    sa.Column("elapsed_s", sa.Float),
    sa.Column("error", sa.Text),
    sa.Column("phase", sa.String(200)),  # a running shard's phase besides walking ("compiling ..."), heartbeats
    sa.Index("ix_tasks_state_id", "state", "id"),
    sa.Index("ix_tasks_job_id", "job_id"),
    sa.Index("ix_tasks_job_shard", "job_id", "shard_index"),  # one task of a job (migration 0004)
    # Live merge tasks, claimed before shards so that the fold keeps up (partial index, 0004).
    sa.Index("ix_tasks_merge_live", "id", sqlite_where=sa.text("kind = 'merge' AND state IN ('queued', 'leased')"),
             postgresql_where=sa.text("kind = 'merge' AND state IN ('queued', 'leased')")),
    # The claim's candidates: queued and leased tasks only (partial index, migration 0002).
    sa.Index("ix_tasks_live", "id", sqlite_where=sa.text("state IN ('queued', 'leased')"),
             postgresql_where=sa.text("state IN ('queued', 'leased')")),
)

shard_results = sa.Table(
    "shard_results",
    metadata,
    sa.Column("job_id", sa.String(36), sa.ForeignKey("jobs.id", ondelete="CASCADE"), primary_key=True),
    sa.Column("shard_index", sa.Integer, primary_key=True),  # unique (job_id, shard_index)
    sa.Column("payload", sa.LargeBinary, nullable=True),  # results stored before migration 0004 only
    sa.Column("uri", sa.Text),  # the ShardTally.to_bytes() file, relative to the storage root
    sa.Column("bytes", sa.BigInteger),
    sa.Column("sha256", sa.String(64)),
    sa.Column("created_at", sa.Float, nullable=False),
)

dataset_versions = sa.Table(
    "dataset_versions",
    metadata,
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("name", sa.String(200), nullable=False),
    sa.Column("version", sa.Integer, nullable=False),
    sa.Column("uri", sa.Text, nullable=False),  # directory of the version on the storage filesystem
    sa.Column("created_at", sa.Float, nullable=False),
    sa.Column("job_id", sa.String(36), sa.ForeignKey("jobs.id"), nullable=True),
    sa.Column("meta", sa.JSON, nullable=False),  # metadata.json content + its own sha256
    sa.Column("deleted_at", sa.Float),  # set: a tombstone (files removed, row and spec hash kept)
    sa.Column("deleted_by", sa.String(200)),  # who deleted it (token fingerprint)
    sa.UniqueConstraint("name", "version", name="uq_dataset_versions_name_version"),
)

dataset_exports = sa.Table(
    "dataset_exports",
    metadata,
    # One stored export per (version, format), made on first request (migration 0002).
    sa.Column("id", sa.Integer, primary_key=True, autoincrement=True),
    sa.Column("version_id", sa.Integer, sa.ForeignKey("dataset_versions.id", ondelete="CASCADE"), nullable=False),
    sa.Column("format", sa.String(32), nullable=False),
    sa.Column("filename", sa.Text, nullable=False),  # archive path relative to the version directory
    sa.Column("sha256", sa.String(64), nullable=False),
    sa.Column("bytes", sa.BigInteger, nullable=False),
    sa.Column("created_at", sa.Float, nullable=False),
    sa.Column("meta", sa.JSON, nullable=False),  # the export's manifest: provenance and its files
    sa.UniqueConstraint("version_id", "format", name="uq_dataset_exports_version_format"),
)
