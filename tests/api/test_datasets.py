"""/v1/datasets: listing, versions, metadata and summary, verified downloads (a real published job)."""

from __future__ import annotations

import hashlib
import io
import json

import pyarrow.parquet as pq
import pytest

FILES = ("radial.parquet", "bins.parquet", "summary.parquet", "summary.json", "metadata.json")


@pytest.fixture
def ds_client(make_client, published):
    store, storage, _jobs = published
    return make_client(store, storage)


def test_list_datasets_and_versions(ds_client, published):
    _store, _storage, jobs = published
    assert ds_client.get("/v1/datasets").json() == [
        {"name": "tiny", "latest_version": 2, "versions": 2, "updated_at": pytest.approx(jobs[1].finished_at, abs=5)}
    ]
    versions = ds_client.get("/v1/datasets/tiny/versions").json()
    assert [v["version"] for v in versions] == [1, 2]
    assert {v["job_id"] for v in versions} == {j.id for j in jobs}
    assert set(versions[0]["files"]) == set(FILES)
    assert all(len(f["sha256"]) == 64 for f in versions[0]["files"].values())
    assert versions[0]["photons"] == 200 and versions[0]["shards"] == 2  # one channel, one angle
    r = ds_client.get("/v1/datasets/nothing-here/versions")
    assert r.status_code == 404 and "GET /v1/datasets" in r.json()["detail"]


def test_version_detail_has_metadata_and_summary_and_latest_works(ds_client, published):
    _store, _storage, jobs = published
    v1 = ds_client.get("/v1/datasets/tiny/versions/1").json()
    assert v1["version"] == 1 and v1["job_id"] == jobs[0].id
    meta = v1["metadata"]
    assert meta["spec"]["seed"] == 7 and meta["seed"] == 7 and meta["shards"] == 2
    assert meta["code_version"]["package"] and meta["files"]["radial.parquet"]["sha256"]
    # One code version in every table and file of a version.
    for table in ("radial.parquet", "bins.parquet", "summary.parquet"):
        data = ds_client.get(f"/v1/datasets/tiny/versions/1/files/{table}").content
        run = json.loads(pq.read_schema(io.BytesIO(data)).metadata[b"bssrdf.run"])
        assert run["code_version"] == meta["code_version"], table
    summary = ds_client.get("/v1/datasets/tiny/versions/1/files/summary.json").json()
    assert summary["run"]["code_version"] == meta["code_version"]
    assert v1["summary"]["name"] == "tiny" and v1["summary"]["results"]
    assert {r["component"] for r in v1["summary"]["results"]} == {"single", "multiple", "total"}
    latest = ds_client.get("/v1/datasets/tiny/versions/latest").json()
    assert latest["version"] == 2 and latest["metadata"]["seed"] == 8


@pytest.mark.parametrize("version, status", [("3", 404), ("0", 422), ("-1", 422), ("v1", 422), ("1.5", 422),
                                             ("LATEST", 422)])
def test_bad_or_unknown_versions(ds_client, version, status):
    r = ds_client.get(f"/v1/datasets/tiny/versions/{version}")
    assert r.status_code == status, r.text
    if status == 422:
        (p,) = r.json()["detail"]
        assert p["field"] == "path.version" and p["received"] == version and "latest" in p["allowed"]
    else:
        assert "no version 3" in r.json()["detail"] and "/v1/datasets/tiny/versions" in r.json()["detail"]


@pytest.mark.parametrize("version", ["1", "latest"])
def test_downloads_are_the_published_bytes(ds_client, published, version):
    store, _storage, _jobs = published
    record = store.get_version("tiny", None if version == "latest" else int(version))
    for name in FILES:
        r = ds_client.get(f"/v1/datasets/tiny/versions/{version}/files/{name}")
        assert r.status_code == 200, r.text
        digest = hashlib.sha256(r.content).hexdigest()
        expected = record.meta["metadata_sha256"] if name == "metadata.json" else record.meta["files"][name]["sha256"]
        assert digest == expected and r.headers["etag"] == f'"{expected}"'
        assert f"tiny-v{record.version}-{name}" in r.headers["content-disposition"]
        if name.endswith(".parquet"):
            assert r.headers["content-type"] == "application/vnd.apache.parquet"
            assert pq.read_table(io.BytesIO(r.content)).num_rows > 0
        else:
            assert r.headers["content-type"].startswith("application/json")
            json.loads(r.content)
    summary = ds_client.get(f"/v1/datasets/tiny/versions/{version}/files/summary.json").json()
    assert summary == ds_client.get(f"/v1/datasets/tiny/versions/{version}").json()["summary"]


@pytest.mark.parametrize("name", ["nope.parquet", "%2E%2E", "../v2/radial.parquet", "..%2Fv2%2Fradial.parquet",
                                  "%2e%2e%2f..%2fjobs.sqlite", ".staging", "RADIAL.parquet"])
def test_unknown_file_names_are_404_and_nothing_outside_the_version_is_served(ds_client, name):
    r = ds_client.get(f"/v1/datasets/tiny/versions/1/files/{name}")
    assert r.status_code == 404, (name, r.status_code, r.text[:200])
    if r.headers["content-type"].startswith("application/json") and "available" in r.text:
        assert "radial.parquet" in r.json()["detail"]  # names what exists


def test_unknown_dataset_file_is_404(ds_client):
    r = ds_client.get("/v1/datasets/other/versions/latest/files/radial.parquet")
    assert r.status_code == 404 and "no versions" in r.json()["detail"]


@pytest.mark.parametrize("name", ["radial.parquet", "summary.json", "metadata.json"])
def test_a_corrupted_file_is_not_served(ds_client, published, name):
    store, storage, _jobs = published
    path = f"{store.get_version('tiny', 1).uri}/{name}"
    with storage.fs.open_input_stream(path) as f:
        original = f.read()
    try:
        corrupted = bytearray(original)
        corrupted[len(corrupted) // 2] ^= 0xFF  # one flipped byte, same size
        with storage.fs.open_output_stream(path) as f:
            f.write(bytes(corrupted))
        r = ds_client.get(f"/v1/datasets/tiny/versions/1/files/{name}")
        assert r.status_code == 500
        detail = r.json()["detail"]
        assert "checksum verification failed" in detail and name in detail and "corrupt" in detail
        assert bytes(corrupted) not in r.content
        # the other files and the other version are still served
        other = "bins.parquet" if name != "bins.parquet" else "radial.parquet"
        assert ds_client.get(f"/v1/datasets/tiny/versions/1/files/{other}").status_code == 200
        assert ds_client.get(f"/v1/datasets/tiny/versions/2/files/{name}").status_code == 200
        storage.fs.delete_file(path)  # a missing file: same answer
        r = ds_client.get(f"/v1/datasets/tiny/versions/1/files/{name}")
        assert r.status_code == 500 and "unreadable" in r.json()["detail"]
    finally:
        with storage.fs.open_output_stream(path) as f:
            f.write(original)
    assert ds_client.get(f"/v1/datasets/tiny/versions/1/files/{name}").status_code == 200


def _published_bytes(published, name: str) -> tuple[bytes, str]:
    store, storage, _jobs = published
    record = store.get_version("tiny", 1)
    with storage.fs.open_input_stream(f"{record.uri}/{name}") as f:
        data = f.read()
    return data, hashlib.sha256(data).hexdigest()


@pytest.mark.parametrize("name", ["radial.parquet", "metadata.json"])
def test_head_etag_304_and_content_length(ds_client, published, name):
    data, digest = _published_bytes(published, name)
    url = f"/v1/datasets/tiny/versions/1/files/{name}"
    get = ds_client.get(url)
    assert get.headers["content-length"] == str(len(data)) and get.headers["accept-ranges"] == "bytes"
    head = ds_client.head(url)
    assert head.status_code == 200 and head.content == b""
    assert {k: head.headers[k] for k in ("etag", "content-length", "content-type", "content-disposition")} == {
        k: get.headers[k] for k in ("etag", "content-length", "content-type", "content-disposition")}
    for tag in (f'"{digest}"', f'W/"{digest}"', f'"other", "{digest}"', "*"):
        r = ds_client.get(url, headers={"If-None-Match": tag})
        assert r.status_code == 304 and r.content == b"" and r.headers["etag"] == f'"{digest}"', tag
    assert ds_client.get(url, headers={"If-None-Match": '"0000"'}).status_code == 200


@pytest.mark.parametrize("header, part", [
    ("bytes=0-9", slice(0, 10)), ("bytes=10-", slice(10, None)), ("bytes=-7", slice(-7, None)),
    ("bytes=5-5", slice(5, 6)), ("bytes=3-999999999", slice(3, None)),
])
def test_range_requests(ds_client, published, header, part):
    data, _ = _published_bytes(published, "radial.parquet")
    r = ds_client.get("/v1/datasets/tiny/versions/1/files/radial.parquet", headers={"Range": header})
    assert r.status_code == 206 and r.content == data[part], header
    start = range(len(data))[part][0]
    assert r.headers["content-range"] == f"bytes {start}-{start + len(r.content) - 1}/{len(data)}"
    assert r.headers["content-length"] == str(len(r.content))


@pytest.mark.parametrize("header, status", [
    ("bytes=999999999-", 416), ("bytes=-0", 416), ("bytes=0-1,4-5", 200), ("lines=1-2", 200), ("bytes=9-2", 200),
    ("bytes=x-y", 200),
])
def test_unsatisfiable_and_ignored_ranges(ds_client, published, header, status):
    data, _ = _published_bytes(published, "radial.parquet")
    r = ds_client.get("/v1/datasets/tiny/versions/1/files/radial.parquet", headers={"Range": header})
    assert r.status_code == status, header
    if status == 416:
        assert r.headers["content-range"] == f"bytes */{len(data)}"
    else:
        assert r.content == data


def test_a_corrupted_file_is_not_served_to_head_or_range_either(ds_client, published):
    store, storage, _jobs = published
    path = f"{store.get_version('tiny', 1).uri}/summary.json"
    data, digest = _published_bytes(published, "summary.json")
    try:
        with storage.fs.open_output_stream(path) as f:
            f.write(data[:-1] + b" ")
        url = "/v1/datasets/tiny/versions/1/files/summary.json"
        assert ds_client.head(url).status_code == 500
        assert ds_client.get(url, headers={"Range": "bytes=0-3"}).status_code == 500
        # the client that already holds the published bytes is told so without a read
        assert ds_client.get(url, headers={"If-None-Match": f'"{digest}"'}).status_code == 304
    finally:
        with storage.fs.open_output_stream(path) as f:
            f.write(data)


@pytest.mark.parametrize("if_range, status", [
    ("ETAG", 206), ('"0000"', 200), ("W/ETAG", 200), ("Wed, 21 Oct 2015 07:28:00 GMT", 200), ("", 200),
], ids=["same-etag", "other-etag", "weak-etag", "a-date", "empty"])
def test_if_range_sends_the_range_only_for_the_same_strong_etag(ds_client, published, if_range, status):
    """RFC 9110 13.1.5: a validator that does not match (strong comparison; the files have no
    Last-Modified, so no date matches) means the whole file, 200, not the range."""
    data, digest = _published_bytes(published, "radial.parquet")
    header = if_range.replace("ETAG", f'"{digest}"')
    r = ds_client.get("/v1/datasets/tiny/versions/1/files/radial.parquet",
                      headers={"Range": "bytes=0-9", "If-Range": header})
    assert r.status_code == status, r.headers
    assert r.content == (data[:10] if status == 206 else data)
    assert ("content-range" in r.headers) == (status == 206)
