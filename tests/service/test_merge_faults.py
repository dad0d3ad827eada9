"""The merge under load and faults (issue 10): a 256-shard job merges in the memory of a 16-shard
one (the fold holds one shard and one accumulator), and a worker SIGKILLed in the middle of a
fold round leaves the last committed fold, from which another worker publishes the same bytes as
an uninterrupted merge."""

from __future__ import annotations

import os
import signal

import pytest

from service.bench_merge import bench_spec, measure, stage_job
from service.datasets import DatasetStorage, open_version, run_merge_task
from service.runner import start_workers, stop_workers
from service.store import JobState, JobStore, TaskKind
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.slow]

FILES = ("radial.parquet", "bins.parquet", "summary.parquet", "summary.json")
ENV = {"BSSRDF_COMPILE": "0", "OMP_NUM_THREADS": "1"}


def test_merge_memory_does_not_grow_with_the_shard_count(tmp_path, monkeypatch):
    for k, v in ENV.items():
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


def test_sigkill_during_a_fold_round(tmp_path, monkeypatch):
    for k, v in ENV.items():
        monkeypatch.setenv(k, v)
    spec = bench_spec(64, radial=128)
    # Reference: the same shards merged without interruption.
    ref_db, ref_storage = f"sqlite:///{tmp_path / 'ref.sqlite'}", str(tmp_path / "ref")
    ref_job = stage_job(ref_db, ref_storage, spec)
    ref_store = JobStore(ref_db)
    assert _one_round(ref_store, DatasetStorage(ref_storage)) is not None
    expected = _published(ref_store, DatasetStorage(ref_storage), ref_job)

    db, storage_uri = f"sqlite:///{tmp_path / 'jobs.sqlite'}", str(tmp_path / "data")
    job_id = stage_job(db, storage_uri, spec, shards=range(31))
    stage_job(db, storage_uri, spec, shards=range(1), job_id=job_id, fold_batch=8)  # this commit queues the merge
    store, storage = JobStore(db, fold_batch=8), DatasetStorage(storage_uri)
    assert _one_round(store, storage) is None  # folds tasks 0..31 and commits that fold
    assert store.fold_position(job_id).folded == 32
    stage_job(db, storage_uri, spec, shards=range(32), job_id=job_id)
    logs = tmp_path / "logs"
    victim = start_workers(1, db, storage_uri, logs, lease_seconds=3.0, extra_env=ENV)
    log = logs / "worker-0.log"
    wait_for(lambda: log.exists() and '"kind": "merge"' in log.read_text(), 120, "the worker to claim the merge",
             poll=0.02)
    os.kill(victim[0].pid, signal.SIGKILL)  # in the middle of folding tasks 32..63
    victim[0].wait()
    assert store.get_job(job_id).state == JobState.MERGING and store.fold_position(job_id).folded == 32
    rescuer = start_workers(1, db, storage_uri, tmp_path / "logs2", lease_seconds=3.0, extra_env=ENV)
    try:
        wait_for(lambda: store.get_job(job_id).state in (JobState.SUCCEEDED, JobState.FAILED), 180, "the merge")
    finally:
        stop_workers(rescuer)
    assert _published(store, storage, job_id) == expected
    assert store.metrics()["leases_expired"] >= 1
    assert not os.path.exists(storage.job_path(job_id))  # the killed round's files went with the rest
