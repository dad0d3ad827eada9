"""``bssrdf export NAME[@VERSION] --format FORMAT --out DIR``: a dataset version's export, as files.

Without ``--api`` it uses the local job service's store and storage (the same defaults as
``bssrdf run``: ``./.bssrdf``, or ``--data-dir``, or the BSSRDF_* settings); with ``--api URL``
it downloads from a running ``bssrdf serve``. Either way the export is made once, stored beside
the version with its sha256 (:mod:`service.datasets.exports`), and unpacked into DIR after every
file is checked against its manifest. VERSION is a number or ``latest`` (the default).

``bssrdf export --tables OUT --format FORMAT --out DIR`` exports the tables ``bssrdf simulate``
wrote into OUT instead (nothing is stored; the export records their sha256 and no version).
"""

from __future__ import annotations

import argparse
import io
import json
import os
import sys
import zipfile
from pathlib import Path
from urllib.parse import quote

from service.client import ApiClient, ApiError
from service.datasets.exports import ensure_export, extract_export, read_export
from service.datasets.storage import check_sha256, sha256_bytes
from service.store.errors import DatasetError
from workers.exports import FORMATS, MANIFEST, ExportError, ExportSource, write_export

__all__ = ["add_parser", "main", "parse_target"]


def parse_target(text: str) -> tuple[str, int | None]:
    """``"skin1"`` -> ("skin1", None), ``"skin1@3"`` -> ("skin1", 3), ``"skin1@latest"`` -> ("skin1", None);
    ValueError naming the allowed forms otherwise."""
    name, sep, version = text.partition("@")
    if not name or (sep and not version):
        raise ValueError(f"expected NAME or NAME@VERSION (VERSION a number >= 1 or latest); received {text!r}")
    if not sep or version == "latest":
        return name, None
    if not (version.isascii() and version.isdigit() and int(version) >= 1):
        raise ValueError(f"VERSION must be a number >= 1 or latest; received {version!r} in {text!r}")
    return name, int(version)


def _local(args: argparse.Namespace, name: str, version: int | None) -> tuple[str, list[str]]:
    from service.datasets import DatasetStorage
    from service.settings import Settings, sqlite_url_for
    from service.store import JobStore

    if args.data_dir:
        db_url, storage_uri = sqlite_url_for(args.data_dir), str(Path(args.data_dir) / "data")
    else:
        settings = Settings()
        db_url, storage_uri = settings.database_url, settings.storage_uri
    store = JobStore(db_url)
    try:
        record, export = ensure_export(store, DatasetStorage(storage_uri), name, version, args.format)
        files = extract_export(read_export(DatasetStorage(storage_uri), record, export), export.meta, args.out)
        return f"{record.name} v{record.version} {args.format} (sha256 {export.sha256})", files
    finally:
        store.dispose()


def _remote(args: argparse.Namespace, name: str, version: int | None) -> tuple[str, list[str]]:
    client = ApiClient(args.api, args.token, timeout=600.0)  # the first request makes the export
    try:
        segments = (quote(str(s), safe="") for s in (name, version or "latest", args.format))
        path = "/v1/datasets/{}/versions/{}/exports/{}".format(*segments)
        response = client.request("GET", path)
    finally:
        client.close()
    data, etag = response.content, response.headers.get("etag", "").strip('"')
    check_sha256(sha256_bytes(data), etag, f"the download of {path}", "sent in its ETag", "retry it",
                 damage="the transfer is damaged")  # ChecksumMismatch, a DatasetError
    with zipfile.ZipFile(io.BytesIO(data)) as zf:
        manifest = json.loads(zf.read(MANIFEST))
    files = extract_export(data, manifest, args.out)
    return f"{manifest['dataset']} v{manifest['version']} {args.format} (sha256 {etag})", files


def _tables(args: argparse.Namespace) -> tuple[str, list[str]]:
    source = ExportSource.from_directory(args.tables)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    return f"{source.label} {args.format} (tables in {args.tables})", sorted(write_export(args.format, source, out))


def main(args: argparse.Namespace) -> int:
    """Run ``bssrdf export`` with parsed arguments; returns the exit status."""
    try:
        if getattr(args, "tables", None):
            if args.target or args.api:
                raise ValueError("give either NAME[@VERSION] (a stored version) or --tables DIR, not both")
            what, files = _tables(args)
        else:
            if not args.target:
                raise ValueError("give NAME[@VERSION] (a stored version) or --tables DIR (bssrdf simulate's output)")
            name, version = parse_target(args.target)
            what, files = (_remote if args.api else _local)(args, name, version)
    except (ValueError, OSError, ExportError, DatasetError, ApiError) as exc:  # ExportError is a ValueError
        print(f"error: {exc}", file=sys.stderr)
        return 2
    print(f"wrote {len(files)} files of {what} to {args.out}:")
    for f in files:
        print(f"  {f}")
    return 0


def add_parser(subparsers) -> argparse.ArgumentParser:
    """Add the ``export`` subcommand to an argparse ``subparsers`` object."""
    p = subparsers.add_parser("export", help="export a dataset version (pbrt, albedo-map, exr, npz, csv, plots)",
                              description="Write a dataset version's export into DIR: made once, stored beside the "
                              "version with its sha256, every file checked against its manifest. Formats: "
                              + ", ".join(FORMATS) + ". Without --api: the local store (as bssrdf run).")
    p.add_argument("target", metavar="NAME[@VERSION]", nargs="?",
                   help="dataset name, optionally @VERSION (number or latest)")
    p.add_argument("--tables", metavar="OUT", default=None,
                   help="export the tables `bssrdf simulate --out OUT` wrote instead of a stored version")
    p.add_argument("--format", required=True, choices=list(FORMATS), help="export format")
    p.add_argument("--out", required=True, help="directory to write the export's files into (created)")
    p.add_argument("--api", default=None, help="download from this API (e.g. http://127.0.0.1:8000) instead of the "
                   "local store; the token is --token or BSSRDF_TOKEN")
    p.add_argument("--token", default=os.environ.get("BSSRDF_TOKEN"), help="bearer token for --api")
    p.add_argument("--data-dir", default=None, help="local data directory (default: BSSRDF_DATA_DIR or ./.bssrdf)")
    p.set_defaults(func=main)
    return p


if __name__ == "__main__":
    parser = argparse.ArgumentParser(prog="bssrdf")
    add_parser(parser.add_subparsers(dest="command", required=True))
    sys.exit(main(parser.parse_args()))
