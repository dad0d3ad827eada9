"""The lease queue, on SQLite and PostgreSQL alike."""

from __future__ import annotations

import time

import pytest

from service.store import JobState, LeaseLost, TaskKind, TaskState, decide_retry, RetryPolicy
from tests.service.conftest import queue_spec
from tests.support.files import stored

SHORT = 0.2  # seconds: a lease that expires within the test


def finish_shards(store, job_id, n):
    for _ in range(n):
        lease = store.claim("w", 30)
        assert lease.kind == TaskKind.SHARD and lease.job_id == job_id
        store.complete_shard(lease, stored(b"p%d" % lease.shard_index), photons=100, elapsed_s=0.1)


def test_claim_order_oldest_job_first_then_shard_index(store):
    a = store.submit(queue_spec("a", shards=2))
    b = store.submit(queue_spec("b", shards=2))
    got = [(l.job_id, l.kind, l.shard_index) for l in iter(lambda: store.claim("w", 30), None)]
    # Merge tasks wait for their shards, so only the four shards are claimable.
    assert got == [(a.id, "shard", 0), (a.id, "shard", 1), (b.id, "shard", 0), (b.id, "shard", 1)]
    assert store.get_job(a.id).state == JobState.RUNNING


def test_merge_task_is_gated_on_all_shards(store):
    job = store.submit(queue_spec(shards=3))
    leases = [store.claim("w", 30) for _ in range(3)]
    assert store.claim("w", 30) is None
    for lease in leases[:2]:
        store.complete_shard(lease, stored(b"x"), photons=10, elapsed_s=0.1)
    assert store.claim("w", 30) is None and store.progress(job.id).merge_state == TaskState.WAITING
    store.complete_shard(leases[2], stored(b"x"), photons=10, elapsed_s=0.1)
    assert store.get_job(job.id).state == JobState.MERGING
    merge = store.claim("w", 30)
    assert merge.kind == TaskKind.MERGE and merge.shard_index is None
    assert [i for i, _ in store.shard_files(job.id)] == [0, 1, 2]


def test_expired_lease_is_reclaimed_with_new_token_and_counts_as_attempt(store):
    store.submit(queue_spec(shards=1))
    # Long enough that the next claim comes before it expires on a loaded machine (0.2 s did not
    # always, with the suite on every core), short enough to wait out.
    lease = 2.0
    first = store.claim("dead", lease)
    assert store.claim("w2", 30) is None  # lease still live
    time.sleep(lease + 0.1)
    second = store.claim("w2", 30)
    assert second.task_id == first.task_id and second.token > first.token
    assert second.attempts == 2
    assert store.metrics()["leases_expired"] == 1


def test_stale_commit_is_refused_and_nothing_counted_twice(store):
    job = store.submit(queue_spec(shards=1))
    stale = store.claim("slow", SHORT)
    time.sleep(SHORT + 0.1)
    fresh = store.claim("fast", 30)
    store.complete_shard(fresh, stored(b"fresh"), photons=100, elapsed_s=1.0)
    with pytest.raises(LeaseLost):
        store.complete_shard(stale, stored(b"stale"), photons=100, elapsed_s=1.0)
    assert store.shard_files(job.id) == [(0, stored(b"fresh"))]
    m = store.metrics()
    assert m["shards_completed"] == 1 and m["photons_simulated"] == 100
    assert store.progress(job.id).photons_done == 100


def test_stale_commit_refused_even_before_the_done_commit(store):
    job = store.submit(queue_spec(shards=1))
    stale = store.claim("slow", SHORT)
    time.sleep(SHORT + 0.1)
    fresh = store.claim("fast", 30)
    with pytest.raises(LeaseLost):
        store.complete_shard(stale, stored(b"stale"), photons=1, elapsed_s=1.0)
    store.complete_shard(fresh, stored(b"fresh"), photons=1, elapsed_s=1.0)
    assert store.shard_files(job.id) == [(0, stored(b"fresh"))]


def test_heartbeat_extends_live_lease_and_reports_lost_lease(store):
    job = store.submit(queue_spec(shards=1))
    lease = store.claim("w1", 0.5)
    for _ in range(3):
        time.sleep(0.25)
        assert store.heartbeat(lease, 0.5, photons=7)
    assert store.claim("w2", 30) is None  # heartbeats kept it
    assert store.progress(job.id).photons_done == 7
    time.sleep(0.6)
    taken = store.claim("w2", 30)
    assert taken is not None
    assert store.heartbeat(lease, 30) is False


def test_release_requeues_without_counting_an_attempt(store):
    store.submit(queue_spec(shards=1))
    lease = store.claim("w1", 30)
    assert store.release(lease)
    again = store.claim("w2", 30)
    assert again.task_id == lease.task_id and again.attempts == 1
    assert store.release(lease) is False  # stale token


def test_failures_retry_then_fail_job_with_error_kept(store):
    job = store.submit(queue_spec(shards=2))
    for attempt in (1, 2, 3):
        lease = store.claim("w", 30)
        assert lease.shard_index == 0 and lease.attempts == attempt
        retried = store.fail_task(lease, f"boom {attempt}")
        assert retried is (attempt < 3)
    failed = store.get_job(job.id)
    assert failed.state == JobState.FAILED
    assert "shard 0" in failed.error and "boom 3" in failed.error and "3 attempts" in failed.error
    assert store.claim("w", 30) is None  # the other shard was cancelled with its job


def test_a_final_failure_fails_the_job_at_the_first_attempt(store):
    job = store.submit(queue_spec(shards=2))
    lease = store.claim("w", 30)
    assert store.fail_task(lease, "NonFiniteResult: medium 0", final=True) is False
    failed = store.get_job(job.id)
    assert failed.state == JobState.FAILED
    assert "not retried" in failed.error and "NonFiniteResult: medium 0" in failed.error, failed.error
    assert store.claim("w", 30) is None


def test_expired_leases_exhaust_attempts_and_fail_job(store):
    job = store.submit(queue_spec(shards=1))
    for _ in range(3):
        assert store.claim("dying", SHORT) is not None
        time.sleep(SHORT + 0.1)
    assert store.claim("w", 30) is None
    store.reap_expired()  # claim runs it every reap_interval_s, not on every empty claim
    failed = store.get_job(job.id)
    assert failed.state == JobState.FAILED and "lease expired" in failed.error


def test_idle_claims_do_not_run_the_reaper_each_time(store, monkeypatch):
    calls = []
    real = store.reap_expired
    monkeypatch.setattr(store, "reap_expired", lambda: calls.append(1) or real())
    for _ in range(20):
        assert store.claim("idle", 30) is None
    assert len(calls) <= 1  # at most once per reap_interval_s (5 s)


def test_pending_tasks_counts_what_can_still_become_claimable(store):
    # has_pending_tasks (the --once poll) agrees with the count at every step.
    assert store.pending_tasks() == 0
    assert store.has_pending_tasks() is False
    job = store.submit(queue_spec(shards=2))
    assert store.pending_tasks() == 3  # two shards and the waiting merge
    assert store.has_pending_tasks() is True
    a, b = store.claim("w", 30), store.claim("w", 30)
    store.complete_shard(a, stored(b"x"), photons=1, elapsed_s=0.0)
    assert store.pending_tasks() == 2  # one running shard, the merge still waits for it
    assert store.has_pending_tasks() is True
    assert store.fail_task(b, "boom")  # retried after a backoff: still pending
    assert store.pending_tasks() == 2
    assert store.has_pending_tasks() is True
    store.cancel(job.id)
    assert store.pending_tasks() == 0
    assert store.has_pending_tasks() is False


def test_cancel_stops_claims_and_refuses_late_commits(store):
    job = store.submit(queue_spec(shards=3))
    lease = store.claim("w", 30)
    cancelled = store.cancel(job.id)
    assert cancelled.state == JobState.CANCELLED
    assert store.claim("w", 30) is None
    assert store.heartbeat(lease, 30) is False
    with pytest.raises(LeaseLost):
        store.complete_shard(lease, stored(b"late"), photons=1, elapsed_s=1)
    assert store.shard_files(job.id) == []
    assert store.cancel(job.id).state == JobState.CANCELLED  # idempotent
    p = store.progress(job.id)
    assert (p.shards_cancelled, p.shards_failed, p.shards_running) == (3, 0, 0) and p.eta_s is None


def test_idempotency_key_returns_same_job(store):
    a = store.submit(queue_spec("x", seed=1), idempotency_key="k1")
    b = store.submit(queue_spec("x", seed=1), idempotency_key="k1")
    c = store.submit(queue_spec("x", seed=1))
    assert a.id == b.id != c.id
    from service.store import IdempotencyConflict

    with pytest.raises(IdempotencyConflict, match="new key"):
        store.submit(queue_spec("x", seed=2), idempotency_key="k1")
    assert len(store.list_jobs()) == 2


def test_progress_counts_and_eta(store):
    job = store.submit(queue_spec(shards=4))
    finish_shards(store, job.id, 2)
    running = store.claim("w", 30)
    store.heartbeat(running, 30, photons=50)
    p = store.progress(job.id)
    assert (p.shards_done, p.shards_running, p.shards_queued, p.shards_failed) == (2, 1, 1, 0)
    assert p.photons_done == 250 and p.rate_photons_per_s > 0 and p.eta_s is not None


def test_retry_decision_formula():
    policy = RetryPolicy(base_delay_s=1.0, factor=2.0, max_delay_s=3.0)
    assert [decide_retry(n, 5, policy).delay_s for n in (1, 2, 3, 4)] == [1.0, 2.0, 3.0, 3.0]
    assert decide_retry(5, 5, policy).retry is False
    with pytest.raises(ValueError, match="attempts must be >= 1"):
        decide_retry(0, 3)


def test_fold_reads_done_results_a_window_at_a_time(store):
    from service.datasets import ResultWindow

    job = store.submit(queue_spec(shards=7))
    leases = {lease.shard_index: lease for lease in (store.claim("w", 30) for _ in range(7))}
    for i in (0, 1, 2, 4, 5, 6):  # task 3 still running
        store.complete_shard(leases[i], stored(f"r{i}".encode()), photons=1, elapsed_s=0.0)
    assert set(store.shard_results_in(job.id, 1, 5)) == {1, 2, 4}
    reads = []
    real = store.shard_results_in
    store.shard_results_in = lambda *a: reads.append(a[1:]) or real(*a)
    window = ResultWindow(store, job.id, size=3)
    got = [window.get(t) for t in range(4)]
    assert got[:3] == [stored(b"r0"), stored(b"r1"), stored(b"r2")] and got[3] is None  # stops at the running task
    assert reads == [(0, 3), (3, 6)]  # two reads for four tasks
    store.complete_shard(leases[3], stored(b"r3"), photons=1, elapsed_s=0.0)
    again = ResultWindow(store, job.id, size=3)
    assert [again.get(t) for t in (3, 4, 6)] == [stored(b"r3"), stored(b"r4"), stored(b"r6")]  # 5 jumped over
