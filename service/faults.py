"""A test-only fault point: a merging worker stops itself where a test wants to kill it.

``BSSRDF_TEST_PAUSE_AT`` names one point of the merge task (:mod:`service.datasets.publish`);
a worker process that reaches it sends itself SIGSTOP, so that a test waiting for the stop
(``os.waitpid(pid, os.WUNTRACED)``) can SIGKILL it exactly there, instead of racing a log line:

- ``fold:K``: the round has folded K shards (read, checked and added to the accumulator in
  memory; nothing of this round committed yet);
- ``staged``: the version's tables and metadata.json are written in its staging directory,
  ``complete_merge`` not yet called;
- ``publish``: the version's tables and metadata.json are written and moved to ``NAME/vN``
  by ``complete_merge``, before the commit of its catalog row (not yet visible); on SQLite
  outside any transaction, under the name's version lock.

Unset (the default, and in every deployment) it costs one environment lookup per point and
does nothing. Used by tests/service/test_merge_faults.py.
"""

from __future__ import annotations

import os
import signal

__all__ = ["PAUSE_ENV", "pause_point"]

PAUSE_ENV = "BSSRDF_TEST_PAUSE_AT"


def pause_point(point: str) -> None:
    """SIGSTOP this process if ``BSSRDF_TEST_PAUSE_AT`` names ``point`` (see the module docstring)."""
    if os.environ.get(PAUSE_ENV) == point:
        os.kill(os.getpid(), signal.SIGSTOP)
