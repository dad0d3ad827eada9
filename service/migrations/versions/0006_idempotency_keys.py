"""Idempotency keys in a table of their own: ``idempotency_keys`` (key -> job).

A submission with a key that the duplicate check answers with an existing job (same spec hash)
stored no job, so its key was nowhere: the same key with another spec then made a new job
instead of a 409. Every key is now a row here naming the job it was answered with, the job's own
key (``jobs.idempotency_key``, still shown) included; rows go with their job (ON DELETE CASCADE).
Backfilled from ``jobs.idempotency_key``.

Revision ID: 0006_idempotency_keys
Revises: 0005_task_phase
"""

import sqlalchemy as sa
from alembic import op

revision = "0006_idempotency_keys"
down_revision = "0005_task_phase"
branch_labels = None
depends_on = None


def upgrade() -> None:
    op.create_table(
        "idempotency_keys",
        sa.Column("key", sa.String(200), primary_key=True),
        sa.Column("job_id", sa.String(36), sa.ForeignKey("jobs.id", ondelete="CASCADE"), nullable=False),
        sa.Column("created_at", sa.Float, nullable=False),
    )
    op.create_index("ix_idempotency_keys_job_id", "idempotency_keys", ["job_id"])
    op.execute("INSERT INTO idempotency_keys (key, job_id, created_at) "
               "SELECT idempotency_key, id, created_at FROM jobs WHERE idempotency_key IS NOT NULL")


def downgrade() -> None:
    op.drop_index("ix_idempotency_keys_job_id", table_name="idempotency_keys")
    op.drop_table("idempotency_keys")
