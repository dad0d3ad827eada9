"""Stored exports: made once from a verified version, kept beside it with their sha256.

    record, export = ensure_export(store, storage, "skin1", 1, "plots")
    files = extract_export(read_export(storage, record, export), export, "out/")

An export of format F of version N of dataset D is one zip archive (the files
:func:`workers.exports.write_export` writes, ``export.json`` among them), stored at
``D/vN/exports/F-<sha256[:16]>.zip`` beside the version's tables and catalogued in
``dataset_exports`` with its sha256 and manifest (:class:`service.store.exports.ExportsMixin`).
The first request makes it from the version's checksum-verified tables; every later request
(API download, ``bssrdf export``) serves the stored bytes through the same verified download
path as the version's own files. The archive is deterministic (sorted names, fixed
timestamps), so two processes making the same export at once write the same bytes, and the
catalog's unique (version, format) keeps one row.
"""

from __future__ import annotations

import io
import json
import tempfile
import uuid
import zipfile
from pathlib import Path

from service.datasets.storage import DatasetStorage, check_sha256, open_version, sha256_bytes, verified_path
from service.store import DatasetVersionRecord, ExportRecord, JobStore
from service.store.errors import ChecksumMismatch
from workers.exports import MANIFEST, ExportError, ExportSource, check_format, write_export
from workers.exports.source import TABLES

__all__ = ["ensure_export", "read_export", "extract_export", "export_archive", "EXPORT_DIR"]

EXPORT_DIR = "exports"
"""Subdirectory of a version's directory holding its export archives."""
_EPOCH = (1980, 1, 1, 0, 0, 0)  # the earliest zip timestamp: archives do not depend on when they were made


def export_archive(directory: str | Path, names: list[str]) -> bytes:
    """A deterministic zip of ``names`` in ``directory`` (sorted, fixed timestamps, deflated)."""
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", compression=zipfile.ZIP_DEFLATED) as zf:
        for name in sorted(names):
            info = zipfile.ZipInfo(name, date_time=_EPOCH)
            info.compress_type = zipfile.ZIP_DEFLATED
            info.external_attr = 0o644 << 16
            zf.writestr(info, (Path(directory) / name).read_bytes())
    return buf.getvalue()


def _store_bytes(storage: DatasetStorage, record: DatasetVersionRecord, filename: str, data: bytes) -> None:
    """Write ``data`` to ``filename`` under the version's directory, atomically where the
    filesystem can rename (written under a temporary name, then moved)."""
    fs = storage.fs
    fs.create_dir(f"{record.uri}/{EXPORT_DIR}", recursive=True)
    tmp = f"{record.uri}/{EXPORT_DIR}/.tmp-{uuid.uuid4().hex}"
    with fs.open_output_stream(tmp) as f:
        f.write(data)
    fs.move(tmp, f"{record.uri}/{filename}")


def ensure_export(store: JobStore, storage: DatasetStorage, name: str, version: int | None,
                  fmt: str) -> tuple[DatasetVersionRecord, ExportRecord]:
    """The stored export ``fmt`` of a version (the latest if ``version`` is None), made and
    stored first if it does not exist. Raises VersionNotFound, ChecksumMismatch (the version's
    tables are corrupt), ExportError (the dataset cannot be exported so; the message says why)."""
    check_format(fmt)
    record = store.get_version(name, version)
    existing = store.get_export(record.name, record.version, fmt)
    if existing is not None:
        return record, existing
    opened = open_version(store, storage, record.name, record.version)  # every sha256 checked
    source = ExportSource.from_tables({t: opened.read_table(f"{t}.parquet") for t in TABLES},
                                      {f: d["sha256"] for f, d in record.meta["files"].items()},
                                      name=record.name, version=record.version)
    with tempfile.TemporaryDirectory(prefix="bssrdf-export-") as tmp:
        names = write_export(fmt, source, tmp)
        manifest = json.loads((Path(tmp) / MANIFEST).read_text(encoding="utf-8"))
        blob = export_archive(tmp, names)
    digest = sha256_bytes(blob)
    filename = f"{EXPORT_DIR}/{fmt}-{digest[:16]}.zip"
    _store_bytes(storage, record, filename, blob)
    export, created = store.add_export(record.name, record.version, fmt, filename=filename, sha256=digest,
                                       size=len(blob), meta=manifest)
    if not created and export.filename != filename:  # another process stored its own first
        storage.fs.delete_file(f"{record.uri}/{filename}")
    return record, export


def read_export(storage: DatasetStorage, record: DatasetVersionRecord, export: ExportRecord) -> bytes:
    """The stored archive's bytes after checking its sha256 (ChecksumMismatch otherwise)."""
    path = verified_path(storage, record, export.filename, export.sha256)
    with storage.fs.open_input_stream(path) as f:
        return f.read()


def extract_export(archive: bytes, manifest: dict, out_dir: str | Path) -> list[str]:
    """Unpack an export archive into ``out_dir`` (created), checking every file against the
    sha256 its manifest records; returns the file names. ChecksumMismatch on any difference,
    and names with a path separator are refused (an archive holds plain file names)."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    files = manifest.get("files", {})
    names = []
    with zipfile.ZipFile(io.BytesIO(archive)) as zf:
        for name in zf.namelist():
            if "/" in name or "\\" in name or name in ("", ".", ".."):
                raise ChecksumMismatch(f"export archive holds {name!r}, not a plain file name")
            data = zf.read(name)
            if name != MANIFEST:
                if name not in files:
                    raise ChecksumMismatch(f"export archive holds {name}, which its manifest does not list")
                check_sha256(sha256_bytes(data), files[name].get("sha256"), f"export file {name}",
                             "recorded in its manifest", "make the export again", damage="the archive is corrupt")
            (out / name).write_bytes(data)
            names.append(name)
    return sorted(names)
