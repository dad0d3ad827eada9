"""No duplicate work, deletion, and progress inside a shard, on SQLite and PostgreSQL.

- a spec whose hash (seed included) matches a live job or a published version returns it (200,
  ``existing``); ``force`` runs it again; two identical submissions at once make one job;
- DELETE of a job (cancels it, removes its tasks, shard results and job files) and of a version
  (files removed, tombstone with the spec hash and the deleter's token fingerprint, 410 after);
- progress: heartbeat photons give rate and ETA before any shard ends; a lease without
  heartbeats for half its length is reported stalled, not running.
"""

from __future__ import annotations

import hashlib
import threading
import time

import pytest

from schema import parse_spec
from service.store import JobNotFound, JobState, LeaseLost
from service.worker import Worker
from tests.api.conftest import AUTH, TINY_SPEC, TOKEN, tiny_spec
from tests.support.files import stored


def run_all(store, storage) -> None:
    Worker(store, storage, once=True, poll_seconds=0.05).loop()


def test_a_duplicate_returns_the_live_job_then_the_published_version(client, store, storage):
    first = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH)
    assert first.status_code == 201 and first.json()["existing"] is None
    again = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH)
    assert again.status_code == 200 and again.json()["id"] == first.json()["id"] and again.json()["existing"] == "job"
    other_seed = client.post("/v1/jobs", json={"spec": tiny_spec(seed=8)}, headers=AUTH)
    assert other_seed.status_code == 201  # the seed is part of the hash
    run_all(store, storage)
    published = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH)
    body = published.json()
    assert published.status_code == 200 and body["existing"] == "version" and body["state"] == "succeeded"
    assert body["id"] == first.json()["id"] and (body["dataset_name"], body["dataset_version"]) == ("tiny", 1)
    assert len(store.list_jobs()) == 2 and [v.version for v in store.list_versions("tiny")] == [1, 2]
    forced = client.post("/v1/jobs", json={"spec": TINY_SPEC, "force": True}, headers=AUTH)
    assert forced.status_code == 201 and forced.json()["id"] not in (first.json()["id"],)
    assert client.post("/v1/jobs", json={"spec": TINY_SPEC, "force": "yes"}, headers=AUTH).status_code == 422


def test_identical_submissions_at_once_make_one_job(store):
    spec = parse_spec(TINY_SPEC)
    results, barrier = [], threading.Barrier(6)

    def submit():
        barrier.wait()
        results.append(store.submit_unique(spec))

    threads = [threading.Thread(target=submit) for _ in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    assert len({r.job.id for r in results}) == 1 and len(store.list_jobs()) == 1
    assert sorted(str(r.existing) for r in results) == ["None"] + ["job"] * 5


def test_delete_a_version_leaves_a_tombstone_and_410(client, store, storage):
    client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH)
    run_all(store, storage)
    record = store.get_version("tiny", 1)
    assert client.delete("/v1/datasets/tiny/versions/1").status_code == 401  # writes need a token
    assert client.delete("/v1/datasets/tiny/versions/latest", headers=AUTH).status_code == 422
    assert client.delete("/v1/datasets/tiny/versions/7", headers=AUTH).status_code == 404
    r = client.delete("/v1/datasets/tiny/versions/1", headers=AUTH)
    fingerprint = "token sha256:" + hashlib.sha256(TOKEN.encode()).hexdigest()[:12]
    assert r.status_code == 200 and r.json()["deleted_by"] == fingerprint and r.json()["files"] == {}
    assert r.json()["spec_hash"] == parse_spec(TINY_SPEC).spec_hash()
    assert not storage.fs.get_file_info(record.uri).type.name == "Directory"  # files gone
    gone = client.get("/v1/datasets/tiny/versions/1")
    assert gone.status_code == 410 and fingerprint in gone.json()["detail"]
    assert client.get("/v1/datasets/tiny/versions/1/files/radial.parquet").status_code == 410
    assert client.get("/v1/datasets/tiny/versions/latest").status_code == 404  # no live version left
    assert client.get("/v1/datasets").json() == []
    listed = client.get("/v1/datasets/tiny/versions", params={"deleted": "true"}).json()
    assert [(v["version"], v["deleted_by"]) for v in listed] == [(1, fingerprint)]
    assert client.delete("/v1/datasets/tiny/versions/1", headers=AUTH).status_code == 200  # idempotent
    # the spec is no longer published: it runs again, as version 2 (numbers are never reused)
    again = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH)
    assert again.status_code == 201
    run_all(store, storage)
    assert store.get_version("tiny").version == 2


def test_delete_a_job(client, store, storage):
    live = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH).json()
    lease = store.claim("w", 60)
    job_dir = storage.job_path(live["id"])
    storage.fs.create_dir(job_dir)
    assert client.delete(f"/v1/jobs/{live['id']}").status_code == 401
    r = client.delete(f"/v1/jobs/{live['id']}", headers=AUTH)
    assert r.status_code == 200 and r.json()["state"] == "cancelled"
    assert client.get(f"/v1/jobs/{live['id']}").status_code == 404
    assert storage.fs.get_file_info(job_dir).type.name == "NotFound"
    assert store.heartbeat(lease, 60) is False  # the worker loses its lease
    with pytest.raises((LeaseLost, JobNotFound)):
        store.complete_shard(lease, stored(b"late"), photons=1, elapsed_s=0.1)
    assert store.claim("w", 60) is None
    # a job whose version is published is its provenance: 409 until the version is deleted
    done = client.post("/v1/jobs", json={"spec": TINY_SPEC}, headers=AUTH).json()
    run_all(store, storage)
    r = client.delete(f"/v1/jobs/{done['id']}", headers=AUTH)
    assert r.status_code == 409 and "DELETE /v1/datasets/tiny/versions/1" in r.json()["detail"]
    client.delete("/v1/datasets/tiny/versions/1", headers=AUTH)
    assert client.delete(f"/v1/jobs/{done['id']}", headers=AUTH).status_code == 200
    tomb = store.list_versions("tiny", deleted=True)[0]
    assert tomb.job_id is None and tomb.spec_hash == parse_spec(TINY_SPEC).spec_hash()


def test_worker_of_a_deleted_job_keeps_running_other_work(store, storage):
    doomed = store.submit(parse_spec(TINY_SPEC))
    lease = store.claim("w", 60)
    store.delete_job(doomed.id)
    kept = store.submit(parse_spec(tiny_spec(seed=11)))
    worker = Worker(store, storage, once=True, poll_seconds=0.05)
    worker.process(lease)  # the shard runs, its commit is refused, nothing raises
    worker.loop()
    assert store.get_job(kept.id).state == JobState.SUCCEEDED


def test_progress_has_rate_and_eta_before_any_shard_ends(client, store):
    spec = parse_spec(tiny_spec(photons=1000, incidence_deg=[0, 30]))
    job = store.submit(spec)
    assert store.get_job(job.id).photons_total == 2000
    lease = store.claim("w", 60)
    time.sleep(0.05)
    assert store.heartbeat(lease, 60, photons=300)
    p = client.get(f"/v1/jobs/{job.id}").json()["progress"]
    assert p["shards_done"] == 0 and p["photons_done"] == 300 and p["photons_total"] == 2000
    assert p["rate_photons_per_s"] > 0
    assert p["eta_s"] == pytest.approx((2000 - 300) / p["rate_photons_per_s"], rel=0.05)


def test_a_lease_without_heartbeats_is_stalled_not_running(store):
    job = store.submit(parse_spec(TINY_SPEC))
    store.claim("dead-worker", 2.0)
    p = store.progress(job.id)
    assert (p.shards_running, p.shards_stalled) == (1, 0)
    time.sleep(1.2)  # more than half the lease without a heartbeat: two heartbeat periods missed
    p = store.progress(job.id)
    assert (p.shards_running, p.shards_stalled, p.shards_queued) == (0, 1, 1)
    time.sleep(1.0)  # expired: claimable again, counted as queued
    p = store.progress(job.id)
    assert (p.shards_running, p.shards_stalled, p.shards_queued) == (0, 0, 2)
