"""The files a job keeps in dataset storage while it runs (its staging area).

Layout under the storage root (``DatasetStorage.job_path``)::

    .jobs/<job id>/shards/<task>-<token>.tally    a shard's result (ShardTally.to_bytes), one per attempt
    .jobs/<job id>/fold/<folded>-<token>.fold     the merge's fold after <folded> tasks
    .jobs/<job id>/parts/m<medium>/*.parquet      a finished medium's tables (sweeps)

The job store records a file's path relative to the storage root, its size and its sha256
(:class:`service.store.StoredFile`); readers check the sha256 (:func:`verified_bytes`). A file
is named by the lease token that wrote it, so a stale worker's late write never replaces the
file a commit recorded; files no commit recorded (a lost lease, a killed process) are removed
with the whole directory once the version is published (unless ``keep_shard_files``) or the job
is deleted.
"""

from __future__ import annotations

import pyarrow.fs as pafs

from service.datasets.storage import DatasetStorage, sha256_bytes, verified_bytes
from service.store.records import StoredFile

__all__ = ["JobFiles"]


class JobFiles:
    """The staging area of one job on the storage filesystem."""

    def __init__(self, storage: DatasetStorage, job_id: str) -> None:
        self.storage, self.job_id = storage, job_id
        self.fs: pafs.FileSystem = storage.fs
        self.path = storage.job_path(job_id)

    def _uri(self, name: str) -> str:
        return f"{self.path}/{name}"[len(self.storage.root) + 1:]

    def path_of(self, ref: StoredFile | str) -> str:
        """Path on ``fs`` of a recorded file (or of a URI relative to the storage root)."""
        return f"{self.storage.root}/{ref.uri if isinstance(ref, StoredFile) else ref}"

    def write(self, name: str, data: bytes) -> StoredFile:
        """Write ``data`` to ``name`` under the job's directory; what the store records of it."""
        path = f"{self.path}/{name}"
        self.fs.create_dir(path.rsplit("/", 1)[0], recursive=True)
        with self.fs.open_output_stream(path) as f:
            f.write(data)
        return StoredFile(self._uri(name), len(data), sha256_bytes(data))

    def read(self, ref: StoredFile, what: str) -> bytes:
        """A recorded file's bytes after checking its sha256 (ChecksumMismatch otherwise)."""
        return verified_bytes(self.fs, self.path_of(ref), ref.sha256, f"job {self.job_id}: {what} ({ref.uri})")

    def delete(self, ref: StoredFile | None) -> None:
        """Remove a file (a result no commit recorded, an old fold); missing is fine."""
        if ref is None:
            return
        try:
            self.fs.delete_file(self.path_of(ref))
        except (FileNotFoundError, OSError):
            pass

    def part_dir(self, medium: int) -> str:
        """Directory (on ``fs``) of a finished medium's tables."""
        return f"{self.path}/parts/m{medium:06d}"

    def part_uri(self, medium: int, name: str) -> str:
        return self._uri(f"parts/m{medium:06d}/{name}")

    def discard(self) -> bool:
        """Remove the job's whole directory; False if it had none."""
        return self.storage.discard_job(self.job_id)
