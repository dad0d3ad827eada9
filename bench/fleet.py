"""The claim path at fleet scale: many simulated workers claiming and committing shards against
PostgreSQL, through pgbouncer (deploy/pgbouncer/pgbouncer.ini) or a bounded connection budget.

    python -m bench.fleet [--workers 1000] [--jobs 40] [--shards 150] [--processes 2]
                                  [--pooler pgbouncer | --pooler budget --budget 20] [--pg URL]

Real: the worker's loop (``service.worker.Worker.loop`` and ``process``: claim, a heartbeat
thread per task, the shard's file written to the job's staging area in dataset storage and its
URI, size and sha256 committed by ``complete_shard``, ``fail_task`` on errors, ``has_pending_tasks``
and the jittered, backed-off idle poll of ``--once``), one ``JobStore`` (one engine, one connection pool of
2 + 4) per simulated worker as one per worker process, the job store's schema and migrations,
pgbouncer 1.x from Debian with the deploy file's settings, PostgreSQL. Simulated: the walk (a
shard is instant; its payload is random bytes of the size the spec's tally has,
``schema.sizes``) and the fold's arithmetic: a merge round reads, sha256-checked, every done
shard file in task order as the real fold does (``fold_position``, ``ResultWindow``), writes a
fold file and commits ``advance_fold``; the last round stages a metadata file and publishes
with ``complete_merge`` through ``DatasetStorage``, then removes the job's files. Workers are
threads (``--processes`` processes of them: one Python process is one core).

A fresh database (``CREATE DATABASE bench_...``, dropped afterwards) on the server of ``--pg``
(default ``BSSRDF_TEST_POSTGRES_URL``); the pooler is a private pgbouncer on a free port.
Timing starts once every worker has connected. Prints: claims/s and commits/s over the run,
p50/p99 of claim and commit latency, empty claims, errors, pgbouncer's peak waiting clients and
wait, CPU seconds of the bench, pgbouncer and the PostgreSQL backends, and the exactly-once
check: every shard claimed once and completed once (as the workers saw it and as the database
records it), one version per job, no job file left.
"""

from __future__ import annotations

import argparse
import json
import multiprocessing as mp
import os
import tempfile
import threading
import time
from collections import Counter

from bench.fleet_report import checks_ok, db_checks, fleet_report
from bench.load import cpu_seconds
from service.datasets import DatasetStorage, JobFiles, ResultWindow
from service.store import JobStore, LeaseLost, TaskKind
from service.worker import Worker

__all__ = ["fleet_spec", "run_fleet", "FleetWorker", "main"]

PHOTONS_PER_SHARD = 1000


def fleet_spec(seed: int, shards: int):
    """A job of ``shards`` shards with a small realistic tally (16 x 2 x 2 bins, exits: 15 KB)."""
    from schema import parse_spec

    return parse_spec({"name": "fleet", "medium": {"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.5, "eta": 1.3},
                       "photons": PHOTONS_PER_SHARD * shards, "shards": shards, "batches_per_shard": 2,
                       "seed": seed, "estimator": "exits",
                       "bins": {"radial": {"count": 16, "max_mfp": 16.0}, "cos_theta_o": {"count": 2},
                                "phi_o": {"count": 2}}})


class _Stats:
    """What the simulated workers of one process saw (lists of seconds, counters)."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.claim_s, self.empty_claim_s, self.commit_s, self.merge_s = [], [], [], []
        self.claims, self.commits = Counter(), Counter()
        self.errors: list[str] = []
        self.first = self.last_commit = None

    def error(self, what: str) -> None:
        with self.lock:
            self.errors.append(what[:300])


class _TimedStore(JobStore):
    """The job store, timing what the fleet measures and counting what it checks."""

    stats: _Stats

    def claim(self, worker_id, lease_seconds):
        t0 = time.perf_counter()
        try:
            lease = super().claim(worker_id, lease_seconds)
        except Exception as exc:
            self.stats.error(f"claim: {type(exc).__name__}: {exc}")
            raise
        dt, st = time.perf_counter() - t0, self.stats
        if lease is None:
            st.empty_claim_s.append(dt)
        else:
            st.first = st.first or time.time() - dt
            if lease.kind == TaskKind.SHARD:
                st.claim_s.append(dt)
                with st.lock:
                    st.claims[(lease.job_id, lease.shard_index)] += 1
        return lease

    def complete_shard(self, lease, result, *, photons, elapsed_s):
        t0 = time.perf_counter()
        super().complete_shard(lease, result, photons=photons, elapsed_s=elapsed_s)
        self.stats.commit_s.append(time.perf_counter() - t0)
        self.stats.last_commit = time.time()
        with self.stats.lock:
            self.stats.commits[(lease.job_id, lease.shard_index)] += 1

    def fail_task(self, lease, error, *, final=False):
        self.stats.error(f"task failed: {error}")
        return super().fail_task(lease, error, final=final)


class FleetWorker(Worker):
    """``service.worker.Worker`` with an instant walk and a merge that skips the fold's arithmetic."""

    payload: bytes

    def _walk(self, lease, progress):
        progress(PHOTONS_PER_SHARD)
        return self.payload, PHOTONS_PER_SHARD, 0.0

    def _process_merge(self, lease, beat, fields):
        t0 = time.perf_counter()
        store, files = self.store, JobFiles(self.storage, lease.job_id)
        pos = store.fold_position(lease.job_id)
        folded = pos.folded
        results = ResultWindow(store, lease.job_id)
        while folded < pos.tasks:
            stored = results.get(folded)
            if stored is None:
                break
            files.read(stored, f"task {folded}")  # read once and sha256-checked, as the fold does
            folded += 1
        try:
            if folded == pos.tasks:
                staged = self.storage.stage("fleet")
                staged.write_bytes("metadata.json", json.dumps({"job": lease.job_id}).encode())
                try:
                    store.complete_merge(lease, "fleet", {"job": lease.job_id}, staged)
                except BaseException:
                    staged.discard()
                    raise
                files.discard()
            else:
                ref = files.write(f"fold/{folded:08d}-{lease.token}.fold", self.payload)
                store.advance_fold(lease, folded=folded, fold=ref, skipped=[])
                files.delete(pos.fold)
        except LeaseLost as exc:
            store.stats.error(f"merge: {exc}")
            raise
        store.stats.merge_s.append(time.perf_counter() - t0)


def _simulate(url: str, storage_uri: str, ids: range, payload: bytes, pool: tuple[int, int] | None,
              ready, deadline_s: float, out, max_poll_seconds: float | None = None) -> None:
    """One process of simulated workers (threads); puts its _Stats' figures on ``out``."""
    stats = _Stats()
    storage = DatasetStorage(storage_uri)

    def make_store(**kw) -> _TimedStore:
        s = _TimedStore(url, migrate=False, **kw)
        s.stats = stats
        return s

    shared = make_store(pool_size=pool[0], max_overflow=pool[1]) if pool else None
    stores = [shared or make_store() for _ in ids]
    workers = []
    for i, store in zip(ids, stores):
        w = FleetWorker(store, storage, worker_id=f"fleet-{i}", lease_seconds=60.0, once=True, poll_seconds=1.0,
                        max_poll_seconds=max_poll_seconds)
        w.payload = payload
        workers.append(w)
    for s in set(stores):
        if shared is None:
            s.now()  # connect now (pgbouncer: one client connection per worker), not inside a claim
    if shared is not None:
        conns = [shared.engine.connect() for _ in range(pool[0])]  # fill the budgeted pool
        for c in conns:
            c.close()
    ready.wait()

    def run(w: FleetWorker) -> None:
        try:
            w.loop()
        except Exception as exc:  # the loop gives up after 10 database errors in a row
            stats.error(f"worker {w.worker_id} stopped: {type(exc).__name__}: {exc}")

    threads = [threading.Thread(target=run, args=(w,), daemon=True) for w in workers]
    for t in threads:
        t.start()
    end = time.monotonic() + deadline_s
    for t in threads:
        t.join(max(0.0, end - time.monotonic()))
    if any(t.is_alive() for t in threads):
        stats.error(f"deadline of {deadline_s} s reached with work left")
        for w in workers:
            w.stopping.set()
        for t in threads:
            t.join(30)
    out.put({"claim_s": stats.claim_s, "empty_claim_s": stats.empty_claim_s, "commit_s": stats.commit_s,
             "merge_s": stats.merge_s, "claims": dict(stats.claims), "commits": dict(stats.commits),
             "errors": stats.errors, "first": stats.first, "last_commit": stats.last_commit,
             "cpu_s": cpu_seconds(os.getpid())})
    ready.wait()  # the parent reads the database backends' CPU time before they go
    for s in set(stores):
        s.dispose()


def _backend_pids(admin_url: str, database: str) -> list[int]:
    import sqlalchemy as sa

    engine = sa.create_engine(admin_url)
    with engine.connect() as conn:
        pids = conn.execute(sa.text("SELECT pid FROM pg_stat_activity WHERE datname = :d"), {"d": database}).scalars()
        pids = list(pids)
    engine.dispose()
    return pids


def _cpu(pids) -> dict[int, float]:
    out = {}
    for pid in pids:
        try:
            out[pid] = cpu_seconds(pid)
        except (FileNotFoundError, ProcessLookupError, IndexError):
            pass
    return out


def run_fleet(pg_url: str, *, workers: int = 1000, jobs: int = 40, shards: int = 150, processes: int = 2,
              pooler: str = "pgbouncer", budget: int = 20, deadline_s: float = 600.0,
              max_poll_seconds: float | None = None) -> dict[str, object]:
    """Create a database and (``pooler="pgbouncer"``) a pgbouncer, submit ``jobs`` x ``shards``,
    run the simulated fleet, check, clean up; the figures (module docstring)."""
    from schema.sizes import estimate_sizes
    from bench.pooler import Pgbouncer, database_url, drop_database, fresh_database

    if pooler not in ("pgbouncer", "budget"):
        raise ValueError(f"pooler must be 'pgbouncer' or 'budget'; received {pooler!r}")
    if workers < processes:
        raise ValueError(f"workers ({workers}) must be at least processes ({processes})")
    name = fresh_database(pg_url, "bench_fleet")
    direct = database_url(pg_url, name)
    bouncer = None
    tmp = tempfile.TemporaryDirectory()
    try:
        if pooler == "pgbouncer":
            bouncer = Pgbouncer(pg_url, name).start()
            url = bouncer.url
        else:
            url = direct
        store = JobStore(url)  # migrates (through the pooler, as a fleet's first worker would)
        spec0 = fleet_spec(0, shards)
        payload = os.urandom(estimate_sizes(spec0).shard_payload_bytes)
        for j in range(jobs):
            store.submit(fleet_spec(j + 1, shards))
        storage_uri = f"{tmp.name}/data"
        DatasetStorage(storage_uri)
        ctx = mp.get_context("fork")
        ready, out = ctx.Barrier(processes + 1), ctx.Queue()
        per = [range(p * workers // processes, (p + 1) * workers // processes) for p in range(processes)]
        # Budget: the connections shared by a process's workers (pool + overflow), split over processes.
        pool = None if pooler == "pgbouncer" else (max(1, budget // processes), 0)
        store.dispose()
        t_connect = time.monotonic()
        procs = [ctx.Process(target=_simulate, args=(url, storage_uri, ids, payload, pool, ready, deadline_s, out,
                                                          max_poll_seconds))
                 for ids in per]
        for p in procs:
            p.daemon = True  # they die with this process, whatever happens to it
            p.start()
        ready.wait(timeout=300)
        connect_s = time.monotonic() - t_connect
        watched = ([bouncer.pid] if bouncer else []) + _backend_pids(pg_url, name)
        cpu0, t0 = _cpu(watched), time.monotonic()
        peak = {"cl_waiting": 0, "sv_active": 0, "maxwait_us": 0, "cl_active": 0}
        results = []
        while len(results) < processes:
            try:
                results.append(out.get(timeout=0.5))
            except Exception:  # queue.Empty: sample the pooler while the fleet runs
                if bouncer is not None:
                    try:
                        pools = bouncer.pools()
                    except Exception as exc:  # a busy pooler: the figure is missing, the run goes on
                        peak["admin_errors"] = peak.get("admin_errors", 0) + 1
                        peak["admin_error"] = f"{type(exc).__name__}: {exc}"[:200]
                        continue
                    peak = {k: max(v, pools.get(k, 0)) if k in pools else v for k, v in peak.items()}
                if time.monotonic() - t0 > deadline_s + 120:
                    raise RuntimeError("the simulated fleet did not report back")
        wall_s = time.monotonic() - t0
        watched += [p for p in _backend_pids(pg_url, name) if p not in cpu0]
        cpu1 = _cpu(watched)
        ready.wait(timeout=60)
        for p in procs:
            p.join(30)
        bouncer_pid = bouncer.pid if bouncer else None
        cpu = {"bench": round(sum(r["cpu_s"] for r in results), 2),
               "pgbouncer": round(cpu1.get(bouncer_pid, 0) - cpu0.get(bouncer_pid, 0), 2) if bouncer else None,
               "postgres_backends": round(sum(v - cpu0.get(pid, 0.0) for pid, v in cpu1.items() if pid != bouncer_pid), 2)}
        report = fleet_report(results, workers=workers, jobs=jobs, shards=shards, processes=processes, pooler=pooler,
                         budget=budget if bouncer is None else None, max_poll_seconds=max_poll_seconds,
                         payload=len(payload), connect_s=connect_s,
                         wall_s=wall_s, cpu=cpu, peak=peak if bouncer else None,
                         bouncer=bouncer and {"version": ".".join(map(str, bouncer.version)), "dropped": bouncer.dropped,
                                              **{k: bouncer.settings[k] for k in ("pool_mode", "default_pool_size",
                                                                                  "reserve_pool_size", "max_client_conn")}})
        check = JobStore(direct, migrate=False)
        try:
            report["checks"] = db_checks(check, jobs, shards, storage_uri)
        finally:
            check.dispose()
        report["checks"]["ok"] = checks_ok(report, jobs * shards)
        return report
    finally:
        if bouncer is not None:
            bouncer.stop()
        drop_database(pg_url, name)
        tmp.cleanup()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.fleet", description=__doc__.split("\n\n")[0])
    p.add_argument("--pg", default=os.environ.get("BSSRDF_TEST_POSTGRES_URL"),
                   help="PostgreSQL server URL (default BSSRDF_TEST_POSTGRES_URL); a fresh database is made on it")
    p.add_argument("--workers", type=int, default=1000, help="simulated workers (threads)")
    p.add_argument("--jobs", type=int, default=40)
    p.add_argument("--shards", type=int, default=150, help="shards per job")
    p.add_argument("--processes", type=int, default=2, help="processes the workers are spread over")
    p.add_argument("--pooler", choices=["pgbouncer", "budget"], default="pgbouncer",
                   help="pgbouncer (one client connection per worker, deploy/pgbouncer/pgbouncer.ini) or "
                   "budget (direct, the workers of a process share --budget / processes connections)")
    p.add_argument("--budget", type=int, default=20, help="connections to PostgreSQL in all, with --pooler budget")
    p.add_argument("--deadline-s", type=float, default=600.0)
    p.add_argument("--max-poll-seconds", type=float, default=None,
                   help="the workers' longest idle wait (default: the worker's, 8 x the 1 s poll; 1 = no backoff)")
    args = p.parse_args(argv)
    if not args.pg:
        p.error("no PostgreSQL URL: pass --pg or set BSSRDF_TEST_POSTGRES_URL")
    report = run_fleet(args.pg, workers=args.workers, jobs=args.jobs, shards=args.shards, processes=args.processes,
                       pooler=args.pooler, budget=args.budget, deadline_s=args.deadline_s,
                       max_poll_seconds=args.max_poll_seconds)
    print(json.dumps(report, indent=1))
    return 0 if report["checks"]["ok"] else 1


if __name__ == "__main__":
    raise SystemExit(main())
