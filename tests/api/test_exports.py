"""GET /v1/datasets/{name}/versions/{version}/exports/{format} and ``bssrdf export``: the export is
made once, stored beside the version, served through the verified download path (ETag, HEAD,
304, Range), refused with a reason for datasets it does not fit; the command line writes the
same files locally and through the API."""

from __future__ import annotations

import argparse
import hashlib
import io
import json
import zipfile

import pytest

import service.export
from schema import parse_spec
from service.client import ApiClient
from service.datasets import DatasetStorage
from service.export import main as export_main
from service.export import parse_target
from service.settings import sqlite_url_for
from service.store import JobStore
from service.worker import Worker
from tests.api.conftest import AUTH, TINY_SPEC


@pytest.fixture(scope="module")
def data_dir(tmp_path_factory):
    """A local data directory (as ``bssrdf run`` makes) with version 1 of ``tiny``."""
    root = tmp_path_factory.mktemp("export-data")
    store = JobStore(sqlite_url_for(root))
    storage = DatasetStorage(str(root / "data"))
    job = store.submit(parse_spec(TINY_SPEC))
    Worker(store, storage, once=True, poll_seconds=0.05).loop()
    assert store.get_job(job.id).state == "succeeded", store.get_job(job.id).error
    store.dispose()
    return root


@pytest.fixture
def ex_client(make_client, data_dir):
    store = JobStore(sqlite_url_for(data_dir))
    yield make_client(store, DatasetStorage(str(data_dir / "data"))), store
    store.dispose()


def test_export_is_made_once_and_served_like_a_file(ex_client):
    client, store = ex_client
    r = client.get("/v1/datasets/tiny/versions/1/exports/csv")
    assert r.status_code == 200, r.text
    assert r.headers["content-type"] == "application/zip" and "tiny-v1-csv.zip" in r.headers["content-disposition"]
    digest = hashlib.sha256(r.content).hexdigest()
    assert r.headers["etag"] == f'"{digest}"' and int(r.headers["content-length"]) == len(r.content)
    (export,) = store.list_exports("tiny", 1)
    assert export.sha256 == digest
    with zipfile.ZipFile(io.BytesIO(r.content)) as zf:
        manifest = json.loads(zf.read("export.json"))
        assert set(zf.namelist()) == {"radial.csv", "bins.csv", "summary.csv", "columns.csv", "provenance.json",
                                      "export.json"}
    assert manifest["dataset"] == "tiny" and manifest["version"] == 1 and manifest["format"] == "csv"
    again = client.get("/v1/datasets/tiny/versions/latest/exports/csv")
    assert again.content == r.content and store.list_exports("tiny", 1) == [export]
    head = client.head("/v1/datasets/tiny/versions/1/exports/csv")
    assert head.status_code == 200 and head.content == b"" and head.headers["etag"] == r.headers["etag"]
    assert client.get("/v1/datasets/tiny/versions/1/exports/csv",
                      headers={"If-None-Match": r.headers["etag"]}).status_code == 304
    part = client.get("/v1/datasets/tiny/versions/1/exports/csv", headers={"Range": "bytes=0-9"})
    assert part.status_code == 206 and part.content == r.content[:10]


@pytest.mark.parametrize("fmt, text", [("tiff", "must be one of pbrt, albedo-map"), ("pbrt", '"spacing": "pbrt"')])
def test_refused_formats_are_422_naming_the_reason(ex_client, fmt, text):
    client, store = ex_client
    r = client.get(f"/v1/datasets/tiny/versions/1/exports/{fmt}")
    assert r.status_code == 422, r.text
    (p,) = r.json()["detail"]
    assert p["field"] == "path.format" and text in p["message"] and "npz" in p["allowed"]
    assert all(e.format != fmt for e in store.list_exports("tiny", 1))


def test_unknown_version_is_404(ex_client):
    client, _store = ex_client
    assert client.get("/v1/datasets/tiny/versions/9/exports/npz").status_code == 404


def test_a_corrupted_export_is_not_served(ex_client, data_dir):
    client, store = ex_client
    assert client.get("/v1/datasets/tiny/versions/1/exports/npz").status_code == 200
    export = next(e for e in store.list_exports("tiny", 1) if e.format == "npz")
    path = data_dir / "data" / "tiny" / "v1" / export.filename
    original = path.read_bytes()
    try:
        path.write_bytes(original[:-1] + bytes([original[-1] ^ 0xFF]))
        r = client.get("/v1/datasets/tiny/versions/1/exports/npz")
        assert r.status_code == 500 and "corrupt" in r.json()["detail"]
    finally:
        path.write_bytes(original)


def _args(tmp_path, target, fmt, **kw) -> argparse.Namespace:
    return argparse.Namespace(target=target, format=fmt, out=str(tmp_path / "out"), api=None, token=None,
                              data_dir=None, **kw)


def test_command_line_local_and_through_the_api(ex_client, data_dir, tmp_path, monkeypatch, capsys):
    client, _store = ex_client
    local = _args(tmp_path / "local", "tiny@1", "npz")
    local.data_dir = str(data_dir)
    assert export_main(local) == 0
    out_local = tmp_path / "local" / "out"
    assert sorted(p.name for p in out_local.iterdir()) == ["export.json", "tiny-v1.npz"]
    assert "wrote 2 files of tiny v1 npz" in capsys.readouterr().out
    monkeypatch.setattr(service.export, "ApiClient", lambda base, token, **kw: ApiClient(base, token, http=client))
    remote = _args(tmp_path / "remote", "tiny", "npz")
    remote.api = "http://testserver"
    assert export_main(remote) == 0
    for name in ("export.json", "tiny-v1.npz"):  # the same stored export either way
        assert (tmp_path / "remote" / "out" / name).read_bytes() == (out_local / name).read_bytes()


def test_command_line_errors(data_dir, tmp_path, capsys):
    args = _args(tmp_path, "tiny@1", "pbrt")
    args.data_dir = str(data_dir)
    assert export_main(args) == 2 and '"spacing": "pbrt"' in capsys.readouterr().err
    args = _args(tmp_path, "nothing", "npz")
    args.data_dir = str(data_dir)
    assert export_main(args) == 2 and "'nothing'" in capsys.readouterr().err
    for bad in ("tiny@", "@1", "tiny@0", "tiny@v1"):
        with pytest.raises(ValueError, match="VERSION"):
            parse_target(bad)
    assert parse_target("tiny@latest") == ("tiny", None) and parse_target("a@12") == ("a", 12)


def test_command_line_exports_simulate_tables(data_dir, tmp_path, capsys):
    """--tables DIR exports tables outside the catalog (a version's directory here), writing the
    same files as the stored export apart from the provenance's missing version."""
    args = _args(tmp_path, None, "csv", tables=str(data_dir / "data" / "tiny" / "v1"))
    assert export_main(args) == 0
    out = tmp_path / "out"
    assert sorted(p.name for p in out.iterdir()) == ["bins.csv", "columns.csv", "export.json", "provenance.json",
                                                     "radial.csv", "summary.csv"]
    manifest = json.loads((out / "export.json").read_text())
    assert manifest["dataset"] == "tiny" and manifest["version"] is None and manifest["format"] == "csv"
    both = _args(tmp_path, "tiny", "csv", tables=str(out))
    assert export_main(both) == 2 and "not both" in capsys.readouterr().err


def test_a_deleted_versions_exports_go_with_it(make_client, tmp_path):
    """DELETE of a version removes its directory, archives included; its exports are gone (410)."""
    root = tmp_path / "del"
    store = JobStore(sqlite_url_for(root))
    storage = DatasetStorage(str(root / "data"))
    store.submit(parse_spec(TINY_SPEC))
    Worker(store, storage, once=True, poll_seconds=0.05).loop()
    client = make_client(store, storage)
    assert client.get("/v1/datasets/tiny/versions/1/exports/csv").status_code == 200
    assert client.delete("/v1/datasets/tiny/versions/1", headers=AUTH).status_code in (200, 204)
    assert not (root / "data" / "tiny" / "v1").exists() and store.list_exports("tiny", 1) == []
    assert client.get("/v1/datasets/tiny/versions/1/exports/csv").status_code in (404, 410)
    store.dispose()
