"""Lifecycle and scale: tombstones of deleted dataset versions, the job's photon total, the
spec-hash lookup of duplicate submissions, and a partial index over live tasks for the claim.

- ``dataset_versions.deleted_at`` / ``deleted_by``: a deleted version keeps its row (name,
  version, its metadata with the spec hash) as a tombstone; its files are removed;
- ``jobs.photons_total``: photons the whole job walks (progress rate and ETA before any shard ends);
- ``ix_jobs_spec_hash``: duplicate submissions are found by the spec hash;
- ``ix_tasks_live``: the claim reads only queued and leased tasks, a few among the done ones of
  a large store (partial index, ``WHERE state IN ('queued', 'leased')``, on both databases).

Revision ID: 0003_lifecycle
Revises: 0002 (dataset exports)
"""

import sqlalchemy as sa
from alembic import op

revision = "0003_lifecycle"
down_revision = "0002"
branch_labels = None
depends_on = None

LIVE = sa.text("state IN ('queued', 'leased')")


def upgrade() -> None:
    with op.batch_alter_table("dataset_versions") as t:
        t.add_column(sa.Column("deleted_at", sa.Float, nullable=True))
        t.add_column(sa.Column("deleted_by", sa.String(200), nullable=True))
    with op.batch_alter_table("jobs") as t:
        t.add_column(sa.Column("photons_total", sa.BigInteger, nullable=True))
    op.create_index("ix_jobs_spec_hash", "jobs", ["spec_hash"])
    op.create_index("ix_tasks_live", "tasks", ["id"], sqlite_where=LIVE, postgresql_where=LIVE)


def downgrade() -> None:
    op.drop_index("ix_tasks_live", table_name="tasks")
    op.drop_index("ix_jobs_spec_hash", table_name="jobs")
    with op.batch_alter_table("jobs") as t:
        t.drop_column("photons_total")
    with op.batch_alter_table("dataset_versions") as t:
        t.drop_column("deleted_by")
        t.drop_column("deleted_at")
