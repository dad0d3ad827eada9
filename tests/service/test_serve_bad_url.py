"""`bssrdf serve` given a wrong job store URL says so in one line and exits 2, like the worker
(tests/service/test_worker_bad_url.py): a URL that is not one, an unsupported backend, an
in-memory SQLite database, an SQLite file in a directory that does not exist (never created), a
PostgreSQL database or user the server refuses. A database server that does not answer is not fatal for the API (it starts and /readyz says why):
serve warns in one line and serves."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
import time
from pathlib import Path

import httpx
import pytest

from tests.service.bad_url import NOT_A_JOB_STORE, assert_refused, pg_refused_urls
from tests.service.conftest import pg_base_url

ROOT = Path(__file__).resolve().parents[2]


def _env(tmp_path: Path) -> dict:
    return {**os.environ, "PYTHONPATH": str(ROOT), "BSSRDF_DATA_DIR": str(tmp_path / "home")}


def _serve(tmp_path: Path, *args: str) -> subprocess.CompletedProcess:
    cmd = [sys.executable, "-m", "service.cli", "serve", "--port", "1", "--storage", str(tmp_path / "data"), *args]
    return subprocess.run(cmd, cwd=tmp_path, env=_env(tmp_path), capture_output=True, text=True, timeout=120)


def test_sqlite_in_a_missing_directory_is_refused_and_not_created(tmp_path):
    missing = tmp_path / "nonexistent" / "dir"
    assert_refused(_serve(tmp_path, "--db", f"sqlite:///{missing / 'jobs.sqlite'}"), "bssrdf serve", str(missing), "does not exist")
    assert not (tmp_path / "nonexistent").exists()


@pytest.mark.parametrize("url, needle", NOT_A_JOB_STORE)
def test_a_url_that_is_not_a_job_store_is_refused(tmp_path, url, needle):
    assert_refused(_serve(tmp_path, "--db", url), "bssrdf serve", needle)


@pytest.mark.skipif(pg_base_url() is None, reason="PostgreSQL tests need BSSRDF_TEST_POSTGRES_URL")
@pytest.mark.parametrize("url, needle", pg_refused_urls(with_port=False))
def test_a_postgresql_database_or_user_that_is_not_there_is_refused(tmp_path, url, needle):
    assert_refused(_serve(tmp_path, "--db", url), "bssrdf serve", "cannot reach the job store", needle)


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


@pytest.mark.skipif(pg_base_url() is None, reason="PostgreSQL tests need BSSRDF_TEST_POSTGRES_URL")
def test_a_database_that_does_not_answer_is_a_one_line_warning_and_the_api_serves(tmp_path):
    from sqlalchemy.engine import make_url

    u = make_url(pg_base_url())
    down = u.set(port=(u.port or 5432) + 1).render_as_string(False)
    port = _free_port()
    cmd = [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--db", down,
           "--storage", str(tmp_path / "data")]
    server = subprocess.Popen(cmd, cwd=tmp_path, env=_env(tmp_path), stderr=subprocess.PIPE, text=True)
    try:
        deadline, ready = time.monotonic() + 60, None
        while time.monotonic() < deadline and server.poll() is None:
            try:
                ready = httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=5)
                break
            except httpx.TransportError:
                time.sleep(0.2)
        assert ready is not None and ready.status_code == 503, (ready, server.poll())
    finally:
        server.terminate()
        _, err = server.communicate(timeout=30)
    warnings = [line for line in err.splitlines() if line.startswith("bssrdf serve: ")]
    assert len(warnings) == 1 and "warning: cannot reach the job store" in warnings[0], err[-3000:]
    assert "Traceback" not in err, err[-3000:]


def test_the_embedded_default_creates_its_own_directory(tmp_path):
    port = _free_port()
    cmd = [sys.executable, "-m", "service.cli", "serve", "--port", str(port), "--storage", str(tmp_path / "data")]
    server = subprocess.Popen(cmd, cwd=tmp_path, env=_env(tmp_path), stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline and server.poll() is None:
            try:
                assert httpx.get(f"http://127.0.0.1:{port}/readyz", timeout=5).status_code == 200
                break
            except httpx.TransportError:
                time.sleep(0.2)
    finally:
        server.terminate()
        _, err = server.communicate(timeout=30)
    assert (tmp_path / "home" / "jobs.sqlite").is_file(), err[-3000:]
