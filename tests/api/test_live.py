"""A real `bssrdf serve` (uvicorn) process and real `bssrdf worker --once` processes: a tiny job
runs to completion through the HTTP API, then the client commands run as `bssrdf` processes against
the same server (each costs a few seconds of imports: the in-process client tests in
tests/api/test_client.py cover the rest of their behaviour)."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
from pathlib import Path

import httpx
import pytest

from tests.api.conftest import TINY_SPEC, tiny_spec
from tests.support.net import free_port
from tests.support.waiting import wait_for

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
TOKEN = "live-test-token"
POLL = 0.2  # seconds between polls of the server (each one an HTTP request)


@pytest.fixture
def live(tmp_path):
    """(base URL, env, db URL, storage dir) of a running `bssrdf serve` on a free loopback port."""
    port = free_port()
    db, storage = f"sqlite:///{tmp_path / 'jobs.sqlite'}", str(tmp_path / "data")
    env = {**os.environ, "PYTHONPATH": str(REPO), "BSSRDF_COMPILE": "0", "OMP_NUM_THREADS": "1",
           "BSSRDF_API_TOKENS": json.dumps([TOKEN]), "BSSRDF_DATA_DIR": str(tmp_path / "unused")}
    env.pop("BSSRDF_TOKEN", None)
    log = open(tmp_path / "serve.log", "wb")
    server = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "serve", "--host", "127.0.0.1", "--port", str(port), "--db", db,
         "--storage", storage, "--log-level", "warning"],
        cwd=tmp_path, env=env, stdout=log, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
    )
    base = f"http://127.0.0.1:{port}"

    def up():
        if server.poll() is not None:
            raise AssertionError(f"bssrdf serve exited: {(tmp_path / 'serve.log').read_text()}")
        try:
            return httpx.get(f"{base}/readyz", timeout=2).status_code == 200
        except httpx.TransportError:
            return False

    try:
        wait_for(up, 30, "bssrdf serve to be ready", poll=POLL)
        yield base, env, db, storage
    finally:
        server.send_signal(signal.SIGTERM)
        try:
            server.wait(15)
        except subprocess.TimeoutExpired:
            server.kill()
            server.wait()
        log.close()


def start_worker(env, db, storage, log: Path) -> subprocess.Popen:
    with open(log, "ab") as out:
        return subprocess.Popen(
            [sys.executable, "-m", "service.cli", "worker", "--db", db, "--storage", storage, "--once",
             "--poll-seconds", "0.1", "--lease-seconds", "30"],
            cwd=log.parent, env=env, stdout=out, stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL,
        )


def bssrdf(args: list[str], env, cwd, timeout: float = 60) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-m", "service.cli", *args], cwd=cwd, env=env, capture_output=True,
                          text=True, timeout=timeout)


def test_a_job_through_the_http_api_and_the_client_commands(live, tmp_path):
    base, env, db, storage = live
    auth = {"Authorization": f"Bearer {TOKEN}"}
    api = httpx.Client(base_url=base, timeout=10)

    # 1. submit over HTTP, run it with one `bssrdf worker --once`, follow it to the end
    r = api.post("/v1/jobs", json={"spec": TINY_SPEC}, headers={**auth, "Idempotency-Key": "live-1"})
    assert r.status_code == 201, r.text
    job_id = r.json()["id"]
    assert api.post("/v1/jobs", json={"spec": TINY_SPEC}, headers={**auth, "Idempotency-Key": "live-1"}).status_code == 200
    worker = start_worker(env, db, storage, tmp_path / "worker-1.log")
    try:
        job = wait_for(lambda: (j := api.get(f"/v1/jobs/{job_id}").json())["state"] in ("succeeded", "failed") and j,
                       60, "the job to end", poll=POLL)
        assert worker.wait(30) == 0
    finally:
        if worker.poll() is None:
            worker.kill()
    assert job["state"] == "succeeded", (job, (tmp_path / "worker-1.log").read_text()[-2000:])
    p = job["progress"]
    assert p["shards_done"] == p["shards_total"] == 2 and p["photons_done"] == 200 and p["eta_s"] == 0
    assert (job["dataset_name"], job["dataset_version"]) == ("tiny", 1)
    summary = api.get("/v1/datasets/tiny/versions/1/files/summary.json")
    assert summary.status_code == 200 and summary.json()["name"] == "tiny"
    metrics = api.get("/metrics").text
    assert 'bssrdf_jobs{state="succeeded"} 1' in metrics and "bssrdf_photons_simulated_total 200" in metrics

    # 2. the client commands against the live server
    cli_env = {**env, "BSSRDF_API": base}
    status = bssrdf(["status", job_id], cli_env, tmp_path)
    assert status.returncode == 0, status.stderr
    assert "succeeded" in status.stdout and "shards 2/2" in status.stdout and "dataset tiny version 1" in status.stdout

    spec_file = tmp_path / "spec.json"
    spec_file.write_text(json.dumps(tiny_spec(seed=11)))
    submit = subprocess.Popen(
        [sys.executable, "-m", "service.cli", "submit", str(spec_file), "--api", base, "--token", TOKEN, "--wait",
         "--poll", "0.2", "--timeout", "60"],
        cwd=tmp_path, env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )
    try:
        wait_for(lambda: len(api.get("/v1/jobs").json()["items"]) == 2 or submit.poll() is not None, 30,
                 "the CLI submission", poll=POLL)
        worker = start_worker(env, db, storage, tmp_path / "worker-2.log")
        out, err = submit.communicate(timeout=75)
        assert worker.wait(30) == 0
    finally:
        for proc in (submit, worker):
            if proc.poll() is None:
                proc.kill()
    assert submit.returncode == 0, err
    assert out.startswith("tiny  (spec ") and "single" in out  # simulate's summary table
    assert "dataset tiny version 2" in out
    assert "shards 2/2" in err  # the progress display (plain lines off a terminal)

    listing = bssrdf(["datasets"], cli_env, tmp_path)
    assert listing.returncode == 0 and "tiny" in listing.stdout
    latest = bssrdf(["datasets", "tiny", "latest"], cli_env, tmp_path)
    assert latest.returncode == 0 and "dataset tiny version 2" in latest.stdout and "radial.parquet" in latest.stdout

    # 3. errors are readable, exit status non-zero, nothing stored
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps(tiny_spec(medium={"sigma_a": -1.0, "sigma_s": 1.0, "g": 1.0, "eta": 1.3})))
    refused = bssrdf(["submit", str(bad), "--token", TOKEN], cli_env, tmp_path)
    assert refused.returncode == 2
    assert "HTTP 422" in refused.stderr and "spec.medium.sigma_a" in refused.stderr and "[0, 1e6]" in refused.stderr
    assert "spec.medium.g" in refused.stderr and "[-0.999, 0.999]" in refused.stderr and "received 1.0" in refused.stderr
    assert len(api.get("/v1/jobs").json()["items"]) == 2
    api.close()

