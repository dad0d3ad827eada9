"""The worker loop and ``bssrdf run`` with the real engine on SQLite."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
from pathlib import Path

import pytest

from service.datasets import DatasetStorage
from service.store import JobState, JobStore
from tests.service.test_end_to_end import REPO, claimed_shard, tiny_spec
from tests.support.engine import ENGINE_ENV
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.usefixtures("engine_env")]


@pytest.fixture
def sqlite_url(tmp_path):
    return f"sqlite:///{tmp_path / 'jobs.sqlite'}"


def test_lost_lease_discards_the_shard(sqlite_url, tmp_path):
    from service.worker import Worker

    store = JobStore(sqlite_url)
    job = store.submit(tiny_spec("lost", photons=200, shards=1))
    worker = Worker(store, DatasetStorage(str(tmp_path / "data")), lease_seconds=30, heartbeat_seconds=0.05)
    lease = worker.claim()
    threading.Timer(0.3, store.cancel, args=(job.id,)).start()  # the heartbeat then finds the lease lost
    worker.process(lease)
    assert store.shard_files(job.id) == []
    assert store.get_job(job.id).state == JobState.CANCELLED


def test_sigterm_mid_shard_releases_the_lease_and_exits_cleanly(sqlite_url, tmp_path):
    store = JobStore(sqlite_url)
    job = store.submit(tiny_spec("term", photons=400, shards=1))
    log = tmp_path / "worker.log"
    env = {**os.environ, **ENGINE_ENV, "PYTHONPATH": str(REPO)}
    with open(log, "wb") as out:
        proc = subprocess.Popen(
            [sys.executable, "-m", "service.worker", "--db", sqlite_url, "--storage", str(tmp_path / "data"),
             "--heartbeat-seconds", "0.2"], cwd=REPO, env=env, stdout=out, stderr=subprocess.STDOUT,
        )
    try:
        wait_for(lambda: claimed_shard(log), 60, "the shard claim", poll=0.02)
        proc.send_signal(signal.SIGTERM)
        assert proc.wait(30) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
    records = [json.loads(line) for line in log.read_text().splitlines()]  # JSON lines off a terminal
    msgs = [r["msg"] for r in records]
    if "shard done" not in msgs:  # stopped mid-shard: the lease is back in the queue, not an attempt
        assert "shard abandoned: stopping; lease released" in msgs
        again = store.claim("next", 30)
        assert again is not None and again.attempts == 1
    assert msgs[-1] == "worker stopped"
    assert store.get_job(job.id).state != JobState.FAILED


def test_bssrdf_run_publishes_versions_with_the_simulate_summary(tmp_path):
    spec_path = tmp_path / "tiny.json"
    spec = tiny_spec("runme", photons=60, shards=2)
    spec_path.write_text(spec.canonical_json())
    env = {**os.environ, **ENGINE_ENV, "PYTHONPATH": str(REPO)}
    cmd = [sys.executable, "-m", "service.runner", str(spec_path), "--workers", "2", "--data-dir",
           str(tmp_path / "d"), "--json"]
    first = json.loads(subprocess.run(cmd, cwd=REPO, env=env, capture_output=True, text=True, check=True,
                                      timeout=150).stdout)
    assert first["state"] == "succeeded" and (first["dataset"], first["version"]) == ("runme", 1)
    assert first["name"] == "runme" and first["results"] and first["run"]["shards"] == 2  # simulate's JSON
    # the second run of the same spec and seed prints the published version and publishes none
    again = subprocess.run(cmd[:-1], cwd=REPO, env=env, capture_output=True, text=True, check=True, timeout=150)
    assert "dataset runme version 1" in again.stdout and "Rd = diffuse reflectance" in again.stdout
    assert "existing version: same spec and seed, nothing recomputed" in again.stdout
    store = JobStore(f"sqlite:///{tmp_path / 'd' / 'jobs.sqlite'}")
    assert [v.version for v in store.list_versions("runme")] == [1] and len(store.list_jobs()) == 1
    forced = subprocess.run(cmd[:-1] + ["--force"], cwd=REPO, env=env, capture_output=True, text=True, check=True,
                            timeout=150)
    assert "dataset runme version 2" in forced.stdout
    assert [v.version for v in store.list_versions("runme")] == [1, 2]
    # same spec and seed: the same tables in both versions
    a, b = (Path(v.uri) for v in store.list_versions("runme"))
    assert (a / "radial.parquet").read_bytes() == (b / "radial.parquet").read_bytes()
    assert store.list_jobs(state=JobState.SUCCEEDED)[0].dataset_version == 2
