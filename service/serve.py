"""``bssrdf serve``: run the HTTP API with uvicorn (its httptools protocol with header limits).

    bssrdf serve [--host 127.0.0.1] [--port 8000] [--db URL] [--storage URI]

Every option defaults to its setting (``BSSRDF_HOST``, ``BSSRDF_PORT``, ``BSSRDF_DATABASE_URL``,
``BSSRDF_STORAGE_URI``). Refuses to start on a non-loopback address unless ``BSSRDF_API_TOKENS``
is set. The API does not run simulations: start ``bssrdf worker`` processes against the same
database and storage.
"""


from __future__ import annotations

import argparse
import sys

__all__ = ["add_parser", "main", "build_settings"]

EPILOG = """\
authentication:
  BSSRDF_API_TOKENS   bearer tokens, a JSON list: BSSRDF_API_TOKENS='["TOKEN1", "TOKEN2"]'
                      (make one: python -c 'import secrets; print(secrets.token_urlsafe(32))').
                      Writes (submit, cancel, delete) need 'Authorization: Bearer TOKEN'; reads
                      too when BSSRDF_READ_OPEN=false. Without tokens authentication is off, and
                      serve refuses any address but loopback. Clients: --token or BSSRDF_TOKEN.
limits (refused with 4xx naming the field, the limit and the value):
  BSSRDF_MAX_JOB_PHOTONS, BSSRDF_MAX_SHARD_CPU_SECONDS, BSSRDF_WORKER_SPEED, BSSRDF_MAX_BODY_BYTES
HTTP (uvicorn with httptools, service/api/server.py):
  BSSRDF_MAX_HEADER_BYTES (16384) and BSSRDF_MAX_HEADERS (100): a bigger head is refused with 431
  while it arrives; BSSRDF_READ_TIMEOUT_SECONDS (10): a head, then a body, arriving slower is 408
"""


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``serve`` subcommand to an argparse ``subparsers`` object."""
    p = subparsers.add_parser("serve", help="serve the HTTP API (uvicorn)", description=__doc__.split("\n\n")[0],
                              epilog=EPILOG, formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_arguments(p)
    p.set_defaults(func=main)
    return p


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--host", default=None, help="bind address (default: BSSRDF_HOST or 127.0.0.1)")
    p.add_argument("--port", type=int, default=None, help="bind port (default: BSSRDF_PORT or 8000)")
    p.add_argument("--db", default=None, help="job store URL (default: BSSRDF_DATABASE_URL or the local SQLite store)")
    p.add_argument("--storage", default=None, help="dataset storage URI (default: BSSRDF_STORAGE_URI or the local data dir)")
    p.add_argument("--log-level", default="info", choices=["critical", "error", "warning", "info", "debug"])


def build_settings(args: argparse.Namespace):
    """Settings from the environment with the command-line options applied."""
    from service.settings import Settings, settings_or_exit

    updates = {"host": args.host, "port": args.port, "database_url": args.db, "storage_uri": args.storage}
    # Validate the updated values like the environment's (port range...): re-run the model.
    base = settings_or_exit()
    return Settings.model_validate({**base.model_dump(), **{k: v for k, v in updates.items() if v is not None}})


def main(args: argparse.Namespace) -> int:
    """Serve until interrupted; returns the exit status (2 on a configuration error)."""
    import uvicorn
    from pydantic import ValidationError

    from service.api import InsecureBindError, create_app
    from service.api.server import limited_protocol

    from service.settings import sqlite_url_for
    from service.store import StoreUnavailable, StoreUnreachable, open_store

    try:
        settings = build_settings(args)
        app = create_app(settings)
    except (InsecureBindError, ValidationError) as exc:
        print(f"bssrdf serve: {exc}", file=sys.stderr)
        return 2
    # The job store URL is checked like the worker's (service.store.opening): one line and exit 2
    # for a URL that is not a job store or an SQLite file in a missing directory (only the embedded
    # default creates its directory) or a database or user the server refuses. A server that does
    # not answer is not fatal: the API starts,
    # /readyz answers 503 naming the reason, and requests work once the database is up.
    url = settings.database_url
    try:
        open_store(url, create_dir=url == sqlite_url_for(settings.data_dir), pool_size=1).dispose()
    except StoreUnreachable as exc:
        print(f"bssrdf serve: warning: {exc}; serving anyway (/readyz answers 503 until it is up)", file=sys.stderr)
    except StoreUnavailable as exc:
        print(f"bssrdf serve: {exc}", file=sys.stderr)
        return 2
    uvicorn.run(app, host=settings.host, port=settings.port, log_level=args.log_level,
                http=limited_protocol(settings))
    return 0


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="bssrdf serve", description=__doc__.split("\n\n")[0], epilog=EPILOG,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    _add_arguments(parser)
    sys.exit(main(parser.parse_args()))
