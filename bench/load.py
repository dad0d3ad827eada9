"""Load on the real service: concurrent clients submit jobs and read their status while workers run.

    python -m bench.load [--db URL] [--jobs 1000] [--reads 10000] [--clients 16] [--workers 2]

Starts ``bssrdf serve`` (uvicorn, one process) on a free loopback port and ``--workers`` worker
processes against the same store (``--db``: default a temporary SQLite file; a PostgreSQL URL
works the same) and a temporary storage directory. ``--clients`` asyncio tasks sharing one httpx
client then send ``--jobs`` submissions of tiny specs (distinct seeds: identical specs are
deduplicated) and ``--reads`` status reads (``GET /v1/jobs/{id}`` of a job already submitted),
interleaved. Afterwards the workers drain the queue (``--drain-seconds`` at most), and the store
is checked: every job succeeded and published one version, every shard and merge task was
claimed once and completed once, the photons counted equal the photons asked for.

Prints request counts, errors (any answer but 200/201, or no answer), latency percentiles of
submissions and status reads, the request rate, the server's and the clients' CPU time per request
and the server's share of one core (from /proc and the process clock: what the latencies are made
of when the machine is busy; clients in a closed loop wait ``clients / rate`` on average whatever
the server's speed), the drain time and the checks.
"""

from __future__ import annotations

import argparse
import asyncio
import json
import math
import os
import random
import socket
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

import httpx

from service.runner import stop_workers

__all__ = ["LoadReport", "run_load", "load_spec", "percentile", "wait_ready", "main"]

_REPO = Path(__file__).resolve().parents[1]
TOKEN = "bench-load-token"


def load_spec(seed: int) -> dict:
    """A job that walks 4 photons in one shard of two batches: the queue and the merge, not the walk."""
    return {"name": "load", "medium": {"sigma_a": 1.0, "sigma_s": 1.0, "g": 0.0, "eta": 1.3}, "photons": 4,
            "shards": 1, "batches_per_shard": 2, "seed": seed, "estimator": "exits",
            "bins": {"radial": {"count": 4, "max_mm": 4.0}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}}}


def percentile(xs: list[float], q: float) -> float:
    """The q-quantile (0..1) by the nearest-rank method: the smallest value with >= q of the data at or below it."""
    s = sorted(xs)
    return s[min(len(s), max(1, math.ceil(q * len(s)))) - 1] if s else float("nan")


@dataclass
class LoadReport:
    """Figures of one load run (seconds unless named otherwise)."""

    backend: str
    submissions: int = 0
    reads: int = 0
    errors: list[str] = field(default_factory=list)
    submit_s: list[float] = field(default_factory=list)
    read_s: list[float] = field(default_factory=list)
    load_wall_s: float = 0.0
    server_cpu_s: float = 0.0
    client_cpu_s: float = 0.0
    drain_s: float | None = None
    checks: dict[str, object] = field(default_factory=dict)

    def summary(self) -> dict[str, object]:
        ms = lambda xs, q: round(1000 * percentile(xs, q), 2)  # noqa: E731
        return {
            "backend": self.backend, "submissions": self.submissions, "reads": self.reads,
            "errors": len(self.errors), "first_errors": self.errors[:5],
            "submit_ms": {"p50": ms(self.submit_s, 0.5), "p99": ms(self.submit_s, 0.99)},
            "read_ms": {"p50": ms(self.read_s, 0.5), "p95": ms(self.read_s, 0.95), "p99": ms(self.read_s, 0.99),
                        "max": ms(self.read_s, 1.0)},
            "requests_per_s": round((self.submissions + self.reads) / self.load_wall_s, 1) if self.load_wall_s else None,
            "server_cpu_ms_per_request": round(1000 * self.server_cpu_s / max(1, self.submissions + self.reads), 2),
            "client_cpu_ms_per_request": round(1000 * self.client_cpu_s / max(1, self.submissions + self.reads), 2),
            "server_cpu_share": round(self.server_cpu_s / self.load_wall_s, 2) if self.load_wall_s else None,
            "load_wall_s": round(self.load_wall_s, 2), "drain_s": None if self.drain_s is None else round(self.drain_s, 2),
            "checks": self.checks,
        }


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _env() -> dict[str, str]:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join(p for p in (str(_REPO), os.environ.get("PYTHONPATH")) if p),
           "BSSRDF_API_TOKENS": json.dumps([TOKEN]), "OMP_NUM_THREADS": "1"}
    env.setdefault("BSSRDF_COMPILE", "0")  # a 4-photon walk: compiling would cost more than it saves
    return env


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (Linux /proc), all its threads."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _start(args: list[str], log: Path, env: dict[str, str], nice: int = 0) -> subprocess.Popen:
    with open(log, "ab") as out:
        return subprocess.Popen([sys.executable, "-m", "service.cli", *args], env=env, stdout=out,
                                stderr=subprocess.STDOUT, stdin=subprocess.DEVNULL, cwd=log.parent,
                                preexec_fn=(lambda: os.nice(nice)) if nice else None)


def wait_ready(base: str, serve: subprocess.Popen, log: Path, timeout: float = 60.0) -> None:
    """Until ``bssrdf serve`` at ``base`` answers /readyz with 200; RuntimeError with the end of
    its log if it exits or takes longer than ``timeout`` seconds."""
    deadline = time.monotonic() + timeout
    while True:
        if serve.poll() is not None or time.monotonic() > deadline:
            raise RuntimeError(f"bssrdf serve did not start: {log.read_text()[-2000:]}")
        try:
            if httpx.get(f"{base}/readyz", timeout=2).status_code == 200:
                return
        except httpx.TransportError:
            pass
        time.sleep(0.2)


async def _drive(base: str, jobs: int, reads: int, clients: int, report: LoadReport) -> list[str]:
    """The clients: ``jobs`` submissions and ``reads`` status reads in a random interleaving."""
    plan = ["submit"] * jobs + ["read"] * reads
    random.Random(1).shuffle(plan)
    # A read needs a job: move the first submission to the front.
    plan.insert(0, plan.pop(plan.index("submit")))
    ids: list[str] = []
    seeds = iter(range(1, jobs + 1))
    pick = random.Random(2)
    queue: asyncio.Queue[str] = asyncio.Queue()
    for op in plan:
        queue.put_nowait(op)
    limits = httpx.Limits(max_connections=clients, max_keepalive_connections=clients)
    async with httpx.AsyncClient(base_url=base, timeout=30.0, limits=limits,
                                 headers={"Authorization": f"Bearer {TOKEN}"}) as http:

        async def client() -> None:
            while True:
                try:
                    op = queue.get_nowait()
                except asyncio.QueueEmpty:
                    return
                if op == "read" and not ids:
                    await asyncio.sleep(0.01)  # the first submission is still on its way
                    queue.put_nowait(op)
                    continue
                t0 = time.perf_counter()
                try:
                    if op == "submit":
                        r = await http.post("/v1/jobs", json={"spec": load_spec(next(seeds))})
                    else:
                        r = await http.get(f"/v1/jobs/{pick.choice(ids)}")
                except httpx.HTTPError as exc:
                    report.errors.append(f"{op}: {type(exc).__name__}: {exc}")
                    continue
                dt = time.perf_counter() - t0
                if r.status_code not in (200, 201) or (op == "submit" and r.status_code != 201):
                    report.errors.append(f"{op}: HTTP {r.status_code}: {r.text[:200]}")
                    continue
                if op == "submit":
                    ids.append(r.json()["id"])
                    report.submissions += 1
                    report.submit_s.append(dt)
                else:
                    report.reads += 1
                    report.read_s.append(dt)

        await asyncio.gather(*(client() for _ in range(clients)))
    return ids


def check_counts(store, job_ids: list[str], photons_per_job: int) -> dict[str, object]:
    """Every job succeeded with one version; every task claimed once and done once; photons add up."""
    import sqlalchemy as sa

    from service.store.tables import dataset_versions, jobs, shard_results, tasks

    with store.engine.connect() as conn:
        states = dict(conn.execute(sa.select(jobs.c.state, sa.func.count()).group_by(jobs.c.state)).all())
        t = conn.execute(sa.select(sa.func.count(), sa.func.sum(tasks.c.attempts), sa.func.sum(tasks.c.expirations),
                                   sa.func.count().filter(tasks.c.state == "done"))).one()
        results = conn.execute(sa.select(sa.func.count()).select_from(shard_results)).scalar_one()
        versions = conn.execute(sa.select(sa.func.count(), sa.func.count(sa.distinct(dataset_versions.c.job_id)))).one()
    metrics = store.metrics()
    return {
        "jobs": len(job_ids), "jobs_by_state": {str(k): int(v) for k, v in states.items()},
        "tasks": int(t[0]), "claims": int(t[1] or 0), "expired_leases": int(t[2] or 0), "tasks_done": int(t[3]),
        "shard_results": int(results), "versions": int(versions[0]), "jobs_with_a_version": int(versions[1]),
        "shards_completed": metrics["shards_completed"], "merges_completed": metrics["merges_completed"],
        "photons_simulated": metrics["photons_simulated"], "photons_asked": photons_per_job * len(job_ids),
    }


def counts_ok(c: dict[str, object]) -> bool:
    """What "every shard counted exactly once" means for :func:`check_counts`'s one-shard jobs."""
    n = c["jobs"]
    return (c["jobs_by_state"] == {"succeeded": n} and c["tasks"] == c["claims"] == c["tasks_done"] == 2 * n
            and c["expired_leases"] == 0 and c["shard_results"] == c["shards_completed"] == n
            and c["versions"] == c["jobs_with_a_version"] == c["merges_completed"] == n
            and c["photons_simulated"] == c["photons_asked"])


def run_load(db_url: str | None = None, *, jobs: int = 1000, reads: int = 10000, clients: int = 16, workers: int = 2,
             drain_seconds: float = 300.0, worker_nice: int = 10, workdir: str | None = None) -> LoadReport:
    """Start the server and workers, run the clients, drain, check; always stops what it started."""
    from service.store import JobStore

    tmp = tempfile.TemporaryDirectory() if workdir is None else None
    root = Path(workdir or tmp.name)
    db_url = db_url or f"sqlite:///{root / 'jobs.sqlite'}"
    storage = str(root / "data")
    report = LoadReport(backend=db_url.split(":", 1)[0].split("+")[0])
    env = _env()
    store = JobStore(db_url)  # migrated before the server and the workers open it
    port = _free_port()
    procs = [_start(["serve", "--host", "127.0.0.1", "--port", str(port), "--db", db_url, "--storage", storage,
                     "--log-level", "warning"], root / "serve.log", env)]
    try:
        base = f"http://127.0.0.1:{port}"
        wait_ready(base, procs[0], root / "serve.log")
        procs += [_start(["worker", "--db", db_url, "--storage", storage, "--poll-seconds", "0.2",
                          "--worker-id", f"load-{i}"], root / f"worker-{i}.log", env, worker_nice)
                  for i in range(workers)]
        t0, cpu0, own0 = time.perf_counter(), cpu_seconds(procs[0].pid), time.process_time()
        ids = asyncio.run(_drive(base, jobs, reads, clients, report))
        report.load_wall_s = time.perf_counter() - t0
        report.server_cpu_s = cpu_seconds(procs[0].pid) - cpu0
        report.client_cpu_s = time.process_time() - own0
        t1 = time.monotonic()
        while store.pending_tasks() and time.monotonic() - t1 < drain_seconds:
            time.sleep(0.25)
        report.drain_s = time.monotonic() - t1 if not store.pending_tasks() else None
        report.checks = check_counts(store, ids, load_spec(0)["photons"])
        report.checks["ok"] = counts_ok(report.checks)
        return report
    finally:
        stop_workers(procs)
        store.dispose()
        if tmp is not None:
            tmp.cleanup()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.load", description=__doc__.split("\n\n")[0])
    p.add_argument("--db", default=None, help="job store URL (default: a temporary SQLite file); with a "
                   "PostgreSQL URL, a fresh database is made on that server and dropped afterwards (the "
                   "checks count every row, and earlier runs' specs would be deduplicated)")
    p.add_argument("--jobs", type=int, default=1000)
    p.add_argument("--reads", type=int, default=10000)
    p.add_argument("--clients", type=int, default=16, help="concurrent client tasks")
    p.add_argument("--workers", type=int, default=2, help="worker processes")
    p.add_argument("--drain-seconds", type=float, default=300.0)
    p.add_argument("--worker-nice", type=int, default=10,
                   help="niceness of the workers (default 10: on the API's host, requests come first)")
    args = p.parse_args(argv)
    fresh = None
    if args.db and args.db.startswith("postgresql"):
        from bench.pooler import database_url, fresh_database

        fresh = fresh_database(args.db, "bench_load")
    try:
        report = run_load(database_url(args.db, fresh) if fresh else args.db, jobs=args.jobs, reads=args.reads,
                          clients=args.clients, workers=args.workers, drain_seconds=args.drain_seconds,
                          worker_nice=args.worker_nice)
    finally:
        if fresh:
            from bench.pooler import drop_database

            drop_database(args.db, fresh)
    s = report.summary()
    print(json.dumps(s, indent=1))
    return 0 if s["errors"] == 0 and s["checks"].get("ok") else 1


if __name__ == "__main__":
    raise SystemExit(main())
