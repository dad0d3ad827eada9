"""A worker keeps running through database errors around a shard's commit (a PostgreSQL restart
while a walk ends): the commit is retried, a commit whose answer was lost is recognised, and a
failure that cannot be recorded is left to the lease instead of ending the worker process."""

from __future__ import annotations

import pytest
from sqlalchemy.exc import OperationalError

from service.datasets import DatasetStorage, JobFiles
from service.store import JobStore, TaskState
from service.worker import Worker
from tests.service.conftest import queue_spec


def down() -> OperationalError:
    return OperationalError("UPDATE tasks ...", {}, ConnectionRefusedError("connection refused"))


class FlakyStore(JobStore):
    """A job store whose named operations fail with a database error while ``outage[name] > 0``;
    ``after_commit`` makes the failure come after the real commit (its answer lost)."""

    def __init__(self, *a, **kw):
        super().__init__(*a, **kw)
        self.outage: dict[str, int] = {}
        self.after_commit = False
        self.calls: list[str] = []

    def _flaky(self, name, real, *a, **kw):
        self.calls.append(name)
        if self.outage.get(name, 0) > 0:
            self.outage[name] -= 1
            if self.after_commit:
                real(*a, **kw)
            raise down()
        return real(*a, **kw)

    def complete_shard(self, *a, **kw):
        return self._flaky("complete_shard", super().complete_shard, *a, **kw)

    def fail_task(self, *a, **kw):
        return self._flaky("fail_task", super().fail_task, *a, **kw)

    def shard_result(self, *a, **kw):
        return self._flaky("shard_result", super().shard_result, *a, **kw)


class InstantWorker(Worker):
    def _walk(self, lease, progress):
        progress(10)
        return b"tally bytes", 10, 0.0


@pytest.fixture
def setup(tmp_path):
    store = FlakyStore(f"sqlite:///{tmp_path / 'jobs.sqlite'}")
    storage = DatasetStorage(str(tmp_path / "data"))
    job = store.submit(queue_spec(shards=1))
    worker = InstantWorker(store, storage, heartbeat_seconds=30)
    worker.stopping.wait = lambda seconds: False  # no real back-off sleeps in the test
    yield store, storage, job, worker
    store.dispose()


def test_the_commit_is_retried_through_an_outage(setup):
    store, storage, job, worker = setup
    store.outage["complete_shard"] = 3
    worker.process(store.claim("w", 60))
    assert store.calls.count("complete_shard") == 4
    files = store.shard_files(job.id)
    assert len(files) == 1 and JobFiles(storage, job.id).read(files[0][1], "shard") == b"tally bytes"
    assert store.progress(job.id).shards_done == 1


def test_a_commit_whose_answer_was_lost_is_recognised_and_its_file_kept(setup):
    store, storage, job, worker = setup
    store.outage["complete_shard"], store.after_commit = 1, True  # committed, then the link dropped
    worker.process(store.claim("w", 60))
    assert store.calls == ["complete_shard", "shard_result"]  # read back, not committed twice
    (_, ref), = store.shard_files(job.id)
    assert JobFiles(storage, job.id).read(ref, "shard") == b"tally bytes"  # the recorded file is still there


def test_giving_up_leaves_the_task_to_its_lease_and_the_worker_running(setup):
    store, storage, job, worker = setup
    worker.commit_retry_seconds = 0.0
    store.outage["complete_shard"] = store.outage["fail_task"] = 1
    lease = store.claim("w", 60)
    worker.process(lease)  # returns: no exception ends the worker's loop
    assert store.calls == ["complete_shard"]  # gave up at once, recorded nothing
    assert store.shard_files(job.id) == []
    assert store.progress(job.id).shards_running == 1  # still leased: it expires and is claimed again


def test_a_failure_that_cannot_be_recorded_does_not_end_the_worker(setup):
    store, storage, job, worker = setup

    class Broken(InstantWorker):
        def _walk(self, lease, progress):
            raise RuntimeError("walk failed")

    broken = Broken(store, storage, heartbeat_seconds=30)
    store.outage["fail_task"] = 1
    broken.process(store.claim("w", 60))  # fail_task raised a database error: logged, not raised
    assert store.calls == ["fail_task"]
    assert store.progress(job.id).shards_running == 1
