"""What a running task is doing besides walking: ``tasks.phase``.

A worker's heartbeat reports, next to the photons walked so far, a phase such as "compiling the
walk for eta = 1.3 (first run on this machine, ~1-2 min)" while a kernel compiles, and clears
it when the walk starts; a claim clears it too. The progress read shows it, so a job's first
minutes on a new machine say what is happening instead of "0 photons/s". Nullable, no backfill.

Revision ID: 0005_task_phase
Revises: 0004_shard_files
"""

import sqlalchemy as sa
from alembic import op

revision = "0005_task_phase"
down_revision = "0004_shard_files"
branch_labels = None
depends_on = None


def upgrade() -> None:
    with op.batch_alter_table("tasks") as t:
        t.add_column(sa.Column("phase", sa.String(200), nullable=True))


def downgrade() -> None:
    with op.batch_alter_table("tasks") as t:
        t.drop_column("phase")
