"""What a fleet run (:mod:`bench.fleet`) reports and checks: claim and commit rates and latencies
from the workers' own records, and the exactly-once check -- every shard claimed once and
completed once as the workers saw it, and as the database records it (one result row per shard,
one version per job, no job file left in storage)."""

from __future__ import annotations

import os
from collections import Counter

from bench.load import percentile
from service.store import JobStore, TaskKind

__all__ = ["fleet_report", "db_checks", "checks_ok"]


def _ms(xs: list[float]) -> dict[str, float]:
    return {q: round(1000 * percentile(xs, v), 2) for q, v in (("p50", 0.5), ("p99", 0.99), ("max", 1.0))} if xs else {}


def fleet_report(results: list[dict], **head) -> dict[str, object]:
    """The run's figures from the simulated workers' records (``results``, one per process) and
    its settings (``head``; its connect_s and wall_s are rounded)."""
    cat = lambda key: [x for r in results for x in r[key]]  # noqa: E731
    claims, commits = Counter(), Counter()
    for r in results:
        claims.update(r["claims"]), commits.update(r["commits"])
    first = min(r["first"] for r in results if r["first"] is not None)
    last = max(r["last_commit"] for r in results if r["last_commit"] is not None)
    span = last - first
    claim_s, commit_s = cat("claim_s"), cat("commit_s")
    return {
        **head, "connect_s": round(head.pop("connect_s"), 2), "wall_s": round(head.pop("wall_s"), 2),
        "span_s": round(span, 2), "shard_claims": len(claim_s), "shard_commits": len(commit_s),
        "claims_per_s": round(len(claim_s) / span, 1), "commits_per_s": round(len(commit_s) / span, 1),
        "claim_ms": _ms(claim_s), "commit_ms": _ms(commit_s),
        "empty_claims": len(cat("empty_claim_s")), "empty_claim_ms": _ms(cat("empty_claim_s")),
        "merge_rounds": len(cat("merge_s")), "merge_round_ms": _ms(cat("merge_s")),
        "errors": len(cat("errors")), "first_errors": cat("errors")[:5],
        "seen": {"shards_claimed": len(claims), "claimed_once": sum(1 for v in claims.values() if v == 1),
                 "shards_committed": len(commits), "committed_once": sum(1 for v in commits.values() if v == 1)},
    }


def db_checks(store: JobStore, jobs_n: int, shards: int, storage_uri: str) -> dict[str, object]:
    """What the database records: every shard task done after one claim, one result row each, every job
    succeeded with one version; and no job file left in storage."""
    import sqlalchemy as sa

    from service.store.tables import dataset_versions, jobs, shard_results, tasks

    t = tasks.c
    with store.engine.connect() as conn:
        states = dict(conn.execute(sa.select(jobs.c.state, sa.func.count()).group_by(jobs.c.state)).all())
        n, done, attempts, expired = conn.execute(
            sa.select(sa.func.count(), sa.func.count().filter(t.state == "done"), sa.func.sum(t.attempts),
                      sa.func.sum(t.expirations)).where(t.kind == TaskKind.SHARD)).one()
        results, distinct = conn.execute(sa.select(
            sa.func.count(), sa.func.count(sa.distinct(shard_results.c.job_id + ":" + sa.cast(shard_results.c.shard_index, sa.String))))
        ).one()
        versions, versioned = conn.execute(sa.select(sa.func.count(), sa.func.count(sa.distinct(dataset_versions.c.job_id)))).one()
        shards_done = conn.execute(sa.select(sa.func.sum(jobs.c.shards_done))).scalar_one()
    left = sum(len(f) for _, _, f in os.walk(os.path.join(storage_uri, ".jobs")))
    return {"jobs_by_state": {str(k): int(v) for k, v in states.items()}, "shard_tasks": int(n), "shard_tasks_done": int(done),
            "shard_attempts": int(attempts or 0), "expired_leases": int(expired or 0), "shard_results": int(results),
            "distinct_shard_results": int(distinct), "jobs_shards_done": int(shards_done or 0), "versions": int(versions),
            "jobs_with_a_version": int(versioned), "job_files_left": left}


def checks_ok(report: dict, total: int) -> bool:
    """Every shard claimed once and completed once, seen by the workers and recorded by the database."""
    c, seen, jobs_n = report["checks"], report["seen"], report["jobs"]
    return (report["errors"] == 0 and report["shard_claims"] == report["shard_commits"] == total
            and seen == {"shards_claimed": total, "claimed_once": total, "shards_committed": total, "committed_once": total}
            and c["jobs_by_state"] == {"succeeded": jobs_n}
            and c["shard_tasks"] == c["shard_tasks_done"] == c["shard_attempts"] == c["shard_results"] == total
            and c["distinct_shard_results"] == c["jobs_shards_done"] == total and c["expired_leases"] == 0
            and c["versions"] == c["jobs_with_a_version"] == jobs_n and c["job_files_left"] == 0)
