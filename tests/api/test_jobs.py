"""POST/GET /v1/jobs and cancel, on SQLite and PostgreSQL: validation, idempotency, progress."""

from __future__ import annotations

import pytest

from schema import parse_spec
from service.store import JobStore

from tests.api.conftest import AUTH, TINY_SPEC, job_count, tiny_spec


def medium(**changes) -> dict:
    return dict(TINY_SPEC["medium"], **changes)


# (spec, field, allowed, received): each spec has exactly one problem.
BAD_SPECS = [
    pytest.param(tiny_spec(medium=medium(sigma_a=-0.5)), "spec.medium.sigma_a", "[0, 1e6]", -0.5, id="negative-sigma_a"),
    pytest.param(tiny_spec(medium=medium(sigma_s=[1.0, -2.0])), "spec.medium.sigma_s", "[0, 1e6]", None,
                 id="negative-sigma_s-entry"),
    pytest.param(tiny_spec(medium=medium(g=1.0)), "spec.medium.g", "[-0.999, 0.999]", 1.0, id="g-is-1"),
    pytest.param(tiny_spec(medium=medium(g=-1.5)), "spec.medium.g", "[-0.999, 0.999]", -1.5, id="g-below-minus-1"),
    pytest.param(tiny_spec(medium=medium(eta=0.0)), "spec.medium.eta", "[0.25, 4]", 0.0, id="eta-zero"),
    pytest.param(tiny_spec(medium=medium(eta=-1.3)), "spec.medium.eta", "[0.25, 4]", -1.3, id="eta-negative"),
    pytest.param(tiny_spec(photon=5), "spec.photon", None, 5, id="unknown-key"),
    pytest.param(tiny_spec(medium=medium(colour="red")), "spec.medium.colour", None, "red", id="unknown-medium-key"),
    pytest.param(tiny_spec(medium=medium(sigma_a=[1.0, 2.0], sigma_s=[1.0, 2.0, 3.0])), "spec.medium", None, None,
                 id="mismatched-channels"),
    pytest.param(tiny_spec(photons=2**41), "spec.photons", "[1, 2**40]", 2**41, id="photons-over-limit"),
    pytest.param(tiny_spec(photons=0), "spec.photons", "[1, 2**40]", 0, id="photons-zero"),
    pytest.param(tiny_spec(bins={"radial": {"count": 0}}), "spec.bins.radial.count", "[1, 4096]", 0,
                 id="radial-bins-zero"),
    pytest.param(tiny_spec(bins={"radial": {"count": 10**6}}), "spec.bins.radial.count", "[1, 4096]", 10**6,
                 id="radial-bins-too-many"),
    pytest.param(tiny_spec(estimator="guess"), "spec.estimator", "'hybrid', 'exits', 'connections' or 'both'", "guess",
                 id="bad-estimator"),
]


@pytest.mark.parametrize("spec, field, allowed, received", BAD_SPECS)
def test_invalid_spec_is_422_naming_field_range_and_value_and_stores_nothing(client, store, spec, field, allowed,
                                                                              received):
    before = job_count(store)
    r = client.post("/v1/jobs", json={"spec": spec}, headers=AUTH)
    assert r.status_code == 422, r.text
    problems = r.json()["detail"]
    mine = [p for p in problems if p["field"] == field or p["field"].startswith(field + ".")]
    assert mine, f"no problem names {field}: {problems}"
    p = mine[0]
    assert p["message"] and "received" in p["message"] or "unknown key" in p["message"], p
    if allowed is not None:
        assert p["allowed"] == allowed and allowed in p["message"], p
    if received is not None:
        assert p["received"] == received, p
    assert job_count(store) == before == 0
    assert sum(store.metrics()["jobs_by_state"].values()) == 0


def test_every_bad_field_is_named_at_once(client, store):
    spec = tiny_spec(medium=medium(sigma_a=-1.0, g=2.0, eta=0.0), photons=-3, typo=1)
    r = client.post("/v1/jobs", json={"spec": spec}, headers=AUTH)
    assert r.status_code == 422
    fields = {p["field"] for p in r.json()["detail"]}
    assert {"spec.medium.sigma_a", "spec.medium.g", "spec.medium.eta", "spec.photons", "spec.typo"} <= fields
    assert job_count(store) == 0


@pytest.mark.parametrize("body, field", [
    ({}, "spec"),
    ({"spec": TINY_SPEC, "idempotency_key": ""}, "idempotency_key"),
    ({"spec": TINY_SPEC, "extra": 1}, "extra"),
    ({"spec": "not an object"}, "spec"),
])
def test_malformed_bodies_are_422(client, store, body, field):
    r = client.post("/v1/jobs", json=body, headers=AUTH)
    assert r.status_code == 422
    assert field in {p["field"] for p in r.json()["detail"]}, r.json()
    assert job_count(store) == 0


def test_submit_returns_201_with_the_job_and_its_progress(client, store):
    r = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH)
    assert r.status_code == 201, r.text
    job = r.json()
    assert r.headers["location"] == f"/v1/jobs/{job['id']}"
    assert job["state"] == "queued" and job["name"] == "tiny" and job["shards"] == 2
    assert job["spec"]["medium"]["sigma_a"] == [1.0]  # stored fully defaulted
    assert job["progress"]["shards_total"] == 2 and job["progress"]["shards_queued"] == 2
    assert store.get_job(job["id"]).spec_hash  # really stored
    assert job_count(store) == 1


def test_idempotency_key_same_spec_200_other_spec_409(client, store):
    first = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers={**AUTH, "Idempotency-Key": "k-1"})
    assert first.status_code == 201
    again = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers={**AUTH, "Idempotency-Key": "k-1"})
    assert again.status_code == 200 and again.json()["id"] == first.json()["id"]
    by_body = client.post("/v1/jobs", json={"spec": TINY_SPEC, "idempotency_key": "k-1"}, headers=AUTH)
    assert by_body.status_code == 200 and by_body.json()["id"] == first.json()["id"]
    other = client.post("/v1/jobs", json={"spec": tiny_spec(seed=99)}, headers={**AUTH, "Idempotency-Key": "k-1"})
    assert other.status_code == 409
    assert "k-1" in other.json()["detail"] and "use a new key" in other.json()["detail"]
    assert job_count(store) == 1
    unkeyed = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH)  # same spec hash: that live job
    assert unkeyed.status_code == 200 and unkeyed.json()["id"] == first.json()["id"]
    assert unkeyed.json()["existing"] == "job" and again.json()["existing"] == "idempotency_key"
    forced = client.post("/v1/jobs", json={"spec": TINY_SPEC, "force": True}, headers=AUTH)
    assert forced.status_code == 201 and forced.json()["id"] != first.json()["id"] and forced.json()["existing"] is None


def test_a_key_answered_by_the_duplicate_check_is_kept(client, store):
    """A key whose submission returned an existing job (same spec hash) names that job from then
    on: the same key with another spec is 409, not a new job; the key then survives no job."""
    first = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers={**AUTH, "Idempotency-Key": "k-first"})
    for key in ("k-dup", "k-dup"):
        dup = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers={**AUTH, "Idempotency-Key": key})
        assert dup.status_code == 200 and dup.json()["id"] == first.json()["id"], dup.text
    assert dup.json()["existing"] == "idempotency_key"  # the second time: the key itself names it
    other = client.post("/v1/jobs", json={"spec": tiny_spec(seed=99)}, headers={**AUTH, "Idempotency-Key": "k-dup"})
    assert other.status_code == 409 and "'k-dup'" in other.json()["detail"] and "use a new key" in other.json()["detail"]
    assert job_count(store) == 1
    assert client.delete(f"/v1/jobs/{first.json()['id']}", headers=AUTH).status_code == 200
    again = client.post("/v1/jobs", json={"spec": tiny_spec(seed=99)}, headers={**AUTH, "Idempotency-Key": "k-dup"})
    assert again.status_code == 201, again.text  # the job it named is gone, and its keys with it


def test_idempotency_header_and_body_must_agree(client, store):
    r = client.post("/v1/jobs", json={"spec": TINY_SPEC, "idempotency_key": "a"},
                    headers={**AUTH, "Idempotency-Key": "b"})
    assert r.status_code == 422
    assert r.json()["detail"][0]["field"] == "header.Idempotency-Key"
    assert job_count(store) == 0


def test_get_job_reports_progress_and_404(client, store):
    job_id = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH).json()["id"]
    lease = store.claim("w1", 60)
    store.heartbeat(lease, 60, photons=50)
    r = client.get(f"/v1/jobs/{job_id}")
    assert r.status_code == 200
    job = r.json()
    assert job["state"] == "running"
    p = job["progress"]
    assert (p["shards_running"], p["shards_queued"], p["shards_done"], p["shards_failed"]) == (1, 1, 0, 0)
    assert p["photons_done"] == 50 and p["merge_state"] == "waiting"
    assert set(p) >= {"rate_photons_per_s", "eta_s", "elapsed_s"}
    assert job["error"] is None and job["dataset_name"] is None and job["dataset_version"] is None
    missing = client.get("/v1/jobs/no-such-job")
    assert missing.status_code == 404 and "no-such-job" in missing.json()["detail"]


def test_list_jobs_filters_and_pages(client, store):
    ids = [client.post("/v1/jobs", json={"spec": tiny_spec(seed=s)}, headers=AUTH).json()["id"] for s in range(3)]
    assert client.post(f"/v1/jobs/{ids[0]}/cancel", headers=AUTH).status_code == 200
    everything = client.get("/v1/jobs").json()
    assert {j["id"] for j in everything["items"]} == set(ids) and everything["next_offset"] is None
    assert all(j["progress"] is None for j in everything["items"])
    cancelled = client.get("/v1/jobs", params={"state": "cancelled"}).json()["items"]
    assert [j["id"] for j in cancelled] == [ids[0]]
    assert len(client.get("/v1/jobs", params={"state": "queued"}).json()["items"]) == 2
    page1 = client.get("/v1/jobs", params={"limit": 2}).json()
    page2 = client.get("/v1/jobs", params={"limit": 2, "offset": page1["next_offset"]}).json()
    assert len(page1["items"]) == 2 and page1["next_offset"] == 2
    assert len(page2["items"]) == 1 and page2["next_offset"] is None
    assert {j["id"] for j in page1["items"] + page2["items"]} == set(ids)
    bad = client.get("/v1/jobs", params={"state": "sleeping", "limit": 5000})
    assert bad.status_code == 422
    by_field = {p["field"]: p for p in bad.json()["detail"]}
    assert "queued" in by_field["query.state"]["allowed"] and by_field["query.state"]["received"] == "sleeping"
    assert by_field["query.limit"]["allowed"] == "<= 1000"


def test_cancel_404_200_idempotent_and_409_when_finished(client, store):
    assert client.post("/v1/jobs/nope/cancel", headers=AUTH).status_code == 404
    job_id = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH).json()["id"]
    r = client.post(f"/v1/jobs/{job_id}/cancel", headers=AUTH)
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    progress = r.json()["progress"]
    assert (progress["shards_cancelled"], progress["shards_failed"]) == (2, 0)  # its tasks are cancelled, not failed
    assert progress["eta_s"] is None  # it will not finish
    assert client.post(f"/v1/jobs/{job_id}/cancel", headers=AUTH).json()["state"] == "cancelled"
    assert store.claim("w", 60) is None  # no claims after cancel

    once = JobStore(store.url, max_attempts=1, migrate=False)  # its tasks fail on the first error
    done_id = once.submit(parse_spec(tiny_spec(shards=1, batches_per_shard=2))).id
    once.fail_task(once.claim("w", 60), "boom")
    once.dispose()
    assert store.get_job(done_id).state == "failed"
    r = client.post(f"/v1/jobs/{done_id}/cancel", headers=AUTH)
    assert r.status_code == 409 and "failed" in r.json()["detail"]
    assert client.get(f"/v1/jobs/{done_id}").json()["error"]
