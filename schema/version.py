"""The code version recorded in every table and file of a dataset version, written once.

``{"package": "0.1.0", "git_commit": "<sha>" | None}``: the installed package version (read from
pyproject.toml when running from a source tree that is not installed) and the commit, from
``BSSRDF_GIT_COMMIT`` (set in container images) or ``git rev-parse HEAD`` of a checkout.  The
Parquet run facts and metadata.json carry this same dictionary.
"""

from __future__ import annotations

import os
import subprocess
from functools import lru_cache
from importlib import metadata as importlib_metadata
from pathlib import Path

__all__ = ["code_version"]

_REPO = Path(__file__).resolve().parents[1]


@lru_cache
def code_version() -> dict[str, str | None]:
    """``{"package": version or None, "git_commit": sha or None}`` (cached per process)."""
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
