"""A shard commit costs O(1) in the job's size: ``complete_shard`` bumps a counter on
the job row and counts only the ``fold_batch`` tasks the fold needs next, through the
(job_id, shard_index) index, instead of counting all of the job's unfinished tasks.

Proof, for the first ``fold_batch`` commits of a 10-task job and of a 2,000-task job (the last of
them queues the merge): the same SQL statements in the same order (captured with SQLAlchemy's
``before_cursor_execute``), on both backends; and, on SQLite, the work the database does
(virtual-machine instructions, counted by the progress handler) grows by less than one
instruction per extra task. Any statement visiting the job's tasks one by one costs at least one
instruction (a ``Next``) per row, so an O(N) count could not pass.
"""

from __future__ import annotations

import sqlalchemy as sa

from service.store import JobStore, RetryPolicy, StoredFile

SMALL, LARGE = 10, 2_000
FOLD_BATCH = 8


class Recorder:
    """Statements a store's engine runs while ``on``, and (SQLite) the VM instructions they take."""

    def __init__(self, store: JobStore) -> None:
        self.on, self.statements, self.steps = False, [], 0
        self.sqlite = store.dialect_name == "sqlite"
        sa.event.listen(store.engine, "before_cursor_execute", self._before)

    def _count(self) -> int:
        self.steps += self.on  # called every VM instruction (progress handler period 1)
        return 0  # 0: carry on

    def _before(self, conn, cursor, statement, parameters, context, executemany) -> None:
        if self.sqlite:
            cursor.connection.set_progress_handler(self._count, 1)
        if self.on:
            self.statements.append(" ".join(statement.split()))

    def commits(self, store: JobStore, job_id: str, n: int) -> list[tuple[list[str], int]]:
        """Claim and commit ``n`` shards of the job; per commit, its statements and VM steps."""
        out = []
        for _ in range(n):
            lease = store.claim("cost-probe", 600)
            assert lease is not None and lease.job_id == job_id
            ref = StoredFile(f".jobs/{job_id}/shards/{lease.shard_index}", 10, "0" * 64)
            self.on, self.statements, self.steps = True, [], 0
            store.complete_shard(lease, ref, photons=1, elapsed_s=0.0)
            self.on = False
            out.append((self.statements, self.steps))
        return out


def test_a_shard_commit_does_not_grow_with_the_job(db_url, fake_spec):
    store = JobStore(db_url, fold_batch=FOLD_BATCH, retry_policy=RetryPolicy(base_delay_s=0.0))
    rec = Recorder(store)
    small = store.submit(fake_spec(name="small", shards=SMALL))
    few = rec.commits(store, small.id, FOLD_BATCH)
    store.cancel(small.id)
    large = store.submit(fake_spec(name="large", shards=LARGE))
    many = rec.commits(store, large.id, FOLD_BATCH)
    assert store.fold_position(large.id).shards_done == FOLD_BATCH
    assert store.pending_tasks() > 0  # the merge is queued (the last commit woke it)

    for i, ((stmts_few, steps_few), (stmts_many, steps_many)) in enumerate(zip(few, many)):
        assert stmts_few == stmts_many, f"commit {i}: the statements depend on the job's size"
        if rec.sqlite:
            assert steps_few > 0
            assert steps_many - steps_few < LARGE - SMALL, (
                f"commit {i}: {steps_few} VM instructions for {SMALL} tasks, {steps_many} for {LARGE}")
    store.dispose()


def test_the_probe_sees_a_count_over_all_tasks(tmp_path, fake_spec):
    """The measuring stick works: counting a job's tasks costs at least one instruction per task."""
    store = JobStore(f"sqlite:///{tmp_path / 'jobs.sqlite'}")
    rec = Recorder(store)
    costs = {}
    for n in (SMALL, LARGE):
        job = store.submit(fake_spec(name=f"count-{n}", shards=n))
        with store.engine.connect() as conn:
            rec.on, rec.steps = True, 0
            conn.execute(sa.text("SELECT count(*) FROM tasks WHERE job_id = :j AND state != 'done'"), {"j": job.id})
            rec.on = False
        costs[n] = rec.steps
    assert costs[LARGE] - costs[SMALL] >= LARGE - SMALL, costs
    store.dispose()


def test_claims_and_commits_take_few_round_trips(db_url, fake_spec):
    """Under a transaction pooler a server connection is held for a whole transaction, client gaps
    included, so statements per claim and commit bound a fleet's throughput (BENCHMARKS.md, fleet):
    a claim is one statement (two on a job's first claim, which also marks the job running); a
    commit is three until the fold's next batch may be complete (then the batch count, and the
    merge's wake-up once it is)."""
    store = JobStore(db_url, fold_batch=4)
    store.reap_interval_s = 1e9
    store.reap_expired()  # not during the probe
    rec = Recorder(store)
    job = store.submit(fake_spec(name="trips", shards=4))
    per_claim, per_commit = [], []
    for _ in range(4):
        rec.on, rec.statements = True, []
        lease = store.claim("w", 600)
        per_claim.append(rec.statements)
        rec.statements = []
        store.complete_shard(lease, StoredFile(f".jobs/{job.id}/s{lease.shard_index}", 1, "0" * 64),
                             photons=1, elapsed_s=0.0)
        per_commit.append(rec.statements)
        rec.on = False
    per_claim, per_commit = ([[s for s in x if not s.startswith("BEGIN")] for x in y] for y in (per_claim, per_commit))
    assert [len(s) for s in per_claim] == [2, 1, 1, 1], per_claim[:2]
    assert per_claim[0][0].startswith("UPDATE tasks") and per_claim[0][1].startswith("UPDATE jobs")
    # The last commit resolves every task: the job turns merging and the merge is queued.
    assert [len(s) for s in per_commit] == [3, 3, 3, 5], per_commit
    merge = store.claim("w", 600)
    assert merge.kind == "merge" and merge.spec_json == store.get_job(job.id).spec_json
    store.dispose()
