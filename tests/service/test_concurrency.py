"""Concurrent claims from several processes and threads never double-claim a task."""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections import Counter
from pathlib import Path

from service.store import JobState, TaskKind
from tests.service.conftest import FakeSpec

REPO = Path(__file__).resolve().parents[2]


def test_four_processes_race_over_fifty_tasks(store, db_url):
    # 5 jobs x 9 shards + 5 merges = 50 tasks
    jobs = [store.submit(FakeSpec(f"race{i}", shards=9)) for i in range(5)]
    start_at = time.time() + 2.0
    procs = [
        subprocess.Popen(
            [sys.executable, "-m", "tests.support.claimer", db_url, str(start_at)],
            cwd=REPO, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
        )
        for _ in range(4)
    ]
    claims = []
    for p in procs:
        out, err = p.communicate(timeout=120)
        assert p.returncode == 0, err
        claims += json.loads(out)
    counts = Counter(task_id for task_id, _, _ in claims)
    assert len(counts) == 50 and set(counts.values()) == {1}, counts
    assert sum(1 for *_, kind in claims if kind == TaskKind.MERGE) == 5
    m = store.metrics()
    assert m["tasks_claimed"] == 50 and m["shards_completed"] == 45 and m["leases_expired"] == 0
    for job in jobs:
        assert store.get_job(job.id).state == JobState.MERGING
        assert [i for i, _ in store.shard_files(job.id)] == list(range(9))


def test_threads_race_without_double_claims(store, db_url):
    from service.store import JobStore

    store.submit(FakeSpec(shards=40))
    claimed: list[int] = []
    lock = threading.Lock()

    def worker():
        own = JobStore(db_url, migrate=False)
        while (lease := own.claim(threading.current_thread().name, 60)) is not None:
            with lock:
                claimed.append(lease.task_id)
        own.dispose()

    threads = [threading.Thread(target=worker, name=f"t{i}") for i in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert len(claimed) == 40 and len(set(claimed)) == 40
