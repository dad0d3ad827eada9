"""Bearer tokens: mutating endpoints always, reads when closed; the non-loopback refusal."""

from __future__ import annotations

import subprocess
import sys

import pytest

from service.api import InsecureBindError, create_app, is_loopback
from service.settings import Settings
from tests.api.conftest import AUTH, TINY_SPEC, TOKEN

READS = ["/v1/jobs", "/v1/jobs/some-id", "/v1/datasets", "/v1/datasets/x/versions", "/v1/datasets/x/versions/1",
         "/v1/datasets/x/versions/latest/files/summary.json", "/metrics"]


def _assert_401(r, error: str | None = None):
    assert r.status_code == 401, r.text
    challenge = r.headers["www-authenticate"]
    assert challenge.startswith("Bearer")
    if error:
        assert f'error="{error}"' in challenge
    assert "BSSRDF_API_TOKENS" in r.json()["detail"]


@pytest.mark.parametrize("headers, error", [
    ({}, None),
    ({"Authorization": "Bearer wrong-token"}, "invalid_token"),
    ({"Authorization": f"Bearer {TOKEN}x"}, "invalid_token"),
    ({"Authorization": f"Basic {TOKEN}"}, None),  # not a bearer credential
])
def test_mutations_need_a_valid_token(make_client, sqlite_store, storage, headers, error):
    client = make_client(sqlite_store, storage)
    _assert_401(client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=headers), error)
    # 401 comes before validation: an unauthenticated caller learns nothing about the spec
    _assert_401(client.post("/v1/jobs", json={"spec": {"bogus": 1}}, headers=headers), error)
    job = sqlite_store.submit(__import__("schema").parse_spec(TINY_SPEC))
    _assert_401(client.post(f"/v1/jobs/{job.id}/cancel", headers=headers), error)
    assert sqlite_store.get_job(job.id).state == "queued"
    assert len(sqlite_store.list_jobs()) == 1  # only the one stored directly


def test_any_configured_token_is_accepted(make_client, sqlite_store, storage):
    client = make_client(sqlite_store, storage, api_tokens=["first-token", TOKEN])
    assert client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers={"Authorization": "Bearer first-token"}).status_code == 201
    assert client.post("/v1/jobs", json={"spec": TINY_SPEC, "force": True}, headers=AUTH).status_code == 201


def test_reads_open_by_default(make_client, sqlite_store, storage):
    client = make_client(sqlite_store, storage)
    for path in READS:
        assert client.get(path).status_code != 401, path
    assert client.get("/healthz").status_code == 200


def test_reads_closed_need_a_token(make_client, sqlite_store, storage):
    client = make_client(sqlite_store, storage, read_open=False)
    for path in READS:
        _assert_401(client.get(path))
        _assert_401(client.get(path, headers={"Authorization": "Bearer nope"}), "invalid_token")
        assert client.get(path, headers=AUTH).status_code != 401, path
    # probes stay open
    assert client.get("/healthz").status_code == 200
    assert client.get("/readyz").status_code == 200


def test_settings_come_from_the_overridable_get_settings(make_client, sqlite_store, storage):
    from service.api.deps import app_settings

    client = make_client(sqlite_store, storage)
    assert client.get("/v1/jobs").status_code == 200
    client.app.dependency_overrides[app_settings] = lambda: Settings(api_tokens=[TOKEN], read_open=False)
    _assert_401(client.get("/v1/jobs"))


def test_without_overrides_the_app_opens_the_store_of_its_settings(tmp_path):
    from fastapi.testclient import TestClient

    settings = Settings(data_dir=str(tmp_path / "d"), api_tokens=[TOKEN])
    with TestClient(create_app(settings)) as client:
        assert client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH).status_code == 201
        assert client.get("/readyz").json() == {"status": "ok", "checks": {"store": "ok", "storage": "ok"}}
    assert (tmp_path / "d" / "jobs.sqlite").exists() and (tmp_path / "d" / "data").is_dir()


def test_no_tokens_means_auth_off_on_loopback(make_client, sqlite_store, storage):
    client = make_client(sqlite_store, storage, api_tokens=[], host="127.0.0.1")
    assert client.post("/v1/jobs", json={"spec": TINY_SPEC}).status_code == 201


@pytest.mark.parametrize("host", ["0.0.0.0", "::", "192.168.1.10", "api.example.org"])
def test_refuses_non_loopback_bind_without_tokens(host, tmp_path):
    with pytest.raises(InsecureBindError, match="BSSRDF_API_TOKENS"):
        create_app(Settings(data_dir=str(tmp_path), host=host))
    create_app(Settings(data_dir=str(tmp_path), host=host, api_tokens=[TOKEN]))  # with tokens: fine


@pytest.mark.parametrize("host, loopback", [("127.0.0.1", True), ("127.1.2.3", True), ("::1", True),
                                            ("[::1]", True), ("localhost", True), ("0.0.0.0", False),
                                            ("10.0.0.1", False), ("example.org", False)])
def test_is_loopback(host, loopback):
    assert is_loopback(host) is loopback


def test_serve_refuses_to_start_on_a_public_address_without_tokens(tmp_path):
    env = {"PATH": "/usr/bin:/bin", "BSSRDF_DATA_DIR": str(tmp_path), "BSSRDF_API_TOKENS": "[]"}
    r = subprocess.run([sys.executable, "-m", "service.serve", "--host", "0.0.0.0", "--port", "1"],
                       capture_output=True, text=True, timeout=60, env=env)
    assert r.returncode == 2
    assert "refusing to serve on '0.0.0.0' without API tokens" in r.stderr and "BSSRDF_API_TOKENS" in r.stderr
