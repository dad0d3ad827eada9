"""The OpenAPI document says what the API does (service/api/openapi.py), and the answers the
fuzzer found unhelpful: a 405 listing only one route's methods, a 400 for a body not in UTF-8."""

from __future__ import annotations

from collections import Counter

import pytest

from tests.api.conftest import AUTH

JSON = {**AUTH, "content-type": "application/json"}


def operations(doc):
    for path, ops in doc["paths"].items():
        for method, op in ops.items():
            yield path, method, op


@pytest.mark.parametrize("read_open", [True, False])
def test_security_of_reads_follows_read_open(make_client, sqlite_store, storage, read_open):
    doc = make_client(sqlite_store, storage, read_open=read_open).get("/openapi.json").json()
    security = {(p, m): op.get("security") for p, m, op in operations(doc)}
    read = security[("/v1/jobs/{job_id}", "get")]
    assert read == ([{}, {"HTTPBearer": []}] if read_open else [{"HTTPBearer": []}])
    assert security[("/v1/datasets/{name}/versions/{version}/files/{filename}", "head")] == read
    assert security[("/v1/jobs", "post")] == [{"HTTPBearer": []}]  # writes always need a token
    assert security[("/v1/datasets/{name}/versions/{version}", "delete")] == [{"HTTPBearer": []}]
    assert security[("/healthz", "get")] is None


def test_errors_are_documented_as_they_are_sent(make_client, sqlite_store, storage):
    doc = make_client(sqlite_store, storage).get("/openapi.json").json()
    assert "HTTPValidationError" not in doc["components"]["schemas"]
    ids = Counter(op["operationId"] for _p, _m, op in operations(doc))
    assert max(ids.values()) == 1, ids  # GET and HEAD of a download are two operations
    for path, method, op in operations(doc):
        for status, response in op["responses"].items():
            if status >= "400" and "content" in response:
                assert list(response["content"]) == ["application/json"], (path, method, status)
            if status == "422":
                assert response["content"]["application/json"]["schema"]["$ref"].endswith("/ValidationErrorBody")
    assert {"408", "413", "431"} <= set(doc["paths"]["/v1/jobs"]["post"]["responses"])
    assert all("431" in op["responses"] for ops in doc["paths"].values() for op in ops.values())
    for route in ("/v1/datasets/{name}/versions/{version}", "/v1/datasets/{name}/versions/{version}/files/{filename}",
                  "/v1/datasets/{name}/versions/{version}/exports/{format}"):
        assert "410" in doc["paths"][route]["get"]["responses"], route


@pytest.mark.parametrize("method, path, allow", [
    ("OPTIONS", "/v1/datasets/tiny/versions/1", "DELETE, GET"),
    ("PATCH", "/v1/jobs", "GET, POST"),
    ("PUT", "/v1/jobs/00000000-0000-0000-0000-000000000000", "DELETE, GET"),
])
def test_405_lists_every_method_of_the_path(client, method, path, allow):
    r = client.request(method, path, headers=AUTH)
    assert r.status_code == 405 and r.headers["allow"] == allow, r.text
    assert allow in r.json()["detail"]


@pytest.mark.parametrize("body", [b"\xc3\x28{}", bytes.fromhex("8f8f62b137c60f0fb2")])
def test_a_body_that_is_not_utf8_is_a_422_on_the_body(client, store, body):
    r = client.post("/v1/jobs", content=body, headers=JSON)
    assert r.status_code == 422, r.text
    (p,) = r.json()["detail"]
    assert p["field"] == "body" and "not UTF-8" in p["message"] and "position 0" in p["message"], p
    assert store.list_jobs() == []
