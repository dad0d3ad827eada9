"""Stand-ins for shard result files in store tests that need no storage: what a commit records."""

from __future__ import annotations

import hashlib

from service.store import StoredFile

__all__ = ["stored"]


def stored(data: bytes) -> StoredFile:
    """The record of a file holding ``data`` (uri named by its digest; no file is written)."""
    digest = hashlib.sha256(data).hexdigest()
    return StoredFile(f".jobs/test/{digest[:16]}", len(data), digest)
