"""Settings from the environment, and migrations that are safe to run from many processes."""

from __future__ import annotations

import threading

import pytest
import sqlalchemy as sa

from service.settings import Settings


def test_settings_defaults_and_env(monkeypatch, tmp_path):
    s = Settings()
    assert s.database_url.startswith("sqlite:///") and s.database_url.endswith("jobs.sqlite")
    assert s.heartbeat_seconds == s.lease_seconds / 4
    monkeypatch.setenv("BSSRDF_DATA_DIR", str(tmp_path))
    monkeypatch.setenv("BSSRDF_LEASE_SECONDS", "8")
    monkeypatch.setenv("BSSRDF_API_TOKENS", '["a", "b"]')
    s = Settings()
    assert s.database_url == f"sqlite:///{tmp_path / 'jobs.sqlite'}"
    assert s.storage_uri == str(tmp_path / "data")
    assert (s.lease_seconds, s.heartbeat_seconds, s.api_tokens) == (8.0, 2.0, ["a", "b"])
    with pytest.raises(ValueError, match="heartbeat_seconds must be below lease_seconds"):
        Settings(lease_seconds=5, heartbeat_seconds=6)


def _open_concurrently(url: str, n: int = 4) -> list[Exception]:
    """Open (and so migrate) the store at url from n threads at once; the errors raised."""
    from service.store import JobStore

    errors: list[Exception] = []

    def open_store():
        try:
            JobStore(url).dispose()
        except Exception as exc:  # pragma: no cover - reported by the caller
            errors.append(exc)

    threads = [threading.Thread(target=open_store) for _ in range(n)]
    for t in threads:
        t.start()
    for t in threads:
        t.join(60)
    return errors


def test_migrations_are_idempotent_and_concurrent(db_url):
    from alembic.script import ScriptDirectory

    from service.store import JobStore
    from service.store.store import MIGRATIONS_DIR

    (head,) = ScriptDirectory(str(MIGRATIONS_DIR)).get_heads()  # one head: revisions chained in order
    assert not _open_concurrently(db_url)
    store = JobStore(db_url)
    store.migrate()
    with store.engine.connect() as conn:
        assert conn.execute(sa.text("SELECT version_num FROM alembic_version")).scalar_one() == head
        names = set(sa.inspect(conn).get_table_names())
    assert {"jobs", "tasks", "shard_results", "dataset_versions", "dataset_exports"} <= names
    store.ping()


def test_many_openers_of_a_new_sqlite_store(tmp_path):
    """Four threads creating the same new SQLite store at once, 50 times over: the switch of a
    new file to WAL reports concurrent openers as locked without waiting (it failed about one
    start in twenty before it was retried)."""
    for round_ in range(50):
        errors = _open_concurrently(f"sqlite:///{tmp_path}/jobs-{round_}.sqlite")
        assert not errors, f"round {round_}: {errors}"


def test_in_memory_sqlite_is_refused():
    from service.store import JobStore

    with pytest.raises(ValueError, match="SQLite file"):
        JobStore("sqlite://")


def test_migration_0006_keeps_the_keys_of_existing_jobs(db_url):
    """Keys stored in jobs.idempotency_key before 0006 still name their jobs after it."""
    from alembic import command
    from alembic.config import Config

    from service.store import IdempotencyConflict, JobStore
    from service.store.store import MIGRATIONS_DIR
    from tests.service.conftest import queue_spec

    store = JobStore(db_url)
    job = store.submit(queue_spec("x", seed=1), idempotency_key="k-old")
    cfg = Config()
    cfg.set_main_option("script_location", str(MIGRATIONS_DIR))
    with store.engine.begin() as conn:
        cfg.attributes["connection"] = conn
        command.downgrade(cfg, "0005_task_phase")
    store.migrate()
    assert store.submit(queue_spec("x", seed=1), idempotency_key="k-old").id == job.id
    with pytest.raises(IdempotencyConflict, match="k-old"):
        store.submit(queue_spec("x", seed=2), idempotency_key="k-old")
    store.dispose()
