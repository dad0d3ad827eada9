"""Dataset storage on any pyarrow filesystem: staging, atomic publish, checksum-verified reads.

Layout under the storage root::

    NAME/v1/radial.parquet, bins.parquet, summary.parquet, summary.json, metadata.json
    NAME/v2/...
    NAME/.staging-<uuid>/      files being written (never listed by the catalog)
    .jobs/<job id>/            files a job keeps while it runs (removed when the job is deleted)
    .jobs/<job id>/.staging-<uuid>/   a job's version being written (removed with the job's files,
                                      so that a merge killed while writing leaves nothing behind)

A version exists when its catalog row exists (``dataset_versions``, written in the same DB
transaction that ends the job). The staged directory is moved to ``NAME/vN`` just before that
commit, under the name's version lock (``JobStore.complete_merge``; on SQLite outside the
transaction, so that a slow move blocks no write): on a local or POSIX shared filesystem the move
is one atomic ``rename``; on object stores (s3://, gs://) it is a copy, still invisible to
readers until the row commits. Readers go
through the catalog and verify every file's sha256 (:func:`open_version`).
"""

from __future__ import annotations

import hashlib
import json
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.fs as pafs
import pyarrow.parquet as pq

from schema.names import InvalidName, check_name
from service.store.errors import ChecksumMismatch, DatasetError
from service.store.records import DatasetVersionRecord

__all__ = [
    "DatasetStorage", "StagedVersion", "OpenVersion", "open_version", "expected_files", "verified_path",
    "verified_bytes", "check_sha256", "sha256_bytes", "sha256_file", "METADATA_FILE",
]

METADATA_FILE = "metadata.json"
_CHUNK = 1 << 20


def sha256_bytes(data: bytes) -> str:
    """Hex sha256 of ``data`` (the digest every file of a job and a version is recorded by)."""
    return hashlib.sha256(data).hexdigest()


def sha256_file(fs: pafs.FileSystem, path: str) -> str:
    """Hex sha256 of a file on ``fs``."""
    h = hashlib.sha256()
    with fs.open_input_stream(path) as f:
        while chunk := f.read(_CHUNK):
            h.update(chunk)
    return h.hexdigest()


def _check_name(name: str) -> str:
    try:
        return check_name(name, "dataset name")
    except InvalidName as exc:
        raise DatasetError(str(exc)) from None


class DatasetStorage:
    """The storage root: a local path, ``file://``, ``s3://``... (anything pyarrow understands)."""

    def __init__(self, uri: str) -> None:
        self.uri = uri
        if "://" in uri:
            self.fs, root = pafs.FileSystem.from_uri(uri)
        else:
            self.fs, root = pafs.LocalFileSystem(), Path(uri).expanduser().resolve().as_posix()
        self.root = root.rstrip("/")
        self.fs.create_dir(self.root, recursive=True)

    def version_path(self, name: str, version: int) -> str:
        """Directory of a version on ``self.fs``."""
        return f"{self.root}/{_check_name(name)}/v{int(version)}"

    def stage(self, name: str, within: str | None = None) -> "StagedVersion":
        """A fresh staging directory for the next version of ``name``: under ``NAME/``, or under
        ``within`` (a job's directory, which goes once its version is published or it is deleted)."""
        parent = within if within is not None else f"{self.root}/{_check_name(name)}"
        path = f"{parent}/.staging-{uuid.uuid4().hex}"
        self.fs.create_dir(path, recursive=True)
        return StagedVersion(self, name, path)

    def job_path(self, job_id: str) -> str:
        """Directory of the files a job keeps while it runs (shard results)."""
        return f"{self.root}/.jobs/{job_id}"

    def discard_job(self, job_id: str) -> bool:
        """Remove a job's directory (a deleted job); False if it had none."""
        return self._remove(self.job_path(job_id))

    def remove_version(self, record: DatasetVersionRecord) -> bool:
        """Remove a deleted version's files (its catalog row is already a tombstone); False if
        they were already gone."""
        return self._remove(record.uri)

    def _remove(self, path: str) -> bool:
        if self.fs.get_file_info(path).type == pafs.FileType.NotFound:
            return False
        self.fs.delete_dir(path)
        return True

    def ping(self) -> None:
        """Raise if the storage root is unreachable (for ``/readyz``)."""
        info = self.fs.get_file_info(self.root)
        if info.type != pafs.FileType.Directory:
            raise DatasetError(f"storage root {self.uri!r} is not a reachable directory")


class StagedVersion:
    """Files written under a staging directory, published as a version by the job store."""

    def __init__(self, storage: DatasetStorage, name: str, path: str) -> None:
        self.storage, self.name, self.path = storage, name, path

    def write_bytes(self, filename: str, data: bytes) -> None:
        with self.storage.fs.open_output_stream(f"{self.path}/{filename}") as f:
            f.write(data)

    def checksums(self, filenames: list[str]) -> dict[str, dict[str, Any]]:
        """``{file: {"sha256": hex, "bytes": size}}`` of staged files."""
        fs = self.storage.fs
        out = {}
        for name in sorted(filenames):
            path = f"{self.path}/{name}"
            out[name] = {"sha256": sha256_file(fs, path), "bytes": fs.get_file_info(path).size}
        return out

    # --- the Publisher protocol of JobStore.complete_merge ---
    def uri_for(self, version: int) -> str:
        return self.storage.version_path(self.name, version)

    def publish(self, version: int) -> None:
        """Move the staged directory to ``NAME/vN`` (replacing an orphan no catalog row names)."""
        fs, target = self.storage.fs, self.uri_for(version)
        if fs.get_file_info(target).type != pafs.FileType.NotFound:
            fs.delete_dir(target)  # orphan of a publish whose DB commit failed: the row is ours now
        try:
            fs.move(self.path, target)  # rename(2) on local/POSIX filesystems: atomic
        except (OSError, NotImplementedError, pa.ArrowNotImplementedError):
            # object stores cannot move directories: copy file by file
            fs.create_dir(target, recursive=True)
            for info in fs.get_file_info(pafs.FileSelector(self.path)):
                fs.copy_file(info.path, f"{target}/{info.base_name}")
            fs.delete_dir(self.path)

    def discard(self) -> None:
        """Delete the staged files (after a failure or a lost lease)."""
        try:
            self.storage.fs.delete_dir(self.path)
        except (OSError, FileNotFoundError):
            pass


@dataclass(frozen=True)
class OpenVersion:
    """A verified dataset version: its record, filesystem and file paths."""

    record: DatasetVersionRecord
    fs: pafs.FileSystem
    paths: dict[str, str]  # file name -> path on fs

    @property
    def metadata(self) -> dict[str, Any]:
        return {k: v for k, v in self.record.meta.items() if k != "metadata_sha256"}

    def read_table(self, filename: str) -> pa.Table:
        """A Parquet table of the version, e.g. ``read_table("radial.parquet")``."""
        return pq.read_table(self.paths[filename], filesystem=self.fs)

    def read_json(self, filename: str) -> Any:
        with self.fs.open_input_stream(self.paths[filename]) as f:
            return json.loads(f.read().decode("utf-8"))

    def read_bytes(self, filename: str) -> bytes:
        with self.fs.open_input_stream(self.paths[filename]) as f:
            return f.read()


def open_version(store, storage: DatasetStorage, name: str, version: int | None = None) -> OpenVersion:
    """Open a published version (latest if ``version`` is None) after verifying every sha256.

    Raises :class:`VersionNotFound` (no such row) or :class:`ChecksumMismatch` (a file missing
    or different from what was published).
    """
    record = store.get_version(name, version)
    paths = {f: verified_path(storage, record, f, digest) for f, digest in sorted(expected_files(record).items())}
    return OpenVersion(record, storage.fs, paths)


def expected_files(record: DatasetVersionRecord) -> dict[str, str]:
    """File name -> sha256 of every file a version published, metadata.json included."""
    files = {name: f["sha256"] for name, f in record.meta.get("files", {}).items()}
    files[METADATA_FILE] = record.meta["metadata_sha256"]
    return files


def verified_path(storage: DatasetStorage, record: DatasetVersionRecord, filename: str, digest: str) -> str:
    """Path of a version's file after checking its sha256 against the one published
    (:class:`ChecksumMismatch` if it is missing, unreadable or different)."""
    path = f"{record.uri}/{filename}"
    what = f"{record.name} v{record.version}: {filename}"
    try:
        actual = sha256_file(storage.fs, path)
    except (FileNotFoundError, OSError) as exc:
        raise ChecksumMismatch(f"{what} unreadable ({exc})") from exc
    check_sha256(actual, digest, what, "published", "restore it from a backup or re-run the job")
    return path


def verified_bytes(fs: pafs.FileSystem, path: str, digest: str, what: str) -> bytes:
    """The content of a file the job store recorded (a shard result, a fold), read once and
    checked against its recorded sha256 (:class:`ChecksumMismatch` if missing, unreadable or
    different)."""
    try:
        with fs.open_input_stream(path) as f:
            data = f.read()
    except (FileNotFoundError, OSError) as exc:
        raise ChecksumMismatch(f"{what} unreadable ({exc})") from exc
    check_sha256(sha256_bytes(data), digest, what, "recorded",
                 "the job fails with this error (nothing corrupt is folded); submit the spec again")
    return data


def check_sha256(actual: str, digest: str, what: str, recorded_as: str, remedy: str, *,
                 damage: str = "the stored copy is corrupt") -> None:
    """The one checksum rule: ChecksumMismatch naming the file and both digests unless equal.

    The message reads ``{what} has sha256 {actual}, {recorded_as} as {digest}; {damage}: {remedy}``:
    ``recorded_as`` says where the expected digest comes from ("published", "sent in its ETag"),
    ``damage`` what a difference means, ``remedy`` what to do about it.
    """
    if actual != digest:
        raise ChecksumMismatch(f"{what} has sha256 {actual}, {recorded_as} as {digest}; {damage}: {remedy}")
