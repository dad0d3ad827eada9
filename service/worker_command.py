"""``bssrdf worker``: the command line of the worker (:mod:`service.worker`), its options and checks.

Apart from the worker's loop so that building the ``bssrdf`` parser does not import torch
(seconds): :func:`main` imports the loop, and with it the walk, only when a worker starts.
"""

from __future__ import annotations

import argparse
import sys

from service.datasets import DatasetStorage
from service.logs import configure_logging
from service.settings import IDLE_BACKOFF_CAP, settings_or_exit, sqlite_url_for
from service.store import StoreUnavailable, open_store

__all__ = ["add_parser", "main", "run_as_script"]

DESCRIPTION = "The worker: claim a task, run it under a heartbeated lease, commit, repeat."


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``worker`` subcommand to an argparse ``subparsers`` object."""
    p = subparsers.add_parser("worker", help="claim and run shard and merge tasks from the job store",
                              description=DESCRIPTION)
    _add_arguments(p)
    p.set_defaults(func=main)
    return p


def _add_arguments(p: argparse.ArgumentParser) -> None:
    p.add_argument("--db", help="job store URL (default: BSSRDF_DATABASE_URL or the local SQLite store)")
    p.add_argument("--storage", help="dataset storage URI (default: BSSRDF_STORAGE_URI or the local data dir)")
    p.add_argument("--once", action="store_true", help="exit once no live job has work left that could become "
                   "claimable (batch schedulers); a merge waiting for shards or a retry backing off keeps it")
    p.add_argument("--max-tasks", type=int, default=None, metavar="N", help="exit after N tasks")
    p.add_argument("--lease-seconds", type=float, default=None, metavar="S", help="lease length (default 60)")
    p.add_argument("--heartbeat-seconds", type=float, default=None, metavar="S", help="default: lease / 4")
    p.add_argument("--poll-seconds", type=float, default=1.0, metavar="S",
                   help="idle wait after an empty claim, doubled per empty claim in a row up to "
                   "--max-poll-seconds (x a random 0.5-1.5, so a fleet does not poll in step)")
    p.add_argument("--max-poll-seconds", type=float, default=None, metavar="S",
                   help=f"longest idle wait (default {IDLE_BACKOFF_CAP:g} x --poll-seconds)")
    p.add_argument("--stall-seconds", type=float, default=None, metavar="S",
                   help="a shard that reports no progress for S seconds loses its lease (default: "
                   "BSSRDF_STALL_SECONDS, 300; the clock starts at its first report, after any compile)")
    p.add_argument("--worker-id", default=None, help="name in leases and logs (default host:pid:random)")


def _argument_problem(args: argparse.Namespace) -> str | None:
    """What is wrong with the numeric options (each must be positive; the idle backoff's cap at
    least the first wait), or None."""
    for name in ("lease_seconds", "heartbeat_seconds", "poll_seconds", "max_poll_seconds", "stall_seconds", "max_tasks"):
        value = getattr(args, name, None)
        if value is not None and not value > 0:
            return f"--{name.replace('_', '-')} must be > 0; received {value}"
    if args.max_poll_seconds is not None and args.max_poll_seconds < args.poll_seconds:
        return f"--max-poll-seconds must be >= --poll-seconds ({args.poll_seconds:g}); received {args.max_poll_seconds:g}"
    return None


def main(args: argparse.Namespace) -> int:
    """Run a worker with parsed arguments; returns the exit status."""
    settings = settings_or_exit()
    problem = _argument_problem(args)
    if problem:
        print(f"bssrdf worker: {problem}", file=sys.stderr)
        return 2
    url = args.db or settings.database_url
    try:  # only the embedded default, jobs.sqlite in the data directory, creates its directory
        store = open_store(url, create_dir=url == sqlite_url_for(settings.data_dir), fold_batch=settings.fold_batch)
    except StoreUnavailable as exc:
        print(f"bssrdf worker: {exc}", file=sys.stderr)
        return 2
    configure_logging()
    # The loop and the walk, torch with them: only now that a worker starts (module docstring).
    # One worker process per core, one torch thread each: shards are independent, so processes
    # scale without per-step synchronisation, and the walk runs exactly as in `bssrdf simulate`.
    import torch

    from service.worker import Worker

    torch.set_num_threads(1)
    lease_seconds = args.lease_seconds or settings.lease_seconds
    heartbeat = args.heartbeat_seconds or (settings.heartbeat_seconds if not args.lease_seconds else None)
    storage = DatasetStorage(args.storage or settings.storage_uri)
    worker = Worker(
        store, storage, worker_id=args.worker_id, lease_seconds=lease_seconds, heartbeat_seconds=heartbeat,
        once=args.once, max_tasks=args.max_tasks, poll_seconds=args.poll_seconds,
        max_poll_seconds=args.max_poll_seconds,
        stall_seconds=args.stall_seconds or settings.stall_seconds,
        keep_shard_files=settings.keep_shard_files,
    )
    try:
        return worker.run()
    finally:
        store.dispose()


def run_as_script() -> int:
    """``python -m service.worker``: the options of ``bssrdf worker``, parsed from sys.argv."""
    parser = argparse.ArgumentParser(prog="bssrdf worker", description=DESCRIPTION)
    _add_arguments(parser)
    return main(parser.parse_args())
