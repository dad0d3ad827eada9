"""The deploy/ SLURM array on a real scheduler: a one-node cluster of the test's own
(tests/support/slurm.py: munged, slurmctld and slurmd from Debian's slurm-wlm and munge), the
workers of ``deploy/slurm/worker-array.sh`` submitted with ``sbatch`` against a fresh PostgreSQL
schema and a storage directory every process sees (as a shared filesystem would be).

1. A job, then one array task of two workers (``--cpus-per-task=2``): the job succeeds, its tables
   are byte-identical to ``bssrdf simulate`` of the same spec, and the array task ends COMPLETED
   with exit code 0 (every worker exited 0 under ``--once``).
2. A second job, then two array tasks of one worker each; once a shard is leased and reports
   photons, its array task is ``scancel``-ed: SLURM sends SIGTERM to every process of the task,
   the worker abandons the shard and releases its lease (had it been killed, the 4 s lease would
   expire instead). Once the other task has committed a shard and walks its next one, its batch
   shell alone gets SIGTERM (``scancel --batch``, what the script's ``--signal=B:TERM@120`` sends
   before the time limit): the trap forwards it, the worker releases its lease, the task ends
   COMPLETED with exit code 0. A third array task (two workers) finishes the job: bytes identical
   to ``bssrdf simulate``, every shard committed once, each given-back shard redone under a newer
   lease.

The walk is eager (``BSSRDF_COMPILE=0``, one thread) in every process, so no kernel is compiled.
Skipped, with the reason, where the SLURM or munge binaries are missing, without root, or without
``BSSRDF_TEST_POSTGRES_URL``; CI installs the packages (.ci/run). Budget: 86-134 s measured on two
cores under a load average of 8-16 from other jobs (four runs); less on a quiet machine.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import sqlalchemy as sa

from schema import parse_spec
from service.datasets import DatasetStorage, open_version
from service.store import JobState, JobStore
from service.store.tables import tasks
from tests.support.slurm import SlurmCluster, slurm_unavailable
from tests.support.waiting import wait_for

pytestmark = [pytest.mark.slow, pytest.mark.postgres]

REPO = Path(__file__).resolve().parents[2]
SCRIPT = REPO / "deploy" / "slurm" / "worker-array.sh"
TABLES = ("radial.parquet", "bins.parquet", "summary.parquet")
ENGINE = {"BSSRDF_COMPILE": "0", "OMP_NUM_THREADS": "1"}
# Options the script passes to every worker: a short lease (an expired lease is redone within
# seconds), frequent heartbeats (photons in progress show in the tasks table), no long idle backoff.
WORKER_OPTIONS = ["--lease-seconds", "4", "--heartbeat-seconds", "0.5", "--poll-seconds", "0.2",
                  "--max-poll-seconds", "1"]


def spec(name: str, seed: int, shards: int, photons_per_shard: int) -> dict:
    """One channel of albedo 0.9, paths capped at 200 events: 10,000 photons take 0.2-0.5 s on
    the eager walk once warm, 150,000 about 4-8 s (long enough to be cancelled mid-shard)."""
    return {"name": name, "medium": {"sigma_a": 0.1, "sigma_s": 0.9, "g": 0.5, "eta": 1.3},
            "photons": photons_per_shard * shards, "shards": shards, "batches_per_shard": 1, "seed": seed,
            "estimator": "exits", "max_scatter": 200,
            "bins": {"radial": {"count": 8, "max_mfp": 16.0, "spacing": "log"}, "cos_theta_o": {"count": 2},
                     "phi_o": {"count": 2}}}


def simulate(data: dict, out: Path) -> subprocess.Popen:
    """``bssrdf simulate`` of the spec (the reference bytes), in the background."""
    out.mkdir(parents=True)
    (out / "spec.json").write_text(json.dumps(data))
    return subprocess.Popen([sys.executable, "-m", "service.cli", "simulate", str(out / "spec.json"), "--out",
                             str(out / "tables"), "--no-progress", "--workers", "1"],
                            env={**_base_env(), **ENGINE}, cwd=REPO, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)


def _base_env() -> dict[str, str]:
    return {**os.environ, "PYTHONPATH": str(REPO)}


def events(log: Path, msg: str, job: str | None = None) -> list[dict]:
    """JSON log lines of a worker log (the array task's output file) with this message."""
    lines = log.read_text(errors="replace").splitlines() if log.exists() else []
    found = [json.loads(line) for line in lines if line.startswith("{")]
    return [e for e in found if e.get("msg") == msg and (job is None or e.get("job") == job)]


class Setup:
    """The cluster, the job store and the storage the array's workers use."""

    def __init__(self, cluster: SlurmCluster, pg_url: str, root: Path) -> None:
        self.cluster, self.pg_url, self.root = cluster, pg_url, root
        self.store = JobStore(pg_url)
        self.storage = DatasetStorage(str(root / "data"))
        self.logs = root / "logs"
        self.logs.mkdir()

    def submit_array(self, array: str, cpus: int) -> str:
        """``sbatch`` the deploy script as a cluster user would, from a shell that exported the
        store, the storage and the worker command; the array's job id."""
        env = {**self.cluster.env, "PYTHONPATH": str(REPO), **ENGINE,
               "BSSRDF_DATABASE_URL": self.pg_url, "BSSRDF_STORAGE_URI": self.storage.uri,
               "BSSRDF_COMMAND": f"{sys.executable} -m service.cli"}
        return self.cluster.sbatch([f"--array={array}", f"--cpus-per-task={cpus}", "--time=10",
                                    f"--output={self.logs}/worker-%A_%a.log", f"--chdir={self.root}",
                                    str(SCRIPT), *WORKER_OPTIONS], env=env)

    def log(self, array_job: str, task: int) -> Path:
        return self.logs / f"worker-{array_job}_{task}.log"

    def tables(self, job_id: str) -> dict[str, bytes]:
        job = self.store.get_job(job_id)
        assert job.state == JobState.SUCCEEDED, job.error
        version = open_version(self.store, self.storage, job.dataset_name, job.dataset_version)
        return {name: version.read_bytes(name) for name in TABLES}

    def wait_job(self, job_id: str, timeout: float, logs: list[Path]) -> None:
        def ended():
            return self.store.get_job(job_id).state in (JobState.SUCCEEDED, JobState.FAILED, JobState.CANCELLED)

        try:
            wait_for(ended, timeout, f"job {job_id} to end")
        except AssertionError as exc:
            tails = "\n".join(f"{p.name}: {p.read_text()[-1500:] if p.exists() else '(none)'}" for p in logs)
            raise AssertionError(f"{exc}\n{tails}") from None

    def leased_in_progress(self, array_job: str, task: int | None = None) -> dict | None:
        """A shard task leased by a worker of this array (of its array task ``task``, if given)
        that has reported photons, or None."""
        owner = f"slurm-{array_job}-%" if task is None else f"slurm-{array_job}-{task}-%"
        with self.store.engine.connect() as conn:
            row = conn.execute(sa.select(tasks.c.shard_index, tasks.c.lease_owner, tasks.c.lease_token,
                                         tasks.c.photons).where(
                tasks.c.state == "leased", tasks.c.kind == "shard", tasks.c.photons > 0,
                tasks.c.lease_owner.like(owner))).first()
        return dict(row._mapping) if row else None

    def task_row(self, job_id: str, shard: int) -> dict:
        with self.store.engine.connect() as conn:
            return dict(conn.execute(sa.select(tasks).where(tasks.c.job_id == job_id,
                                                            tasks.c.shard_index == shard)).one()._mapping)


def reference(proc: subprocess.Popen, out: Path) -> dict[str, bytes]:
    assert proc.wait(240) == 0, proc.stderr.read().decode()[-2000:]
    return {name: (out / "tables" / name).read_bytes() for name in TABLES}


@pytest.fixture
def setup(pg_url, tmp_path):
    reason = slurm_unavailable()
    if reason:
        pytest.skip(reason)
    with SlurmCluster() as cluster:
        s = Setup(cluster, pg_url, tmp_path)
        try:
            yield s
        finally:
            s.store.dispose()


def test_the_deploy_array_runs_jobs_on_slurm_and_survives_scancel_mid_shard(setup):
    s, cluster = setup, setup.cluster

    # 1. One array task of two workers.
    a = spec("slurm-a", seed=1, shards=3, photons_per_shard=10_000)
    ref_a = simulate(a, s.root / "ref-a")
    job_a = s.store.submit(parse_spec(a)).id
    array_a = s.submit_array("0", cpus=2)
    s.wait_job(job_a, 150, [s.log(array_a, 0)])
    assert s.tables(job_a) == reference(ref_a, s.root / "ref-a")
    (task,) = cluster.wait_ended(array_a, 1, 60).values()
    assert (task.state, task.exit_code) == ("COMPLETED", "0:0"), (task, s.log(array_a, 0).read_text()[-3000:])
    stopped = events(s.log(array_a, 0), "worker stopped")
    assert sorted(e["worker"] for e in stopped) == [f"slurm-{array_a}-0-1", f"slurm-{array_a}-0-2"]
    m = s.store.metrics()
    assert m["shards_completed"] == a["shards"] and m["merges_completed"] == 1, m

    # 2. Two array tasks of one worker each; one is scancel-ed while it walks a shard.
    b = spec("slurm-b", seed=2, shards=3, photons_per_shard=150_000)
    ref_b = simulate(b, s.root / "ref-b")
    job_b = s.store.submit(parse_spec(b)).id
    array_b = s.submit_array("0-1", cpus=1)
    first = wait_for(lambda: s.leased_in_progress(array_b), 120, "a shard leased and in progress", poll=0.05)
    victim = int(first["lease_owner"].split("-")[2])
    other = 1 - victim
    cluster.scancel(f"{array_b}_{victim}")

    # 3. The time-limit warning (the script's `--signal=B:TERM@120`) reaches the batch shell alone,
    # which forwards it: sent once the other task has committed a shard and walks its next one.
    other_log = s.log(array_b, other)
    second = wait_for(lambda: events(other_log, "shard done", job_b) and s.leased_in_progress(array_b, other), 150,
                      "the other array task to walk its second shard", poll=0.05)
    cluster.signal_batch_shell(f"{array_b}_{other}", "TERM")
    tasks_b = cluster.wait_ended(array_b, 2, 60)
    assert tasks_b[victim].state == "CANCELLED", tasks_b
    # Stopped workers exit 0, and so does the array task: nothing failed.
    assert (tasks_b[other].state, tasks_b[other].exit_code) == ("COMPLETED", "0:0"), tasks_b

    # A new array task of two workers finishes the job: the same bytes as bssrdf simulate.
    array_c = s.submit_array("0", cpus=2)
    s.wait_job(job_b, 180, [s.log(array_c, 0)])
    assert s.tables(job_b) == reference(ref_b, s.root / "ref-b")
    (task_c,) = cluster.wait_ended(array_c, 1, 60).values()
    assert (task_c.state, task_c.exit_code) == ("COMPLETED", "0:0"), task_c
    for log, lease in ((s.log(array_b, victim), first), (other_log, second)):
        assert_given_back(s, log, job_b, lease)
    m = s.store.metrics()
    assert m["shards_completed"] == a["shards"] + b["shards"] and m["merges_completed"] == 2, m


def assert_given_back(s: Setup, log: Path, job_id: str, lease: dict) -> None:
    """The stopped worker gave its shard back (released the lease, or, had it been killed, let
    it expire) and never recorded it; a later lease of the shard committed it."""
    shard, token = lease["shard_index"], lease["lease_token"]
    text = log.read_text()[-3000:]
    mine = [e for e in events(log, "shard abandoned: stopping; lease released", job_id)
            if (e["shard"], e["token"]) == (shard, token)]
    row = s.task_row(job_id, shard)
    assert (mine and mine[0]["released"] is True) or row["expirations"] >= 1, (row, text)
    assert not [e for e in events(log, "shard done", job_id) if (e["shard"], e["token"]) == (shard, token)], text
    assert row["state"] == "done" and row["lease_token"] > token, row
    # A released lease is not counted as a try, an expired one is: one try plus the expirations.
    assert row["attempts"] == 1 + row["expirations"], row
    assert events(log, "worker stopped"), text
