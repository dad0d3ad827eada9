"""The client commands (submit, status, datasets) in-process, sending through FastAPI's TestClient
to the real app and store; tests/api/test_live.py runs them as processes against uvicorn."""

from __future__ import annotations

import io
import json
import threading

import pytest
from fastapi.testclient import TestClient

from service.client import ApiClient, follow_job, main
from tests.api.conftest import TINY_SPEC, TOKEN, tiny_spec
from tests.support.net import free_port


@pytest.fixture
def spec_file(tmp_path):
    def write(spec, name="spec.json"):
        path = tmp_path / name
        path.write_text(json.dumps(spec))
        return str(path)

    return write


def test_submit_prints_the_job_id_and_stores_it(cli, sqlite_store, storage, capsys, spec_file):
    run = cli(sqlite_store, storage, capsys)
    status, out, err = run("submit", spec_file(TINY_SPEC), "--token", TOKEN)
    assert status == 0 and sqlite_store.get_job(out.strip()).name == "tiny"
    assert "queued" in err
    status, out, err = run("submit", spec_file(TINY_SPEC), "--token", TOKEN)  # same spec: that job, not a new one
    assert status == 0 and len(sqlite_store.list_jobs()) == 1 and "existing job" in err
    status, out, _ = run("submit", spec_file(TINY_SPEC), "--token", TOKEN, "--json", "--idempotency-key", "k",
                         "--force")
    assert json.loads(out)["idempotency_key"] == "k" and len(sqlite_store.list_jobs()) == 2


def test_submit_errors_are_readable_with_field_range_and_value(cli, sqlite_store, storage, capsys, spec_file):
    run = cli(sqlite_store, storage, capsys)
    bad = tiny_spec(medium={"sigma_a": -1.0, "sigma_s": 1.0, "g": 1.0, "eta": 1.3}, photons=2**41)
    status, out, err = run("submit", spec_file(bad), "--token", TOKEN)
    assert status == 2 and out == ""
    assert "HTTP 422 from POST /v1/jobs: 3 problems" in err
    assert "spec.medium.sigma_a: sigma_a [1/mm] must be in the allowed range [0, 1e6]; received -1.0" in err
    assert "spec.medium.g:" in err and "(allowed: [-0.999, 0.999])" in err
    assert "spec.photons:" in err and "2**40" in err
    status, _, err = run("submit", spec_file(TINY_SPEC))
    assert status == 2 and "HTTP 401" in err and "BSSRDF_TOKEN" in err
    status, _, err = run("submit", "/nonexistent/spec.json",
                         "--token", TOKEN)
    assert status == 2 and "cannot read spec" in err
    assert sqlite_store.list_jobs() == []


def test_status_shows_progress_and_404(cli, sqlite_store, storage, capsys):
    from schema import parse_spec

    run = cli(sqlite_store, storage, capsys)
    job = sqlite_store.submit(parse_spec(TINY_SPEC))
    status, out, _ = run("status", job.id)
    assert status == 0 and job.id in out and "queued" in out and "shards 0/2" in out
    status, out, _ = run("status", job.id, "--json")
    assert json.loads(out)["progress"]["shards_queued"] == 2
    status, _, err = run("status", "missing-job")
    assert status == 2 and "HTTP 404" in err and "missing-job" in err


def test_follow_prints_plain_lines_off_a_terminal_and_returns_the_final_job(make_client, sqlite_store, storage):
    from schema import parse_spec

    app = make_client(sqlite_store, storage).app
    api = ApiClient("http://testserver", TOKEN, http=TestClient(app))
    job = sqlite_store.submit(parse_spec(TINY_SPEC))
    timer = threading.Timer(0.5, sqlite_store.cancel, args=(job.id,))
    timer.start()
    stream = io.StringIO()
    final = follow_job(api, job.id, stream=stream, poll=0.05, timeout=20)
    timer.join()
    assert final["state"] == "cancelled"
    lines = stream.getvalue().splitlines()
    assert lines[0].startswith("queued") and lines[-1].startswith("cancelled")
    assert "\r" not in stream.getvalue() and len(lines) == 2  # a line per change, not per poll
    with pytest.raises(TimeoutError):
        follow_job(api, sqlite_store.submit(parse_spec(TINY_SPEC)).id, stream=io.StringIO(), poll=0.05, timeout=0.2)


def test_status_follow_of_a_finished_job_prints_the_simulate_summary(cli, published, capsys):
    store, storage, jobs = published
    run = cli(store, storage, capsys)
    status, out, _ = run("status", jobs[0].id, "--follow", "--poll", "0.05")
    assert status == 0
    assert out.startswith("tiny  (spec ") and "single" in out and "dataset tiny version 1" in out
    status, out, _ = run("status", jobs[0].id, "--follow", "--json")
    doc = json.loads(out)
    assert doc["results"] and (doc["dataset"], doc["version"]) == ("tiny", 1)


def test_datasets_commands(cli, published, capsys, tmp_path):
    store, storage, _jobs = published
    run = cli(store, storage, capsys)
    status, out, _ = run("datasets")
    assert status == 0 and out.split("\n")[1].split() == ["tiny", "2", "2"]
    status, out, _ = run("datasets", "tiny")
    assert status == 0 and [line.split()[0] for line in out.strip().splitlines()[1:]] == ["1", "2"]
    status, out, _ = run("datasets", "tiny", "latest")
    assert status == 0 and "dataset tiny version 2" in out and "radial.parquet" in out and "sha256" in out
    target = tmp_path / "radial.parquet"
    status, _, err = run("datasets", "tiny", "1", "--download", "radial.parquet", "-o", str(target))
    assert status == 0 and target.stat().st_size == store.get_version("tiny", 1).meta["files"]["radial.parquet"]["bytes"]
    status, _, err = run("datasets", "tiny", "1", "--download", "../../jobs.sqlite")
    assert status == 2 and "HTTP 404" in err  # never a path outside the version
    status, _, err = run("datasets", "tiny", "1", "--download", "jobs.sqlite")
    assert status == 2 and "HTTP 404" in err and "available: bins.parquet" in err
    status, _, err = run("datasets", "nothing")
    assert status == 2 and "HTTP 404" in err
    status, _, err = run("datasets", "tiny", "--download", "radial.parquet")
    assert status == 2 and "needs NAME and VERSION" in err


def test_unreachable_api_is_reported(capsys):
    assert main(["datasets", "--api", f"http://127.0.0.1:{free_port()}"]) == 2
    err = capsys.readouterr().err
    assert "cannot reach the API" in err and "bssrdf serve" in err
