"""The `bssrdf` command: one entry point, one module per subcommand.

Each subcommand module exposes ``add_parser(subparsers)``, which registers its parser and sets
``func`` to a ``main(args) -> int``.  Modules are imported lazily by name so that the light
commands' imports stay in their modules.
"""

from __future__ import annotations

import argparse
import importlib
import sys

from schema.version import code_version

__all__ = ["main", "SUBCOMMANDS", "version_text"]

SUBCOMMANDS = (
    "workers.run.simulate",  # simulate: in-process measurement
    "workers.measure.bench",  # bench: walk throughput
    "service.runner",  # run: local job service end to end
    "service.worker_command",  # worker: claim, run, commit
    "service.serve",  # serve: the HTTP API
    "service.client",  # submit, status, datasets
    "service.export",  # export: a version's export as files
)


def version_text() -> str:
    """``bssrdf-db 0.1.0 (commit abc123...)``: the code version every dataset version records."""
    v = code_version()
    return f"bssrdf-db {v['package'] or 'unknown'} (commit {v['git_commit'] or 'unknown'})"


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(
        prog="bssrdf",
        description="Exact, error-barred BSSRDF tables from Monte Carlo photon random walks.",
    )
    parser.add_argument("--version", action="version", version=version_text(),
                        help="print the package version and git commit, and exit")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    for name in SUBCOMMANDS:
        importlib.import_module(name).add_parser(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    if not getattr(args, "func", None):
        parser.print_help()
        return 2
    return int(args.func(args) or 0)


if __name__ == "__main__":
    sys.exit(main())
