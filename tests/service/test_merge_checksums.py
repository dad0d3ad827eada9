"""The merge reads every shard file against the sha256 its commit recorded: one byte
changed in a committed shard file is found, the shard is never folded, the job fails with the
file and both digests in its error, and no version is published. The design does not redo the
shard: the merge fails on each attempt (the corruption is persistent), then the job fails."""

from __future__ import annotations

import hashlib

import pyarrow.fs as pafs
import pytest

from bench.merge import bench_spec, stage_job
from service.datasets import DatasetStorage, JobFiles
from service.store import JobState, JobStore, RetryPolicy, StoredFile, VersionNotFound
from service.worker import Worker

SHARDS = 4
BAD = 2  # the corrupted shard: folding stops before it


def _flip_one_byte(storage: DatasetStorage, path: str) -> bytes:
    """Flip one byte in the middle of the file (same size); the new content."""
    with storage.fs.open_input_stream(path) as f:
        data = bytearray(f.read())
    data[len(data) // 2] ^= 0xFF
    with storage.fs.open_output_stream(path) as f:
        f.write(bytes(data))
    return bytes(data)


def test_a_corrupted_shard_file_fails_the_merge_and_publishes_nothing(db_url, tmp_path, monkeypatch):
    monkeypatch.setenv("BSSRDF_COMPILE", "0")
    spec = bench_spec(SHARDS, radial=4, cos=2, phi=2, name="corrupt-shard")
    storage = DatasetStorage(str(tmp_path / "data"))
    # Two attempts, no backoff: the retried merge meets the same corrupt file.
    store = JobStore(db_url, max_attempts=2, retry_policy=RetryPolicy(base_delay_s=0.0), fold_batch=SHARDS + 1)
    job_id = store.submit(spec).id
    stage_job(db_url, storage.uri, spec, job_id=job_id)  # every shard committed: the merge is claimable
    ref = store.shard_result(job_id, BAD)
    assert isinstance(ref, StoredFile)
    corrupted = _flip_one_byte(storage, JobFiles(storage, job_id).path_of(ref))
    actual = hashlib.sha256(corrupted).hexdigest()
    assert actual != ref.sha256

    Worker(store, storage, once=True, poll_seconds=0.05).loop()

    job = store.get_job(job_id)
    assert job.state == JobState.FAILED, (job.state, job.error)
    assert "ChecksumMismatch" in job.error and ref.uri in job.error, job.error
    assert f"has sha256 {actual}, recorded as {ref.sha256}" in job.error, job.error
    assert store.fold_position(job_id).folded <= BAD  # never folded past the corrupt shard
    with pytest.raises(VersionNotFound):
        store.get_version(spec.name)
    version_dir = storage.version_path(spec.name, 1)
    assert storage.fs.get_file_info(version_dir).type == pafs.FileType.NotFound
    store.dispose()
