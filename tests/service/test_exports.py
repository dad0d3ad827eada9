"""Stored exports (service.datasets.exports, service.store.exports) on SQLite and PostgreSQL: made
once from the verified tables, stored beside the version with its sha256, one catalog row even
when two processes make it at once, refused cleanly when the dataset cannot be exported."""

from __future__ import annotations

import hashlib
import io
import json
import threading
import zipfile

import pytest
from pyarrow.fs import FileSelector

from schema import parse_spec
from service.datasets import DatasetStorage
from service.datasets.exports import ensure_export, extract_export, read_export
from service.store import ChecksumMismatch, VersionNotFound
from service.worker import Worker
from workers.exports import ExportError

SPEC = {
    "name": "exp", "medium": {"sigma_a": 1.0, "sigma_s": 1.0, "g": 0.0, "eta": 1.3},
    "photons": 200, "shards": 2, "batches_per_shard": 1, "seed": 7, "estimator": "exits",
    "bins": {"radial": {"count": 4, "max_mm": 4.0}, "cos_theta_o": {"count": 2}, "phi_o": {"count": 1}},
}


@pytest.fixture(scope="module", params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def published(request, tmp_path_factory):
    """A store (SQLite or PostgreSQL) and storage holding version 1 of dataset ``exp``, shared by
    this module's tests (each uses its own export format)."""
    from service.store import JobStore
    from tests.service.conftest import PG_ENV, drop_pg_schema, fresh_pg_schema_url, pg_base_url

    root = tmp_path_factory.mktemp("exports")
    schema = None
    if request.param == "sqlite":
        url = f"sqlite:///{root / 'jobs.sqlite'}"
    else:
        base = pg_base_url()
        if base is None:
            pytest.skip(f"PostgreSQL tests need {PG_ENV}")
        url, schema = fresh_pg_schema_url(base)
    store = JobStore(url)
    storage = DatasetStorage(str(root / "data"))
    job = store.submit(parse_spec(SPEC))
    Worker(store, storage, once=True, poll_seconds=0.05).loop()
    assert store.get_job(job.id).state == "succeeded", store.get_job(job.id).error
    yield store, storage
    store.dispose()
    if schema is not None:
        drop_pg_schema(pg_base_url(), schema)


def test_made_once_stored_beside_the_version_with_its_sha256(published, tmp_path):
    store, storage = published
    record, export = ensure_export(store, storage, "exp", None, "npz")
    assert (record.version, export.format) == (1, "npz")
    assert export.filename.startswith("exports/npz-") and export.filename.endswith(".zip")
    data = read_export(storage, record, export)
    assert hashlib.sha256(data).hexdigest() == export.sha256 and len(data) == export.bytes
    manifest = export.meta
    assert manifest["dataset"] == "exp" and manifest["version"] == 1 and manifest["format"] == "npz"
    assert manifest["spec_hash"] == store.get_job(record.job_id).spec_hash
    assert manifest["tables_sha256"] == {f: record.meta["files"][f]["sha256"]
                                         for f in ("radial.parquet", "bins.parquet", "summary.parquet")}
    assert manifest["code_version"]["package"]
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        assert json.loads(zf.read("export.json")) == manifest
    files = extract_export(data, manifest, tmp_path / "out")
    assert files == ["exp-v1.npz", "export.json"]
    # the second request serves the stored export: same row, same bytes, nothing rebuilt
    again_record, again = ensure_export(store, storage, "exp", 1, "npz")
    assert again == export and [e for e in store.list_exports("exp", 1) if e.format == "npz"] == [export]
    listing = storage.fs.get_file_info(FileSelector(f"{record.uri}/exports"))
    assert [i.base_name for i in listing] == [export.filename.split("/")[1]]


def test_two_processes_making_the_same_export_keep_one(published):
    store, storage = published
    results, errors = [], []

    def make():
        try:
            results.append(ensure_export(store, storage, "exp", 1, "csv")[1])
        except Exception as exc:  # pragma: no cover - reported below
            errors.append(exc)

    threads = [threading.Thread(target=make) for _ in range(3)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert not errors and len({r.sha256 for r in results}) == 1
    assert len([e for e in store.list_exports("exp", 1) if e.format == "csv"]) == 1  # deterministic: one row


def test_refusals_and_corruption(published):
    store, storage = published
    with pytest.raises(ExportError, match='"spacing": "pbrt"'):
        ensure_export(store, storage, "exp", 1, "pbrt")
    with pytest.raises(ExportError, match="unknown export format 'tiff'"):
        ensure_export(store, storage, "exp", 1, "tiff")
    with pytest.raises(VersionNotFound):
        ensure_export(store, storage, "exp", 2, "npz")
    assert {e.format for e in store.list_exports("exp", 1)} <= {"npz", "csv"}  # nothing stored by a refusal
    record, export = ensure_export(store, storage, "exp", 1, "exr")
    path = f"{record.uri}/{export.filename}"
    with storage.fs.open_output_stream(path) as f:
        f.write(b"not the archive")
    with pytest.raises(ChecksumMismatch):
        read_export(storage, record, export)
    first = next(iter(export.meta["files"]))
    with pytest.raises(ChecksumMismatch, match=rf"export file {first} has sha256 \w+, recorded in its manifest as "
                       + export.meta["files"][first]["sha256"]):
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as zf:
            zf.writestr(first, b"other bytes")
        extract_export(buf.getvalue(), export.meta, "unused")
    with pytest.raises(ChecksumMismatch, match="holds stray.txt, which its manifest does not list"):
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w") as zf:
            zf.writestr("stray.txt", b"not exported")
        extract_export(buf.getvalue(), export.meta, "unused")
