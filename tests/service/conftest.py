"""Fixtures: the same store tests run on SQLite (a temp file) and on the real PostgreSQL.

PostgreSQL isolation: every test gets a fresh schema (``CREATE SCHEMA``), selected through the
libpq ``options=-csearch_path=...`` URL parameter, so worker subprocesses given the same URL see
the same schema; the schema is dropped afterwards.
"""

from __future__ import annotations

import os
import uuid
from urllib.parse import quote

import pytest
import sqlalchemy as sa

from schema import SimulationSpec, parse_spec

from tests.support.engine import engine_settings

PG_ENV = "BSSRDF_TEST_POSTGRES_URL"


def queue_spec(name: str = "queue-test", shards: int = 3, seed: int = 1) -> SimulationSpec:
    """A small real spec of one medium and ``shards`` shards for the queue tests (whose workers
    never walk it): the store is given what the API gives it."""
    return parse_spec({"name": name, "medium": {"sigma_a": [0.1], "sigma_s": [0.9], "g": [0.0], "eta": 1.0},
                       "photons": 10 * shards, "shards": shards, "batches_per_shard": 2, "seed": seed,
                       "estimator": "exits"})


def pg_base_url() -> str | None:
    return os.environ.get(PG_ENV) or None


def fresh_pg_schema_url(base: str) -> tuple[str, str]:
    """Create a new schema; return (url selecting it, schema name)."""
    schema = f"t_{uuid.uuid4().hex[:12]}"
    engine = sa.create_engine(base)
    with engine.begin() as conn:
        conn.exec_driver_sql(f'CREATE SCHEMA "{schema}"')
    engine.dispose()
    sep = "&" if "?" in base else "?"
    return f"{base}{sep}options={quote(f'-csearch_path={schema}')}", schema


def drop_pg_schema(base: str, schema: str) -> None:
    engine = sa.create_engine(base)
    with engine.begin() as conn:
        conn.exec_driver_sql(f'DROP SCHEMA "{schema}" CASCADE')
    engine.dispose()


@pytest.fixture(scope="module")
def engine_env():
    """ENGINE_ENV (tests.support.engine) in the test process for a whole module: its references,
    computed here, run the same walk as its worker subprocesses."""
    with engine_settings():
        yield


@pytest.fixture
def pg_url():
    """URL of a fresh PostgreSQL schema (skips when BSSRDF_TEST_POSTGRES_URL is unset)."""
    base = pg_base_url()
    if base is None:
        pytest.skip(f"PostgreSQL tests need {PG_ENV} (e.g. postgresql+psycopg://postgres@127.0.0.1:5432/test)")
    url, schema = fresh_pg_schema_url(base)
    yield url
    drop_pg_schema(base, schema)


@pytest.fixture(params=["sqlite", pytest.param("postgres", marks=pytest.mark.postgres)])
def db_url(request, tmp_path):
    """A fresh, empty job store URL on each backend."""
    if request.param == "sqlite":
        yield f"sqlite:///{tmp_path / 'jobs.sqlite'}"
    else:
        yield request.getfixturevalue("pg_url")


@pytest.fixture
def store(db_url):
    from service.store import JobStore, RetryPolicy

    s = JobStore(db_url, retry_policy=RetryPolicy(base_delay_s=0.0))
    yield s
    s.dispose()


@pytest.fixture
def fake_spec():
    return queue_spec
