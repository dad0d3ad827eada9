"""The service across hosts: network namespaces joined by veth pairs (tests/support/netns.py), a
PostgreSQL server of the test's own on host ``db`` (tests/support/pgserver.py), ``bssrdf serve``
on ``api``, one ``bssrdf worker`` on each of ``w1`` and ``w2``, and a client on ``client`` that
submits over HTTP (tests/support/netns_client.py). Storage is a directory every host sees, as a
shared filesystem would be.

1. A job submitted over HTTP succeeds; its tables are byte-identical to `bssrdf simulate` of the
   same spec.
2. A second job under faults: ``w1``'s link is cut while it walks a shard (its lease expires and
   ``w2`` redoes the shard; ``w1``'s late result, once its link is back, is refused), PostgreSQL
   is restarted (fast shutdown) mid-job, and the API is killed (SIGKILL) and started again while
   the client follows the job. The job still succeeds with bytes identical to `bssrdf simulate`,
   nothing is counted twice, and both workers are still running.

Skipped, with the reason, only where namespaces cannot be made (not root, no iproute2) or there
is no PostgreSQL server to run; CI runs as root. Budget: about 60-90 s on two cores (150 s when
the machine is busy).
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import pytest

from tests.support.netns import Network, netns_unavailable
from tests.support.pgserver import PgServer, pg_unavailable
from tests.support.waiting import wait_for

pytestmark = pytest.mark.slow

REPO = Path(__file__).resolve().parents[2]
TOKEN = "multihost-token"
TABLES = ("radial.parquet", "bins.parquet", "summary.parquet")
HOSTS = ["db", "api", "w1", "w2", "client"]
LEASE_S = 4.0
ENV = {**os.environ, "PYTHONPATH": str(REPO), "BSSRDF_COMPILE": "0", "OMP_NUM_THREADS": "1",
       "BSSRDF_API_TOKENS": json.dumps([TOKEN])}


PHOTONS_PER_SHARD = 10_000


def spec(name: str, seed: int, shards: int) -> dict:
    """One channel of albedo 0.9, 10,000 photons per shard, paths capped at 200 events: 0.2-0.3 s
    per shard on the eager walk once warm on an AVX-512 machine (2,000 photons took 0.12 s there,
    close to the time the test takes to see a claim and cut the link), so the cut lands mid-shard."""
    return {"name": name, "medium": {"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.5, "eta": 1.3},
            "photons": PHOTONS_PER_SHARD * shards,
            "shards": shards, "batches_per_shard": 1, "seed": seed, "estimator": "exits", "max_scatter": 200,
            "bins": {"radial": {"count": 8, "max_mfp": 16.0, "spacing": "log"}, "cos_theta_o": {"count": 2},
                     "phi_o": {"count": 2}}}


class Cluster:
    """The hosts, the database, and the service processes started on them."""

    def __init__(self, net: Network, pg: PgServer, root: Path) -> None:
        self.net, self.pg, self.root = net, pg, root
        self.storage = str(root / "data")
        self.base = f"http://{net.address('api')}:8000"
        self.api: subprocess.Popen | None = None
        self.workers: dict[str, subprocess.Popen] = {}

    def start_api(self) -> None:
        self.api = self.net.popen("api", [sys.executable, "-m", "service.cli", "serve", "--host",
                                          self.net.address("api"), "--port", "8000", "--db", self.pg.url,
                                          "--storage", self.storage, "--log-level", "warning"],
                                  self.root / "api.log", env=ENV, cwd=REPO)

    def start_worker(self, host: str) -> None:
        self.workers[host] = self.net.popen(
            host, [sys.executable, "-m", "service.cli", "worker", "--db", self.pg.url, "--storage", self.storage,
                   "--lease-seconds", str(LEASE_S), "--heartbeat-seconds", "1", "--poll-seconds", "0.2",
                   "--max-poll-seconds", "0.2",  # no idle backoff: both workers take part in each job
                   "--worker-id", host], self.root / f"{host}.log", env=ENV, cwd=REPO)

    def log(self, host: str) -> list[dict]:
        path = self.root / f"{host}.log"
        lines = path.read_text().splitlines() if path.exists() else []
        return [json.loads(line) for line in lines if line.startswith("{")]

    def events(self, host: str, msg: str, job: str | None = None) -> list[dict]:
        return [e for e in self.log(host) if e.get("msg") == msg and (job is None or e.get("job") == job)]

    def client(self, name: str, data: dict, timeout: float) -> tuple[subprocess.Popen, Path]:
        spec_file, out = self.root / f"{name}.json", self.root / f"{name}-out"
        spec_file.write_text(json.dumps(data))
        proc = self.net.popen("client", [sys.executable, "-m", "tests.support.netns_client", self.base, TOKEN,
                                         str(spec_file), str(out), str(timeout)],
                              self.root / f"client-{name}.log", env=ENV, cwd=REPO)
        return proc, out


def simulate(data: dict, out: Path) -> subprocess.Popen:
    """`bssrdf simulate` of the same spec on this machine (the reference bytes), in the background."""
    out.mkdir(parents=True)
    (out / "spec.json").write_text(json.dumps(data))
    return subprocess.Popen([sys.executable, "-m", "service.cli", "simulate", str(out / "spec.json"), "--out",
                             str(out / "tables"), "--no-progress", "--workers", "1"],
                            env=ENV, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def finished(proc: subprocess.Popen, out: Path, what: str, timeout: float) -> dict:
    try:
        proc.wait(timeout)
    except subprocess.TimeoutExpired:
        raise AssertionError(f"{what} did not finish in {timeout} s") from None
    assert proc.returncode == 0, f"{what} exited {proc.returncode}"
    return json.loads((out / "result.json").read_text())


def assert_same_tables(served: Path, reference: subprocess.Popen, ref_dir: Path) -> None:
    assert reference.wait(120) == 0, reference.stderr.read().decode()[-2000:]
    for name in TABLES:
        assert (served / name).read_bytes() == (ref_dir / "tables" / name).read_bytes(), name


def metric(text: str, name: str) -> int:
    return int(next(line.split()[-1] for line in text.splitlines() if line.startswith(name + " ")))


@pytest.fixture
def cluster(tmp_path):
    reason = netns_unavailable() or pg_unavailable()
    if reason:
        pytest.skip(reason)
    with Network(HOSTS) as net:
        pg = PgServer(net, "db")
        try:
            pg.start()
            c = Cluster(net, pg, tmp_path)
            c.start_api()
            c.start_worker("w1")
            c.start_worker("w2")
            yield c
        finally:
            pg.cleanup()  # before the namespaces go: the postmaster is not one of net's processes


def test_a_job_across_hosts_survives_a_cut_link_a_database_restart_and_an_api_restart(cluster):
    c = cluster
    # 1. No fault.
    a = spec("multihost-a", seed=1, shards=2)
    ref_a = simulate(a, c.root / "ref-a")
    client_a, out_a = c.client("a", a, timeout=120)
    result = finished(client_a, out_a, "the first job's client", 150)
    assert result["job"]["state"] == "succeeded", result["job"]
    assert_same_tables(out_a, ref_a, c.root / "ref-a")

    # 2. Faults.
    b = spec("multihost-b", seed=2, shards=4)
    ref_b = simulate(b, c.root / "ref-b")
    claimed_before = len(c.events("w1", "task claimed"))
    client_b, out_b = c.client("b", b, timeout=180)
    victim = wait_for(lambda: next((e for e in c.events("w1", "task claimed")[claimed_before:]
                                    if e["kind"] == "shard"), None), 60, "w1 to claim a shard of the second job",
                      poll=0.02)
    job_b = victim["job"]
    c.net.cut("w1")  # mid-shard: its heartbeats stop reaching the database

    done_before = len(c.events("w2", "shard done", job_b))
    wait_for(lambda: len(c.events("w2", "shard done", job_b)) > done_before, 60, "w2 to finish a shard")
    c.pg.restart()
    done_before = len(c.events("w2", "shard done", job_b))
    wait_for(lambda: len(c.events("w2", "shard done", job_b)) > done_before, 60,
             "w2 to finish a shard after the database restart")

    c.net.kill(c.api)
    c.api.wait(10)
    time.sleep(1.0)
    c.start_api()
    # w1's shard is redone elsewhere once its lease expires (claimed again, with a new token).
    wait_for(lambda: any(e["shard"] == victim["shard"] and e["token"] > victim["token"]
                         for e in c.events("w2", "task claimed", job_b)), 60, "w2 to redo w1's shard")
    c.net.restore("w1")

    result = finished(client_b, out_b, "the second job's client", 180)
    job = result["job"]
    assert job["state"] == "succeeded", job
    assert_same_tables(out_b, ref_b, c.root / "ref-b")
    assert result["unreachable"] >= 1, result  # the client saw the API down, and carried on
    m = result["metrics"]
    assert metric(m, "bssrdf_shards_completed_total") == a["shards"] + b["shards"]  # nothing counted twice
    assert metric(m, "bssrdf_merges_completed_total") == 2
    assert metric(m, "bssrdf_photons_simulated_total") == a["photons"] + b["photons"]  # one channel each
    assert metric(m, "bssrdf_leases_expired_total") >= 1
    # w1's late result was refused, not stored: it learns its lease is gone once its link is back.
    wait_for(lambda: c.events("w1", "result refused: lease lost", job_b) or c.events("w1", "shard abandoned: lease lost",
                                                                                       job_b), 60,
             "w1 to learn its lease was lost")
    for host, proc in c.workers.items():
        assert proc.poll() is None, f"worker {host} exited: {(c.root / f'{host}.log').read_text()[-3000:]}"
