"""Real worker processes against PostgreSQL give the bytes of the in-process pipeline.

``run_shard`` for every shard, ``merge``, ``write_tables`` in this process is the reference (what
``bssrdf simulate`` does). Three ``python -m service.worker`` processes must publish a version whose
Parquet files are byte-identical, also when one of them is SIGKILLed in the middle of a shard
(its lease expires after 3 s and another worker redoes the shard).
"""

from __future__ import annotations

import json
import os
import signal
from pathlib import Path

import pytest

from service.datasets import DatasetStorage, open_version
from service.runner import start_workers, stop_workers
from service.store import JobState, JobStore
from tests.support.engine import ENGINE_ENV  # the reference runs with the same settings
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.postgres, pytest.mark.usefixtures("engine_env")]

REPO = Path(__file__).resolve().parents[2]
TABLES = ("radial.parquet", "bins.parquet", "summary.parquet")


def tiny_spec(name: str, photons: int, shards: int):
    from schema import parse_spec

    data = json.loads((REPO / "examples" / "skimmilk.json").read_text())
    # max_scatter bounds each shard's duration (skim milk paths run to thousands of events; the
    # truncated weight is reported), so a shard lasts a second or two on the eager walk.
    data.update(name=name, photons=photons, shards=shards, batches_per_shard=1 if shards > 1 else 2,
                estimator="exits", max_scatter=2000)
    data["bins"] = {"radial": {"count": 8, "max_mfp": 16.0, "spacing": "log"},
                    "cos_theta_o": {"count": 2}, "phi_o": {"count": 2}}
    return parse_spec(data)


def reference_bytes(spec, out_dir: Path) -> dict[str, bytes]:
    from workers.fold.merge import merge
    from workers.fold.output import write_tables
    from workers.run.shard import run_shard

    tallies = [run_shard(spec, i) for i in range(spec.shards)]
    write_tables(merge(spec, tallies), str(out_dir))
    return {name: (out_dir / name).read_bytes() for name in TABLES}


def claimed_shard(log: Path) -> bool:
    if not log.exists():
        return False
    return any('"task claimed"' in line and '"kind": "shard"' in line for line in log.read_text().splitlines())


def run_job(pg_url, tmp_path, spec, *, kill_one: bool):
    store = JobStore(pg_url)
    storage = DatasetStorage(str(tmp_path / "data"))
    job = store.submit(spec)
    logs = tmp_path / "logs"
    procs = start_workers(3, pg_url, storage.uri, logs, lease_seconds=3.0 if kill_one else 30.0,
                          extra_env=ENGINE_ENV)
    try:
        if kill_one:
            victim = wait_for(
                lambda: next((i + 1 for i in range(3) if claimed_shard(logs / f"worker-{i}.log")), None),
                60, "a worker to claim a shard", poll=0.02,
            ) - 1
            assert store.progress(job.id).shards_done < spec.shards
            os.kill(procs[victim].pid, signal.SIGKILL)
        wait_for(lambda: store.get_job(job.id).state in (JobState.SUCCEEDED, JobState.FAILED), 150, "the job to end")
    finally:
        stop_workers(procs)
    job = store.get_job(job.id)
    assert job.state == JobState.SUCCEEDED, job.error
    version = open_version(store, storage, job.dataset_name, job.dataset_version)
    return store, job, version


def test_three_workers_on_postgres_match_in_process_bytes(pg_url, tmp_path):
    spec = tiny_spec("e2e", photons=90, shards=3)
    expected = reference_bytes(spec, tmp_path / "ref")
    store, job, version = run_job(pg_url, tmp_path, spec, kill_one=False)
    assert {name: version.read_bytes(name) for name in TABLES} == expected
    meta = version.metadata
    assert meta["shards"] == 3 and meta["seed"] == spec.seed and meta["photons"] == sum(meta["photons_per_shard"])
    assert set(meta["files"]) == {*TABLES, "summary.json"}
    m = store.metrics()
    assert m["shards_completed"] == 3 and m["merges_completed"] == 1


def test_sigkill_mid_shard_still_gives_identical_bytes(pg_url, tmp_path):
    spec = tiny_spec("e2e-kill", photons=240, shards=4)
    expected = reference_bytes(spec, tmp_path / "ref")
    store, job, version = run_job(pg_url, tmp_path, spec, kill_one=True)
    assert {name: version.read_bytes(name) for name in TABLES} == expected
    m = store.metrics()
    # the killed worker's shard was leased twice; nothing was counted twice
    assert m["leases_expired"] >= 1 and m["shards_completed"] == 4
    assert m["photons_simulated"] == version.metadata["photons"]
