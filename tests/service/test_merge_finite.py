"""The merge publishes no non-finite number: a shard whose tally holds an infinite sum (what an
absurd medium used to give, now refused at submission: tests/schema/test_ranges.py) reaches the
merge, the job fails with an error naming the medium and the column, and nothing is published.
The value is forced through behind validation, as a defence in depth. A non-finite table is a
deterministic failure (the same shards merge to the same numbers): the merge is not retried."""

from __future__ import annotations

import numpy as np
import pyarrow.fs as pafs
import pytest
import sqlalchemy as sa

from bench.merge import bench_spec
from service.datasets import DatasetStorage, JobFiles
from service.store import JobState, JobStore, RetryPolicy, TaskKind, VersionNotFound
from service.store.tables import tasks
from service.worker import Worker
from workers.run.shard import run_shard

SHARDS = 2


@pytest.mark.parametrize("value", [np.inf, np.nan])
def test_a_non_finite_tally_fails_the_job_and_publishes_nothing(db_url, tmp_path, monkeypatch, value):
    monkeypatch.setenv("BSSRDF_COMPILE", "0")
    spec = bench_spec(SHARDS, radial=4, cos=2, phi=2, name="non-finite")
    storage = DatasetStorage(str(tmp_path / "data"))
    store = JobStore(db_url, max_attempts=3, retry_policy=RetryPolicy(base_delay_s=0.0), fold_batch=SHARDS + 1)
    job_id = store.submit(spec).id
    files = JobFiles(storage, job_id)
    for _ in range(SHARDS):
        lease = store.claim("stager", 600)
        tally = run_shard(spec, lease.shard_index)
        tally.stats["exits/radial_G"][0][0, 2, 1] = value  # S1 of one annulus of the total
        ref = files.write(f"shards/{lease.shard_index:08d}-{lease.token}.tally", tally.to_bytes())
        store.complete_shard(lease, ref, photons=tally.photons, elapsed_s=0.0)

    Worker(store, storage, once=True, poll_seconds=0.05).loop()

    job = store.get_job(job_id)
    assert job.state == JobState.FAILED, (job.state, job.error)
    assert "NonFiniteResult" in job.error and "medium 0" in job.error and "Rd_r" in job.error, job.error
    assert "not retried" in job.error, job.error
    with store._read() as conn:  # one attempt of the merge, of the three allowed
        merges = conn.execute(sa.select(tasks.c.attempts, tasks.c.state).where(
            tasks.c.job_id == job_id, tasks.c.kind == TaskKind.MERGE)).all()
    assert [m.attempts for m in merges] == [1], merges
    with pytest.raises(VersionNotFound):
        store.get_version(spec.name)
    assert store.list_versions(spec.name, deleted=True) == []
    assert storage.fs.get_file_info(storage.version_path(spec.name, 1)).type == pafs.FileType.NotFound
    store.dispose()
