"""The lease queue: claim, heartbeat, complete, fail, release, reap.

Every write that follows a claim is fenced: it applies only ``WHERE id = :task AND lease_token =
:token AND state = 'leased'``. A worker whose lease expired and was re-claimed (new token), or
whose job was cancelled, gets :class:`LeaseLost` and nothing it sends is stored or counted.
"""

from __future__ import annotations

import time

import sqlalchemy as sa
from sqlalchemy.engine import Connection

from service.store.base import StoreBase
from service.store.errors import JobNotFound, LeaseLost
from service.store.records import Lease, StoredFile
from service.store.retry import decide_retry
from service.store.states import ACTIVE_JOB_STATES, JobState, TaskKind, TaskState
from service.store.tables import jobs, shard_results, tasks

__all__ = ["QueueMixin"]


class _Keep:
    """The default of :meth:`QueueMixin.heartbeat`'s ``phase``: leave the stored phase as it is."""


class QueueMixin(StoreBase):
    """Task-level operations of workers."""

    def claim(self, worker_id: str, lease_seconds: float) -> Lease | None:
        """Lease the next claimable task, or return None.

        Claimable: job active, and task queued (and past its retry backoff) or leased with an
        expired lease and attempts left. Order: merge tasks first (a fold round is short and
        keeps the merge up with the shards), then oldest job first and task index. One atomic ``UPDATE ... WHERE id = (SELECT ... FOR UPDATE SKIP LOCKED LIMIT 1)
        RETURNING`` (the lock clause renders to nothing on SQLite, where BEGIN IMMEDIATE holds the
        single write lock instead). Every claim counts as an attempt and bumps the fencing token.
        """
        if time.monotonic() >= getattr(self, "_next_reap", 0.0):
            self.reap_expired()
        now = self._now()
        with self._tx() as conn:
            # One statement: merge tasks first (few: one per live job, ix_tasks_merge_live), so
            # that the fold keeps up with the shards as they arrive; then shards in fair order.
            # The job's state and spec come back with the task (no second round trip per claim:
            # under a transaction pooler a server connection is held for the whole transaction).
            row = conn.execute(self._claim_statement(now, worker_id, lease_seconds)).first()
            if row is not None and row.job_state == JobState.QUEUED:
                # Lock order elsewhere is job row, then task rows; here the task is already locked,
                # so skip a locked job row instead of waiting (no deadlock with cancel). Whoever
                # holds it is another first claim (it sets running) or a cancel.
                first_claim = (
                    sa.select(jobs.c.id)
                    .where(jobs.c.id == row.job_id, jobs.c.state == JobState.QUEUED)
                    .with_for_update(skip_locked=True)
                    .scalar_subquery()
                )
                conn.execute(
                    sa.update(jobs)
                    .where(jobs.c.id == first_claim)
                    .values(state=JobState.RUNNING, started_at=now, updated_at=now)
                )
        if row is None:
            return None  # the reaper runs every reap_interval_s above, not on every empty claim
        return Lease(
            task_id=row.id, token=row.lease_token, job_id=row.job_id, kind=TaskKind(row.kind),
            shard_index=row.shard_index, attempts=row.attempts, max_attempts=row.max_attempts,
            lease_expires_at=row.lease_expires_at, spec_json=row.spec_json, owner=worker_id,
        )

    def _candidate(self, now, kind: TaskKind | None):
        """The first claimable task (of ``kind``, if given), locked, skipping locked rows."""
        expired = sa.and_(
            tasks.c.state == TaskState.LEASED,
            tasks.c.lease_expires_at < now,
            tasks.c.attempts < tasks.c.max_attempts,
        )
        where = [
            jobs.c.state.in_(list(ACTIVE_JOB_STATES)),
            sa.or_(tasks.c.state == TaskState.QUEUED, expired),
            sa.or_(tasks.c.not_before.is_(None), tasks.c.not_before <= now),
        ]
        if kind is not None:
            where.append(tasks.c.kind == kind)
        return (
            sa.select(tasks.c.id)
            .join(jobs, jobs.c.id == tasks.c.job_id)
            .where(*where)
            .order_by(tasks.c.id)
            .limit(1)
            .with_for_update(skip_locked=True, of=tasks)
            .scalar_subquery()
        )

    def _claim_statement(self, now, worker_id: str, lease_seconds: float):
        """The atomic claim (see :meth:`claim`): ``UPDATE tasks ... WHERE id = coalesce(first
        claimable merge, first claimable task) RETURNING`` the task, its job's state and spec.

        ``coalesce`` evaluates its second argument only when the first is null (PostgreSQL runs
        each uncorrelated subquery as an init plan when first needed, so the shard candidate is
        neither looked for nor locked when a merge is claimable; SQLite holds the write lock).
        """
        # SQLite's RETURNING renders columns unqualified ("WHERE id = job_id"): in the subquery
        # "id" is the inner (job) table's and "job_id", a column jobs lacks, the updated task's.
        owner = jobs.alias("owner")
        job = lambda col: sa.select(owner.c[col]).where(owner.c.id == tasks.c.job_id).scalar_subquery()  # noqa: E731
        return (
            sa.update(tasks)
            .where(tasks.c.id == sa.func.coalesce(self._candidate(now, TaskKind.MERGE), self._candidate(now, None)))
            .values(
                expirations=tasks.c.expirations
                + sa.case((tasks.c.state == TaskState.LEASED, 1), else_=0),
                state=TaskState.LEASED,
                attempts=tasks.c.attempts + 1,
                lease_token=tasks.c.lease_token + 1,
                lease_owner=worker_id,
                lease_expires_at=now + sa.literal(float(lease_seconds), sa.Float),
                heartbeat_at=now,
                started_at=now,
                not_before=None,
                photons=0,
                phase=None,
            )
            .returning(
                tasks.c.id, tasks.c.lease_token, tasks.c.job_id, tasks.c.kind, tasks.c.shard_index,
                tasks.c.attempts, tasks.c.max_attempts, tasks.c.lease_expires_at,
                job("state").label("job_state"), job("spec_json").label("spec_json"),
            )
        )

    def _fenced(self, lease: Lease):
        return sa.and_(
            tasks.c.id == lease.task_id,
            tasks.c.lease_token == lease.token,
            tasks.c.state == TaskState.LEASED,
        )

    def heartbeat(self, lease: Lease, lease_seconds: float, *, photons: int | None = None,
                  phase: str | None | type[_Keep] = _Keep) -> bool:
        """Extend the lease by ``lease_seconds`` from now; False if the lease was lost.

        ``photons`` (photons simulated so far in this attempt) and ``phase`` (what the task does
        besides walking, e.g. "compiling the walk ...", or None once it walks; cut to 200
        characters; left as it is when not given) feed the progress query.
        """
        now = self._now()
        values = dict(lease_expires_at=now + sa.literal(float(lease_seconds), sa.Float), heartbeat_at=now)
        if photons is not None:
            values["photons"] = int(photons)
        if phase is not _Keep:
            values["phase"] = None if phase is None else str(phase)[:200]
        with self._tx() as conn:
            return conn.execute(sa.update(tasks).where(self._fenced(lease)).values(**values)).rowcount == 1

    def _finish(self, conn: Connection, lease: Lease, **values) -> None:
        """Mark the leased task done, fenced; raise LeaseLost (rolling back) if not ours."""
        now = self._now()
        done = conn.execute(
            sa.update(tasks)
            .where(self._fenced(lease))
            .values(state=TaskState.DONE, finished_at=now, lease_expires_at=None, error=None, **values)
        )
        if done.rowcount != 1:
            raise LeaseLost(lease.task_id, lease.token, "lease expired and re-claimed, or job cancelled")

    def complete_shard(self, lease: Lease, result: StoredFile, *, photons: int, elapsed_s: float) -> None:
        """Record a shard's result file (URI, size, sha256) and mark the task done, in one fenced
        transaction costing O(1) whatever the job's size: the job row's ``shards_done`` counter
        goes up by one (no count over its tasks).

        The merge task is queued once the next ``fold_batch`` tasks the fold needs are done (or
        every remaining one); the job turns ``merging`` when every task is done or skipped.
        Raises :class:`LeaseLost` if the token is stale; then nothing was written (the caller
        removes its file).
        """
        if lease.kind != TaskKind.SHARD:
            raise ValueError(f"complete_shard needs a shard lease; received a {lease.kind} lease")
        now = self._now()
        with self._tx() as conn:
            # The counter's UPDATE takes the job row's lock first (the lock order of every write:
            # job row, then its tasks), in the same round trip; a refused fence rolls it back.
            job = conn.execute(
                sa.update(jobs).where(jobs.c.id == lease.job_id)
                .values(shards_done=jobs.c.shards_done + 1, updated_at=now)
                .returning(jobs.c.shards, jobs.c.shards_done, jobs.c.shards_skipped, jobs.c.folded)
            ).first()
            if job is None:
                raise JobNotFound(lease.job_id)
            self._finish(conn, lease, photons=int(photons), elapsed_s=float(elapsed_s))
            conn.execute(
                sa.insert(shard_results).values(
                    job_id=lease.job_id, shard_index=lease.shard_index, uri=result.uri, bytes=int(result.bytes),
                    sha256=result.sha256, created_at=now,
                )
            )
            self._wake_merge(conn, lease.job_id, job.folded, job.shards, job.shards_done, job.shards_skipped)

    def _wake_merge(self, conn: Connection, job_id: str, folded: int, total: int, done: int, skipped: int) -> None:
        """Queue the waiting merge task if the fold can advance: the ``fold_batch`` tasks from
        ``folded`` on are done (indexed range count, O(fold_batch)), or every task is resolved;
        set the job ``merging`` once every task is done or skipped.

        The count is skipped when the job's counters already rule it out: the tasks below
        ``folded`` are resolved, so at most ``done + skipped - folded`` done tasks lie at or above
        it; fewer than the batch cannot fill it (most commits of a large job: one round trip less).
        """
        if done + skipped >= total:
            ready = True
            conn.execute(
                sa.update(jobs).where(jobs.c.id == job_id, jobs.c.state == JobState.RUNNING)
                .values(state=JobState.MERGING, updated_at=self._now())
            )
        else:
            n = min(self.fold_batch, total - folded)
            ready = n > 0 and done + skipped - folded >= n and conn.execute(
                sa.select(sa.func.count()).where(
                    tasks.c.job_id == job_id, tasks.c.shard_index >= folded, tasks.c.shard_index < folded + n,
                    tasks.c.kind == TaskKind.SHARD, tasks.c.state == TaskState.DONE,
                )
            ).scalar_one() == n
        if ready:
            # The merge task is the job's one task without a shard index: (job_id, shard_index IS
            # NULL) finds it through ix_tasks_job_shard, where job_id and kind alone visited every
            # task of the job (O(N) per wake-up, O(N^2 / fold_batch) per job).
            conn.execute(
                sa.update(tasks)
                .where(tasks.c.job_id == job_id, tasks.c.shard_index.is_(None), tasks.c.kind == TaskKind.MERGE,
                       tasks.c.state == TaskState.WAITING)
                .values(state=TaskState.QUEUED)
            )

    def fail_task(self, lease: Lease, error: str, *, final: bool = False) -> bool:
        """Record a failed attempt. Returns True if the task will be retried.

        The retry decision is :func:`service.store.retry.decide_retry`; without attempts left the
        task fails and its job fails with ``error`` kept. ``final``: the failure is deterministic
        (another attempt would fail the same way, e.g. a non-finite table), so the task and its
        job fail at once whatever attempts are left. Raises :class:`LeaseLost` if stale.
        """
        with self._tx() as conn:
            self._lock_job(conn, lease.job_id)
            row = conn.execute(
                sa.select(tasks.c.attempts, tasks.c.max_attempts).where(self._fenced(lease))
            ).first()
            if row is None:
                raise LeaseLost(lease.task_id, lease.token, "cannot record the failure")
            decision = decide_retry(row.attempts, row.max_attempts, self.retry_policy)
            now = self._now()
            if decision.retry and not final:
                conn.execute(
                    sa.update(tasks).where(tasks.c.id == lease.task_id).values(
                        state=TaskState.QUEUED, error=error, lease_expires_at=None,
                        not_before=now + sa.literal(float(decision.delay_s), sa.Float),
                    )
                )
                return True
            conn.execute(
                sa.update(tasks).where(tasks.c.id == lease.task_id).values(
                    state=TaskState.FAILED, error=error, lease_expires_at=None, finished_at=now
                )
            )
            what = "merge" if lease.kind == TaskKind.MERGE else f"shard {lease.shard_index}"
            after = "(not retried: it would fail the same way)" if final and decision.retry else \
                f"after {row.attempts} attempts"
            self._end_job(conn, lease.job_id, JobState.FAILED, error=f"{what} failed {after}: {error}")
            return False

    def pending_tasks(self) -> int:
        """Tasks of live jobs that are or may become claimable: queued (a retry backing off
        included), leased (running, or a lease that will expire) and waiting merges. Zero means
        no work can appear without a new submission (``bssrdf worker --once`` exits then)."""
        with self._read() as conn:
            return int(conn.execute(
                sa.select(sa.func.count()).select_from(tasks).join(jobs, jobs.c.id == tasks.c.job_id).where(
                    jobs.c.state.in_(list(ACTIVE_JOB_STATES)),
                    tasks.c.state.in_([TaskState.QUEUED, TaskState.LEASED, TaskState.WAITING]))
            ).scalar_one())

    def has_pending_tasks(self) -> bool:
        """``pending_tasks() > 0`` without counting: stops at the first such task (the idle poll
        of every ``--once`` worker of a fleet runs it after each empty claim)."""
        with self._read() as conn:
            return conn.execute(sa.select(
                sa.select(tasks.c.id).join(jobs, jobs.c.id == tasks.c.job_id).where(
                    jobs.c.state.in_(list(ACTIVE_JOB_STATES)),
                    tasks.c.state.in_([TaskState.QUEUED, TaskState.LEASED, TaskState.WAITING])).exists()
            )).scalar_one()

    def release(self, lease: Lease) -> bool:
        """Give a lease back unfinished (worker stopping): queued again, not counted as an attempt."""
        with self._tx() as conn:
            return conn.execute(
                sa.update(tasks).where(self._fenced(lease)).values(
                    state=TaskState.QUEUED, attempts=tasks.c.attempts - 1, lease_expires_at=None,
                    lease_owner=None, photons=0,
                )
            ).rowcount == 1

    reap_interval_s = 5.0

    def reap_expired(self) -> int:
        """Fail tasks whose lease expired with no attempts left, and their jobs. Returns how many.

        ``claim`` calls it at most every ``reap_interval_s`` seconds (an idle fleet polling does
        not run it once per poll).
        """
        self._next_reap = time.monotonic() + self.reap_interval_s
        now = self._now()
        exhausted = sa.and_(
            tasks.c.state == TaskState.LEASED,
            tasks.c.lease_expires_at < now,
            tasks.c.attempts >= tasks.c.max_attempts,
        )
        with self._read() as conn:
            job_ids = conn.execute(sa.select(tasks.c.job_id).where(exhausted).distinct()).scalars().all()
        rows = []
        for job_id in job_ids:
            with self._tx() as conn:
                # Job row first, then its tasks: the lock order of every other write.
                if self._lock_job(conn, job_id) not in ACTIVE_JOB_STATES:
                    continue
                failed = conn.execute(
                    sa.update(tasks)
                    .where(tasks.c.job_id == job_id, exhausted)
                    .values(
                        state=TaskState.FAILED, expirations=tasks.c.expirations + 1, finished_at=now,
                        error=sa.func.coalesce(tasks.c.error, "lease expired (worker died or stalled)"),
                    )
                    .returning(tasks.c.kind, tasks.c.shard_index, tasks.c.attempts)
                ).all()
                if failed:
                    r = failed[0]
                    what = "merge" if r.kind == TaskKind.MERGE else f"shard {r.shard_index}"
                    self._end_job(
                        conn, job_id, JobState.FAILED,
                        error=f"{what} failed after {r.attempts} attempts: lease expired every time "
                        "(worker died, was killed, or stalled without heartbeats)",
                    )
                rows += failed
        return len(rows)
