"""The engine settings of tests that compare a job's bytes with a reference computed in the
test process: worker subprocesses and the test itself run the same walk (eager, one thread).

    pytestmark = pytest.mark.usefixtures("engine_env")   # the fixture is in tests/service/conftest.py
    start_workers(..., extra_env=ENGINE_ENV)
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager

import pytest

__all__ = ["ENGINE_ENV", "engine_settings"]

ENGINE_ENV = {"BSSRDF_COMPILE": "0", "OMP_NUM_THREADS": "1"}
"""Eager walk, one OpenMP thread: what every process of a bitwise comparison runs with."""


@contextmanager
def engine_settings() -> Iterator[None]:
    """ENGINE_ENV set in this process's environment, the previous values restored on exit."""
    with pytest.MonkeyPatch.context() as mp:
        for key, value in ENGINE_ENV.items():
            mp.setenv(key, value)
        yield
