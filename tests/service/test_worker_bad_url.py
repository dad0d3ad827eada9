"""A worker given a wrong job store URL says so in one line and exits non-zero: a URL that is not
one, an unsupported backend, an SQLite file in a directory that does not exist (never created:
a typo must not start a new, empty store), a PostgreSQL server, database or user that is not
there. Only the embedded default, jobs.sqlite in BSSRDF_DATA_DIR, creates its directory."""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from tests.service.bad_url import NOT_A_JOB_STORE, assert_refused, pg_refused_urls
from tests.service.conftest import pg_base_url

ROOT = Path(__file__).resolve().parents[2]


def _worker(tmp_path: Path, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    full = {**os.environ, "PYTHONPATH": str(ROOT), "BSSRDF_DATA_DIR": str(tmp_path / "home"), **(env or {})}
    cmd = [sys.executable, "-m", "service.worker", "--storage", str(tmp_path / "data"), "--once", *args]
    return subprocess.run(cmd, cwd=tmp_path, env=full, capture_output=True, text=True, timeout=120)


def test_sqlite_in_a_missing_directory_is_refused_and_not_created(tmp_path):
    missing = tmp_path / "nonexistent" / "dir"
    out = _worker(tmp_path, "--db", f"sqlite:///{missing / 'jobs.sqlite'}")
    assert_refused(out, "bssrdf worker", str(missing), "does not exist")
    assert not (tmp_path / "nonexistent").exists()


@pytest.mark.parametrize("url, needle", NOT_A_JOB_STORE)
def test_a_url_that_is_not_a_job_store_is_refused(tmp_path, url, needle):
    assert_refused(_worker(tmp_path, "--db", url), "bssrdf worker", needle)


@pytest.mark.skipif(pg_base_url() is None, reason="PostgreSQL tests need BSSRDF_TEST_POSTGRES_URL")
@pytest.mark.parametrize("url, needle", pg_refused_urls(with_port=True))
def test_a_postgresql_server_database_or_user_that_is_not_there(tmp_path, url, needle):
    assert_refused(_worker(tmp_path, "--db", url), "bssrdf worker", "cannot reach the job store", needle)


def test_the_embedded_default_creates_its_own_directory(tmp_path):
    out = _worker(tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "home" / "jobs.sqlite").is_file()
