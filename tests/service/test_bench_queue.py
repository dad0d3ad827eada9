"""The queue benchmark (bench/queue.py) runs against the current job store: it claims and
commits every shard of its job (it had broken silently when shard results became files)."""

from __future__ import annotations

from bench.queue import bench_store
from service.store import JobStore


def test_bench_queue_commits_every_shard(tmp_path):
    url = f"sqlite:///{tmp_path / 'bench.sqlite'}"
    figures = bench_store(url, 5, b"x" * 1024)
    assert set(figures) == {"claim_ms", "commit_ms", "claim_commit_ms", "claim_commit_p95_ms", "heartbeat_ms"}
    assert all(v > 0 for v in figures.values()), figures
    store = JobStore(url)
    try:
        (job,) = store.list_jobs()
        assert store.progress(job.id).shards_done == 5
    finally:
        store.dispose()
