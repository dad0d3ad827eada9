"""Opening the job store from a URL someone typed: every way it can be wrong is one line.

``open_store(url, create_dir=...)`` is ``JobStore(url)`` for the command-line entry points, with
:class:`StoreUnavailable` (one line, no traceback) for a URL that is not one, an unsupported
backend, an SQLite file in a directory that does not exist, or a database that cannot be
reached or opened (a wrong host, port, database name or user). An SQLite store's directory is
created only when ``create_dir`` is set, which the entry points set for the embedded default
(``jobs.sqlite`` in ``BSSRDF_DATA_DIR``) alone: a typo in a path must not start a new, empty
store that workers then idle on.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

from sqlalchemy.engine import make_url
from sqlalchemy.exc import ArgumentError, DBAPIError

from service.store.errors import StoreError
from service.store.store import JobStore

__all__ = ["StoreUnavailable", "StoreUnreachable", "check_store_url", "open_store"]

_FORMS = "sqlite:///FILE or postgresql+psycopg://USER@HOST:PORT/DATABASE"


class StoreUnavailable(StoreError):
    """The job store of a URL cannot be opened; the message is one line."""


class StoreUnreachable(StoreUnavailable):
    """The URL is well formed but no database server answered it (down, or a wrong host or port);
    a server that answers and refuses the URL's database or user is a plain StoreUnavailable."""


_REFUSALS = ("does not exist", "password authentication failed", "no pg_hba.conf entry")
"""What PostgreSQL answers to a database or role that is not there, or credentials it refuses
(libpq's messages; psycopg gives no SQLSTATE for a failed connection): a wrong URL, not an
outage. A server starting up or out of connections is an outage (StoreUnreachable)."""


def open_store(url: str, *, create_dir: bool = False, **kwargs: Any) -> JobStore:
    """``JobStore(url, **kwargs)``, or :class:`StoreUnavailable` saying in one line what is wrong
    (module docstring)."""
    shown = check_store_url(url, create_dir=create_dir)
    try:
        return JobStore(url, **kwargs)
    except ValueError as exc:
        raise StoreUnavailable(_one_line(exc)) from None
    except DBAPIError as exc:
        message = f"cannot reach the job store {shown}: {_one_line(exc.orig)}"
        if any(refusal in message for refusal in _REFUSALS):  # the URL is wrong, not the server down
            raise StoreUnavailable(message) from None
        raise StoreUnreachable(message) from None


def check_store_url(url: str, *, create_dir: bool = False) -> str:
    """The checks of :func:`open_store` that need no database server: :class:`StoreUnavailable`
    for a URL that is not one or an SQLite file in a directory that does not exist (created
    instead if ``create_dir``). Returns the URL to show (password hidden)."""
    try:
        parsed = make_url(url)
    except ArgumentError:
        raise StoreUnavailable(f"{url!r} is not a database URL; give {_FORMS}") from None
    shown = parsed.render_as_string(hide_password=True)
    if parsed.get_backend_name() == "sqlite" and parsed.database not in (None, "", ":memory:"):
        directory = Path(parsed.database).expanduser().absolute().parent
        if not directory.is_dir():
            if not create_dir:
                raise StoreUnavailable(
                    f"job store {shown}: the directory {directory} does not exist; create it or correct the "
                    "URL (no database is created outside an existing directory)")
            directory.mkdir(parents=True, exist_ok=True)
    return shown


def _one_line(exc: BaseException) -> str:
    return " ".join(part.strip() for part in str(exc).splitlines() if part.strip())
