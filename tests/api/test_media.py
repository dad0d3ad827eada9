"""GET /v1/jobs/{id}/media and `bssrdf status --media`: progress per medium of a sweep."""

from __future__ import annotations

import pytest

from schema import parse_spec
from service.client import ApiClient, media_text
from service.worker import Worker
from tests.api.conftest import AUTH, tiny_spec

SWEEP = tiny_spec(name="tiny-sweep", sweep={"albedo": [0.3, 0.9], "g": [0.0, 0.5], "eta": [1.3]})
SWEEP.pop("medium")


@pytest.fixture
def sweep_client(make_client, store, storage):
    return make_client(store, storage)


def test_media_of_a_sweep_before_and_after_it_runs(sweep_client, store, storage):
    job = sweep_client.post("/v1/jobs", json={"spec": SWEEP}, headers=AUTH).json()
    spec = parse_spec(SWEEP)
    before = sweep_client.get(f"/v1/jobs/{job['id']}/media").json()
    assert before["media_total"] == 4 == len(before["items"]) and before["next_offset"] is None
    coords = [(m.albedo, m.g, m.eta) for m in spec.media()]
    assert [(tuple(m["albedo"]), tuple(m["g"]), m["eta"]) for m in before["items"]] == coords
    assert all(m["shards_total"] == 2 and m["shards_done"] == 0 and not m["merged"] for m in before["items"])
    assert all(m["photons_total"] == 200 for m in before["items"])  # photons x one angle x one channel

    page = sweep_client.get(f"/v1/jobs/{job['id']}/media", params={"limit": 3, "offset": 1}).json()
    assert [m["medium"] for m in page["items"]] == [1, 2, 3] and page["next_offset"] is None
    page = sweep_client.get(f"/v1/jobs/{job['id']}/media", params={"limit": 2}).json()
    assert [m["medium"] for m in page["items"]] == [0, 1] and page["next_offset"] == 2

    Worker(store, storage, once=True, poll_seconds=0.05).loop()
    assert store.get_job(job["id"]).state == "succeeded", store.get_job(job["id"]).error
    after = sweep_client.get(f"/v1/jobs/{job['id']}/media").json()["items"]
    assert all(m["merged"] and m["shards_done"] == 2 and m["shards_folded"] == 2 for m in after)
    assert [m["photons_done"] for m in after] == [200] * 4
    overall = sweep_client.get(f"/v1/jobs/{job['id']}").json()["progress"]
    assert sum(m["photons_done"] for m in after) == overall["photons_done"]

    client = ApiClient("http://testserver", http=sweep_client)
    text = media_text(client.media(job["id"])["items"])
    assert len(text.splitlines()) == 5 and text.count("merged") == 4 and "0.3" in text and "0.9" in text


@pytest.mark.parametrize("params", [{"limit": 0}, {"limit": 1001}, {"offset": -1}, {"offset": 2**31}])
def test_bad_pages_are_422(sweep_client, params):
    job = sweep_client.post("/v1/jobs", json={"spec": SWEEP}, headers=AUTH).json()
    r = sweep_client.get(f"/v1/jobs/{job['id']}/media", params=params)
    assert r.status_code == 422 and r.json()["detail"][0]["field"] in ("query.limit", "query.offset")


def test_a_single_medium_has_one_entry(sweep_client):
    job = sweep_client.post("/v1/jobs", json={"spec": tiny_spec(name="single")}, headers=AUTH).json()
    items = sweep_client.get(f"/v1/jobs/{job['id']}/media").json()["items"]
    assert len(items) == 1 and items[0]["albedo"] == [0.5] and items[0]["eta"] == 1.3
    assert sweep_client.get("/v1/jobs/00000000-0000-0000-0000-000000000000/media").status_code == 404


def test_media_of_a_sweep_with_shared_walks(sweep_client, store, storage):
    """Two walk groups of two albedos each (tasks = groups x shards): every medium is listed with
    its group's shards, and the job's progress counts media."""
    shared = dict(SWEEP, sweep={"albedo": [0.8, 0.9], "g": [0.0, 0.5], "eta": [1.3], "walks": "shared"})
    spec = parse_spec(shared)
    assert spec.walk_groups() == [(0, 1), (2, 3)]
    job = sweep_client.post("/v1/jobs", json={"spec": shared}, headers=AUTH).json()
    page = sweep_client.get(f"/v1/jobs/{job['id']}/media", params={"limit": 2, "offset": 1}).json()
    assert [m["medium"] for m in page["items"]] == [1, 2] and all(m["shards_total"] == 2 for m in page["items"])
    Worker(store, storage, once=True, poll_seconds=0.05).loop()
    assert store.get_job(job["id"]).state == "succeeded", store.get_job(job["id"]).error
    after = sweep_client.get(f"/v1/jobs/{job['id']}/media").json()
    assert after["media_total"] == 4
    assert all(m["merged"] and m["shards_done"] == 2 and m["shards_folded"] == 2 for m in after["items"])
    progress = store.progress(job["id"])
    assert (progress.media_total, progress.media_merged, progress.shards_total) == (4, 4, 4)
