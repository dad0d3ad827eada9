"""The metadata.json of a dataset version (its code version is :func:`schema.version.code_version`)."""

from __future__ import annotations

import json
from typing import Any

from schema.version import code_version

__all__ = ["build_metadata", "metadata_bytes", "METADATA_FORMAT"]

METADATA_FORMAT = 1


def build_metadata(
    *, name: str, job_id: str, spec_json: str, spec_hash: str, seed: int, shards: int,
    photons: int, photons_per_shard: list[int], timings: dict[str, float], summary: Any,
    files: dict[str, dict[str, Any]],
) -> dict[str, Any]:
    """Everything a version records about itself (docs/architecture.md, "Datasets and exports").

    ``files`` maps every table file to its sha256 and size; the metadata file's own sha256 is
    kept in the catalog row (``metadata_sha256``).
    """
    return {
        "format": METADATA_FORMAT,
        "name": name,
        "job_id": job_id,
        "spec": json.loads(spec_json),
        "spec_hash": spec_hash,
        "seed": seed,
        "shards": shards,
        "photons": photons,
        "photons_per_shard": photons_per_shard,
        "code_version": code_version(),
        "timings": timings,
        "summary": summary,
        "files": files,
    }


def metadata_bytes(meta: dict[str, Any]) -> bytes:
    """Stable JSON encoding of the metadata (sorted keys, indented, trailing newline)."""
    return (json.dumps(meta, sort_keys=True, indent=2, allow_nan=True) + "\n").encode("utf-8")
