"""The idle worker's poll: jittered, doubling per empty claim up to a cap, reset by a claim; and
the worker CLI's refusal of bad numeric options."""

from __future__ import annotations

import subprocess
import sys

import pytest

from service.settings import IDLE_BACKOFF_CAP
from service.worker import Worker
from tests.service.test_end_to_end import REPO


class _Store:
    """Claims from a script: None is an empty claim, anything else a lease."""

    def __init__(self, script):
        self.script = list(script)

    def claim(self, worker_id, lease_seconds):
        return self.script.pop(0) if self.script else None

    def has_pending_tasks(self):
        return True


def test_idle_wait_doubles_to_the_cap_within_the_jitter():
    w = Worker(_Store([]), storage=None, poll_seconds=0.5, max_poll_seconds=3.0)
    for k, base in enumerate([0.5, 1.0, 2.0, 3.0, 3.0, 3.0]):
        waits = [w.idle_wait(k) for _ in range(2000)]
        assert base * 0.5 <= min(waits) and max(waits) <= base * 1.5
        # Uniform jitter: the mean of 2,000 draws is base within 5 standard errors (sd base/sqrt(12)).
        assert abs(sum(waits) / len(waits) - base) < 5 * base / (12 * 2000) ** 0.5
    assert Worker(_Store([]), storage=None, poll_seconds=0.25).max_poll_seconds == IDLE_BACKOFF_CAP * 0.25
    assert w.idle_wait(10_000) <= 4.5  # no overflow far into an idle spell


def test_a_claim_resets_the_backoff(monkeypatch):
    lease = object()
    w = Worker(_Store([None, None, None, lease, None, None]), storage=None, poll_seconds=1.0, max_poll_seconds=100.0)
    monkeypatch.setattr("service.worker.random.uniform", lambda a, b: 1.0)  # no jitter: the bases
    waits = []

    def wait(seconds):
        waits.append(seconds)
        if len(waits) == 5:
            w.stopping.set()
        return w.stopping.is_set()

    monkeypatch.setattr(w.stopping, "wait", wait)
    monkeypatch.setattr(w, "process", lambda lease: None)
    w.loop()
    assert waits == [1.0, 2.0, 4.0, 1.0, 2.0]


@pytest.mark.parametrize("kw, message", [
    (dict(poll_seconds=0.0), "poll_seconds must be > 0; received 0.0"),
    (dict(poll_seconds=2.0, max_poll_seconds=1.0), "max_poll_seconds must be >= poll_seconds (2.0); received 1.0"),
])
def test_bad_poll_settings_are_refused(kw, message):
    with pytest.raises(ValueError, match=message.replace("(", r"\(").replace(")", r"\)")):
        Worker(_Store([]), storage=None, **kw)


@pytest.mark.parametrize("argv, message", [
    (["--poll-seconds", "0"], "--poll-seconds must be > 0; received 0.0"),
    (["--lease-seconds", "-5"], "--lease-seconds must be > 0; received -5.0"),
    (["--max-tasks", "0"], "--max-tasks must be > 0; received 0"),
    (["--poll-seconds", "2", "--max-poll-seconds", "1"], "--max-poll-seconds must be >= --poll-seconds (2); received 1"),
])
def test_worker_cli_refuses_bad_numbers(tmp_path, argv, message):
    db = tmp_path / "jobs.sqlite"
    proc = subprocess.run([sys.executable, "-m", "service.cli", "worker", "--db", f"sqlite:///{db}",
                           "--storage", str(tmp_path / "data"), "--once", *argv],
                          cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert proc.stderr.strip().splitlines()[-1] == f"bssrdf worker: {message}"
    assert not db.exists()  # refused before the store is opened: nothing made
