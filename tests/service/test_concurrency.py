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
from tests.service.conftest import queue_spec
from tests.support.files import stored

REPO = Path(__file__).resolve().parents[2]


def test_four_processes_race_over_fifty_tasks(store, db_url):
    # 5 jobs x 9 shards + 5 merges = 50 tasks
    jobs = [store.submit(queue_spec(f"race{i}", shards=9)) for i in range(5)]
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

    store.submit(queue_spec(shards=40))
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


class _SlowPublisher:
    """A Publisher whose move takes a while inside the transaction, as a real rename of a
    version directory on a shared filesystem can: it widens the window in which concurrent
    publishers of one name race for the next version number."""

    def __init__(self, name: str) -> None:
        self.name = name

    def uri_for(self, version: int) -> str:
        return f"{self.name}/v{version}"

    def publish(self, version: int) -> None:
        time.sleep(0.02)


def test_concurrent_publishes_of_one_name_all_get_consecutive_versions(store, db_url):
    from service.store import JobStore

    n = 16  # more than the 10 version-number retries the allocation once had
    for i in range(n):
        store.submit(queue_spec("same-name", shards=1, seed=i))
    leases = []
    for _ in range(n):  # each shard done, then its merge (claimed first) leased
        shard = store.claim("prep", 60)
        store.complete_shard(shard, stored(f"tally {shard.job_id}".encode()), photons=1, elapsed_s=0.0)
        leases.append(store.claim("prep", 60))
    assert {lease.kind for lease in leases} == {TaskKind.MERGE}
    barrier = threading.Barrier(n)
    versions: dict[str, int] = {}
    errors: list[BaseException] = []

    def publisher(lease):
        own = JobStore(db_url, migrate=False)
        try:
            barrier.wait(30)
            versions[lease.job_id] = own.complete_merge(lease, "same-name", {"job": lease.job_id},
                                                        _SlowPublisher("same-name"))
        except BaseException as exc:  # reported below, with the versions that were allocated
            errors.append(exc)
        finally:
            own.dispose()

    threads = [threading.Thread(target=publisher, args=(lease,)) for lease in leases]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors, (errors, versions)
    assert sorted(versions.values()) == list(range(1, n + 1))
    assert [v.version for v in store.list_versions("same-name")] == list(range(1, n + 1))
    for job_id, version in versions.items():
        job = store.get_job(job_id)
        assert job.state == JobState.SUCCEEDED and job.dataset_version == version
        assert store.get_version("same-name", version).job_id == job_id
