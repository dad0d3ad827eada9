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


def test_simulate_prints_a_sweeps_target_per_medium(tmp_path, capsys):
    """A sweep run to a target error records one status per medium; the printed summary says in
    how many media the target was reached and which medium's worst check came nearest its limit
    (the printout once took the sweep's list of statuses for one medium's and crashed after the
    tables were written)."""
    spec_path = tmp_path / "sweep.json"
    spec_path.write_text(json.dumps(dict(SWEEP, photons=4000, target={"rel_stderr": 0.5})))
    capsys.readouterr()
    assert bssrdf(["simulate", str(spec_path), "--out", str(tmp_path / "out"), "--workers", "1", "--no-progress"]) == 0
    out = capsys.readouterr().out
    summary = json.loads((tmp_path / "out" / "summary.json").read_text())
    statuses = summary["target"]
    assert len(statuses) == 2 and all(t["reached"] for t in statuses), statuses
    line = next(line for line in out.splitlines() if line.startswith("target"))
    checks = sum(t["checks"] for t in statuses)
    assert "target reached in 2 of 2 media" in line and f"({checks} of {checks} checks met)" in line, out
    assert "worst: medium " in line and "limit 0.5" in line, line


def test_a_sweeps_target_lines_name_the_worst_medium_and_the_media_that_missed():
    from workers.run.simulate import target_lines

    def status(reached, rel, photons, limit=0.01):
        worst = {"r_lo_mm": 0.1, "r_hi_mm": 0.2, "rel_stderr": rel, "limit": limit, "estimator": "hybrid", "channel": "c0",
                 "incidence_deg": 0.0, "dof": photons - 1}
        return {"reached": reached, "photons": photons, "met": 3 if reached else 2, "checks": 3, "worst": worst}

    rows = [{"medium": m, "albedo": a, "g": 0.0, "eta": 1.33} for m, a in enumerate((0.2, 0.5, 0.9, 0.99))]
    lines = target_lines([status(True, 0.009, 1000), status(False, 0.03, 4000), None, status(True, None, 2000)], rows)
    assert lines[0].startswith("target reached in 2 of 4 media with 1000-4000 photons") and "(8 of 9 checks met)" in lines[0]
    assert "worst: medium 3 (albedo 0.99" in lines[0] and "relative error no estimate" in lines[0]  # no estimate is the worst
    assert lines[1] == "target NOT reached in media 1, 2"
    one = target_lines(status(True, 0.009, 1000), rows)
    assert one == ["target reached with 1000 photons per angle and channel (3 of 3 checks met; worst: Rd(r) in [0.1, 0.2) mm, "
                   "hybrid, c0, theta_i 0: relative error 0.009 on 999 dof, limit 0.01)"]


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
