"""The merge under load and faults: a 256-shard job merges in the memory of a 16-shard
one (the fold holds one shard and one accumulator), and a worker SIGKILLed in the middle of a
fold round, or inside the publish (tables moved into place, catalog row not committed), leaves
the last committed state, from which another worker publishes the same bytes as an uninterrupted
merge. The kills are placed, not raced: ``BSSRDF_TEST_PAUSE_AT`` (service.faults) makes the
merging worker stop itself at the point, and the test kills it there."""

from __future__ import annotations

import os
import signal
import threading

import pyarrow.fs as pafs
import pytest

from bench.merge import bench_spec, measure, stage_job
from service.datasets import DatasetStorage, open_version, run_merge_task
from service.faults import PAUSE_ENV
from service.runner import start_workers, stop_workers
from service.store import JobState, JobStore, TaskKind
from tests.support.engine import ENGINE_ENV
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.slow]

FILES = ("radial.parquet", "bins.parquet", "summary.parquet", "summary.json")
SHARDS = 16


def test_merge_memory_does_not_grow_with_the_shard_count(tmp_path, monkeypatch):
    for k, v in ENGINE_ENV.items():
        monkeypatch.setenv(k, v)
    small = measure(16, tmp_path / "16", radial=64)
    large = measure(256, tmp_path / "256", radial=64)
    # Holding every shard would add 240 x 2.3 MiB = 550 MiB; one shard is 2.3 MiB.
    assert large["growth_mib"] - small["growth_mib"] < 3 * large["payload_mib"], (small, large)


def _published(store, storage, job_id) -> dict[str, bytes]:
    job = store.get_job(job_id)
    assert job.state == JobState.SUCCEEDED, job.error
    version = open_version(store, storage, job.dataset_name, job.dataset_version)
    return {name: version.read_bytes(name) for name in FILES}


def _one_round(store, storage) -> int | None:
    lease = store.claim("in-process", 600)
    assert lease is not None and lease.kind == TaskKind.MERGE
    return run_merge_task(store, storage, lease)


@pytest.fixture(scope="module")
def spec():
    return bench_spec(SHARDS, radial=32, cos=4, phi=4)


@pytest.fixture(scope="module")
def expected(spec, tmp_path_factory):
    """The published files of the same shards merged without interruption, in this process."""
    with pytest.MonkeyPatch.context() as mp:
        for k, v in ENGINE_ENV.items():
            mp.setenv(k, v)
        root = tmp_path_factory.mktemp("reference")
        db, storage_uri = f"sqlite:///{root / 'ref.sqlite'}", str(root / "data")
        job_id = stage_job(db, storage_uri, spec)
        store = JobStore(db)
        assert _one_round(store, DatasetStorage(storage_uri)) is not None
        files = _published(store, DatasetStorage(storage_uri), job_id)
        store.dispose()
    return files


def _paused_worker(db: str, storage_uri: str, logs, point: str):
    """A worker process that stops itself (SIGSTOP) at ``point`` of its merge round; returns it
    stopped there (AssertionError if it exits or does not get there)."""
    proc = start_workers(1, db, storage_uri, logs, lease_seconds=3.0, extra_env={**ENGINE_ENV, PAUSE_ENV: point})[0]

    def stopped() -> bool:
        pid, status = os.waitpid(proc.pid, os.WUNTRACED | os.WNOHANG)
        if pid == 0:
            return False
        assert os.WIFSTOPPED(status), f"the worker exited (status {status}) before {point}; see {logs}"
        return True

    try:
        wait_for(stopped, 120, f"the worker to pause at {point}", poll=0.02)
    except BaseException:
        proc.kill()
        raise
    return proc


def _kill(proc) -> None:
    os.kill(proc.pid, signal.SIGKILL)  # a stopped process dies of SIGKILL without running again
    proc.wait()
    assert proc.returncode == -signal.SIGKILL


def _rescue(store, storage, db: str, storage_uri: str, logs, job_id: str) -> None:
    """Another worker finishes the job once the killed one's lease expires."""
    rescuer = start_workers(1, db, storage_uri, logs, lease_seconds=3.0, extra_env=ENGINE_ENV)
    try:
        wait_for(lambda: store.get_job(job_id).state in (JobState.SUCCEEDED, JobState.FAILED), 120, "the merge")
    finally:
        stop_workers(rescuer)
    assert store.metrics()["leases_expired"] >= 1


def test_sigkill_during_a_fold_round(spec, expected, tmp_path):
    db, storage_uri = f"sqlite:///{tmp_path / 'jobs.sqlite'}", str(tmp_path / "data")
    job_id = stage_job(db, storage_uri, spec, shards=range(7))
    stage_job(db, storage_uri, spec, shards=range(1), job_id=job_id, fold_batch=4)  # this commit queues the merge
    store, storage = JobStore(db, fold_batch=4), DatasetStorage(storage_uri)
    assert _one_round(store, storage) is None  # folds tasks 0..7 and commits that fold
    committed = store.fold_position(job_id)
    assert committed.folded == 8
    stage_job(db, storage_uri, spec, shards=range(SHARDS - 8), job_id=job_id)

    victim = _paused_worker(db, storage_uri, tmp_path / "logs", "fold:3")  # tasks 8, 9, 10 folded in memory
    _kill(victim)
    assert store.get_job(job_id).state == JobState.MERGING
    now = store.fold_position(job_id)
    assert (now.folded, now.fold) == (committed.folded, committed.fold)  # nothing of the killed round committed

    _rescue(store, storage, db, storage_uri, tmp_path / "logs2", job_id)
    assert _published(store, storage, job_id) == expected
    assert not os.path.exists(storage.job_path(job_id))  # the killed round's files went with the rest
    store.dispose()


@pytest.mark.parametrize("point", ["staged", "publish"])
def test_sigkill_while_publishing(spec, expected, tmp_path, point):
    """``staged``: tables written, complete_merge not called; ``publish``: inside complete_merge,
    the files moved to NAME/v1, the catalog row not committed."""
    db, storage_uri = f"sqlite:///{tmp_path / 'jobs.sqlite'}", str(tmp_path / "data")
    job_id = stage_job(db, storage_uri, spec)
    store, storage = JobStore(db), DatasetStorage(storage_uri)

    victim = _paused_worker(db, storage_uri, tmp_path / "logs", point)
    orphan = storage.fs.get_file_info(storage.version_path(spec.name, 1)).type
    assert orphan == (pafs.FileType.Directory if point == "publish" else pafs.FileType.NotFound)
    _kill(victim)
    assert store.get_job(job_id).state == JobState.MERGING and store.list_versions(spec.name) == []

    _rescue(store, storage, db, storage_uri, tmp_path / "logs2", job_id)
    assert [v.version for v in store.list_versions(spec.name)] == [1]  # the orphan's number, replaced
    assert _published(store, storage, job_id) == expected  # open_version checked every sha256, metadata.json's too
    assert not os.path.exists(storage.job_path(job_id))
    leftovers = storage.fs.get_file_info(pafs.FileSelector(f"{storage.root}/{spec.name}"))
    assert [f.base_name for f in leftovers] == ["v1"]  # no staging directory left behind
    store.dispose()


def test_a_worker_paused_at_publish_blocks_no_submission(spec, expected, tmp_path, db_url):
    """A worker stopped inside the publish (files moved to NAME/v1, catalog row not committed)
    holds no SQLite write lock: a ``POST /v1/jobs`` meanwhile is answered at once (it used to
    wait out the 30 s busy timeout and get 503 "database is locked"); the job publishes after."""
    from fastapi.testclient import TestClient

    from service.api import create_app
    from service.settings import Settings
    from tests.api.conftest import TINY_SPEC

    db, storage_uri = db_url, str(tmp_path / "data")
    job_id = stage_job(db, storage_uri, spec)
    store, storage = JobStore(db), DatasetStorage(storage_uri)
    victim = _paused_worker(db, storage_uri, tmp_path / "logs", "publish")
    try:
        app = create_app(Settings(database_url=db, storage_uri=storage_uri, api_tokens=["t" * 20]))
        answers = []

        def post() -> None:
            with TestClient(app) as client:
                answers.append(client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers={"Authorization": "Bearer " + "t" * 20}))

        poster = threading.Thread(target=post, daemon=True)
        poster.start()
        poster.join(10)  # the busy timeout is 30 s: a blocked POST is still waiting here
        assert not poster.is_alive(), "POST /v1/jobs waited for the paused publish"
        assert answers[0].status_code == 201, answers[0].text
    finally:
        _kill(victim)
    _rescue(store, storage, db, storage_uri, tmp_path / "logs2", job_id)
    assert _published(store, storage, job_id) == expected
    store.dispose()


def test_a_cancel_during_a_paused_publish_is_answered_at_once_and_nothing_is_published(spec, tmp_path, db_url):
    """The stalled publish holds no lock of its job either: cancelling the job meanwhile is
    answered at once (on PostgreSQL it used to wait for the publishing transaction, which held the
    job row, until the worker died), the cancel wins, and the worker's late commit publishes
    nothing (its lease is fenced)."""
    db, storage_uri = db_url, str(tmp_path / "data")
    job_id = stage_job(db, storage_uri, spec)
    store = JobStore(db)
    victim = _paused_worker(db, storage_uri, tmp_path / "logs", "publish")
    try:
        answers = []
        canceller = threading.Thread(target=lambda: answers.append(store.cancel(job_id)), daemon=True)
        canceller.start()
        canceller.join(10)
        assert not canceller.is_alive(), "the cancel waited for the paused publish"
        assert answers[0].state == JobState.CANCELLED, answers[0]
        os.kill(victim.pid, signal.SIGCONT)  # let it try its commit: refused, the lease is fenced
        log = tmp_path / "logs" / "worker-0.log"
        wait_for(lambda: "result refused: lease lost" in log.read_text(), 60, "the late commit to be refused")
    finally:
        stop_workers([victim])
    assert store.get_job(job_id).state == JobState.CANCELLED
    assert store.list_versions(spec.name, deleted=True) == []
    store.dispose()
