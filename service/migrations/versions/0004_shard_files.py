"""Shard results as files in dataset storage, an O(1) shard commit and the fold cursor.

- ``shard_results``: ``uri`` (path of the shard's tally file relative to the storage root),
  ``bytes`` and ``sha256``; ``payload`` (tallies in the job store, before this revision) becomes
  nullable and is only read for results stored before it;
- ``jobs.shards_done`` / ``jobs.shards_skipped``: counters kept by the shard commit and the fold
  (the commit no longer counts the job's unfinished tasks); backfilled for existing jobs;
- ``jobs.folded``: tasks folded by the merge so far, in task order (the next task it needs), with
  ``fold_uri`` / ``fold_bytes`` / ``fold_sha256``, the file holding that fold;
- ``ix_tasks_job_shard`` (job_id, shard_index): one task of a job found by index;
- ``ix_tasks_merge_live``: queued and leased merge tasks (partial), claimed before shards.

``jobs.shards`` holds the job's shard tasks (media x shards) from here on; for a single medium
that is the spec's shards, as before.

Revision ID: 0004_shard_files
Revises: 0003_lifecycle
"""

import sqlalchemy as sa
from alembic import op

revision = "0004_shard_files"
down_revision = "0003_lifecycle"
branch_labels = None
depends_on = None

MERGE_LIVE = sa.text("kind = 'merge' AND state IN ('queued', 'leased')")


def upgrade() -> None:
    with op.batch_alter_table("shard_results") as t:
        t.alter_column("payload", existing_type=sa.LargeBinary, nullable=True)
        t.add_column(sa.Column("uri", sa.Text, nullable=True))
        t.add_column(sa.Column("bytes", sa.BigInteger, nullable=True))
        t.add_column(sa.Column("sha256", sa.String(64), nullable=True))
    with op.batch_alter_table("jobs") as t:
        t.add_column(sa.Column("shards_done", sa.Integer, nullable=False, server_default="0"))
        t.add_column(sa.Column("shards_skipped", sa.Integer, nullable=False, server_default="0"))
        t.add_column(sa.Column("folded", sa.Integer, nullable=False, server_default="0"))
        t.add_column(sa.Column("fold_uri", sa.Text, nullable=True))
        t.add_column(sa.Column("fold_bytes", sa.BigInteger, nullable=True))
        t.add_column(sa.Column("fold_sha256", sa.String(64), nullable=True))
    op.execute(
        "UPDATE jobs SET shards_done = (SELECT count(*) FROM tasks WHERE tasks.job_id = jobs.id "
        "AND tasks.kind = 'shard' AND tasks.state = 'done')"
    )
    op.create_index("ix_tasks_job_shard", "tasks", ["job_id", "shard_index"])
    op.create_index("ix_tasks_merge_live", "tasks", ["id"], sqlite_where=MERGE_LIVE, postgresql_where=MERGE_LIVE)


def downgrade() -> None:
    op.drop_index("ix_tasks_merge_live", table_name="tasks")
    op.drop_index("ix_tasks_job_shard", table_name="tasks")
    with op.batch_alter_table("jobs") as t:
        for name in ("fold_sha256", "fold_bytes", "fold_uri", "folded", "shards_skipped", "shards_done"):
            t.drop_column(name)
    op.execute("DELETE FROM shard_results WHERE payload IS NULL")  # file results cannot go back into rows
    with op.batch_alter_table("shard_results") as t:
        t.drop_column("sha256")
        t.drop_column("bytes")
        t.drop_column("uri")
        t.alter_column("payload", existing_type=sa.LargeBinary, nullable=False)
