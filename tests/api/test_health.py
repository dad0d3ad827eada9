"""/healthz, /readyz (503 with the reason), /metrics (Prometheus text format), OpenAPI."""

from __future__ import annotations

import re

import pytest

from service.datasets import DatasetStorage
from service.store import JobStore
from tests.api.conftest import AUTH, TINY_SPEC, TOKEN
from tests.support.files import stored
from tests.support.net import free_port

# name{label="value",...} value   (the value: a float, an integer, NaN or +-Inf)
SAMPLE = re.compile(r'^([a-zA-Z_:][a-zA-Z0-9_:]*)(\{([a-zA-Z_][a-zA-Z0-9_]*="(?:[^"\\]|\\.)*",?)*\})? '
                    r'(-?[0-9.]+(e[+-]?[0-9]+)?|NaN|[+-]Inf)$')
COMMENT = re.compile(r"^# (HELP|TYPE) ([a-zA-Z_:][a-zA-Z0-9_:]*) .+$")


def parse_metrics(text: str) -> dict[str, float]:
    """Every sample as {'name{labels}': value}; asserts each line is a sample or a HELP/TYPE comment."""
    assert text.endswith("\n")
    samples, typed = {}, set()
    for line in text.splitlines():
        if line.startswith("#"):
            m = COMMENT.match(line)
            assert m, f"bad comment line: {line!r}"
            if m.group(1) == "TYPE":
                typed.add(m.group(2))
            continue
        m = SAMPLE.match(line)
        assert m, f"bad sample line: {line!r}"
        assert m.group(1) in typed, f"sample before its TYPE: {line!r}"
        samples[line.rsplit(" ", 1)[0]] = float(line.rsplit(" ", 1)[1])
    return samples


def test_healthz(client):
    assert client.get("/healthz").json() == {"status": "ok"}


def test_readyz_ok(client):
    r = client.get("/readyz")
    assert r.status_code == 200 and r.json() == {"status": "ok", "checks": {"store": "ok", "storage": "ok"}}


def test_readyz_503_when_the_database_is_unreachable(make_client, storage):
    # Nothing listens on this loopback port: the connection is refused at once.
    dead = JobStore(f"postgresql+psycopg://postgres@127.0.0.1:{free_port()}/test?connect_timeout=2", migrate=False)
    client = make_client(dead, storage)
    r = client.get("/readyz")
    assert r.status_code == 503
    body = r.json()
    assert body["status"] == "unavailable" and body["checks"]["storage"] == "ok"
    assert "OperationalError" in body["checks"]["store"] and "127.0.0.1" in body["checks"]["store"]
    assert client.get("/healthz").status_code == 200  # alive, not ready
    # other endpoints say the same, with what to check
    r = client.get("/v1/jobs")
    assert r.status_code == 503 and "BSSRDF_DATABASE_URL" in r.json()["detail"] and r.headers["retry-after"]
    dead.dispose()


def test_readyz_503_when_the_database_is_not_migrated(make_client, storage, tmp_path):
    bare = JobStore(f"sqlite:///{tmp_path / 'empty.sqlite'}", migrate=False)
    r = make_client(bare, storage).get("/readyz")
    assert r.status_code == 503 and "no such table" in r.json()["checks"]["store"]


def test_readyz_503_when_storage_is_gone(make_client, sqlite_store, tmp_path):
    storage = DatasetStorage(str(tmp_path / "vanishing"))
    (tmp_path / "vanishing").rmdir()
    r = make_client(sqlite_store, storage).get("/readyz")
    assert r.status_code == 503
    assert r.json()["checks"]["store"] == "ok"
    assert "not a reachable directory" in r.json()["checks"]["storage"]


def test_readyz_503_when_the_store_cannot_be_opened(tmp_path):
    from fastapi.testclient import TestClient

    from service.api import create_app
    from service.settings import Settings

    settings = Settings(data_dir=str(tmp_path), database_url=f"postgresql+psycopg://postgres@127.0.0.1:{free_port()}/x")
    with TestClient(create_app(settings)) as client:
        r = client.get("/readyz")
    assert r.status_code == 503 and "job store unavailable" in r.json()["detail"]
    assert "BSSRDF_DATABASE_URL" in r.json()["detail"]


@pytest.fixture
def store_down(tmp_path):
    """A TestClient of an app whose job store cannot be opened (nothing listens on its port)."""
    from fastapi.testclient import TestClient

    from service.api import create_app
    from service.settings import Settings

    settings = Settings(data_dir=str(tmp_path), api_tokens=[TOKEN],
                        database_url=f"postgresql+psycopg://postgres@127.0.0.1:{free_port()}/x?connect_timeout=2")
    with TestClient(create_app(settings)) as client:
        yield client


def test_bad_input_is_refused_before_the_store_is_opened(store_down):
    """With the job store down, bad input is still 4xx (validated first), only good input is 503."""
    r = store_down.post("/v1/jobs", json={"spec": dict(TINY_SPEC, photons=-1)}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "spec.photons", r.text
    for method, path in (("GET", "/v1/jobs/xyz"), ("POST", "/v1/jobs/xyz/cancel"), ("DELETE", "/v1/jobs/xyz"),
                         ("GET", "/v1/jobs/xyz/media")):
        r = store_down.request(method, path, headers=AUTH)
        assert r.status_code == 404 and "UUID" in r.json()["detail"], (method, path, r.text)
    assert store_down.get("/v1/jobs?limit=0").status_code == 422
    assert store_down.get("/v1/datasets/tiny/versions/0").status_code == 422
    assert store_down.post("/v1/jobs", json={"spec": TINY_SPEC}).status_code == 401
    r = store_down.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH)
    assert r.status_code == 503 and "BSSRDF_DATABASE_URL" in r.json()["detail"] and r.headers["retry-after"]
    r = store_down.get(f"/v1/jobs/{'0' * 8}-0000-4000-8000-{'0' * 12}")
    assert r.status_code == 503 and "job store unavailable" in r.json()["detail"]


def test_metrics_prometheus_text(client, store):
    text = client.get("/metrics")
    assert text.status_code == 200 and text.headers["content-type"].startswith("text/plain; version=0.0.4")
    empty = parse_metrics(text.text)
    assert empty['bssrdf_jobs{state="queued"}'] == 0 and empty["bssrdf_photons_simulated_total"] == 0
    client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH)
    lease = store.claim("w", 60)
    store.complete_shard(lease, stored(b"payload"), photons=123, elapsed_s=0.5)
    m = parse_metrics(client.get("/metrics").text)
    assert m['bssrdf_jobs{state="running"}'] == 1 and m['bssrdf_jobs{state="queued"}'] == 0
    for state in ("queued", "running", "merging", "succeeded", "failed", "cancelled"):
        assert f'bssrdf_jobs{{state="{state}"}}' in m
    assert m["bssrdf_tasks_claimed_total"] == 1 and m["bssrdf_shards_completed_total"] == 1
    assert m["bssrdf_leases_expired_total"] == 0 and m["bssrdf_photons_simulated_total"] == 123
    assert m["bssrdf_merges_completed_total"] == 0


def test_metrics_after_a_real_job(make_client, published):
    store, storage, _jobs = published
    m = parse_metrics(make_client(store, storage).get("/metrics").text)
    assert m['bssrdf_jobs{state="succeeded"}'] == 2 and m["bssrdf_merges_completed_total"] == 2
    assert m["bssrdf_shards_completed_total"] == 4 and m["bssrdf_photons_simulated_total"] == 400


def test_openapi_documents_every_route(client):
    doc = client.get("/openapi.json").json()
    ops = {(path, method): op for path, item in doc["paths"].items() for method, op in item.items()}
    expected = {("/v1/jobs", "post"), ("/v1/jobs", "get"), ("/v1/jobs/{job_id}", "get"),
                ("/v1/jobs/{job_id}/cancel", "post"), ("/v1/datasets", "get"), ("/v1/datasets/{name}/versions", "get"),
                ("/v1/datasets/{name}/versions/{version}", "get"),
                ("/v1/datasets/{name}/versions/{version}/files/{filename}", "get"),
                ("/healthz", "get"), ("/readyz", "get"), ("/metrics", "get")}
    assert expected <= set(ops)
    for key in expected:
        assert ops[key].get("summary") and ops[key].get("tags"), key
    assert {"201", "200", "401", "409", "422"} <= set(ops[("/v1/jobs", "post")]["responses"])
    assert {"404", "409"} <= set(ops[("/v1/jobs/{job_id}/cancel", "post")]["responses"])
    assert "500" in ops[("/v1/datasets/{name}/versions/{version}/files/{filename}", "get")]["responses"]
    assert "HTTPBearer" in doc["components"]["securitySchemes"]
    assert "JobCreate" in doc["components"]["schemas"] and "JobPublic" in doc["components"]["schemas"]
    assert ops[("/v1/jobs", "post")]["parameters"][0]["name"] == "Idempotency-Key"
