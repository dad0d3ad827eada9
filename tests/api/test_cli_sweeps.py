"""The command line on sweeps: ``bssrdf simulate`` and ``bssrdf run`` print rows that
carry each medium's coordinates, and ``bssrdf status`` (plain and ``--media``) reports a sweep's
progress overall and per medium."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

from schema import parse_spec
from service.cli import main as bssrdf
from service.datasets import DatasetStorage
from service.store import JobStore
from service.worker import Worker
from tests.api.conftest import TOKEN, tiny_spec
from tests.support.engine import ENGINE_ENV

REPO = Path(__file__).resolve().parents[2]
SWEEP = tiny_spec(name="cli-sweep", sweep={"albedo": [0.3, 0.9], "g": [0.5], "eta": [1.3]})
SWEEP.pop("medium")


def coordinates(spec) -> set[tuple]:
    """(medium, albedo, g, eta) of every medium of a one-channel sweep."""
    return {(m.index, m.albedo[0], m.g[0], m.eta) for m in spec.media()}


def rows_coordinates(doc: dict) -> set[tuple]:
    return {(r["medium"], r["albedo"], r["g"], r["eta"]) for r in doc["results"]}


def test_simulate_json_rows_carry_the_medium(tmp_path, capsys):
    spec_path = tmp_path / "sweep.json"
    spec_path.write_text(json.dumps(SWEEP))
    capsys.readouterr()
    assert bssrdf(["simulate", str(spec_path), "--out", str(tmp_path / "out"), "--workers", "1", "--json",
                   "--no-progress"]) == 0
    doc = json.loads(capsys.readouterr().out)
    spec = parse_spec(SWEEP)
    assert doc["run"]["media"] == 2
    assert rows_coordinates(doc) == coordinates(spec)
    # every medium has every row of a single-medium summary: estimator x angle x channel x component
    per_medium = {m: sum(r["medium"] == m for r in doc["results"]) for m in (0, 1)}
    assert per_medium[0] == per_medium[1] > 0, per_medium


def test_run_then_status_shows_every_medium(tmp_path, cli, capsys):
    data_dir = tmp_path / "d"
    spec_path = tmp_path / "sweep.json"
    spec_path.write_text(json.dumps(SWEEP))
    env = {**os.environ, **ENGINE_ENV, "PYTHONPATH": str(REPO)}
    done = subprocess.run([sys.executable, "-m", "service.cli", "run", str(spec_path), "--workers", "1",
                           "--data-dir", str(data_dir), "--json"],
                          cwd=REPO, env=env, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr
    report = json.loads(done.stdout)
    spec = parse_spec(SWEEP)
    assert report["state"] == "succeeded" and (report["dataset"], report["version"]) == ("cli-sweep", 1)
    assert rows_coordinates(report) == coordinates(spec)

    store = JobStore(f"sqlite:///{data_dir / 'jobs.sqlite'}")
    storage = DatasetStorage(str(data_dir / "data"))
    run = cli(store, storage, capsys)
    status, out, _ = run("status", report["job_id"], "--token", TOKEN)
    assert status == 0, out
    assert "succeeded" in out and "shards 4/4" in out and "(media 2/2)" in out
    assert "dataset cli-sweep version 1" in out
    status, out, _ = run("status", report["job_id"], "--media", "--token", TOKEN)
    lines = out.splitlines()
    header = next(i for i, line in enumerate(lines) if line.split()[:4] == ["medium", "albedo", "g", "eta"])
    media = [line.split() for line in lines[header + 1:]]
    assert [m[:4] for m in media] == [["0", "0.3", "0.5", "1.3"], ["1", "0.9", "0.5", "1.3"]], out
    assert all(m[4] == "2/2" and m[-1] == "merged" for m in media), out

    # Partway through another sweep: the first medium has one shard done, the second none.
    job = store.submit(parse_spec(dict(SWEEP, seed=99)))
    Worker(store, storage, max_tasks=1, poll_seconds=0.05).loop()
    status, out, _ = run("status", job.id, "--token", TOKEN)
    assert "running" in out and "shards 1/4" in out and "(media 0/2)" in out, out
    status, out, _ = run("status", job.id, "--media", "--token", TOKEN)
    media = [line.split() for line in out.splitlines()[-2:]]
    assert [(m[0], m[4], m[-1]) for m in media] == [("0", "1/2", "waiting"), ("1", "0/2", "waiting")], out
    store.dispose()
