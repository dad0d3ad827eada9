"""The claim path with a fleet of simulated workers (bench/fleet.py): threads in two
processes, each worker its own job store, claiming and committing instant shards whose files go
through dataset storage, against PostgreSQL through a private pgbouncer configured from
deploy/pgbouncer/pgbouncer.ini (transaction pooling), and directly with a bounded connection
budget. Every shard is claimed once and completed once (as the workers saw it and as the
database records it), every job publishes one version, no job file is left, and no worker
meets an error. Figures at 1,000 workers: `python -m bench.fleet`, in BENCHMARKS.md.

Budget: about 10 s per test here (100 workers, 4 jobs of 25 shards).
"""

from __future__ import annotations

import pytest

from bench.fleet import run_fleet
from bench.pooler import pgbouncer_unavailable
from tests.service.conftest import PG_ENV, pg_base_url

pytestmark = pytest.mark.postgres


@pytest.fixture
def pg_server():
    base = pg_base_url()
    if base is None:
        pytest.skip(f"the fleet test needs a PostgreSQL server: set {PG_ENV}")
    return base


def _assert_exactly_once(report: dict, jobs: int, shards: int) -> None:
    assert report["errors"] == 0, report["first_errors"]
    assert report["shard_claims"] == report["shard_commits"] == jobs * shards
    assert report["checks"]["ok"], (report["seen"], report["checks"])
    assert report["checks"]["versions"] == jobs and report["checks"]["job_files_left"] == 0


def test_a_fleet_through_pgbouncer_claims_and_completes_every_shard_once(pg_server):
    reason = pgbouncer_unavailable()
    if reason:
        pytest.skip(reason)
    report = run_fleet(pg_server, workers=100, jobs=4, shards=25, processes=2, pooler="pgbouncer", deadline_s=120)
    _assert_exactly_once(report, 4, 25)
    # Every worker held its own client connection; pgbouncer multiplexed them onto its pool.
    assert report["bouncer"]["pool_mode"] == "transaction"
    assert report["peak"]["cl_active"] + report["peak"]["cl_waiting"] >= 100 or report["peak"].get("admin_errors")
    assert report["peak"]["sv_active"] <= int(report["bouncer"]["default_pool_size"]) + int(report["bouncer"]["reserve_pool_size"])


def test_a_fleet_on_a_connection_budget_claims_and_completes_every_shard_once(pg_server):
    report = run_fleet(pg_server, workers=100, jobs=4, shards=25, processes=2, pooler="budget", budget=4, deadline_s=120)
    _assert_exactly_once(report, 4, 25)
