"""Job creation and deletion of the largest allowed job against concurrent small submissions.

    python -m bench.submit [--db URL] [--tasks 50000] [--repeat 3]

Starts ``bssrdf serve`` (no workers) on a free loopback port against ``--db`` (default a temporary
SQLite file; with a PostgreSQL URL a fresh database on that server, dropped afterwards). Then,
``--repeat`` times: one client POSTs a sweep of exactly ``--tasks`` shard tasks (the largest job
``BSSRDF_MAX_JOB_TASKS`` allows by default) while another POSTs small jobs one after the other
(distinct seeds), until the large POST is answered; then the large job is DELETEd while the
small POSTs go on. Prints the large POST's and the DELETE's wall time and the small POSTs'
latency percentiles during each (what a user submitting beside the large job waits).
"""

from __future__ import annotations

import argparse
import itertools
import json
import tempfile
import threading
import time
from pathlib import Path

import httpx

from bench.load import TOKEN, _env, _free_port, _start, load_spec, percentile, wait_ready
from service.runner import stop_workers

__all__ = ["large_spec", "run", "main"]


def large_spec(tasks: int, seed: int = 0) -> dict:
    """A sweep of ``tasks`` shard tasks with independent walks: albedos x 1 g x 1 eta media of
    ``shards`` each (tiny bins and photons: the job store's rows, not the walk)."""
    shards = next(s for s in (10, 15, 8, 5, 4, 2, 1) if tasks % s == 0 and tasks // s <= 65536)
    media = tasks // shards
    n_g = next(n for n in (64, 32, 16, 8, 4, 2, 1) if media % n == 0 and media // n <= 1024)
    return {"name": "large", "sweep": {"albedo": {"count": media // n_g, "spacing": "linear"},
                                        "g": [i / 128 for i in range(n_g)], "eta": [1.3], "walks": "independent"},
            "photons": 2 * shards, "shards": shards, "batches_per_shard": 2, "seed": seed, "estimator": "exits",
            "bins": {"radial": {"count": 4, "max_mm": 4.0}, "cos_theta_o": {"count": 1}, "phi_o": {"count": 1}}}


def _small_posts(http: httpx.Client, seeds, stop: threading.Event, out: list[float], errors: list[str]) -> None:
    while not stop.is_set():
        t0 = time.perf_counter()
        r = http.post("/v1/jobs", json={"spec": load_spec(next(seeds))})
        dt = time.perf_counter() - t0
        if r.status_code != 201:
            errors.append(f"small POST: HTTP {r.status_code}: {r.text[:200]}")
        out.append(dt)


def _while(http: httpx.Client, seeds, action) -> tuple[float, list[float], list[str], httpx.Response]:
    """Run ``action()`` while small POSTs go on; its wall time and answer and their latencies."""
    stop, latencies, errors = threading.Event(), [], []
    poster = threading.Thread(target=_small_posts, args=(http, seeds, stop, latencies, errors))
    poster.start()
    time.sleep(0.2)  # the small POSTs are under way before the large request starts
    t0 = time.perf_counter()
    answer = action()
    wall = time.perf_counter() - t0
    time.sleep(0.2)
    stop.set()
    poster.join()
    return wall, latencies, errors, answer


def _stats(xs: list[float]) -> dict:
    return {"n": len(xs), "p50_s": round(percentile(xs, 0.5), 4), "p99_s": round(percentile(xs, 0.99), 4),
            "max_s": round(max(xs), 4) if xs else None}


def run(db_url: str | None, tasks: int, repeat: int) -> dict:
    tmp = tempfile.TemporaryDirectory()
    root = Path(tmp.name)
    db_url = db_url or f"sqlite:///{root / 'jobs.sqlite'}"
    env = _env() | {"BSSRDF_MAX_JOB_TASKS": str(tasks)}
    port = _free_port()
    procs = [_start(["serve", "--host", "127.0.0.1", "--port", str(port), "--db", db_url, "--storage",
                     str(root / "data"), "--log-level", "warning"], root / "serve.log", env)]
    rounds = []
    try:
        base = f"http://127.0.0.1:{port}"
        wait_ready(base, procs[0], root / "serve.log")
        seeds = itertools.count(1)
        headers = {"Authorization": f"Bearer {TOKEN}"}
        with httpx.Client(base_url=base, timeout=120.0, headers=headers) as small, \
                httpx.Client(base_url=base, timeout=600.0, headers=headers) as large:
            for k in range(repeat):
                spec = large_spec(tasks, seed=k)
                wall, lat, errors, r = _while(small, seeds, lambda: large.post("/v1/jobs", json={"spec": spec}))
                if r.status_code != 201:
                    raise RuntimeError(f"the large POST was refused: HTTP {r.status_code}: {r.text[:500]}")
                job_id = r.json()["id"]
                d_wall, d_lat, d_errors, d = _while(small, seeds, lambda: large.delete(f"/v1/jobs/{job_id}"))
                if d.status_code != 200:
                    raise RuntimeError(f"the DELETE failed: HTTP {d.status_code}: {d.text[:500]}")
                rounds.append({"create_s": round(wall, 3), "small_posts_during_create": _stats(lat),
                               "delete_s": round(d_wall, 3), "small_posts_during_delete": _stats(d_lat),
                               "errors": errors + d_errors})
    finally:
        stop_workers(procs)
        tmp.cleanup()
    return {"backend": db_url.split(":", 1)[0].split("+")[0], "tasks": tasks, "rounds": rounds}


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.submit", description=__doc__.split("\n\n")[0])
    p.add_argument("--db", default=None, help="job store URL (default: a temporary SQLite file); with a "
                   "PostgreSQL URL, a fresh database is made on that server and dropped afterwards")
    p.add_argument("--tasks", type=int, default=50_000, help="shard tasks of the large job (default: the "
                   "default BSSRDF_MAX_JOB_TASKS)")
    p.add_argument("--repeat", type=int, default=3)
    args = p.parse_args(argv)
    fresh = None
    if args.db and args.db.startswith("postgresql"):
        from bench.pooler import database_url, fresh_database

        fresh = fresh_database(args.db, "bench_submit")
    try:
        report = run(database_url(args.db, fresh) if fresh else args.db, args.tasks, args.repeat)
    finally:
        if fresh:
            from bench.pooler import drop_database

            drop_database(args.db, fresh)
    print(json.dumps(report, indent=1))
    return 0 if not any(r["errors"] for r in report["rounds"]) else 1


if __name__ == "__main__":
    raise SystemExit(main())
