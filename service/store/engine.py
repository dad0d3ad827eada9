"""Engines for SQLite and PostgreSQL with one transactional behaviour.

SQLite (one host, several processes):
- WAL journal and ``busy_timeout``; ``synchronous=NORMAL``: in WAL mode the database stays
  consistent on power loss but may lose the last commits, which the queue tolerates (a lost shard
  commit leaves its lease to expire and the shard is recomputed, bit-identically); FULL costs an
  fsync per commit (about 3-10 ms here);
- every transaction starts with ``BEGIN IMMEDIATE`` (SQLAlchemy's documented pysqlite recipe:
  the driver's own BEGIN is disabled in a ``connect`` hook, ours is emitted in a ``begin`` hook),
  so a transaction that reads then writes never fails to upgrade its lock with SQLITE_BUSY;
  except on a connection marked :data:`READ_ONLY` (the store's reads): a deferred ``BEGIN``,
  which in WAL mode reads a snapshot without waiting for the writer. Every read taking the write
  lock made status reads queue behind workers' commits (p50 500 ms under load, BENCHMARKS.md);
- a small connection pool per engine, and one engine per process (never shared across ``fork()``).
  Not NullPool: closing the last connection of a WAL database checkpoints it, about 10 ms a
  transaction.

PostgreSQL: a normal pool with pre-ping; claims use ``FOR UPDATE SKIP LOCKED``.
"""

from __future__ import annotations

import sqlite3
import time

import sqlalchemy as sa
from sqlalchemy import event
from sqlalchemy.engine import Engine, make_url

__all__ = ["make_engine", "db_now", "SQLITE_BUSY_TIMEOUT_MS", "READ_ONLY", "PG_CONNECT_ARGS"]

SQLITE_BUSY_TIMEOUT_MS = 30_000

PG_CONNECT_ARGS = {"connect_timeout": 10, "keepalives": 1, "keepalives_idle": 30, "keepalives_interval": 10,
                   "keepalives_count": 3, "tcp_user_timeout": 60_000, "prepare_threshold": None}
"""Options of every PostgreSQL connection. The libpq ones: a host cut off from the database (a
dead link, a partitioned switch) gets an error within about a minute instead of waiting forever
on a socket (TCP retransmits for ~15 minutes), so its worker goes on when the network is back;
its lease has long expired to another worker by then (tests/service/test_multihost.py).
``prepare_threshold=None``: psycopg prepares no server-side statements, so the store works
through pgbouncer in transaction mode (before 1.21 it cannot track them; the queries here are
short, planning them costs little; BENCHMARKS.md, fleet claims)."""

READ_ONLY = "bssrdf_read_only"
"""Execution option of a connection that only reads (``StoreBase._read``)."""


def db_now(dialect) -> sa.ColumnElement[float]:
    """SQL expression of the database clock in seconds since the Unix epoch (float).

    PostgreSQL: ``extract(epoch from clock_timestamp())`` (real time, not transaction start);
    SQLite: ``(julianday('now') - 2440587.5) * 86400`` (millisecond resolution).
    """
    if dialect.name == "sqlite":
        return sa.cast((sa.func.julianday("now") - 2440587.5) * 86400.0, sa.Float)
    return sa.cast(sa.extract("epoch", sa.func.clock_timestamp()), sa.Float)


def _enable_wal(cursor) -> None:
    """PRAGMA journal_mode = WAL, retried while the database is locked.

    Switching a new database file to WAL takes an exclusive lock, and SQLite reports a
    concurrent opener (another process or thread creating the same store) as locked at once,
    without waiting in the busy handler; seen in about one in twenty starts of four openers.
    WAL is a property of the file, so once one connection has switched it the others find it set.
    """
    deadline = time.monotonic() + SQLITE_BUSY_TIMEOUT_MS / 1000
    delay = 0.005
    while True:
        try:
            cursor.execute("PRAGMA journal_mode = WAL")
            return
        except sqlite3.OperationalError as exc:
            if "locked" not in str(exc) or time.monotonic() > deadline:
                raise
            time.sleep(delay)
            delay = min(2 * delay, 0.2)


def _sqlite_hooks(engine: Engine) -> None:
    @event.listens_for(engine, "connect")
    def _on_connect(dbapi_connection, _record):
        # Disable pysqlite's implicit BEGIN; we emit our own in the "begin" hook.
        dbapi_connection.isolation_level = None
        cursor = dbapi_connection.cursor()
        cursor.execute(f"PRAGMA busy_timeout = {SQLITE_BUSY_TIMEOUT_MS}")
        _enable_wal(cursor)
        cursor.execute("PRAGMA synchronous = NORMAL")
        cursor.execute("PRAGMA foreign_keys = ON")
        cursor.close()

    @event.listens_for(engine, "begin")
    def _on_begin(conn):
        conn.exec_driver_sql("BEGIN" if conn.get_execution_options().get(READ_ONLY) else "BEGIN IMMEDIATE")


def make_engine(url: str, pool_size: int = 2, max_overflow: int | None = None) -> Engine:
    """An engine for ``url`` (``sqlite:///path`` or ``postgresql+psycopg://...``).

    Create one per process: engines are not shared across ``fork()``. ``pool_size`` connections
    are kept open; beyond them up to ``max_overflow`` (default 4 on PostgreSQL, 8 on SQLite) more
    are opened when needed and closed when returned. A worker needs 2 (its loop and its heartbeat); the API, serving
    requests concurrently, keeps more (``service.api.deps.API_POOL_SIZE``): a PostgreSQL
    connection opened and closed per request costs a server process fork each (status reads'
    p99 from 8 to over 100 ms with 4 concurrent clients, BENCHMARKS.md).
    """
    parsed = make_url(url)
    if parsed.get_backend_name() == "sqlite":
        if parsed.database in (None, "", ":memory:"):
            raise ValueError(
                f"the job store needs an SQLite file shared by worker processes; received {url!r}"
            )
        engine = sa.create_engine(
            parsed, pool_size=pool_size, max_overflow=8 if max_overflow is None else max_overflow,
            connect_args={"timeout": SQLITE_BUSY_TIMEOUT_MS / 1000}
        )
        _sqlite_hooks(engine)
        return engine
    if parsed.get_backend_name() == "postgresql":
        return sa.create_engine(parsed, pool_pre_ping=True, pool_size=pool_size,
                                max_overflow=4 if max_overflow is None else max_overflow, connect_args=PG_CONNECT_ARGS)
    raise ValueError(
        f"database URL must be sqlite:///FILE or postgresql+psycopg://...; received {url!r}"
    )
