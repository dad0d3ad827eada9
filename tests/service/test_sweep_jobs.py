"""Sweeps through the job service: real worker processes give the bytes of
``simulate_sweep`` on SQLite with one worker and on PostgreSQL with three, with shard results as
files in dataset storage (local, and an S3-compatible server started here: moto), checked by
sha256, folded in task order as they arrive, a medium stopped at its target error (its other
tasks skipped), and the job's files removed once the version is published (or kept on request).
"""

from __future__ import annotations

import pyarrow.fs as pafs
import pytest

from schema import parse_spec
from service.datasets import DatasetStorage, open_version
from service.runner import start_workers, stop_workers
from service.store import JobState, JobStore
from tests.support.engine import ENGINE_ENV
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("engine_env")]

FILES = ("radial.parquet", "bins.parquet", "summary.parquet", "summary.json")


def sweep_spec():
    # Four media on two etas; with the target, the bright media stop before their fourth shard
    # (their other tasks are skipped or, if they already ran, never counted).
    return parse_spec({
        "name": "sweep-e2e", "sweep": {"albedo": [0.3, 0.9], "g": [0.5], "eta": [1.0, 1.4]},
        "incidence_deg": [0, 35], "photons": 160, "shards": 4, "batches_per_shard": 2, "estimator": "exits",
        "absorption": "analog", "seed": 3, "target": {"rel_stderr": 0.3},
        "bins": {"radial": {"count": 4, "max_mm": 3.0}, "theta_s": {"count": 2}, "cos_theta_o": {"count": 2},
                 "phi_o": {"count": 2}},
    })


@pytest.fixture(scope="module")
def reference(tmp_path_factory):
    from workers.run.simulate import simulate_sweep

    out = tmp_path_factory.mktemp("reference")
    simulate_sweep(sweep_spec(), str(out), threads=1)
    return {name: (out / name).read_bytes() for name in FILES}


def shared_spec():
    # Weights absorption: each eta's two albedos share one walk (one group per eta, leader 0.9).
    return parse_spec({
        "name": "sweep-shared", "sweep": {"albedo": [0.3, 0.9], "g": [0.5], "eta": [1.0, 1.4], "walks": "shared",
                                          "group_edges": [0.0]},
        "incidence_deg": [0, 35], "photons": 400, "shards": 3, "batches_per_shard": 2, "estimator": "hybrid",
        "seed": 3, "target": {"rel_stderr": 0.2},
        "bins": {"radial": {"count": 4, "max_mm": 3.0}, "theta_s": {"count": 2}, "cos_theta_o": {"count": 2},
                 "phi_o": {"count": 2}},
    })


def run_sweep(db_url: str, storage_uri: str, logs, workers: int, env: dict | None = None, spec=None):
    spec = spec or sweep_spec()
    store = JobStore(db_url)
    storage = DatasetStorage(storage_uri)
    job = store.submit(spec)
    procs = start_workers(workers, db_url, storage_uri, logs, extra_env={**ENGINE_ENV, **(env or {})})
    try:
        wait_for(lambda: store.get_job(job.id).state in (JobState.SUCCEEDED, JobState.FAILED), 240, "the sweep to end")
    finally:
        stop_workers(procs)
    done = store.get_job(job.id)
    assert done.state == JobState.SUCCEEDED, done.error
    version = open_version(store, storage, done.dataset_name, done.dataset_version)
    return store, storage, done, {name: version.read_bytes(name) for name in FILES}


def _job_files(storage: DatasetStorage, job_id: str) -> list[str]:
    info = storage.fs.get_file_info(storage.job_path(job_id))
    if info.type == pafs.FileType.NotFound:
        return []
    return [i.path for i in storage.fs.get_file_info(pafs.FileSelector(storage.job_path(job_id), recursive=True))
            if i.type == pafs.FileType.File]


def _check_progress(store: JobStore, job, folded: list[int] | None = None) -> None:
    p = store.progress(job.id)
    assert (p.shards_total, p.media_total, p.media_merged, p.tasks_folded) == (16, 4, 4, 16)
    assert p.shards_done + p.shards_skipped == 16
    media = store.medium_progress(job.id, 4)
    assert [m.medium for m in media] == [0, 1, 2, 3] and all(m.merged for m in media)
    if folded is not None:  # one worker folding after every shard: no task past a stop ever ran
        assert [m.shards_skipped for m in media] == [4 - k for k in folded] and p.shards_skipped == 16 - sum(folded)


def test_one_worker_on_sqlite_keeping_its_files(tmp_path, reference):
    """Fold after every shard (BSSRDF_FOLD_BATCH=1), shard files kept: every recorded file is
    there with its sha256."""
    url = f"sqlite:///{tmp_path / 'jobs.sqlite'}"
    store, storage, job, got = run_sweep(url, str(tmp_path / "data"), tmp_path / "logs", 1,
                                         {"BSSRDF_FOLD_BATCH": "1", "BSSRDF_KEEP_SHARD_FILES": "true"})
    assert got == reference
    folded = __import__("json").loads(reference["summary.json"])["run"]["shards_folded"]
    assert sum(folded) < 16  # some medium stopped early
    _check_progress(store, job, folded)
    from service.datasets import JobFiles

    files = JobFiles(storage, job.id)
    recorded = store.shard_files(job.id)
    assert recorded and all(files.read(ref, f"task {t}") for t, ref in recorded)  # sha256 checked
    assert any("/parts/" in p for p in _job_files(storage, job.id))


@pytest.mark.postgres
def test_three_workers_on_postgres_give_the_same_bytes_and_clean_up(pg_url, tmp_path, reference):
    store, storage, job, got = run_sweep(pg_url, str(tmp_path / "data"), tmp_path / "logs", 3)
    assert got == reference
    _check_progress(store, job)
    assert _job_files(storage, job.id) == []  # shard files, folds and parts removed once published


@pytest.fixture
def s3_uri(monkeypatch):
    """An S3-compatible server (moto) on a free loopback port, with an empty bucket; the URI of a
    storage root in it (credentials in the environment, inherited by the workers)."""
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    for k, v in {"AWS_ACCESS_KEY_ID": "test", "AWS_SECRET_ACCESS_KEY": "test", "AWS_DEFAULT_REGION": "us-east-1"}.items():
        monkeypatch.setenv(k, v)
    uri = f"s3://bssrdf/db?endpoint_override={host}:{port}&scheme=http&region=us-east-1&allow_bucket_creation=true"
    fs, _ = pafs.FileSystem.from_uri(uri)
    fs.create_dir("bssrdf")
    yield uri
    server.stop()


def test_two_workers_on_an_s3_store_give_the_same_bytes(tmp_path, s3_uri, reference):
    url = f"sqlite:///{tmp_path / 'jobs.sqlite'}"
    store, storage, job, got = run_sweep(url, s3_uri, tmp_path / "logs", 2)
    assert got == reference
    _check_progress(store, job)
    assert _job_files(storage, job.id) == []
    assert all(ref.uri.startswith(f".jobs/{job.id}/shards/") for _, ref in store.shard_files(job.id))


def test_shared_walks_through_the_service_give_the_simulate_bytes(tmp_path):
    """A job of shared walk groups (2 groups x 3 shards, a group folded and stopped as one) on two
    workers: the same bytes as `bssrdf simulate`."""
    from workers.run.simulate import simulate_sweep

    spec = shared_spec()
    assert spec.walk_groups() == [(0, 1), (2, 3)] and spec.task_count() == 6
    out = tmp_path / "reference"
    simulate_sweep(spec, str(out), threads=1)
    url = f"sqlite:///{tmp_path / 'jobs.sqlite'}"
    store, _storage, job, got = run_sweep(url, str(tmp_path / "data"), tmp_path / "logs", 2, spec=spec)
    assert got == {name: (out / name).read_bytes() for name in FILES}
    assert store.progress(job.id).shards_total == 6


def test_progress_counts_media_of_shared_walk_groups():
    """A job's task rows are walk groups x shards: progress reports media, not groups."""
    import json

    from service.store.jobs import _media_counts

    spec = shared_spec()  # 2 groups of 2 media, 3 shards
    doc = json.dumps(spec.model_dump(mode="json"))
    assert _media_counts(doc, 0, 6, 3) == {"media_total": 4, "media_merged": 0}
    assert _media_counts(doc, 3, 6, 3) == {"media_total": 4, "media_merged": 2}
    assert _media_counts(doc, 6, 6, 3) == {"media_total": 4, "media_merged": 4}
