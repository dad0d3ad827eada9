"""How many cores this process may use (kept free of torch so command-line parsing stays fast)."""

from __future__ import annotations

import os

__all__ = ["default_workers"]


def default_workers() -> int:
    """One worker per core this process may run on."""
    try:
        return max(1, len(os.sched_getaffinity(0)))
    except AttributeError:  # pragma: no cover - not Linux
        return max(1, os.cpu_count() or 1)
