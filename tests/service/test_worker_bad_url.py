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

from tests.service.conftest import pg_base_url

ROOT = Path(__file__).resolve().parents[2]


def _worker(tmp_path: Path, *args: str, env: dict | None = None) -> subprocess.CompletedProcess:
    full = {**os.environ, "PYTHONPATH": str(ROOT), "BSSRDF_DATA_DIR": str(tmp_path / "home"), **(env or {})}
    cmd = [sys.executable, "-m", "service.worker", "--storage", str(tmp_path / "data"), "--once", *args]
    return subprocess.run(cmd, cwd=tmp_path, env=full, capture_output=True, text=True, timeout=120)


def _refused(out: subprocess.CompletedProcess, *needles: str) -> None:
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2, (out.returncode, out.stderr[-3000:])
    assert len(lines) == 1 and lines[0].startswith("bssrdf worker: "), out.stderr[-3000:]
    for needle in needles:
        assert needle in lines[0], lines[0]


def test_sqlite_in_a_missing_directory_is_refused_and_not_created(tmp_path):
    missing = tmp_path / "nonexistent" / "dir"
    out = _worker(tmp_path, "--db", f"sqlite:///{missing / 'jobs.sqlite'}")
    _refused(out, str(missing), "does not exist")
    assert not (tmp_path / "nonexistent").exists()


@pytest.mark.parametrize("url, needle", [
    ("notaurl", "'notaurl' is not a database URL"),
    ("mysql://u@h/db", "sqlite:///FILE or postgresql+psycopg://"),
    ("sqlite://", "SQLite file"),
])
def test_a_url_that_is_not_a_job_store_is_refused(tmp_path, url, needle):
    _refused(_worker(tmp_path, "--db", url), needle)


def _pg_variants():
    base = pg_base_url()
    if base is None:
        return []
    from sqlalchemy.engine import make_url

    u = make_url(base)
    return [
        pytest.param(u.set(port=(u.port or 5432) + 1).render_as_string(False), "Connection refused", id="port"),
        pytest.param(u.set(database="no_such_database").render_as_string(False), "no_such_database", id="database"),
        pytest.param(u.set(username="no_such_user").render_as_string(False), "no_such_user", id="user"),
    ]


@pytest.mark.skipif(pg_base_url() is None, reason="PostgreSQL tests need BSSRDF_TEST_POSTGRES_URL")
@pytest.mark.parametrize("url, needle", _pg_variants())
def test_a_postgresql_server_database_or_user_that_is_not_there(tmp_path, url, needle):
    _refused(_worker(tmp_path, "--db", url), "cannot reach the job store", needle)


def test_the_embedded_default_creates_its_own_directory(tmp_path):
    out = _worker(tmp_path)
    assert out.returncode == 0, out.stderr[-3000:]
    assert (tmp_path / "home" / "jobs.sqlite").is_file()
