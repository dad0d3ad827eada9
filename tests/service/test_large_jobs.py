"""A large job's rows: created by one INSERT ... SELECT in task order, deleted in chunks of short
transactions, with nothing of the job left and nothing of another job touched. (How long either
holds the store is measured by ``python -m bench.submit``, BENCHMARKS.md.)"""

from __future__ import annotations

import pytest
import sqlalchemy as sa

import service.store.lifecycle as lifecycle
from service.store import JobNotFound, StoredFile, TaskKind, TaskState
from service.store.tables import shard_results, tasks
from tests.service.conftest import queue_spec


def _rows(store, table, job_id):
    with store._read() as conn:
        return conn.execute(sa.select(table).where(table.c.job_id == job_id).order_by(table.c.shard_index)).all()


def test_tasks_are_created_in_task_order_with_their_defaults(store):
    job = store.submit(queue_spec(name="big", shards=1234))
    with store._read() as conn:
        rows = conn.execute(sa.select(tasks).where(tasks.c.job_id == job.id).order_by(tasks.c.id)).all()
    assert [r.shard_index for r in rows] == [*range(1234), None]
    assert [r.kind for r in rows] == [TaskKind.SHARD] * 1234 + [TaskKind.MERGE]
    assert {r.state for r in rows[:-1]} == {TaskState.QUEUED} and rows[-1].state == TaskState.WAITING
    assert {(r.attempts, r.expirations, r.lease_token, r.photons, r.max_attempts) for r in rows} == {(0, 0, 0, 0, 3)}
    assert store.claim("w", 60).shard_index == 0


def test_a_large_job_is_deleted_in_chunks_and_completely(store, monkeypatch):
    monkeypatch.setattr(lifecycle, "DELETE_CHUNK", 100)
    monkeypatch.setattr(store, "fold_batch", 10**6)  # no merge round in between: shards only
    job = store.submit(queue_spec(name="big", shards=1050))
    other = store.submit(queue_spec(name="other", shards=5))
    for _ in range(250):  # the older job's tasks are claimed first: 250 results of big's
        lease = store.claim("w", 60)
        store.complete_shard(lease, StoredFile(f"x/{lease.task_id}", 1, "0" * 64), photons=1, elapsed_s=0.0)
    running = store.claim("w", 60)
    assert running.job_id == job.id and len(_rows(store, shard_results, job.id)) == 250
    deleted = store.delete_job(job.id)
    assert deleted.id == job.id
    with pytest.raises(JobNotFound):
        store.get_job(job.id)
    assert _rows(store, tasks, job.id) == [] and _rows(store, shard_results, job.id) == []
    assert len(_rows(store, tasks, other.id)) == 6 and store.get_job(other.id).state == "queued"
    assert not store.heartbeat(running, 60)  # its worker learns at the next heartbeat
