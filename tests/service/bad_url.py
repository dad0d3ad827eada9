"""What the worker's and the API server's wrong-URL tests share: the one-line refusal, the URLs
that are not a job store, and the PostgreSQL URLs a running server refuses."""

from __future__ import annotations

import subprocess

import pytest

from tests.service.conftest import pg_base_url

NOT_A_JOB_STORE = [
    ("notaurl", "'notaurl' is not a database URL"),
    ("mysql://u@h/db", "sqlite:///FILE or postgresql+psycopg://"),
    ("sqlite://", "SQLite file"),
]
"""(URL, what the one line must say)."""


def assert_refused(out: subprocess.CompletedProcess, program: str, *needles: str) -> None:
    """Exit 2 and exactly one line on stderr, from `program`, holding every needle."""
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2, (out.returncode, out.stderr[-3000:])
    assert len(lines) == 1 and lines[0].startswith(f"{program}: "), out.stderr[-3000:]
    for needle in needles:
        assert needle in lines[0], lines[0]


def pg_refused_urls(with_port: bool) -> list:
    """PostgreSQL URLs next to the test server's: an unknown database and user (and, with_port, a
    port nobody listens on), each with the name the one line must hold."""
    base = pg_base_url()
    if base is None:
        return []
    from sqlalchemy.engine import make_url

    u = make_url(base)
    port = [pytest.param(u.set(port=(u.port or 5432) + 1).render_as_string(False), "Connection refused", id="port")]
    return (port if with_port else []) + [
        pytest.param(u.set(database="no_such_database").render_as_string(False), "no_such_database", id="database"),
        pytest.param(u.set(username="no_such_user").render_as_string(False), "no_such_user", id="user"),
    ]
