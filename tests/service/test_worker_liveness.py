"""Liveness follows progress, and ``--once`` waits for work that can still appear (SQLite and
PostgreSQL): a hung walk stops heartbeating and its shard is redone elsewhere; a ``--once``
worker stays while a merge waits for another worker's shard, then runs the merge and leaves."""

from __future__ import annotations

import threading
import time

import pytest

from schema import parse_spec
from service.datasets import DatasetStorage, JobFiles
from service.store import JobState, TaskKind
from service.worker import Worker, _Heartbeat
from tests.api.conftest import TINY_SPEC


def test_a_walk_without_progress_loses_its_lease(store, fake_spec):
    store.submit(fake_spec(shards=1))
    lease = store.claim("hung", 1.0)
    stale = time.monotonic() - 10.0  # last progress report 10 s ago
    beat = _Heartbeat(store, lease, 1.0, 0.1, lambda: 5, lambda: stale, stall_seconds=0.5)
    beat.start()
    assert beat.stalled.wait(2.0) and beat.lost.is_set()
    time.sleep(1.1)  # no more heartbeats: the lease runs out
    again = store.claim("other", 30)
    assert again is not None and again.task_id == lease.task_id and again.attempts == 2
    beat.stop()


def test_a_walk_that_progresses_keeps_its_lease(store, fake_spec):
    store.submit(fake_spec(shards=1))
    lease = store.claim("busy", 1.0)
    beat = _Heartbeat(store, lease, 1.0, 0.1, lambda: 5, time.monotonic, stall_seconds=0.5)
    beat.start()
    time.sleep(1.5)
    assert not beat.stalled.is_set() and store.claim("other", 30) is None
    beat.stop()
    # before its first progress report (compiling) no stall is judged
    store2_beat = _Heartbeat(store, lease, 1.0, 0.1, lambda: 0, lambda: None, stall_seconds=0.01)
    store2_beat.start()
    time.sleep(0.3)
    assert not store2_beat.stalled.is_set()
    store2_beat.stop()


def test_once_waits_for_a_merge_that_waits_for_another_worker(store, tmp_path):
    from workers.run.shard import run_shard

    spec = parse_spec(TINY_SPEC)
    job = store.submit(spec)
    other = store.claim("other-worker", 60)  # shard 0, held by someone else
    storage = DatasetStorage(str(tmp_path / "data"))
    worker = Worker(store, storage, once=True, poll_seconds=0.05)
    thread = threading.Thread(target=worker.loop)
    thread.start()
    deadline = time.monotonic() + 60
    while store.progress(job.id).shards_done < 1 and time.monotonic() < deadline:
        time.sleep(0.05)
    time.sleep(0.3)
    assert thread.is_alive(), "--once left while the job's merge still waited for a running shard"
    tally = run_shard(spec, other.shard_index)
    ref = JobFiles(storage, job.id).write(f"shards/{other.shard_index:08d}-{other.token}.tally", tally.to_bytes())
    store.complete_shard(other, ref, photons=tally.photons, elapsed_s=tally.elapsed_s)
    thread.join(60)
    assert not thread.is_alive() and store.get_job(job.id).state == JobState.SUCCEEDED
    assert other.kind == TaskKind.SHARD
