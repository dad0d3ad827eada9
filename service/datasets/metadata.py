"""The metadata.json of a dataset version, and the code version recorded in it."""

from __future__ import annotations

import json
import os
import subprocess
from functools import lru_cache
from importlib import metadata as importlib_metadata
from pathlib import Path
from typing import Any

__all__ = ["code_version", "build_metadata", "metadata_bytes", "METADATA_FORMAT"]

METADATA_FORMAT = 1
_REPO = Path(__file__).resolve().parents[2]


@lru_cache
def code_version() -> dict[str, str | None]:
    """``{"package": version, "git_commit": sha or None}``.

    The commit comes from ``BSSRDF_GIT_COMMIT`` (set in container images) or ``git rev-parse``
    when running from a checkout; None otherwise.
    """
    try:
        package = importlib_metadata.version("bssrdf-db")
    except importlib_metadata.PackageNotFoundError:  # running from a checkout: read pyproject
        try:
            import tomllib

            package = tomllib.loads((_REPO / "pyproject.toml").read_text())["project"]["version"]
        except (OSError, KeyError, ValueError):
            package = None
    commit = os.environ.get("BSSRDF_GIT_COMMIT")
    if not commit and (_REPO / ".git").exists():
        try:
            commit = subprocess.run(
                ["git", "rev-parse", "HEAD"], cwd=_REPO, capture_output=True, text=True, timeout=5, check=True
            ).stdout.strip()
        except (OSError, subprocess.SubprocessError):
            commit = None
    return {"package": package, "git_commit": commit or None}


def build_metadata(
    *, name: str, job_id: str, spec_json: str, spec_hash: str, seed: int, shards: int,
    photons: int, photons_per_shard: list[int], timings: dict[str, float], summary: Any,
    files: dict[str, dict[str, Any]],
) -> dict[str, Any]:
    """Everything a version records about itself (ARCHITECTURE.md, Datasets).

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
