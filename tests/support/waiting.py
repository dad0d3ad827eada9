"""Polling helper shared by the tests that drive real processes (tests/api/test_live.py,
tests/service/test_end_to_end.py, tests/service/test_worker.py)."""

from __future__ import annotations

import time

__all__ = ["wait_for"]


def wait_for(predicate, timeout: float, what: str, poll: float = 0.1):
    """Call ``predicate`` every ``poll`` seconds until it returns a truthy value, and return that value.

    Raises AssertionError naming ``what`` once ``timeout`` seconds have passed without one.
    """
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        value = predicate()
        if value:
            return value
        time.sleep(poll)
    raise AssertionError(f"timed out after {timeout} s waiting for {what}")
