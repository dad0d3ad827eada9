"""Queue overhead per shard: claim + commit of a realistic payload, on SQLite and PostgreSQL.

    python -m bench.queue [--shards 200] [--payload-kib 512] [--pg URL] [--walk-spec SPEC]

PostgreSQL is benchmarked when ``--pg`` or ``BSSRDF_TEST_POSTGRES_URL`` gives a URL (a temporary
schema is created and dropped). ``--walk-spec`` also times ``run_shard`` of shard 0 of that spec,
to express the overhead as a fraction of walk time at that shard size.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
import uuid
from urllib.parse import quote

__all__ = ["bench_store", "main"]


def _spec(shards: int):
    """A small real job of ``shards`` shards (never walked here: the queue's cost alone)."""
    from schema import parse_spec

    return parse_spec({"name": "bench", "medium": {"sigma_a": [0.1], "sigma_s": [0.9], "g": [0.0], "eta": 1.0},
                       "photons": 10 * shards, "shards": shards, "batches_per_shard": 2, "seed": 1, "estimator": "exits"})


def bench_store(url: str, shards: int, payload: bytes) -> dict[str, float]:
    """Per-shard timings (ms) of claim, heartbeat and complete_shard on one store.

    A shard's result is a file in dataset storage; the job store records its URI, size and sha256
    (:class:`service.store.StoredFile`), which is what is committed here: the file write itself is
    storage's cost, not the queue's."""
    import hashlib

    from service.store import JobStore, StoredFile

    store = JobStore(url)
    store.submit(_spec(shards))
    claim, beat, commit = [], [], []
    while len(commit) < shards:
        t0 = time.perf_counter()
        lease = store.claim("bench", 60)
        t1 = time.perf_counter()
        if lease.kind != "shard":
            continue  # the incremental merge's task, claimable between shards: held, not timed
        store.heartbeat(lease, 60, photons=1)
        t2 = time.perf_counter()
        result = StoredFile(f".jobs/bench/{uuid.uuid4().hex}.npz", len(payload), hashlib.sha256(payload).hexdigest())
        store.complete_shard(lease, result, photons=1, elapsed_s=0.0)
        t3 = time.perf_counter()
        claim.append(t1 - t0), beat.append(t2 - t1), commit.append(t3 - t2)
    store.dispose()
    total = [a + c for a, c in zip(claim, commit)]
    ms = lambda xs: 1000 * statistics.median(xs)  # noqa: E731
    return {"claim_ms": ms(claim), "commit_ms": ms(commit), "claim_commit_ms": ms(total),
            "claim_commit_p95_ms": 1000 * sorted(total)[int(0.95 * (len(total) - 1))], "heartbeat_ms": ms(beat)}


def _pg_schema_url(base: str) -> tuple[str, str, object]:
    import sqlalchemy as sa

    schema = f"bench_{uuid.uuid4().hex[:10]}"
    engine = sa.create_engine(base)
    with engine.begin() as conn:
        conn.exec_driver_sql(f'CREATE SCHEMA "{schema}"')
    sep = "&" if "?" in base else "?"
    return f"{base}{sep}options={quote(f'-csearch_path={schema}')}", schema, engine


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m bench.queue", description=__doc__.split("\n\n")[0])
    p.add_argument("--shards", type=int, default=200)
    p.add_argument("--payload-kib", type=int, default=512, help="shard payload size (default: 512 KiB)")
    p.add_argument("--pg", default=os.environ.get("BSSRDF_TEST_POSTGRES_URL"))
    p.add_argument("--walk-spec", default=None, help="also time run_shard(spec, 0) of this spec")
    args = p.parse_args(argv)
    payload = os.urandom(args.payload_kib * 1024)
    rows = []
    with tempfile.TemporaryDirectory() as tmp:
        rows.append(("sqlite", bench_store(f"sqlite:///{tmp}/bench.sqlite", args.shards, payload)))
    if args.pg:
        url, schema, engine = _pg_schema_url(args.pg)
        try:
            rows.append(("postgresql", bench_store(url, args.shards, payload)))
        finally:
            with engine.begin() as conn:
                conn.exec_driver_sql(f'DROP SCHEMA "{schema}" CASCADE')
    walk_s = None
    if args.walk_spec:
        from schema import load_spec
        from workers.run.shard import run_shard

        spec = load_spec(args.walk_spec)
        t0 = time.perf_counter()
        tally = run_shard(spec, 0)
        walk_s = time.perf_counter() - t0
        print(f"walk: shard 0 of {args.walk_spec}: {walk_s:.2f} s, {tally.photons} photons, "
              f"payload {len(tally.to_bytes()) / 1024:.0f} KiB")
    print(f"{args.shards} shards, payload {args.payload_kib} KiB (median ms per shard)")
    print(f"{'backend':<11}{'claim':>8}{'commit':>8}{'claim+commit':>14}{'p95':>8}{'heartbeat':>11}"
          + ("  overhead/walk" if walk_s else ""))
    for name, r in rows:
        extra = f"  {100 * r['claim_commit_ms'] / 1000 / walk_s:.3f} %" if walk_s else ""
        print(f"{name:<11}{r['claim_ms']:>8.2f}{r['commit_ms']:>8.2f}{r['claim_commit_ms']:>14.2f}"
              f"{r['claim_commit_p95_ms']:>8.2f}{r['heartbeat_ms']:>11.2f}{extra}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
