"""Dataset versions: numbered 1, 2, ..., published atomically with the job, verified on read."""

from __future__ import annotations

import hashlib
import threading
import time

import pyarrow.fs as pafs
import pytest

from service.datasets import DatasetStorage, open_version
from service.datasets.metadata import metadata_bytes
from service.store import ChecksumMismatch, JobState, LeaseLost, VersionNotFound
from tests.service.conftest import queue_spec
from tests.support.files import stored


def merge_lease(store, name="ds", lease_seconds=30):
    store.submit(queue_spec(name, shards=1))
    shard = store.claim("w", 30)
    store.complete_shard(shard, stored(b"tally"), photons=5, elapsed_s=0.1)
    return store.claim("w", lease_seconds)


def publish(store, storage, lease, name="ds", content=b"table bytes"):
    """What run_merge_task does, with stand-in files instead of merged tables."""
    staged = storage.stage(name)
    staged.write_bytes("radial.parquet", content)
    files = staged.checksums(["radial.parquet"])
    blob = metadata_bytes({"name": name, "files": files})
    staged.write_bytes("metadata.json", blob)
    meta = {"name": name, "files": files, "metadata_sha256": hashlib.sha256(blob).hexdigest()}
    try:
        return store.complete_merge(lease, name, meta, staged), staged
    except BaseException:
        staged.discard()
        raise


@pytest.fixture
def storage(tmp_path):
    return DatasetStorage(str(tmp_path / "data"))


def test_versions_count_up_and_end_the_job(store, storage):
    v1, _ = publish(store, storage, merge_lease(store), content=b"one")
    lease = merge_lease(store)
    v2, _ = publish(store, storage, lease, content=b"two")
    assert (v1, v2) == (1, 2)
    job = store.get_job(lease.job_id)
    assert job.state == JobState.SUCCEEDED and (job.dataset_name, job.dataset_version) == ("ds", 2)
    assert open_version(store, storage, "ds", 1).read_bytes("radial.parquet") == b"one"
    latest = open_version(store, storage, "ds")
    assert latest.record.version == 2 and latest.read_bytes("radial.parquet") == b"two"
    assert [d.latest_version for d in store.list_datasets()] == [2]
    assert [v.version for v in store.list_versions("ds")] == [1, 2]
    # no staging directory is left behind
    names = [i.base_name for i in storage.fs.get_file_info(pafs.FileSelector(f"{storage.root}/ds"))]
    assert sorted(names) == ["v1", "v2"]


def test_corrupt_or_missing_file_is_detected_on_read(store, storage):
    publish(store, storage, merge_lease(store), content=b"good")
    path = f"{storage.version_path('ds', 1)}/radial.parquet"
    with storage.fs.open_output_stream(path) as f:
        f.write(b"evil")
    with pytest.raises(ChecksumMismatch, match="radial.parquet"):
        open_version(store, storage, "ds", 1)
    storage.fs.delete_file(path)
    with pytest.raises(ChecksumMismatch, match="unreadable"):
        open_version(store, storage, "ds", 1)
    with pytest.raises(VersionNotFound):
        open_version(store, storage, "ds", 7)


def test_publish_with_lost_lease_leaves_nothing_visible(store, storage):
    lease = merge_lease(store, lease_seconds=0.2)
    time.sleep(0.3)
    thief = store.claim("other", 30)
    assert thief.task_id == lease.task_id
    with pytest.raises(LeaseLost):
        publish(store, storage, lease)
    assert store.list_versions("ds") == []
    assert storage.fs.get_file_info(f"{storage.root}/ds/v1").type == pafs.FileType.NotFound
    assert publish(store, storage, thief)[0] == 1


def test_orphan_directory_of_a_failed_commit_is_replaced(store, storage):
    orphan = storage.version_path("ds", 1)
    storage.fs.create_dir(orphan)
    with storage.fs.open_output_stream(f"{orphan}/radial.parquet") as f:
        f.write(b"half")
    publish(store, storage, merge_lease(store), content=b"whole")
    assert open_version(store, storage, "ds", 1).read_bytes("radial.parquet") == b"whole"


def test_concurrent_publishers_get_distinct_versions(store, storage, db_url):
    from service.store import JobStore

    leases = [merge_lease(store) for _ in range(4)]
    versions, errors = [], []

    def go(lease):
        own = JobStore(db_url, migrate=False)
        try:
            versions.append(publish(own, DatasetStorage(storage.uri), lease, content=lease.job_id.encode())[0])
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)
        finally:
            own.dispose()

    threads = [threading.Thread(target=go, args=(lease,)) for lease in leases]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    assert not errors and sorted(versions) == [1, 2, 3, 4]
    for v in store.list_versions("ds"):
        assert open_version(store, storage, "ds", v.version).read_bytes("radial.parquet") == v.job_id.encode()


def test_bad_dataset_name_is_refused(storage):
    from service.store import DatasetError

    with pytest.raises(DatasetError, match=r"\[A-Za-z0-9._-\]"):
        storage.stage("../escape")
