"""Alembic environment: runs on the connection (and transaction) handed over by the store.

``JobStore.migrate()`` opens a transaction (``BEGIN IMMEDIATE`` on SQLite, an advisory lock on
PostgreSQL so concurrent workers migrate once), puts the connection in
``config.attributes["connection"]`` and calls ``alembic.command.upgrade``. Running ``alembic``
from the command line also works: set ``sqlalchemy.url`` in the config.
"""

from alembic import context

from service.store.engine import make_engine
from service.store.tables import metadata

config = context.config


def run_migrations_online() -> None:
    connection = config.attributes.get("connection")
    if connection is not None:
        context.configure(connection=connection, target_metadata=metadata)
        with context.begin_transaction():
            context.run_migrations()
        return
    engine = make_engine(config.get_main_option("sqlalchemy.url"))
    with engine.begin() as conn:
        context.configure(connection=conn, target_metadata=metadata)
        with context.begin_transaction():
            context.run_migrations()


if context.is_offline_mode():
    raise SystemExit("offline (--sql) migrations are not supported; run against a database")
run_migrations_online()
