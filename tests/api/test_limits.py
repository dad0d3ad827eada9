"""Hostile and careless input on SQLite and PostgreSQL: every refusal is a 4xx naming the field,
the limit and the value (shortened), nothing is stored, and no input reaches a 5xx.

Limits: photons per job and estimated CPU seconds per shard (schema.estimate), request body size
(413 before parsing), problem count and echoed values; overflowing integers in path and query
parameters; strings PostgreSQL cannot store (NUL) or UTF-8 cannot encode (lone surrogates).
"""

from __future__ import annotations

import json
import subprocess
import sys
from urllib.parse import quote

import pytest

from schema import parse_spec
from schema.estimate import estimate_shard
from tests.api.conftest import AUTH, job_count, tiny_spec

JSON = {**AUTH, "content-type": "application/json"}


def one_problem(r, field: str) -> dict:
    assert r.status_code == 422, r.text
    mine = [p for p in r.json()["detail"] if p["field"] == field]
    assert mine, r.json()
    return mine[0]


@pytest.mark.parametrize("path", [
    "/v1/datasets/tiny/versions/9223372036854775808",
    "/v1/datasets/tiny/versions/2147483648",
    "/v1/datasets/tiny/versions/99999999999999999999999999999999",
    "/v1/datasets/tiny/versions/9223372036854775808/files/radial.parquet",
    "/v1/jobs?offset=99999999999999999999",
    "/v1/jobs?offset=2147483648",
    "/v1/jobs?limit=99999999999999999999",
])
def test_overflowing_integers_are_422_not_5xx(client, path):
    r = client.get(path)
    assert r.status_code == 422, r.text
    p = r.json()["detail"][0]
    assert p["allowed"] and "received" in p["message"], p


@pytest.mark.parametrize("name", [".hidden", "-rf", "a b", "x" * 101, "a\x00b", "é"])
def test_dataset_path_names_follow_the_one_name_rule(client, name):
    r = client.get(f"/v1/datasets/{quote(name, safe='')}/versions")
    p = one_problem(r, "path.name")
    assert "starting with a letter or digit" in p["message"], p


@pytest.mark.parametrize("job_id", ["missing-job", "a\x00b", "x" * 5000, "00000000-0000-0000-0000-00000000000G"])
def test_malformed_job_ids_are_404_without_a_lookup(client, job_id):
    job_id = quote(job_id, safe="")
    for method, path in (("GET", f"/v1/jobs/{job_id}"), ("POST", f"/v1/jobs/{job_id}/cancel")):
        r = client.request(method, path, headers=AUTH)
        assert r.status_code == 404 and "UUID" in r.json()["detail"], r.text
        assert len(r.content) < 1000


def test_strings_postgresql_or_utf8_cannot_hold_are_refused(client, store):
    r = client.post("/v1/jobs", json={"spec": tiny_spec(), "idempotency_key": "a\x00b"}, headers=AUTH)
    assert one_problem(r, "idempotency_key")["allowed"] == "matching ^[!-~]+$"
    r = client.post("/v1/jobs", json={"spec": tiny_spec()}, headers={**AUTH, "Idempotency-Key": "a b"})
    assert r.status_code == 422
    body = json.dumps({"spec": tiny_spec(description="SURROGATE")}).replace("SURROGATE", "a\\ud800b")
    r = client.post("/v1/jobs", content=body.encode(), headers=JSON)
    one_problem(r, "spec.description")
    assert job_count(store) == 0


def test_lone_surrogates_are_refused_by_the_spec_itself():
    with pytest.raises(Exception, match="unicode string"):  # pydantic-core refuses them itself
        parse_spec(tiny_spec(description="a\ud800b"))


@pytest.mark.parametrize("body, reason", [
    (b'{"spec": {"name": "x",, }}', "at character 22"),
    (b"", "this field is required"),
    (b"\xff\xfe", "not valid JSON"),
    (b'{"spec": ', "not valid JSON"),
])
def test_malformed_json_is_reported_on_the_body(client, store, body, reason):
    p = one_problem(client.post("/v1/jobs", content=body, headers=JSON), "body")
    assert reason in p["message"], p
    assert job_count(store) == 0


@pytest.mark.parametrize("field, value", [("photons", True), ("seed", False), ("shards", "2"), ("photons", "200")])
def test_numbers_are_strict_about_json_types(client, store, field, value):
    p = one_problem(client.post("/v1/jobs", json={"spec": tiny_spec(**{field: value})}, headers=AUTH), f"spec.{field}")
    assert "must be a JSON number" in p["message"] and p["allowed"] == "a JSON number", p
    assert job_count(store) == 0


def test_a_float_with_an_integral_value_is_still_an_integer(client):
    r = client.post("/v1/jobs", json={"spec": tiny_spec(photons=2e2)}, headers=AUTH)
    assert r.status_code == 201 and r.json()["spec"]["photons"] == 200


def test_photons_per_job_limit(make_client, store, storage):
    client = make_client(store, storage, max_job_photons=1000)
    spec = tiny_spec(photons=600, incidence_deg=[0, 45])  # 1200 photons in all
    p = one_problem(client.post("/v1/jobs", json={"spec": spec}, headers=AUTH), "spec.photons")
    assert "600 x 2 x 1 = 1200" in p["message"] and "BSSRDF_MAX_JOB_PHOTONS" in p["message"]
    assert p["allowed"] == "photons x angles x channels <= 1000" and p["received"] == 600
    assert job_count(store) == 0
    assert client.post("/v1/jobs", json={"spec": tiny_spec(photons=500, incidence_deg=[0, 45])},
                       headers=AUTH).status_code == 201


def test_the_issue_spec_of_a_trillion_photons_in_one_shard_is_refused(client, store):
    spec = tiny_spec(photons=10**12, shards=1, batches_per_shard=2)
    r = client.post("/v1/jobs", json={"spec": spec}, headers=AUTH)
    fields = {p["field"] for p in r.json()["detail"]}
    assert r.status_code == 422 and fields == {"spec.photons", "spec.shards"}, r.text
    assert job_count(store) == 0


def test_shard_cpu_limit_names_the_estimate_and_the_shards_needed(make_client, store, storage):
    spec = tiny_spec(photons=4_000_000, shards=2, batches_per_shard=1)
    cpu = estimate_shard(parse_spec(spec)).cpu_s
    client = make_client(store, storage, max_shard_cpu_seconds=cpu / 3 * 1.001)
    p = one_problem(client.post("/v1/jobs", json={"spec": spec}, headers=AUTH), "spec.shards")
    assert f"{cpu:.4g} CPU seconds" in p["message"] and "use at least 6 shards" in p["message"], p
    assert p["received"] == 2 and "BSSRDF_MAX_SHARD_CPU_SECONDS" in p["message"]
    assert job_count(store) == 0
    r = client.post("/v1/jobs", json={"spec": dict(spec, shards=6)}, headers=AUTH)
    assert r.status_code == 201, r.text  # the count the message asked for is accepted
    faster = make_client(store, storage, max_shard_cpu_seconds=cpu / 3 * 1.001, worker_speed=4.0)
    assert faster.post("/v1/jobs", json={"spec": dict(spec, seed=99)}, headers=AUTH).status_code == 201


def test_large_bodies_are_413_before_parsing(make_client, store, storage):
    client = make_client(store, storage, max_body_bytes=4096)
    r = client.post("/v1/jobs", content=b"x" * 5000, headers=JSON)
    assert r.status_code == 413 and "5000 bytes" in r.json()["detail"] and "BSSRDF_MAX_BODY_BYTES" in r.json()["detail"]

    def chunks():  # no Content-Length: cut off once past the limit
        for _ in range(100):
            yield b"x" * 1000

    r = client.post("/v1/jobs", content=chunks(), headers=JSON)
    assert r.status_code == 413, r.text
    assert job_count(store) == 0
    assert client.post("/v1/jobs", json={"spec": tiny_spec()}, headers=AUTH).status_code == 201


def test_echoed_values_are_shortened(client, store):
    r = client.post("/v1/jobs", json={"spec": tiny_spec(description="x" * 500_000)}, headers=AUTH)
    p = one_problem(r, "spec.description")
    assert len(r.content) < 2000 and len(p["received"]) <= 80, len(r.content)
    r = client.post("/v1/jobs", json={"spec": tiny_spec(incidence_deg=list(range(90, 50_090)))}, headers=AUTH)
    detail = r.json()["detail"]
    assert r.status_code == 422 and len(detail) == 20 and detail[-1]["field"] == "(more)", detail[-1]
    assert "49981 more problems" in detail[-1]["message"] and len(r.content) < 10_000
    r = client.post("/v1/jobs", json={"spec": tiny_spec(medium={"preset": "y" * 10_000})}, headers=AUTH)
    assert r.status_code == 422 and len(r.content) < 5000
    assert job_count(store) == 0


def test_version_endpoint_and_command():
    from fastapi.testclient import TestClient

    from schema.version import code_version
    from service.api import create_app
    from service.settings import Settings

    with TestClient(create_app(Settings(api_tokens=["t"], read_open=False))) as c:
        r = c.get("/v1/version")  # no token needed
    assert r.status_code == 200 and r.json() == {"api": "1", **code_version()}
    out = subprocess.run([sys.executable, "-m", "service.cli", "--version"], capture_output=True, text=True)
    assert out.returncode == 0 and out.stdout.strip() == (
        f"bssrdf-db {code_version()['package']} (commit {code_version()['git_commit'] or 'unknown'})")


@pytest.mark.parametrize("value", ["tok1", "[1, 2]", '["a", ""]', "[not json"])
def test_a_bad_token_setting_is_one_clear_line_not_a_traceback(value, tmp_path):
    env = {"BSSRDF_API_TOKENS": value, "BSSRDF_DATA_DIR": str(tmp_path), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-m", "service.cli", "serve"], capture_output=True, text=True, env=env,
                         timeout=60)
    assert out.returncode == 2 and "Traceback" not in out.stderr, out.stderr
    assert "BSSRDF_API_TOKENS must be a JSON list of non-empty strings" in out.stderr
    assert len(out.stderr.splitlines()) <= 3, out.stderr


SECRET = "s3cr3t-Tok3n-0123456789"


@pytest.mark.parametrize("value, said", [
    (SECRET, "text that is not JSON"), (f'["{SECRET}"', "text that is not JSON"), (f'"{SECRET}"', "a JSON string"),
    (f'{{"{SECRET}": 1}}', "a JSON object"), (f'["{SECRET}", 5]', "entry 2 is a number"),
    (f'["{SECRET}", ""]', "entry 2 is an empty string"),
], ids=["bare", "unclosed", "string", "object", "number", "empty"])
def test_a_bad_token_setting_echoes_no_character_of_the_secret(value, said, tmp_path):
    from pydantic import ValidationError

    from service.settings import Settings

    env = {"BSSRDF_API_TOKENS": value, "BSSRDF_DATA_DIR": str(tmp_path), "PATH": "/usr/bin:/bin"}
    out = subprocess.run([sys.executable, "-m", "service.cli", "serve"], capture_output=True, text=True, env=env,
                         timeout=60)
    assert out.returncode == 2 and said in out.stderr, out.stderr
    pieces = {SECRET[i:i + 4] for i in range(len(SECRET) - 3)}  # no 4 characters of it in a row
    assert not any(p in out.stderr for p in pieces), out.stderr
    with pytest.raises(ValidationError) as error:  # the model's own message too (create_app(Settings()))
        Settings(api_tokens=value)
    assert not any(p in str(error.value) for p in pieces), str(error.value)


def test_serve_help_explains_tokens():
    out = subprocess.run([sys.executable, "-m", "service.cli", "serve", "--help"], capture_output=True, text=True)
    assert "BSSRDF_API_TOKENS" in out.stdout and "Authorization: Bearer TOKEN" in out.stdout


def test_shard_payload_and_dataset_size_limits_name_the_estimates(make_client, store, storage):
    from schema.sizes import estimate_sizes

    spec = tiny_spec()
    spec.pop("medium", None)
    spec["sweep"] = {"albedo": {"count": 8}, "g": [0.0], "eta": [1.3]}
    est = estimate_sizes(parse_spec(spec))
    client = make_client(store, storage, max_shard_bytes=est.shard_payload_bytes - 1,
                         max_dataset_bytes=est.dataset_bytes - 1)
    r = client.post("/v1/jobs", json={"spec": spec}, headers=AUTH)
    assert r.status_code == 422, r.text
    by_field = {p["field"]: p for p in r.json()["detail"]}
    assert str(est.shard_payload_bytes) in by_field["spec.bins"]["message"]
    assert "8 media" in by_field["spec.sweep"]["message"] and by_field["spec.sweep"]["received"] == est.dataset_bytes
    assert job_count(store) == 0
    fits = make_client(store, storage, max_shard_bytes=est.shard_payload_bytes, max_dataset_bytes=est.dataset_bytes)
    assert fits.post("/v1/jobs", json={"spec": spec}, headers=AUTH).status_code == 201


def test_the_issue_spec_of_983040_tasks_is_refused_naming_the_task_limit(client, store):
    """1024 albedos x 64 g x 15 shards with independent walks: 983 040 shard tasks, once stored in
    one transaction of 25 s; now over BSSRDF_MAX_JOB_TASKS (default 50 000) at submission."""
    spec = tiny_spec(photons=30, shards=15, batches_per_shard=2)
    spec.pop("medium")
    spec["sweep"] = {"albedo": {"count": 1024}, "g": [i / 64 for i in range(64)], "eta": [1.3], "walks": "independent"}
    p = one_problem(client.post("/v1/jobs", json={"spec": spec}, headers=AUTH), "spec.shards")
    assert "983040 shard tasks (65536 walk groups x 15 shards" in p["message"], p
    assert "50000" in p["message"] and "BSSRDF_MAX_JOB_TASKS" in p["message"], p
    assert p["allowed"] == "shard tasks <= 50000" and p["received"] == 15, p
    assert job_count(store) == 0


def test_task_limit_is_a_setting(make_client, store, storage):
    spec = tiny_spec(shards=4, photons=100, batches_per_shard=2)
    client = make_client(store, storage, max_job_tasks=3)
    p = one_problem(client.post("/v1/jobs", json={"spec": spec}, headers=AUTH), "spec.shards")
    assert "4 shard tasks (1 walk groups x 4 shards" in p["message"] and p["allowed"] == "shard tasks <= 3", p
    assert job_count(store) == 0
    fits = make_client(store, storage, max_job_tasks=4)
    assert fits.post("/v1/jobs", json={"spec": spec}, headers=AUTH).status_code == 201


def with_literal(body: dict, marker: str, literal: str) -> bytes:
    """``body`` as JSON with the string ``marker`` replaced by a raw JSON literal."""
    return json.dumps(body).replace(json.dumps(marker), literal).encode()


@pytest.mark.parametrize("digits", [309, 400, 4300, 4301, 5000, 200_000])
@pytest.mark.parametrize("where, field", [
    (lambda v: {"spec": tiny_spec(photons=v)}, "spec.photons"),
    (lambda v: {"spec": tiny_spec(seed=v)}, "spec.seed"),
    (lambda v: {"spec": tiny_spec(medium={"sigma_a": v, "sigma_s": 1.0, "g": 0.0, "eta": 1.3})},
     "spec.medium.sigma_a.float"),
    (lambda v: {"spec": tiny_spec(), "unknown": v}, "unknown"),
], ids=["photons", "seed", "sigma_a", "unknown-key"])
def test_integers_of_any_length_are_422_naming_the_field(client, store, caplog, digits, where, field):
    sign = "-" * (field == "spec.seed")
    r = client.post("/v1/jobs", content=with_literal(where("N"), "N", sign + "9" * digits), headers=JSON)
    p = one_problem(r, field)
    # 4 significant digits; past 400 digits (service.api.bodies.LongInt) the leading ones and the length
    assert p["received"] == sign + (f"1.000e+{digits}" if digits <= 400 else f"9.9999...e+{digits - 1}"), p
    assert len(r.content) < 2000, len(r.content)
    assert all("9" * 100 not in rec.getMessage() for rec in caplog.records)  # the log never holds the number
    assert job_count(store) == 0


@pytest.mark.parametrize("body, field, reason", [
    (b'{"spec": ' + b"[" * 50_000 + b"]" * 50_000 + b"}", "body", "nest too deep for the parser"),
    (json.dumps({"spec": tiny_spec()}).encode("utf-16"), "body", "JSON must be UTF-8 (RFC 8259)"),
    (json.dumps({"spec": tiny_spec()}).encode("utf-16-le"), "body", "JSON must be UTF-8 (RFC 8259)"),
    (json.dumps({"spec": tiny_spec()}).encode("utf-16-be"), "body", "JSON must be UTF-8 (RFC 8259)"),
    (json.dumps({"spec": tiny_spec()}).encode("utf-32"), "body", "JSON must be UTF-8 (RFC 8259)"),
], ids=["nested-50000-deep", "utf-16", "utf-16-le", "utf-16-be", "utf-32"])
def test_bodies_that_are_not_json_in_utf8_are_422_naming_the_body(client, store, body, field, reason):
    p = one_problem(client.post("/v1/jobs", content=body, headers=JSON), field)
    assert reason in p["message"] and "not valid JSON" in p["message"], p
    assert job_count(store) == 0


def test_too_deep_a_body_says_where(client):
    p = one_problem(client.post("/v1/jobs", content=b'{"spec": ' + b"[" * 5000, headers=JSON), "body")
    assert "at character 107" in p["message"], p  # 9 characters, then the 100th bracket


def test_a_utf8_byte_order_mark_is_ignored(client):
    body = b"\xef\xbb\xbf" + json.dumps({"spec": tiny_spec()}).encode()
    assert client.post("/v1/jobs", content=body, headers=JSON).status_code == 201


@pytest.mark.parametrize("body", [
    b'{"spec": {"name": "x",, }}', b"\xff\xfe{", b'{"spec": ' + b"[" * 50_000,
    json.dumps({"spec": tiny_spec()}).encode("utf-16"), with_literal({"spec": tiny_spec(seed="N")}, "N", "9" * 5000),
], ids=["malformed", "not-utf8", "too-deep", "utf-16", "5000-digits"])
def test_a_bad_body_without_a_token_is_401_before_422(client, store, body):
    r = client.post("/v1/jobs", content=body, headers={"content-type": "application/json"})
    assert r.status_code == 401 and "bearer token" in r.json()["detail"], r.text
    r = client.post("/v1/jobs", content=body, headers={"content-type": "application/json",
                                                       "Authorization": "Bearer wrong"})
    assert r.status_code == 401, r.text
    assert job_count(store) == 0
